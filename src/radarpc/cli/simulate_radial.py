"""``radarpc simulate radial``: write a simulated dataset in RADIal's on-disk layout."""
from __future__ import annotations

import argparse

from radarpc.cli.options import RADIAL_SENSOR_NAMES

__all__ = ["add_parser", "run"]


def _scenes(text: str):
    """``--scenes`` value -> SceneMix (argparse reports a bad name with the known ones)."""
    from radarpc.sim.scenes import scene_mix

    try:
        return scene_mix(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_parser(kinds) -> argparse.ArgumentParser:
    """Register ``radial`` on the ``simulate`` sub-command's parsers; sets ``func``."""
    p = kinds.add_parser(
        "radial", help="RADIal layout: radar_FFT, radar_Freespace, labels.csv (resumable)",
        description="Simulate procedural road sequences seen by the RADIal-like DDMA radar and write "
                    "them in RADIal's layout. Rerunning on a partial output of the same sensor, seed, "
                    "sizes and scene resumes it: frames whose cube or freespace PNG does not load and "
                    "validate are regenerated; --overwrite starts over.")
    p.add_argument("--out", required=True, help="dataset root to write")
    p.add_argument("--sequences", type=int, default=6, help="number of sequences (default 6)")
    p.add_argument("--frames-per-sequence", type=int, default=50, help="frames per sequence (default 50)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    p.add_argument("--sensor", choices=sorted(RADIAL_SENSOR_NAMES), default="radial",
                   help="sensor config (default radial: 512 x 256 x 16 cubes)")
    p.add_argument("--overwrite", action="store_true",
                   help="start over: delete the dataset files of a non-empty folder (even a matching "
                        "partial run) and simulate every frame again")
    p.add_argument("--device", default="cpu", help="synthesis device, e.g. cpu or cuda (default cpu)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--cube-format", choices=("npy", "npz"), default="npy",
                   help="radar_FFT/fft_*.npy (default; FFTRadNet's loader) or .npz holding arr_0 (RADIal's "
                        "ready-to-use release, its loader/dataset.py)")
    p.add_argument("--no-camera", action="store_true",
                   help="do not write camera/image_*.jpg (the label columns x1_pix..y2_pix are filled anyway)")
    p.add_argument("--no-laser", action="store_true", help="do not write laser_PCL/pcl_*.npy")
    p.add_argument("--scenes", type=_scenes, default=None, metavar="NAMES",
                   help="scene presets, comma-separated from city, countryside, highway (default all three "
                        "in RADIal's proportions of frames: 31 / 32 / 38 %%; a subset keeps their relative "
                        "shares); one preset per sequence")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Write the dataset described by ``args``; returns the exit code."""
    from radarpc.cli.text import plural
    from radarpc.machine import check_device
    from radarpc.sensors.radial import radial_sensor
    from radarpc.sim.radial_writer import write_radial_dataset

    cfg = radial_sensor(args.sensor)
    check_device(args.device, "--device")
    counts = {}
    root = write_radial_dataset(args.out, cfg, args.sequences, args.frames_per_sequence, args.seed,
                                overwrite=args.overwrite, progress=not args.no_progress,
                                device=args.device, on_finish=lambda w, k: counts.update(written=w, kept=k),
                                cube_format=args.cube_format, camera=not args.no_camera, laser=not args.no_laser,
                                scenes=args.scenes)
    n = args.sequences * args.frames_per_sequence
    print(f"{root}: {plural(n, 'frame')} ({plural(args.sequences, 'sequence')} x {args.frames_per_sequence}) "
          f"of sensor {cfg.name!r} {cfg.rd_shape}; {counts['written']} simulated now, {counts['kept']} kept from "
          f"an earlier run")
    return 0
