"""``radarpc show ROOT --frame N``: one frame's RD spectrum with its CFAR detections and its
spectral point cloud in bird's-eye view, beside the ground-truth vehicles.

Example::

    radarpc show data/sim_radial --frame 10 --density 0.057 --out frame10.png

Panels: (a) ``A(r, d) = sum_rx |R|`` in dB on the full Doppler axis with the encoded set marked
(``S(tau)``, or ``S*(tau)`` with an ``rdN`` enrichment: the replica bins of every point), (b) the
consolidated envelope ``E(r, l)`` in dB with the CFAR peaks ``P(tau)``, (c) the points in BEV (x forward, y left; drawn with left on the left) coloured by
radial velocity or by angle-spectrum amplitude, with the labelled vehicle centres. Range bin ``r``
is drawn centred on ``r * range_res_m`` (the points' ``range_m``) in both RD panels.

With ``--density-mode per-dataset`` tau is calibrated on the training split at every call (one
pass over the train cubes); :func:`plot_frame` takes ``tau=`` to reuse a calibrated value.
"""
from __future__ import annotations

import argparse

from radarpc.cli.pointcloud import add_density_args, check_density_args, parse_enrich, resolve_cfar_args
from radarpc.pipelines.pointclouds import ConvertSettings
from radarpc.viz import COLOR_BY, plot_frame

__all__ = ["add_parser", "run"]


def run(args: argparse.Namespace) -> int:
    check_density_args(args)
    settings = None
    if args.store is None:
        cfar = resolve_cfar_args(args)
        settings = ConvertSettings(tau=args.snr, density=args.density, density_mode=args.density_mode,
                                   enrich=parse_enrich(args.enrich), **cfar)
    out = args.out if args.out is not None else f"frame{args.frame}.png"
    res = plot_frame(args.root, args.frame, out, settings, store=args.store, color_by=args.color,
                     device=args.device if args.device is not None else "cpu")
    print(f"wrote {res.path}: frame {res.frame}, {res.n_peaks} CFAR peaks, {res.n_points} points, "
          f"tau {res.tau:.4g}, achieved density {res.density:.5f} (CFAR peaks S(tau) alone "
          f"{res.peak_density:.5f}), {res.n_vehicles} labelled vehicles")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("show", help="plot one frame: RD spectrum + CFAR cells + BEV point cloud",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="RADIal-layout root")
    p.add_argument("--frame", type=int, required=True, help="RADIal numSample of the frame")
    p.add_argument("--out", default=None, metavar="PNG", help="figure path (default frame{N}.png)")
    group = add_density_args(p)
    group.add_argument("--store", metavar="FILE.parquet", default=None,
                       help="plot the points of this point store (made from ROOT) instead of recomputing")
    p.add_argument("--enrich", default="none", metavar="LIST", help="enrichments, e.g. rd3 (default none)")
    p.add_argument("--color", choices=COLOR_BY, default="velocity", help="point colour (default velocity)")
    p.add_argument("--device", default=None, help="torch device (default cpu)")
    p.set_defaults(func=run)
