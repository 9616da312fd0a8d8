"""What several test modules share: tiny ColoRadar simulation settings, a stalling writer and a
point-cloud comparison.

Importable from any test as ``testkit`` (``pythonpath = ["tests"]`` in pyproject.toml).
"""
from __future__ import annotations

import dataclasses
import textwrap

import torch

from radarpc.sensors.coloradar import AWR1843, CASCADE, DEFAULT_CALIB, beam_angles
from radarpc.sim.coloradar_synth import RadarSimConfig

__all__ = ["TINY_CASCADE", "TINY_CALIB", "TINY_RADAR", "TINY_KW", "same_cloud", "stalling_writer_script"]

TINY_CASCADE = CASCADE.replace(num_range_bins=64, num_azimuth_bins=16, num_elevation_bins=4,
                               azimuth_bins=beam_angles(16, CASCADE.element_spacing, half_bin=True),
                               elevation_bins=beam_angles(4, CASCADE.element_spacing, half_bin=True))
"""A cascade heatmap of 64 x 16 x 4 bins (the real one is 128 x 128 x 32)."""
TINY_CALIB = dataclasses.replace(DEFAULT_CALIB, single_chip=AWR1843.replace(num_chirps_per_frame=8),
                                 cascade=TINY_CASCADE)
"""ColoRadar's calibration with 8 chirps per single-chip frame and the tiny cascade."""
TINY_RADAR = RadarSimConfig(az_step_deg=4.0, el_step_deg=5.0)
TINY_KW = dict(lidar_beams=8, lidar_azimuth_steps=128, calib=TINY_CALIB, radar=TINY_RADAR, progress=False)
"""Keyword arguments of :func:`radarpc.sim.coloradar_writer.write_coloradar` for a tiny root."""


def stalling_writer_script(module: str, suffix: str, call: str) -> str:
    """Python source for a second real process that runs ``call`` and stalls (prints
    ``writing``, then sleeps) inside the atomic write of its first file ending in ``suffix``:
    a writer holding the output's lock with a temp file on disk, as a job killed mid-write.
    ``module`` is the writer module whose ``atomic_write`` is wrapped; ``call`` may use it as
    ``writer`` and ``sys.argv``."""
    return textwrap.dedent(f"""
        import contextlib, sys, time
        import {module} as writer
        real = writer.atomic_write

        @contextlib.contextmanager
        def stalling(path, mode="wb"):
            with real(path, mode) as f:
                if str(path).endswith({suffix!r}):
                    print("writing", flush=True)
                    time.sleep(120)
                yield f

        writer.atomic_write = stalling
    """) + call + "\n"


def same_cloud(a, b) -> bool:
    """Whether two :class:`~radarpc.points.PointCloudBatch` hold equal tensors in every
    field (the same optional fields absent)."""
    for f in dataclasses.fields(a):
        u, v = getattr(a, f.name), getattr(b, f.name)
        if (u is None) != (v is None) or (u is not None and not torch.equal(u, v)):
            return False
    return True
