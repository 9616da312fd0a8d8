"""Which dataset layout a root folder holds: RADIal's or ColoRadar's."""
from __future__ import annotations

import os
from pathlib import Path

from radarpc.io import DataFileError

__all__ = ["root_layout"]


def root_layout(root: str | os.PathLike) -> str:
    """``"radial"`` for a RADIal root (``labels.csv``), ``"coloradar"`` for a ColoRadar root
    (``calib/``).

    Raises
    ------
    DataFileError
        ``root`` is not a folder, or holds neither layout (the message names what each needs).
    """
    root = Path(root)
    if not root.is_dir():
        raise DataFileError(root, "dataset root folder is missing")
    if (root / "labels.csv").is_file():
        return "radial"
    if (root / "calib").is_dir():
        return "coloradar"
    raise DataFileError(root, "is neither a RADIal root (labels.csv, radar_FFT/, radar_Freespace/) nor a "
                              "ColoRadar root (calib/ and run folders)")
