"""The outputs of ``radarpc info`` (the summary figure, the skip list), checked before any work on
either kind of root (:mod:`radarpc.cli.info` for RADIal, :mod:`radarpc.cli.info_coloradar`)."""
from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["check_outputs"]


def check_outputs(args: argparse.Namespace, default_plot: Path) -> None:
    """Fail before any work when the figure (``--plot``, else ``default_plot``, unless ``--no-plot``)
    or the skip list (``--write-skip``) cannot be written (one clear line)."""
    from radarpc.runs import check_writable
    from radarpc.viz import figure_format

    outputs = [(Path(args.write_skip), "skip list")] if getattr(args, "write_skip", None) else []
    if not getattr(args, "no_plot", False):
        outputs.append((Path(args.plot) if getattr(args, "plot", None) else default_plot, "figure"))
    for path, what in outputs:
        if path.is_dir():
            raise IsADirectoryError(f"the {what} path {path} is a directory; give a file name")
        if what == "figure":
            figure_format(path)                 # the suffix names the format (.png, .pdf, .svg, ...)
        check_writable(path, what)
