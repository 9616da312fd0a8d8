"""``radarpc pointcloud ROOT``: convert a RADIal root into a Parquet store of spectral point
clouds (``--out``) and/or a sparse-RD root masked to the same detected set (``--sparse-rd-out``).

Examples::

    radarpc pointcloud data/sim_radial --density 0.057 --enrich rd3,sector32 --out data/pc057.parquet
    radarpc pointcloud data/sim_radial --snr 1.585 --out data/pc_2db.parquet
    radarpc pointcloud data/radial --snr 1.585 --cfar radial --out data/pc_rpl.parquet   # RADIal rpl.py
    radarpc pointcloud data/sim_radial --density 0.057 --density-mode per-dataset \\
        --sparse-rd-out data/sim_radial_srd057
    torchrun --nproc-per-node 4 -m radarpc pointcloud data/radial --density 0.057 --out pc.parquet

A killed conversion resumes when the same command is run again (``--no-resume`` starts over).
An existing --out or --sparse-rd-out made with other settings is refused unless ``--overwrite``
(the same command on changed source files converts again); a second conversion to the same
output while one runs is refused.
Under torchrun each rank converts its share of the chunks (on ``cuda:LOCAL_RANK`` when CUDA is
available) and rank 0 merges; ``--sparse-rd-out`` is written by rank 0 alone.

CFAR geometry: ``--window`` / ``--guard`` are *full* odd side lengths (the paper's default: 9 x 9
window, 3 x 3 guard). RADIal's ``rpl.py`` writes ``(9, 9, 3, 3)`` as *half* widths, i.e. ``--window 19,19 --guard
7,7``, sums every DDMA slot into its envelope (``--envelope all-slots``) and thresholds at 2 dB
(``--snr 1.585``), a value chosen for that geometry; ``--cfar radial`` selects the first two.
"""
from __future__ import annotations

import argparse
import math
import sys

# The parsers use torch-free copies of the choices (`radarpc --help` imports no torch); the
# library is imported inside the functions that run a command.
from radarpc.cli.options import BEAMFORMING_MODES, CFAR_PRESET_NAMES, DEFAULT_WAIT_S, ENVELOPES

__all__ = ["add_parser", "run", "parse_pair", "parse_enrich", "add_density_args", "check_density_args",
           "resolve_cfar_args"]


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
    """Add the threshold and CFAR options shared by ``pointcloud`` and ``show``; returns the
    required mutually exclusive group (``--density`` | ``--snr``) so that a command can add to it."""
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--density", type=_fraction, metavar="D",
                   help="target density |S(tau)| / (Nr * ND) in (0, n_tx / n_slots] (0.75 for RADIal), e.g. "
                        "0.057 (RADIal's default); with an rdN enrichment the density of the enlarged set "
                        "|S*(tau)| / (Nr * ND)")
    g.add_argument("--snr", type=_fraction, metavar="TAU",
                   help="fixed linear CFAR SNR threshold tau (> 0), e.g. 1.585 (= 2 dB, RADIal rpl.py's "
                        "threshold, chosen for its CFAR geometry: rpl.py's (9,9,3,3) are half widths, i.e. "
                        "--window 19,19 --guard 7,7, with the all-slot envelope; --cfar radial sets both)")
    p.add_argument("--density-mode", choices=("per-frame", "per-dataset"), default="per-frame",
                   help="with --density: a tau per frame, or one tau calibrated on the train split "
                        "(default per-frame)")
    p.add_argument("--window", type=parse_pair, default=None, metavar="R,D",
                   help="CA-CFAR training window, full odd side lengths (default 9,9; RADIal rpl.py: 19,19)")
    p.add_argument("--guard", type=parse_pair, default=None, metavar="R,D",
                   help="CA-CFAR guard window, full odd side lengths (default 3,3; RADIal rpl.py: 7,7)")
    p.add_argument("--beamforming", choices=BEAMFORMING_MODES, default="auto",
                   help="how each point's direction is found; all give the same points: 'exact' "
                        "(whole float32 spectrum), 'screened' (bf16 GEMM screen with a rigorous error "
                        "bound, survivors evaluated exactly; fast where the CPU multiplies bf16 natively), "
                        "'subspace' (certified block low-rank screen, survivors evaluated exactly), 'auto' "
                        "(default: whichever of the three a one-off timing on this device and grid finds "
                        "fastest; exact when sector descriptors are asked for or RADARPC_NO_NATIVE=1)")
    p.add_argument("--envelope", choices=ENVELOPES, default=None,
                   help="RD envelope: 'replicas' = sum over the n_tx replica bins of each consolidated cell "
                        "(the spectral point-cloud paper's eq. 1, default); 'all-slots' = RADIal rpl.py, sum over every DDMA slot "
                        "including the empty ones")
    p.add_argument("--cfar", choices=CFAR_PRESET_NAMES, default=None,
                   help="preset: 'radial' = RADIal rpl.py's processing, --window 19,19 --guard 7,7 "
                        "--envelope all-slots (use with --snr 1.585)")
    return g


def resolve_cfar_args(args: argparse.Namespace) -> dict:
    """``window``, ``guard`` and ``envelope`` of the point-cloud config from the command line: the
    ``--cfar`` preset (:data:`radarpc.dsp.pointcloud.CFAR_PRESETS`), which explicit
    ``--window/--guard/--envelope`` must not contradict; without a preset the explicit values or
    the config's defaults."""
    from radarpc.dsp.pointcloud import CFAR_PRESETS, SpectralPointCloudConfig

    defaults = SpectralPointCloudConfig()
    preset = getattr(args, "cfar", None)
    base = CFAR_PRESETS[preset] if preset is not None else {k: getattr(defaults, k) for k in ("window", "guard", "envelope")}
    explicit = {k: getattr(args, k, None) for k in ("window", "guard", "envelope")}
    if preset is not None:
        clash = [f"--{k} {v}" for k, v in explicit.items() if v is not None and v != base[k]]
        if clash:
            raise ValueError(f"--cfar {preset} sets window {base['window']}, guard {base['guard']}, envelope "
                             f"{base['envelope']!r}; it contradicts {', '.join(clash)}")
    return {k: explicit[k] or base[k] for k in base}


def check_density_args(args: argparse.Namespace) -> None:
    """Range checks of ``--density`` / ``--snr`` (the library's checks), messages naming the flag."""
    from radarpc.dsp.cfar import check_tau
    from radarpc.dsp.density import check_density_value

    for flag, attr, check in (("--density", "density", check_density_value), ("--snr", "snr", check_tau)):
        v = getattr(args, attr, None)
        if v is not None:
            try:
                check(v)
            except ValueError as e:
                raise ValueError(f"{flag}: {e}") from None


# A per-frame density target missed by more than this (relative) is reported on stderr.
DENSITY_WARN_REL = 0.25


def density_warning(target: float | None, achieved: float, enrich: tuple[str, ...]) -> str | None:
    """A warning when the mean achieved density is far from the target (``None`` otherwise).

    Thresholds move the encoded set in steps: one CFAR peak adds ``n_tx`` cells, and with an
    ``rdN`` enrichment up to ``n^2 n_tx``, so a small sensor cannot hit a small target closely.
    """
    if target is None or not math.isfinite(achieved):
        return None
    off = abs(achieved - target) / target
    if off <= DENSITY_WARN_REL:
        return None
    rd = next((e for e in enrich if e.startswith("rd")), None)
    why = (f"with {rd}, each CFAR peak adds up to {rd[2:]}x{rd[2:]} neighbourhood cells, so the encoded set "
           f"grows in coarse steps on this sensor" if rd is not None else
           "each CFAR peak adds n_tx cells, so the set grows in steps")
    return (f"warning: the achieved density {achieved:.5f} is {100 * off:.0f} % off the target {target} ({why}); "
            f"a larger sensor, a larger target or a fixed --snr threshold gives a closer density")


def run(args: argparse.Namespace) -> int:
    from radarpc.cli.text import plural
    from radarpc.distributed import dist_env
    from radarpc.pipelines.pointclouds import ConvertSettings, convert_dataset
    from radarpc.pipelines.sparse_rd import write_sparse_rd
    from radarpc.runs import check_writable

    check_density_args(args)
    cfar = resolve_cfar_args(args)
    if args.out is None and args.sparse_rd_out is None:
        raise ValueError("nothing to write: give --out FILE.parquet and/or --sparse-rd-out DIR")
    enrich = parse_enrich(args.enrich)
    # One config, validated once, passed whole to both writers.
    settings = ConvertSettings(tau=args.snr, density=args.density, density_mode=args.density_mode,
                               enrich=enrich, **cfar,
                               split=args.split, chunk_frames=args.chunk_frames,
                               calibration_frames=args.calibration_frames, beamforming=args.beamforming)
    # Both outputs are checked before any work: a store must not be written when the sparse
    # root cannot be.
    for path, what in ((args.out, "point store"), (args.sparse_rd_out, "sparse-RD root")):
        if path is not None:
            check_writable(path, what)
    run_args = dict(batch_size=args.batch_size, device=args.device, resume=not args.no_resume,
                    progress=not args.quiet, overwrite=args.overwrite)
    calibrated = None
    if args.out is not None:
        res = convert_dataset(args.root, args.out, settings, workers=args.workers,
                              wait_timeout_s=args.wait_timeout, **run_args)
        calibrated = res.tau if args.density is not None and args.density_mode == "per-dataset" else None
        if res.path is not None:
            tau = "per frame" if res.tau is None else f"{res.tau:.6g}"
            rd = next((e for e in enrich if e.startswith("rd")), None)
            # the achieved (and target) density is that of the encoded set: S*(tau) with rdN, else S(tau)
            extra = "" if rd is None else \
                f" of S*(tau) with {rd} neighbourhoods; CFAR peaks S(tau) alone {res.peak_density:.5f}"
            head = (f"{res.path} already holds this conversion (nothing to do)" if res.already_finished else
                    f"wrote {res.path}: {plural(res.n_frames - res.frames_reused, 'frame')} converted now, "
                    f"{res.frames_reused} reused from an earlier run")
            print(f"{head}; {plural(res.n_frames, 'frame')}, {plural(res.n_points, 'point')}, tau {tau}, "
                  f"achieved density {res.achieved_density:.5f}"
                  + (f" (target {args.density})" if args.density is not None else "") + extra
                  + f"; parts of {plural(res.chunk_frames, 'frame')}: {res.chunks_converted} converted, "
                  f"{res.chunks_skipped} reused")
            warn = density_warning(args.density, res.achieved_density, enrich)
            if warn is not None:
                print(warn, file=sys.stderr)
    if args.sparse_rd_out is not None and dist_env().rank == 0:
        srd = write_sparse_rd(args.root, args.sparse_rd_out, settings, calibrated_tau=calibrated, **run_args)
        # the mean over every frame of the root, kept ones included (sparse_rd.json's mean_density)
        print(f"wrote sparse-RD root {srd.root}: {plural(srd.n_frames, 'frame')} ({srd.frames_written} written "
              f"now), achieved density {srd.achieved_density:.5f} (per-frame taus and densities in sparse_rd.json)")
        if args.out is None:                                  # else the store's line warned already
            warn = density_warning(args.density, srd.achieved_density, enrich)
            if warn is not None:
                print(warn, file=sys.stderr)
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("pointcloud", help="RADIal root -> Parquet spectral point clouds (and/or sparse RD)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="RADIal-layout root (real or simulated)")
    p.add_argument("--out", metavar="FILE.parquet", default=None, help="point store to write")
    p.add_argument("--sparse-rd-out", metavar="DIR", default=None,
                   help="also write a RADIal-layout root whose RD cubes are masked to exactly the set the "
                        "point store encodes: S(tau), or S*(tau) with an rdN enrichment (the replica bins of "
                        "the n x n neighbourhoods), with the same envelope, CFAR and per-frame taus "
                        "(recorded with the achieved densities in DIR/sparse_rd.json); cubes are stored "
                        "compressed (radar_FFT/fft_*.npz), so the root's size follows the density")
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
    p.add_argument("--workers", type=int, default=1,
                   help="local processes sharing the chunks (default 1); chunks are shrunk when there are "
                        "fewer than processes")
    p.add_argument("--wait-timeout", type=float, default=DEFAULT_WAIT_S, metavar="SECONDS",
                   help="under torchrun without a process group: how long ranks wait for each other's "
                        f"files (default {DEFAULT_WAIT_S:.0f} s)")
    p.add_argument("--device", default=None,
                   help="torch device (default cuda:LOCAL_RANK if CUDA is available, else cpu)")
    p.add_argument("--no-resume", action="store_true",
                   help="compute every frame again instead of reusing an earlier run's finished parts or store")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out (or --sparse-rd-out) that holds another conversion (other "
                        "settings or source) or another file; without it such an output is refused")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
