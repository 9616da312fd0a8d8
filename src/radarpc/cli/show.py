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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from radarpc.cli.pointcloud import add_density_args, check_density_args, parse_enrich, resolve_cfar_args
from radarpc.data.pointstore import PointStore
from radarpc.data.radial import RADIal
from radarpc.data.radial_format import LABEL_TENSOR_COLUMNS
from radarpc.dsp.convert import ConvertSettings, build_point_cloud, calibrate_tau
from radarpc.io import atomic_write
from radarpc.machine import check_device

__all__ = ["FramePlot", "plot_frame", "rd_extent", "peak_marker_range_m", "add_parser", "run"]

COLOR_BY = ("velocity", "amplitude")


@dataclass(frozen=True)
class FramePlot:
    """What :func:`plot_frame` drew."""

    path: Path               # the PNG
    frame: int               # RADIal numSample
    n_points: int            # points of the cloud
    n_peaks: int             # consolidated CFAR peaks |P(tau)|
    density: float           # density of the encoded set: |S*(tau)| / (Nr * ND) with rdN, else |S(tau)| / (Nr * ND)
    tau: float               # threshold used
    n_vehicles: int          # labelled vehicles drawn
    peak_density: float = float("nan")   # |S(tau)| / (Nr * ND), CFAR peaks alone


def rd_extent(cfg, n_cols: int) -> tuple[float, float, float, float]:
    """``imshow`` extent of an ``(Nr, n_cols)`` RD image (origin lower): row ``r`` spans
    ``[(r - 0.5) res, (r + 0.5) res]``, centred on ``r * res`` = the points' ``range_m``."""
    res = cfg.range_res_m
    return (-0.5, n_cols - 0.5, -0.5 * res, (cfg.n_range - 0.5) * res)


def peak_marker_range_m(cfg, range_bin: np.ndarray) -> np.ndarray:
    """Vertical position of the CFAR-peak markers: ``r * res``, as ``range_m`` and :func:`rd_extent`."""
    return np.asarray(range_bin, dtype=np.float64) * cfg.range_res_m


def plot_frame(root: str | Path, frame: int, out: str | Path, settings: ConvertSettings | None = None, *,
               store: str | Path | None = None, color_by: str = "velocity",
               device: torch.device | str = "cpu", tau: float | None = None) -> FramePlot:
    """Draw frame ``frame`` (numSample) of ``root`` to ``out`` (PNG, atomic, matplotlib Agg).

    Parameters
    ----------
    root : path-like
        RADIal-layout root.
    frame : int
        RADIal numSample of the frame.
    out : path-like
        PNG to write.
    settings : ConvertSettings, optional
        Threshold or density, enrichments and CFAR geometry (``split`` is ignored: any frame of
        the root can be shown; per-dataset mode calibrates on the training split at every call
        unless ``tau`` is given).
    store : path-like, optional
        Instead of ``settings``: a point store made from ``root``; the points are read from it
        and the CFAR panels use its CFAR geometry and the frame's stored threshold.
    color_by : {"velocity", "amplitude"}
    device : torch.device or str
    tau : float, optional
        Per-dataset mode: the tau already calibrated (e.g. ``ConvertResult.tau`` or a store's
        ``metadata.tau``), so that plotting many frames does not recalibrate each time.
    """
    if color_by not in COLOR_BY:
        raise ValueError(f"color_by must be one of {COLOR_BY}, got {color_by!r}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    root, out = Path(root), Path(out)
    if out.is_dir():
        raise IsADirectoryError(f"the figure path {out} is a directory; give the path of a .png file")
    if (settings is None) == (store is None):
        raise ValueError("give exactly one of settings (a threshold or density) and store (a point store)")
    ds = RADIal(root, split="all")
    try:
        i = ds.index_of(int(frame))
    except KeyError:
        raise ValueError(f"frame {frame} is not in {root} (numSample from {ds.frame_ids[0] if ds.frame_ids else '-'} "
                         f"to {ds.frame_ids[-1] if ds.frame_ids else '-'})") from None
    rd, labels, _ = ds[i]
    dev = check_device(device)
    stored = None
    if store is not None:
        pstore = PointStore(store)
        stored = pstore[pstore.index_of(int(frame))] if int(frame) in pstore.frames else None
        if stored is None:
            raise ValueError(f"frame {frame} is not in the point store {store}")
        m = pstore.metadata
        made_from = Path(m.source_root) if m.source_root else None
        # a store made from a root records its resolved path (one made from a dataset object its
        # repr): refuse it over another root that still exists beside its own
        if (made_from is not None and made_from.is_absolute() and made_from.is_dir()
                and made_from.resolve() != root.resolve()):
            raise ValueError(f"the point store {store} was made from {m.source_root}, not from {root}: "
                             f"its points would be drawn over another dataset's spectrum")
        settings = ConvertSettings(tau=float(stored.tau[0]), enrich=m.enrich, window=m.window, guard=m.guard,
                                   envelope=m.envelope)
    if settings.mode == "per-dataset":
        tau = calibrate_tau(root, settings, device=dev) if tau is None else float(tau)
    else:
        tau = settings.tau
    spc = build_point_cloud(ds, settings, tau, dev)
    cfg = ds.sensor
    rd_b = rd.unsqueeze(0).to(dev)                                          # (1, Nr, Nd, Nrx)
    with torch.no_grad():
        env, cfar, peaks = spc.detect(rd_b)                                 # (1, Nr, W) each
        cloud = spc(rd_b) if stored is None else stored
    from radarpc.dsp.ddma import replica_bins, rx_magnitude_sum

    full = rx_magnitude_sum(rd_b)[0].cpu().numpy()                          # (Nr, Nd)
    # the encoded set: every point's range bin x the n_tx replica bins of its Tx-0 Doppler bin
    mask_t = torch.zeros(cfg.n_range, cfg.n_doppler, dtype=torch.bool)
    bins = replica_bins(cfg, cloud.doppler_full.cpu())                      # (N, n_tx)
    mask_t[cloud.range_bin.cpu().long()[:, None].expand_as(bins), bins] = True
    mask_full = mask_t.numpy()                                              # (Nr, Nd) bool
    set_name = "S*(tau)" if settings.point_cloud_config().neighbourhood is not None else "S(tau)"
    e = env[0].cpu().numpy()                                                # (Nr, W)
    pk = peaks[0].cpu().numpy()                                             # (Nr, W) bool
    tau_used = float(cloud.tau[0])
    density = float(cloud.density[0])
    x, y = cloud.x.cpu().numpy(), cloud.y.cpu().numpy()
    if color_by == "velocity":
        cval = cloud.velocity_mps.cpu().numpy()
    else:  # Ae in dB: amplitudes span decades
        cval = 20.0 * np.log10(np.maximum(cloud.amplitude.cpu().numpy(), 1e-30))
    lab = labels.cpu().numpy()
    gx = lab[:, LABEL_TENSOR_COLUMNS.index("radar_X_m")]
    gy = lab[:, LABEL_TENSOR_COLUMNS.index("radar_Y_m")]

    def db(a: np.ndarray) -> np.ndarray:
        return 20.0 * np.log10(np.maximum(a, 1e-12 * max(float(a.max()), 1e-30)))  # magnitudes -> dB

    fig, ax = plt.subplots(1, 3, figsize=(17, 6.5), gridspec_kw={"width_ratios": [1.4, 0.8, 1.4]})
    rmax = cfg.max_range_m
    im0 = ax[0].imshow(db(full), aspect="auto", origin="lower", cmap="viridis",
                       extent=rd_extent(cfg, cfg.n_doppler))
    # S(tau) as an exact per-cell overlay (markers would hide the spectrum on a 512 x 256 grid)
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    ax[0].imshow(np.ma.masked_where(~mask_full, mask_full.astype(float)), aspect="auto", origin="lower",
                 cmap=ListedColormap(["red"]), alpha=0.85, interpolation="nearest",
                 extent=rd_extent(cfg, cfg.n_doppler))
    ax[0].legend(handles=[Patch(color="red", label=f"{set_name}: {int(mask_full.sum())} cells")],
                 loc="upper right", fontsize=8)
    ax[0].set(xlabel="Doppler bin (full axis)", ylabel="range [m]",
              title=f"sum_rx |R| [dB], frame {frame}")
    fig.colorbar(im0, ax=ax[0], label="dB")
    im1 = ax[1].imshow(db(e), aspect="auto", origin="lower", cmap="magma",
                       extent=rd_extent(cfg, cfg.slot_width))
    pr, pl = np.nonzero(pk)
    ax[1].scatter(pl, peak_marker_range_m(cfg, pr), s=8, marker="x", c="cyan", linewidths=0.6,
                  label=f"P(tau): {int(pk.sum())} peaks")
    ax[1].set(xlabel="consolidated Doppler l", ylabel="range [m]", title="envelope E(r, l) [dB] + CFAR")
    ax[1].legend(loc="upper right", fontsize=8)
    fig.colorbar(im1, ax=ax[1], label="dB")
    if color_by == "velocity":  # symmetric colour scale: white = 0 m/s
        vmax = max(float(np.abs(cval).max()) if cval.size else 0.0, cfg.velocity_res_mps)
        sc = ax[2].scatter(y, x, c=cval, s=5, cmap="coolwarm", vmin=-vmax, vmax=vmax)
    else:
        sc = ax[2].scatter(y, x, c=cval, s=5, cmap="viridis")
    fig.colorbar(sc, ax=ax[2], label="radial velocity [m/s]" if color_by == "velocity" else "amplitude Ae [dB]")
    ax[2].scatter(gy, gx, s=140, marker="s", facecolors="none", edgecolors="k", linewidths=1.5,
                  label=f"labelled vehicles ({len(gx)})")
    ax[2].set(xlabel="y [m] (left +)", ylabel="x [m] (forward)",
              title=f"BEV: {len(x)} points, density {density:.4f}, tau {tau_used:.3g}")
    # lateral half-width: every point and label, and at least 40 % of the range (a readable panel)
    half = max(0.4 * rmax, 1.05 * float(np.abs(np.concatenate([y, gy])).max()) if len(y) + len(gy) else 0.0)
    ax[2].set_xlim(min(half, rmax), -min(half, rmax))  # left of the car drawn on the left
    ax[2].set_ylim(0.0, rmax)
    ax[2].set_aspect("equal")
    ax[2].legend(loc="upper left", fontsize=7, framealpha=0.6)
    fig.suptitle(f"{root.name}, frame {frame} ({ds.sequences[i]})")
    fig.tight_layout()
    with atomic_write(out, "wb") as f:
        fig.savefig(f, format="png", dpi=80)
    plt.close(fig)
    peak_density = float(pk.sum()) * cfg.n_tx / (cfg.n_range * cfg.n_doppler)
    return FramePlot(path=out, frame=int(frame), n_points=int(len(x)), n_peaks=int(pk.sum()),
                     density=density, tau=tau_used, n_vehicles=int(len(gx)), peak_density=peak_density)


def run(args: argparse.Namespace) -> int:
    check_density_args(args)
    settings = None
    if args.store is None:
        cfar = resolve_cfar_args(args)
        settings = ConvertSettings(tau=args.snr, density=args.density, density_mode=args.density_mode,
                                   enrich=parse_enrich(args.enrich), window=cfar.window, guard=cfar.guard,
                                   envelope=cfar.envelope)
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
