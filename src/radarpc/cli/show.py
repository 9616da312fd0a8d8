"""``radarpc show``: look at one frame of a RADIal or ColoRadar root, or at an OS-CFAR tuning search.

RADIal root (``labels.csv``)::

    radarpc show data/sim_radial --frame 10 --density 0.057 --out frame10.png

  (a) ``A(r, d) = sum_rx |R|`` in dB against Doppler in m/s (the cube's bin index on the top axis)
  with the encoded set marked (S(tau), or S*(tau) with an rdN enrichment: the replica bins of every
  point), (b) the consolidated envelope E(r, l) in dB with the CFAR peaks P(tau), against the
  consolidated Doppler in m/s (l on the top axis), (c) the points in bird's-eye view (x forward,
  y left, drawn with left on the left) coloured by radial velocity or by angle-spectrum amplitude,
  with the labelled vehicles as RADIal's 4 m x 1.8 m boxes (near edge centred on the label). tau
  is a linear SNR (power ratio); the title gives it in dB too. With --density-mode per-dataset tau
  is calibrated on the training split at every call (one pass over the train cubes).

ColoRadar root (``calib/`` and run folders)::

    radarpc show data/sim_coloradar --run lab_run2 --frame 3 --pred preds/oscfar --out colo3.png

  (a) the single-chip radar cube, max over elevation, in dB (range against azimuth), (b) the
  paired LiDAR scan in bird's-eye view (blue inside the radar frustum, grey outside) with the
  predicted cloud of --pred (red), (c) the same in side view. --frame is the radar (ADC) frame
  index in its run, as in a prediction folder; --run defaults to the first run.

OS-CFAR tuning search of ``radarpc baseline os-cfar``::

    radarpc show --tuning preds/oscfar --out tuning.png

  Mean Chamfer distance of every candidate against its threshold and against its cloud size
  (--tuning takes tuning.json or the prediction folder holding it).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from radarpc.runs import check_writable

__all__ = ["add_parser", "run"]


def _check_figure_path(out: str | Path) -> None:
    """Fail before any work when ``out`` is a folder, names no figure format by its suffix
    (:func:`radarpc.viz.figure_format`) or cannot be written."""
    from radarpc.viz import figure_format

    if Path(out).is_dir():
        raise IsADirectoryError(f"the figure path {out} is a directory; give the path of a .png file")
    figure_format(out)
    check_writable(out, "figure")


def _run_tuning(args: argparse.Namespace) -> int:
    from radarpc.cli.text import plural
    from radarpc.data.summary import read_tuning
    from radarpc.viz import plot_oscfar_tuning

    if args.root is not None or args.frame is not None or args.pred is not None:
        raise ValueError("--tuning draws the tuning search alone: give no ROOT, --frame or --pred with it")
    out = Path(args.out) if args.out is not None else Path("tuning.png")
    _check_figure_path(out)
    table = read_tuning(args.tuning)
    plot_oscfar_tuning(table, out)
    b = table.best
    print(f"wrote {out}: {plural(len(table.tau_db), 'OS-CFAR candidate')} on "
          f"{plural(table.n_frames, f'{table.split} frame')}; best "
          f"{table.setting[b]}, tau {table.tau_db[b]:g} dB: mean Chamfer {table.chamfer_m[b]:.3f} m, "
          f"{table.points_per_frame[b]:.0f} points per frame")
    return 0


def _run_coloradar(args: argparse.Namespace) -> int:
    from radarpc.cli.text import plural
    from radarpc.pipelines.frames import coloradar_view_with_prediction
    from radarpc.viz import plot_coloradar_view

    given = [f for f, v in (("--density", args.density), ("--snr", args.snr), ("--store", args.store)) if v is not None]
    if given:
        raise ValueError(f"{', '.join(given)} apply to RADIal roots; {args.root} is a ColoRadar root "
                         "(give --frame, optionally --run and --pred)")
    out = args.out if args.out is not None else (f"{args.run}_frame{args.frame}.png" if args.run
                                                 else f"frame{args.frame}.png")
    _check_figure_path(out)
    view = coloradar_view_with_prediction(args.root, args.frame, run=args.run, pred=args.pred)
    plot_coloradar_view(view, out)
    pred = "" if view.pred_xyz is None else f", {plural(len(view.pred_xyz), 'predicted point')} ({view.pred_label})"
    print(f"wrote {out}: run {view.run}, radar frame {view.radar_index}, LiDAR scan {view.lidar_index} "
          f"({len(view.inside_xyz)} of {plural(len(view.lidar_xyz), 'point')} in the radar frustum){pred}")
    return 0


def _run_radial(args: argparse.Namespace) -> int:
    from radarpc.cli.pointcloud import check_density_args, parse_enrich, resolve_cfar_args
    from radarpc.cli.text import plural
    from radarpc.pipelines.frames import frame_view
    from radarpc.pipelines.pointclouds import ConvertSettings
    from radarpc.viz import plot_frame_view

    if args.run is not None or args.pred is not None:
        raise ValueError(f"--run and --pred apply to ColoRadar roots; {args.root} is a RADIal root")
    if args.density is None and args.snr is None and args.store is None:
        raise ValueError("on a RADIal root give one of --density, --snr or --store")
    check_density_args(args)
    settings = None
    if args.store is None:
        cfar = resolve_cfar_args(args)
        settings = ConvertSettings(tau=args.snr, density=args.density, density_mode=args.density_mode,
                                   enrich=parse_enrich(args.enrich), **cfar)
    out = args.out if args.out is not None else f"frame{args.frame}.png"
    _check_figure_path(out)
    view = frame_view(args.root, args.frame, settings, store=args.store,
                      device=args.device if args.device is not None else "cpu")
    res = plot_frame_view(view, out, args.color)
    print(f"wrote {res.path}: frame {res.frame}, {plural(res.n_peaks, 'CFAR peak')}, "
          f"{plural(res.n_points, 'point')}, tau {res.tau:.4g} (linear SNR), achieved density {res.density:.5f} "
          f"(CFAR peaks S(tau) alone {res.peak_density:.5f}), {plural(res.n_vehicles, 'labelled vehicle')}")
    return 0


def run(args: argparse.Namespace) -> int:
    from radarpc.data.layout import root_layout

    if args.tuning is not None:
        return _run_tuning(args)
    if args.root is None:
        raise ValueError("give a dataset ROOT (RADIal or ColoRadar) with --frame, or --tuning FILE")
    if args.frame is None:
        raise ValueError("--frame is required with a dataset ROOT")
    return _run_radial(args) if root_layout(args.root) == "radial" else _run_coloradar(args)


def add_parser(sub) -> None:
    from radarpc.cli.pointcloud import add_density_args

    p = sub.add_parser("show", help="plot a RADIal or ColoRadar frame, or an OS-CFAR tuning search",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", nargs="?", default=None, help="dataset root: RADIal or ColoRadar layout")
    p.add_argument("--frame", type=int, default=None,
                   help="RADIal: numSample of the frame; ColoRadar: radar (ADC) frame index in its run")
    p.add_argument("--out", default=None, metavar="FILE",
                   help="figure path; its suffix picks the format (.png, .pdf, .svg, .jpg, ...; default "
                        "frame{N}.png, {run}_frame{N}.png with --run, tuning.png with --tuning)")
    colo = p.add_argument_group("ColoRadar roots")
    colo.add_argument("--run", default=None, help="run folder name (default: the first run)")
    colo.add_argument("--pred", default=None, metavar="FOLDER",
                      help="prediction folder (e.g. of radarpc baseline os-cfar): draw its cloud for this frame")
    colo.add_argument("--tuning", default=None, metavar="FILE",
                      help="draw the OS-CFAR tuning search of this tuning.json (or prediction folder) instead of a frame")
    group = add_density_args(p)
    group.required = False                  # RADIal roots only: checked in run()
    group.add_argument("--store", metavar="FILE.parquet", default=None,
                       help="plot the points of this point store (made from ROOT) instead of recomputing")
    p.add_argument("--enrich", default="none", metavar="LIST", help="enrichments, e.g. rd3 (default none)")
    p.add_argument("--color", choices=("velocity", "amplitude"), default="velocity",
                   help="point colour (default velocity)")
    p.add_argument("--device", default=None, help="torch device (default cpu)")
    p.set_defaults(func=run)
