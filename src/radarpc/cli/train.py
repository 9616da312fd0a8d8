"""radarpc train CONFIG: train a model from an experiment config (resumable, DDP under torchrun):
a RADIal detector (FFTRadNet, polar PointPillars, SpectralPillars), or a RaLD stage on a
ColoRadar-layout root.

::

    radarpc train configs/spectralpillars-s.yaml --data data/sim_radial_s --points data/sim_radial_s_pc057.parquet --out runs/sp057
    radarpc train configs/fftradnet-s.yaml --data data/sim_radial_s --out runs/fft
    torchrun --nproc-per-node 2 -m radarpc train configs/fftradnet.yaml --data data/radial --out runs/fft
    radarpc train configs/spectralpillars-s.yaml --data sim_a sim_b --points pc_a.parquet pc_b.parquet --out runs/sp_ab
    radarpc train configs/rald-ae-s.yaml --data data/sim_colo --out runs/ae
    radarpc train configs/rald-s.yaml --data data/sim_colo --ae runs/ae --out runs/rald
    radarpc train configs/rald/generalization/rald-s-finetune.yaml --data data/sim_colo --ae runs/ae --init runs/rald --out runs/rald-ft
    radarpc train configs/rpdnet-s.yaml --data data/sim_colo --out runs/rpdnet

What the config is decides the rest. A config with a stage key is a RaLD experiment: stage
autoencoder trains RaLD's LiDAR occupancy autoencoder (stage 1), stage diffusion its
radar-conditioned latent diffusion model against a stage-1 run given by --ae RUN, whose
autoencoder is frozen (stage 2), stage occupancy the learned baseline of RaLD's Table 2 (a
radar-to-occupancy network, RPDNet-style, supervised by the LiDAR truth's occupancy of a coarse
frustum grid). All three read one ColoRadar-layout root (--data; its runs give the
train and val splits; a RaLD config's scenes list keeps the runs of those scene types only).
--init RUN starts a RaLD stage from the best weights of another run of the same stage, model and
inputs instead of fresh ones (fine-tuning; a stage-2 RUN must have been trained against the --ae
weights); the run key records it, so a rerun from other weights is refused. A config without a
stage key is a detection experiment on RADIal-layout roots.

Detection: several roots (--data A B, with one point store each for the pillar models) train as
one dataset: the training frames of every root, validated on the validation frames of every root.
A root's RD cubes may be deleted once converted to its point store: the point models read only the
stores and each root's labels and freespace. --runs N trains N seeds into OUT/run0 .. OUT/run{N-1}
and writes OUT/summary.md with the mean and standard deviation.

The run folder --out holds config.yaml (the resolved config), run.json (the key: the config and the
data paths; for RaLD stage 2 also the stage-1 run's path, key and weights hash),
checkpoints/last.safetensors (the whole training state, written atomically every
train.checkpoint_every steps and at each validation), best.safetensors (the weights of the best
validation train.select_metric; for RaLD stage 2 the diffusion model and the frozen autoencoder),
log.csv and TensorBoard events in tb/ (when the tensorboard package is installed). Run the same
command again after an interruption: it resumes from the last checkpoint and ends with the same
weights as an uninterrupted run. Another config, data or stage-1 run in the same folder is refused
unless --overwrite, which deletes that run's files and the evaluations of its weights (eval_*,
figures/). Under torchrun the run uses DistributedDataParallel (NCCL on GPUs, gloo on CPUs);
train.batch_size is the global batch. The loop is radarpc.training.loop.
"""
from __future__ import annotations

import argparse

from radarpc.cli.options import MODEL_NAMES

__all__ = ["add_parser", "run"]


def run(args: argparse.Namespace) -> int:
    import sys

    from radarpc.config import load_yaml_mapping

    from radarpc.experiments.rpdnet.config import is_occupancy_config

    mapping = load_yaml_mapping(args.config)
    if is_occupancy_config(mapping):
        return _run_occupancy(args)
    if "stage" in mapping:
        return _run_rald(args)
    for opt, what in (("ae", "the stage-1 autoencoder run of a RaLD diffusion config (stage: diffusion)"),
                      ("init", "the run a RaLD stage fine-tunes (stage: autoencoder or diffusion)")):
        if getattr(args, opt) is not None:
            raise ValueError(f"--{opt} names {what}; {args.config} is a detection experiment (it has no 'stage')")
    return _run_detection(args, notice=lambda s: print(s, file=sys.stderr))


def _train_changes(args: argparse.Namespace) -> dict:
    return {k: v for k, v in (("epochs", args.epochs), ("batch_size", args.batch_size),
                              ("num_workers", args.num_workers), ("seed", args.seed)) if v is not None}


def _with_model(cfg, variant: str | None):
    import dataclasses

    if variant is None or variant == cfg.model.variant:
        return cfg
    from radarpc.models import ModelSpec

    # the config's overrides belong to its own variant; another variant starts from its own sizes
    return dataclasses.replace(cfg, model=ModelSpec(variant))


def _run_detection(args: argparse.Namespace, notice) -> int:
    from radarpc.distributed import dist_env
    from radarpc.experiments.radial_detection.config import load_experiment, with_train
    from radarpc.experiments.radial_detection.train import train_runs

    cfg = _with_model(load_experiment(args.config, notice=notice), args.model)
    changes = _train_changes(args)
    if changes:
        cfg = with_train(cfg, **changes)
    rank0 = dist_env().rank == 0
    results = train_runs(cfg, args.data, args.out, points=args.points, runs=args.runs, device=args.device,
                         overwrite=args.overwrite, progress=not args.no_progress,
                         log=print if rank0 else (lambda s: None))
    if rank0:
        for r in results:
            print(f"{r.out}: best validation {cfg.train.select_metric} {r.best_score:.4f} at epoch {r.best_epoch}")
    return 0


def _run_rald(args: argparse.Namespace) -> int:
    import sys

    from radarpc.distributed import dist_env
    from radarpc.experiments.rald.config import load_experiment, with_train
    from radarpc.experiments.rald.train import train_rald

    if args.points is not None:
        raise ValueError(f"--points is a detection experiment's point store; {args.config} is a RaLD experiment, "
                         f"which reads the ColoRadar root given by --data")
    if args.runs != 1:
        raise ValueError(f"--runs {args.runs}: RaLD experiments train one run per folder; train each seed "
                         f"(--seed) into its own --out")
    cfg = load_experiment(args.config, notice=lambda s: print(s, file=sys.stderr))
    cfg = _with_model(cfg, args.model)
    changes = _train_changes(args)
    if changes:
        cfg = with_train(cfg, **changes)
    rank0 = dist_env().rank == 0
    r = train_rald(cfg, args.data, args.out, ae=args.ae, device=args.device, overwrite=args.overwrite,
                   progress=not args.no_progress, log=print if rank0 else (lambda s: None), init=args.init)
    if rank0:
        print(f"{r.out}: best validation {cfg.train.select_metric} {r.best_score:.4f} at step {r.best_step} "
              f"(epoch {r.best_epoch})")
    return 0


def _run_occupancy(args: argparse.Namespace) -> int:
    import sys

    from radarpc.distributed import dist_env
    from radarpc.experiments.rpdnet.config import load_experiment, with_train
    from radarpc.experiments.rpdnet.train import train_occupancy

    for given, what in ((args.points is not None, "--points (a detection experiment's point store)"),
                        (args.ae is not None, "--ae (RaLD stage 2's autoencoder run)"),
                        (args.init is not None, "--init (fine-tuning a RaLD stage)"),
                        (args.runs != 1, f"--runs {args.runs} (train each seed with --seed into its own --out)")):
        if given:
            raise ValueError(f"{args.config} is the occupancy baseline (stage: occupancy), which takes no {what}")
    cfg = _with_model(load_experiment(args.config, notice=lambda s: print(s, file=sys.stderr)), args.model)
    changes = _train_changes(args)
    if changes:
        cfg = with_train(cfg, **changes)
    rank0 = dist_env().rank == 0
    r = train_occupancy(cfg, args.data, args.out, device=args.device, overwrite=args.overwrite,
                        progress=not args.no_progress, log=print if rank0 else (lambda s: None))
    if rank0:
        print(f"{r.out}: best validation {cfg.train.select_metric} {r.best_score:.4f} at step {r.best_step} "
              f"(epoch {r.best_epoch})")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("train", help="train a detector, a RaLD stage or RaLD's learned baseline from a config "
                                     "(resumable, DDP under torchrun)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("config", help="experiment YAML (see configs/)")
    p.add_argument("--data", required=True, nargs="+", metavar="ROOT",
                   help="RADIal-layout root (or a sparse-RD root for FFTRadNet), several train together; for RaLD "
                        "one ColoRadar-layout root")
    p.add_argument("--points", default=None, nargs="+", metavar="FILE",
                   help="point store made from each --data root, in the same order (pillar models)")
    p.add_argument("--ae", default=None, metavar="RUN",
                   help="RaLD stage 2 (stage: diffusion): the stage-1 autoencoder run folder, frozen while the "
                        "diffusion model trains")
    p.add_argument("--init", default=None, metavar="RUN",
                   help="RaLD stages: start from the best weights of this run (same stage and model; fine-tuning)")
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--model", default=None, choices=MODEL_NAMES,
                   help="train this variant of the model registry instead of the config's model.variant "
                        "(without its overrides; see `radarpc models`)")
    p.add_argument("--runs", type=int, default=1,
                   help="train this many seeds (train.seed, +1, ...) and summarise (detection experiments)")
    p.add_argument("--device", default=None, help="torch device (default: this rank's GPU, else the CPU)")
    p.add_argument("--epochs", type=int, default=None, help="override train.epochs")
    p.add_argument("--batch-size", type=int, default=None, help="override train.batch_size (global)")
    p.add_argument("--num-workers", type=int, default=None, help="override train.num_workers")
    p.add_argument("--seed", type=int, default=None, help="override train.seed")
    p.add_argument("--overwrite", action="store_true", help="start over in a folder that holds another run")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
