"""``radarpc pointcloud ROOT``: convert a RADIal root into a Parquet store of spectral point
clouds (``--out``) and/or a sparse-RD root masked to the same detected set (``--sparse-rd-out``).

Examples::

    radarpc pointcloud data/sim_radial --density 0.057 --enrich rd3,sector32 --out data/pc057.parquet
    radarpc pointcloud data/sim_radial --snr 1.585 --out data/pc_2db.parquet
    radarpc pointcloud data/sim_radial --density 0.057 --density-mode per-dataset \\
        --sparse-rd-out data/sim_radial_srd057
    torchrun --nproc-per-node 4 "$(which radarpc)" pointcloud data/radial --density 0.057 --out pc.parquet

A killed conversion resumes when the same command is run again (``--no-resume`` starts over).
Under torchrun each rank converts its share of the chunks (on ``cuda:LOCAL_RANK`` when CUDA is
available) and rank 0 merges; ``--sparse-rd-out`` is written by rank 0 alone.
"""
from __future__ import annotations

import argparse
import math

from radarpc.dsp.convert import convert_dataset, dist_env, write_sparse_rd

__all__ = ["add_parser", "run", "parse_pair", "parse_enrich"]


def parse_pair(text: str) -> tuple[int, int]:
    """``"9,9"`` -> ``(9, 9)`` (argparse type for ``--window`` / ``--guard``)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        vals = tuple(int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two integers 'range,doppler' such as 9,9, got {text!r}") from None
    if len(vals) != 2:
        raise argparse.ArgumentTypeError(f"expected two integers 'range,doppler' such as 9,9, got {text!r}")
    return vals  # type: ignore[return-value]


def parse_enrich(text: str) -> tuple[str, ...]:
    """``"rd3,sector32"`` -> ``("rd3", "sector32")``; ``"none"`` or ``""`` -> ``()``."""
    if text.strip().lower() in ("", "none"):
        return ()
    return tuple(p.strip() for p in text.split(",") if p.strip())


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    return v


def add_density_args(p: argparse.ArgumentParser):
    """Add the threshold options shared by ``pointcloud`` and ``show``; returns the required
    mutually exclusive group (``--density`` | ``--snr``) so that a command can add to it."""
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--density", type=_fraction, metavar="D",
                   help="target density |S(tau)| / (Nr * ND) in (0, 1], e.g. 0.057 (RADIal's default); "
                        "with an rdN enrichment the density of the enlarged set |S*(tau)| / (Nr * ND)")
    g.add_argument("--snr", type=_fraction, metavar="TAU",
                   help="fixed linear CFAR SNR threshold tau (> 0), e.g. 1.585 (= 2 dB)")
    p.add_argument("--density-mode", choices=("per-frame", "per-dataset"), default="per-frame",
                   help="with --density: a tau per frame, or one tau calibrated on the train split "
                        "(default per-frame)")
    p.add_argument("--window", type=parse_pair, default=(9, 9), metavar="R,D",
                   help="CA-CFAR window, full odd side lengths (default 9,9)")
    p.add_argument("--guard", type=parse_pair, default=(3, 3), metavar="R,D",
                   help="CA-CFAR guard, full odd side lengths (default 3,3)")
    return g


def check_density_args(args: argparse.Namespace) -> None:
    """Range checks of ``--density`` / ``--snr`` with messages naming the flag."""
    if getattr(args, "density", None) is not None and not (math.isfinite(args.density) and 0.0 < args.density <= 1.0):
        raise ValueError(f"--density must be a fraction of RD cells in (0, 1], got {args.density}")
    if getattr(args, "snr", None) is not None and not (math.isfinite(args.snr) and args.snr > 0.0):
        raise ValueError(f"--snr must be a positive linear SNR threshold, got {args.snr}")


def run(args: argparse.Namespace) -> int:
    check_density_args(args)
    if args.out is None and args.sparse_rd_out is None:
        raise ValueError("nothing to write: give --out FILE.parquet and/or --sparse-rd-out DIR")
    common = dict(tau=args.snr, density=args.density, density_mode=args.density_mode, window=args.window,
                  guard=args.guard, split=args.split, batch_size=args.batch_size, device=args.device,
                  resume=not args.no_resume, progress=not args.quiet,
                  calibration_frames=args.calibration_frames)
    if args.out is not None:
        res = convert_dataset(args.root, args.out, enrich=parse_enrich(args.enrich), workers=args.workers,
                              chunk_frames=args.chunk_frames, **common)
        if res.path is not None:
            tau = "per frame" if res.tau is None else f"{res.tau:.6g}"
            rd = next((e for e in parse_enrich(args.enrich) if e.startswith("rd")), None)
            # the achieved (and target) density is that of the encoded set: S*(tau) with rdN, else S(tau)
            extra = "" if rd is None else \
                f" of S*(tau) with {rd} neighbourhoods; CFAR peaks S(tau) alone {res.peak_density:.5f}"
            print(f"wrote {res.path}: {res.n_frames} frames, {res.n_points} points, tau {tau}, "
                  f"achieved density {res.achieved_density:.5f}"
                  + (f" (target {args.density})" if args.density is not None else "") + extra
                  + f"; {res.chunks_converted} chunk(s) converted, {res.chunks_skipped} resumed")
    if args.sparse_rd_out is not None and dist_env().rank == 0:
        srd = write_sparse_rd(args.root, args.sparse_rd_out, **common)
        dens = "n/a (all frames existed)" if math.isnan(srd.achieved_density) else f"{srd.achieved_density:.5f}"
        print(f"wrote sparse-RD root {srd.root}: {srd.n_frames} frames ({srd.frames_written} written now), "
              f"achieved density {dens}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("pointcloud", help="RADIal root -> Parquet spectral point clouds (and/or sparse RD)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="RADIal-layout root (real or simulated)")
    p.add_argument("--out", metavar="FILE.parquet", default=None, help="point store to write")
    p.add_argument("--sparse-rd-out", metavar="DIR", default=None,
                   help="also write a RADIal-layout root whose RD cubes are masked to S(tau)")
    add_density_args(p)
    p.add_argument("--enrich", default="none", metavar="LIST",
                   help="comma-separated enrichments, e.g. rd3,sector32 (default none)")
    p.add_argument("--split", choices=("all", "train", "val", "test"), default="all",
                   help="frames to convert (default all)")
    p.add_argument("--batch-size", type=int, default=8, help="frames per forward pass (default 8)")
    p.add_argument("--chunk-frames", type=int, default=64,
                   help="frames per part file, the unit of resume and sharding (default 64)")
    p.add_argument("--calibration-frames", type=int, default=None,
                   help="per-dataset mode: train frames used to calibrate tau (default all)")
    p.add_argument("--workers", type=int, default=1, help="local processes sharing the chunks (default 1)")
    p.add_argument("--device", default=None,
                   help="torch device (default cuda:LOCAL_RANK if CUDA is available, else cpu)")
    p.add_argument("--no-resume", action="store_true", help="discard finished parts of an earlier run")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
