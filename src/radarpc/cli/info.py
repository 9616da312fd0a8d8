"""``radarpc info ROOT``: what a dataset root holds (frames, sequences, splits, labels), a summary
plot, and with ``--check`` a scan of every file for missing or corrupt ones.

Nothing is written into the dataset root: the plot goes to ``./info_{root name}.png`` in the
current directory unless ``--plot PATH`` chooses another path or ``--no-plot`` skips it."""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarpc.data.radial import (
    SPLITS,
    CheckReport,
    LabelTable,
    check_root,
    find_fft_file,
    load_rd,
    read_labels,
    root_sensor,
    split_of_sequence,
    write_skip_file,
)
from radarpc.io import DataFileError, atomic_write
from radarpc.sensors.radial import DDMARadarConfig

__all__ = ["RadialSummary", "add_parser", "run", "summarize_radial", "format_summary", "plot_summary",
           "info_radial", "default_plot_path"]

_SPLITS = tuple(s for s in SPLITS if s != "all")   # the three disjoint splits


@dataclass(frozen=True)
class RadialSummary:
    """Counts and label ranges of a RADIal root (what ``radarpc info`` prints)."""

    root: Path
    sensor: DDMARadarConfig
    simulated: bool                            # has a sensor.json
    n_frames: int
    n_sequences: int
    split_frames: dict[str, int]               # frames per split (train/val/test)
    split_sequences: dict[str, int]            # sequences per split
    n_vehicles: int                            # label rows that are vehicles
    n_difficult: int                           # of which Difficult == 1
    n_empty_frames: int                        # frames without any vehicle
    range_m: tuple[float, float] | None        # min/max radar_R_m of vehicles
    azimuth_deg: tuple[float, float] | None    # min/max radar_A_deg
    doppler_mps: tuple[float, float] | None    # min/max radar_D


def summarize_radial(root: str | Path, labels: LabelTable | None = None) -> RadialSummary:
    """Summarize a RADIal root from its ``labels.csv`` and ``sensor.json`` (no cube is read)."""
    root = Path(root)
    sensor, meta = root_sensor(root)
    labels = labels if labels is not None else read_labels(root / "labels.csv")
    seq_of: dict[int, str] = {}
    for n, s in zip(labels.num_sample.tolist(), labels.dataset):
        seq_of.setdefault(int(n), s)
    names = sorted(set(seq_of.values()))
    n_seq = meta.n_sequences if meta is not None else None
    split_of = {s: split_of_sequence(s, names, n_sequences=n_seq) for s in names}
    split_frames = {k: 0 for k in _SPLITS}
    for s in seq_of.values():
        split_frames[split_of[s]] += 1
    split_sequences = {k: sum(1 for s in names if split_of[s] == k) for k in _SPLITS}
    veh = labels.has_vehicle
    frames_with = set(labels.num_sample[veh].tolist())

    def span(col: str) -> tuple[float, float] | None:
        v = labels.column(col)[veh]
        return (float(v.min()), float(v.max())) if v.size else None

    return RadialSummary(
        root=root, sensor=sensor, simulated=meta is not None, n_frames=len(seq_of),
        n_sequences=len(names), split_frames=split_frames, split_sequences=split_sequences,
        n_vehicles=int(veh.sum()), n_difficult=int((labels.difficult[veh] == 1).sum()),
        n_empty_frames=len(seq_of) - len(frames_with),
        range_m=span("radar_R_m"), azimuth_deg=span("radar_A_deg"), doppler_mps=span("radar_D"))


def format_summary(s: RadialSummary) -> str:
    """The text ``radarpc info`` prints for a RADIal root."""
    def rng(v: tuple[float, float] | None, unit: str) -> str:
        return "-" if v is None else f"{v[0]:.2f} .. {v[1]:.2f} {unit}"

    c = s.sensor
    lines = [
        f"root:        {s.root} (RADIal layout, {'simulated' if s.simulated else 'real: no sensor.json'})",
        f"sensor:      {c.name}  RD {c.n_range} x {c.n_doppler} x {c.n_rx}, {c.n_tx} Tx DDMA, "
        f"{c.range_res_m:.4f} m/bin, {c.velocity_res_mps:.4f} m/s/bin",
        f"frames:      {s.n_frames}",
        f"sequences:   {s.n_sequences}",
        "splits:      " + ", ".join(f"{k} {s.split_frames[k]} frames / {s.split_sequences[k]} seq"
                                   for k in _SPLITS),
        f"vehicles:    {s.n_vehicles} labels ({s.n_difficult} difficult)",
        f"empty:       {s.n_empty_frames} frames without vehicles",
        f"range:       {rng(s.range_m, 'm')}",
        f"azimuth:     {rng(s.azimuth_deg, 'deg')}",
        f"velocity:    {rng(s.doppler_mps, 'm/s')}",
    ]
    for k in _SPLITS:
        if s.split_frames[k] == 0:
            rule = ("simulated sequences: the last is test and the one before it val when there are at "
                    "least 3" if s.simulated else "real sequences: RADIal's official val/test lists")
            lines.append(f"warning:     split {k!r} is empty ({s.n_sequences} sequence(s); {rule}); "
                         f"RADIal(root, split={k!r}) raises, use random_split or more sequences")
    return "\n".join(lines)


def plot_summary(root: str | Path, labels: LabelTable, sensor: DDMARadarConfig, out: str | Path) -> Path:
    """Write a 2 x 2 summary figure (PNG, atomic): range and azimuth histograms of the vehicles,
    their bird's-eye positions, and the RD envelope (dB, mean power over Rx) of the first frame
    whose cube loads."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    root, out = Path(root), Path(out)
    veh = labels.has_vehicle
    r, a = labels.column("radar_R_m")[veh], labels.column("radar_A_deg")[veh]
    x, y = labels.column("radar_X_m")[veh], labels.column("radar_Y_m")[veh]
    fig, ax = plt.subplots(2, 2, figsize=(11, 8))
    r_top = max(sensor.max_range_m, float(r.max()) if r.size else 0.0)
    ax[0, 0].hist(r, bins=40, range=(0.0, r_top), color="C0")
    ax[0, 0].set(xlabel="radar_R_m [m]", ylabel="vehicles", title="range of labels")
    ax[0, 1].hist(a, bins=36, range=(-90.0, 90.0), color="C1")
    ax[0, 1].set(xlabel="radar_A_deg [deg]", ylabel="vehicles", title="azimuth of labels")
    ax[1, 0].scatter(y, x, s=4, alpha=0.5)
    ax[1, 0].set(xlabel="radar_Y_m [m] (left +)", ylabel="radar_X_m [m] (forward)", title="vehicles, BEV")
    ax[1, 0].invert_xaxis()  # left of the car on the left of the plot
    ax[1, 0].set_aspect("equal", adjustable="datalim")
    env, shown = None, None
    for num in np.unique(labels.num_sample).tolist():
        try:
            cube = load_rd(find_fft_file(root, num), sensor)      # (R, D, Rx)
        except DataFileError:
            continue
        env = 10.0 * np.log10(np.mean(np.abs(cube) ** 2, axis=2) + 1e-30)  # (R, D) dB
        shown = num
        break
    if env is None:
        ax[1, 1].text(0.5, 0.5, "no readable RD cube", ha="center", va="center")
        ax[1, 1].set_axis_off()
    else:
        im = ax[1, 1].imshow(env, aspect="auto", origin="lower", cmap="viridis",
                             extent=(0, sensor.n_doppler, 0, sensor.max_range_m))
        fig.colorbar(im, ax=ax[1, 1], label="dB")
        ax[1, 1].set(xlabel="Doppler bin", ylabel="range [m]", title=f"RD envelope, frame {shown}")
    fig.suptitle(f"{root.name}: {len(np.unique(labels.num_sample))} frames, {int(veh.sum())} vehicles")
    fig.tight_layout()
    with atomic_write(out, "wb") as f:
        fig.savefig(f, format="png", dpi=90)
    plt.close(fig)
    return out


def _print_check(report: CheckReport, write_skip: str | None) -> int:
    print(report.format())
    if write_skip is not None:
        write_skip_file(write_skip, report.bad_frames)
        print(f"skip list:   {len(report.bad_frames)} frame(s) written to {write_skip}")
    return 0 if report.ok else 1


def default_plot_path(root: str | Path) -> Path:
    """``./info_{root name}.png`` in the current directory (the dataset root is never written)."""
    return Path.cwd() / f"info_{Path(root).resolve().name}.png"


def info_radial(args: argparse.Namespace) -> int:
    """``radarpc info`` on a RADIal root. Returns 1 if ``--check`` found a bad file, else 0."""
    root = Path(args.root)
    check = bool(args.check or args.write_skip)
    try:
        labels = read_labels(root / "labels.csv")
        summary = summarize_radial(root, labels)
    except DataFileError:
        if not check:
            raise
        return _print_check(check_root(root), args.write_skip)  # lists the bad labels.csv / sensor.json
    print(format_summary(summary))
    if not args.no_plot:
        out = Path(args.plot) if args.plot else default_plot_path(root)
        plot_summary(root, labels, summary.sensor, out)
        print(f"plot:        {out}")
    if check:
        return _print_check(check_root(root, progress=True), args.write_skip)
    return 0


def run(args: argparse.Namespace) -> int:
    """Dispatch on the kind of root: RADIal (``labels.csv``) or ColoRadar (``calib/``)."""
    root = Path(args.root)
    if not root.is_dir():
        raise DataFileError(root, "dataset root folder is missing")
    if (root / "labels.csv").is_file():
        return info_radial(args)
    if (root / "calib").is_dir():
        from radarpc.cli.info_coloradar import info_coloradar
        return info_coloradar(args)
    raise DataFileError(root, "is neither a RADIal root (labels.csv, radar_FFT/, radar_Freespace/) "
                              "nor a ColoRadar root (calib/ and sequence folders)")


def add_parser(sub) -> None:
    p = sub.add_parser("info", help="summarize a dataset root; --check scans it for bad files",
                       description=__doc__)
    p.add_argument("root", help="dataset root (RADIal or ColoRadar layout)")
    p.add_argument("--check", action="store_true",
                   help="open and validate every file; list each bad or missing one (exit code 1 if any)")
    p.add_argument("--write-skip", metavar="FILE", default=None,
                   help="write the numSample of every bad frame to FILE, one per line (implies --check); "
                        "pass it to RADIal(skip=FILE)")
    p.add_argument("--plot", metavar="PATH", default=None,
                   help="summary plot path (default ./info_{root name}.png in the current directory; "
                        "nothing is written into the dataset root)")
    p.add_argument("--no-plot", action="store_true", help="do not write the summary plot")
    p.set_defaults(func=run)
