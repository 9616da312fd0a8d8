"""``radarpc info ROOT``: what a dataset root holds (frames, sequences, splits, labels), a summary
plot, and with ``--check`` a scan of every file for missing or corrupt ones.

Nothing is written into the dataset root: the plot goes to ``./info_{root name}.png`` in the
current directory unless ``--plot PATH`` chooses another path or ``--no-plot`` skips it."""
from __future__ import annotations

import argparse
from pathlib import Path

from typing import TYPE_CHECKING

from radarpc.cli.info_outputs import check_outputs
from radarpc.cli.text import plural
from radarpc.io import DataFileError

if TYPE_CHECKING:                  # the readers import torch: loaded when a command runs, not for --help
    from radarpc.data.radial import CheckReport
    from radarpc.data.summary import RadialSummary

__all__ = ["add_parser", "run", "format_summary", "info_radial", "default_plot_path"]


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
        "splits:      " + ", ".join(f"{k} {plural(s.split_frames[k], 'frame')} / {s.split_sequences[k]} seq"
                                   for k in s.split_frames),
        f"vehicles:    {plural(s.n_vehicles, 'label')} ({s.n_difficult} difficult)",
        f"empty:       {plural(s.n_empty_frames, 'frame')} without vehicles",
        f"range:       {rng(s.range_m, 'm')}",
        f"azimuth:     {rng(s.azimuth_deg, 'deg')}",
        f"velocity:    {rng(s.doppler_mps, 'm/s')}",
        *s.statistics.format(),
    ]
    for k in s.split_frames:
        if s.split_frames[k] == 0:
            rule = ("simulated sequences: the last is test and the one before it val when there are at "
                    "least 3" if s.simulated else "real sequences: RADIal's official val/test lists")
            lines.append(f"warning:     split {k!r} is empty ({plural(s.n_sequences, 'sequence')}; {rule}); "
                         f"RADIal(root, split={k!r}) raises, use random_split or more sequences")
    return "\n".join(lines)


def _print_check(report: CheckReport, write_skip: str | None) -> int:
    from radarpc.data.radial import write_skip_file

    print(report.format())
    if write_skip is not None:
        write_skip_file(write_skip, report.bad_frames)
        print(f"skip list:   {plural(len(report.bad_frames), 'frame')} written to {write_skip}")
    return 0 if report.ok else 1


def default_plot_path(root: str | Path) -> Path:
    """``./info_{root name}.png`` in the current directory (the dataset root is never written)."""
    return Path.cwd() / f"info_{Path(root).resolve().name}.png"


def info_radial(args: argparse.Namespace) -> int:
    """``radarpc info`` on a RADIal root. Returns 1 if ``--check`` found a bad file, else 0."""
    from radarpc.data.radial import check_root, read_labels
    from radarpc.data.summary import first_rd_power_db, summarize_radial
    from radarpc.viz import plot_radial_info

    root = Path(args.root)
    check = bool(args.check or args.write_skip)
    check_outputs(args, default_plot_path(root))
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
        plot_radial_info(summary, labels, out, first_rd_power_db(root, labels, summary.sensor))
        print(f"plot:        {out}")
    if check:
        return _print_check(check_root(root, progress=True), args.write_skip)
    return 0


def run(args: argparse.Namespace) -> int:
    """Dispatch on the kind of root: RADIal (``labels.csv``) or ColoRadar (``calib/``)."""
    from radarpc.data.layout import root_layout

    if root_layout(args.root) == "radial":
        return info_radial(args)
    from radarpc.cli.info_coloradar import info_coloradar
    return info_coloradar(args)


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
                   help="summary plot path, its suffix picks the format: .png, .pdf, .svg, ... (default "
                        "./info_{root name}.png in the current directory; nothing is written into the dataset root)")
    p.add_argument("--no-plot", action="store_true", help="do not write the summary plot")
    p.set_defaults(func=run)
