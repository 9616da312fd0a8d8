"""``radarpc generate RUN``: RaLD's clouds of a ColoRadar split, one per paired radar frame (or, for
a stage-1 run, the autoencoder's reconstruction of each frame's LiDAR).

::

    radarpc generate runs/rald --data data/sim_colo --split test --out preds/rald
    radarpc generate runs/ae --data data/sim_colo --split test --out preds/rald-ae    # the reconstruction
    radarpc generate runs/rald-official --data data/coloradar --split test --out preds/official --device cuda
    radarpc generate runs/rald --data data/sim_colo --out preds/quick --random-queries 50000 \\
        --guided-queries 50000 --refine-queries 50000 --steps 8 --guide os-cfar
    radarpc evaluate-points preds/rald preds/rald-ae preds/oscfar --data data/sim_colo --split test

RUN is a stage-2 run folder: ``radarpc train`` with a diffusion config (the autoencoder it was
trained against is stored with it), or ``radarpc import-rald`` (the official weights). Per frame:
the radar condition once, the Heun sampler's latents, the occupancy of random and guided queries
decoded in chunks of --chunk queries, the refinement, and the occupied queries as Cartesian
points in the single-chip radar frame, in metres (the frame of the LiDAR truth ``radarpc
evaluate-points`` scores them against). The defaults are the official evaluation's: 500,000
random and 700,000 guided queries, 500,000 refinement queries, 18 Heun steps, guided queries
around RaLD's intensity peaks (--guide peaks; os-cfar: radarpc's OS-CFAR points; none: random
queries only). --config takes a YAML with a generation section (random_queries, guided_queries,
guided_spread, refine_queries, refine_spread, refine_rounds, chunk, num_steps, sigma_min,
sigma_max, rho, seed) and a guide section (source, n_points, angle_bins, upsample, oscfar), each
optional; the options above replace its values.

RUN may also be a stage-1 run (``radarpc train`` with an autoencoder config, or OUT/ae of
``radarpc import-rald``): then each frame's LiDAR truth, drawn as the autoencoder's training draws
it (the same points for a frame and --seed), is encoded to latents, a posterior sample as the
official evaluation decodes (--posterior mean: the posterior mean), and decoded exactly as a
generation decodes (the same queries, chunks, refinement and Cartesian output) without the sampler:
the autoencoder's reconstruction, the best a generation with this autoencoder can reach. Its folder
is the same layout with method ``rald-ae`` and ``"kind": "reconstruction"`` in generation.json, and
stages encoding, decoding and refinement in generation.csv. --steps (and the sampler's fields of
--config) are refused with a stage-1 run, --posterior (and the reconstruction section of
--config: posterior) with a stage-2 run. The official
autoencoder evaluation decodes 500,000 random queries only: --guide none with ``generation:
{refine_rounds: 0}`` in --config.

OUT gets ``{run}/{frame:06d}.npy`` (float32 (N, 3)), ``index.json``, ``generation.json`` (the key:
root, split, settings, grid, the run folder and its weights' SHA-256) and ``generation.csv`` (per
frame: points, empty flag, seed, query counts, seconds per stage). Every file is written
atomically; the same command again keeps the frames already written and generates the rest, so an
interrupted job resumes to the files an uninterrupted one writes. Other settings, another run or
other weights into the same OUT are refused unless --overwrite. A frame whose decoding is empty is
written as an empty cloud, flagged in the CSV and the index, and reported. A run that has not
finished is refused unless --allow-unfinished. The driver is
``radarpc.experiments.rald.generation``.

RUN may also be a run of RaLD's learned baseline (``radarpc train`` with a stage: occupancy config,
e.g. configs/rpdnet-s.yaml): one forward pass per frame, and a point per cell of its coarse frustum
grid whose occupancy probability exceeds --threshold (default 0.5), at the cell's centre or, with
--jitter, uniform inside the cell (seeded by --seed, the run and the frame). OUT gets the same
clouds and index.json, with prediction.json (the key) and prediction.csv (per frame: points, empty
flag, seconds of the forward pass); resumable in the same way. The driver is
``radarpc.experiments.rpdnet.generation``::

    radarpc generate runs/rpdnet --data data/sim_colo --split test --out preds/rpdnet
    radarpc evaluate-points preds/rpdnet preds/rald preds/oscfar --data data/sim_colo --split test
"""
from __future__ import annotations

import argparse

from radarpc.cli.options import GUIDE_SOURCES, POSTERIORS, frame_step

__all__ = ["add_parser", "run"]

_GENERATION_OPTIONS = (("random_queries", "random_queries"), ("guided_queries", "guided_queries"),
                       ("refine_queries", "refine_queries"), ("steps", "num_steps"), ("seed", "seed"),
                       ("chunk", "chunk"))


def run(args: argparse.Namespace) -> int:
    import sys

    from radarpc.cli.text import plural
    from radarpc.experiments.rpdnet.runs import is_occupancy_run

    if is_occupancy_run(args.run):
        return _run_occupancy(args)
    if args.threshold is not None or args.jitter:
        raise ValueError(f"--threshold and --jitter read a radar-to-occupancy run's cells; {args.run} is not one "
                         f"(RaLD's generation decodes queries: see --random-queries, --guided-queries)")
    from radarpc.experiments.rald.generation import GenerateConfig, generate_run, load_generate_config, with_generation

    config = load_generate_config(args.config) if args.config else GenerateConfig()
    changes = {field: getattr(args, opt) for opt, field in _GENERATION_OPTIONS if getattr(args, opt) is not None}
    config = with_generation(config, guide=args.guide, posterior=args.posterior, **changes)
    res = generate_run(args.run, args.out, data=args.data, split=args.split, every=args.every, config=config,
                       device=args.device,
                       allow_unfinished=args.allow_unfinished, overwrite=args.overwrite,
                       progress=not args.no_progress,
                       on_warning=lambda s: print(f"warning: {s}", file=sys.stderr),
                       notice=lambda s: print(s, file=sys.stderr),
                       given=[f for f, v in (("num_steps", args.steps), ("posterior", args.posterior)) if v is not None])
    if res.seconds:
        stages = ", ".join(f"{k} {v:.3g}" for k, v in res.seconds.items())
        print(f"seconds per frame ({plural(res.n_new, 'new frame')}): {stages}")
    empty = f", {len(res.empty)} empty" if res.empty else ""
    print(f"wrote {plural(res.n_new, 'new point cloud')} ({plural(res.n_frames, 'frame')}{empty}) to {res.out}")
    return 0


def _run_occupancy(args: argparse.Namespace) -> int:
    import sys

    from radarpc.cli.text import plural
    from radarpc.experiments.rpdnet.generation import predict_run
    from radarpc.pipelines.occupancy_clouds import CloudConfig

    rald_only = [f"--{opt.replace('_', '-')}" for opt, _ in _GENERATION_OPTIONS
                 if opt != "seed" and getattr(args, opt) is not None]
    rald_only += ["--config"] * (args.config is not None) + ["--guide"] * (args.guide is not None)
    rald_only += ["--posterior"] * (args.posterior is not None)
    if rald_only:
        raise ValueError(f"{args.run} is a radar-to-occupancy run (stage: occupancy): {', '.join(rald_only)} "
                         f"belong to RaLD's generation; its clouds take --threshold, --jitter and --seed")
    cloud = CloudConfig(**{k: v for k, v in (("threshold", args.threshold), ("seed", args.seed)) if v is not None},
                        jitter=args.jitter)
    res = predict_run(args.run, args.out, data=args.data, split=args.split, every=args.every, cloud=cloud, device=args.device,
                      allow_unfinished=args.allow_unfinished, overwrite=args.overwrite, progress=not args.no_progress,
                      on_warning=lambda s: print(f"warning: {s}", file=sys.stderr),
                      notice=lambda s: print(s, file=sys.stderr))
    if res.seconds is not None:
        print(f"seconds per forward pass ({plural(res.n_new, 'new frame')}): {res.seconds:.3g}")
    empty = f", {len(res.empty)} empty" if res.empty else ""
    print(f"wrote {plural(res.n_new, 'new point cloud')} ({plural(res.n_frames, 'frame')}{empty}) to {res.out}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("generate", help="RaLD's (or its learned baseline's) point clouds of a ColoRadar split from a "
                                        "trained or imported run, or a stage-1 run's reconstruction (resumable)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="stage-2 RaLD run folder (radarpc train with a diffusion config, or radarpc import-rald), "
                               "a stage-1 one (the autoencoder's reconstruction), or a run of the occupancy baseline "
                               "(stage: occupancy)")
    p.add_argument("--data", default=None, metavar="ROOT",
                   help="ColoRadar root (default: the root the run was trained on, or given to import-rald)")
    p.add_argument("--split", default="test", choices=("train", "val", "test", "all"),
                   help="split whose paired frames are generated (default test)")
    p.add_argument("--every", type=frame_step, default=1, metavar="K",
                   help="generate every K-th paired frame of each run (default 1: all); radarpc evaluate-points "
                        "scores the frames the folder lists")
    p.add_argument("--out", required=True, help="prediction folder")
    p.add_argument("--config", default=None, metavar="YAML",
                   help="generation settings (generation and guide sections, and for a stage-1 run a "
                        "reconstruction section; default the official values)")
    p.add_argument("--random-queries", type=int, default=None, metavar="N",
                   help="random queries per frame, uniform over the grid (default 500,000)")
    p.add_argument("--guided-queries", type=int, default=None, metavar="N",
                   help="queries per frame around the guide points (default 700,000)")
    p.add_argument("--refine-queries", type=int, default=None, metavar="N",
                   help="queries per frame of the refinement around the occupied ones (default 500,000)")
    p.add_argument("--steps", type=int, default=None, metavar="N",
                   help="Heun steps of the sampler, 2N - 1 network calls (default 18; stage-2 runs only)")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="base seed; each frame draws from a seed of it, its run and its index (default 0)")
    p.add_argument("--chunk", type=int, default=None, metavar="N",
                   help="queries per decoder call: bounds the memory, not the result (default 65,536)")
    p.add_argument("--guide", default=None, choices=GUIDE_SOURCES,
                   help="where the guided queries start: RaLD's intensity peaks, radarpc's OS-CFAR points or "
                        "nowhere (default peaks)")
    p.add_argument("--posterior", default=None, choices=POSTERIORS,
                   help="stage-1 runs only: decode a seeded sample of the posterior, as the official evaluation, or "
                        "its mean (default sample)")
    p.add_argument("--threshold", type=float, default=None, metavar="P",
                   help="occupancy runs: a cell is a point when its probability exceeds P (default 0.5)")
    p.add_argument("--jitter", action="store_true",
                   help="occupancy runs: each point uniform inside its cell (seeded by --seed, run and frame) "
                        "instead of at its centre")
    p.add_argument("--device", default=None, help="torch device (default: a GPU if any, else the CPU)")
    p.add_argument("--allow-unfinished", action="store_true",
                   help="generate with the best weights so far of a run that has not finished")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a folder holding another generation (settings, root, split, run or weights)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
