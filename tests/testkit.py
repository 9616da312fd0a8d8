"""What several test modules share: tiny ColoRadar simulation settings, a stalling writer, a
point-cloud comparison and point clouds from (range, azimuth) pairs.

Importable from any test as ``testkit`` (``pythonpath = ["tests"]`` in pyproject.toml).
"""
from __future__ import annotations

import contextlib
import dataclasses
import textwrap

import pytest
import torch

from radarpc.points import PointCloudBatch
from radarpc.sensors.coloradar import AWR1843, CASCADE, DEFAULT_CALIB, beam_angles
from radarpc.sim.coloradar_synth import RadarSimConfig

__all__ = ["TINY_CASCADE", "TINY_CALIB", "TINY_RADAR", "TINY_KW", "make_cloud", "same_cloud", "stalling_writer_script"]

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


def make_cloud(frames: list[list[tuple[float, float]]], *, sector: int | None = None, patch: int | None = None,
               seed: int = 0) -> PointCloudBatch:
    """Clouds of ``len(frames)`` frames from (range m, azimuth deg) pairs; other fields drawn at random."""
    g = torch.Generator().manual_seed(seed)
    ra = [p for f in frames for p in f]
    n = len(ra)
    r = torch.tensor([p[0] for p in ra], dtype=torch.float32)
    a = torch.tensor([p[1] for p in ra], dtype=torch.float32)
    rand = lambda lo, hi: lo + (hi - lo) * torch.rand(n, generator=g)   # noqa: E731
    return PointCloudBatch(
        offset=torch.cumsum(torch.tensor([len(f) for f in frames]), 0), range_bin=torch.zeros(n, dtype=torch.long),
        doppler_bin=torch.randint(0, 16, (n,), generator=g), doppler_full=torch.zeros(n, dtype=torch.long),
        range_m=r, azimuth_deg=a, elevation_deg=rand(-10, 10), velocity_mps=rand(-20, 20),
        amplitude=rand(1e2, 1e5), snr=rand(1, 100), x=r * torch.cos(torch.deg2rad(a)),
        y=r * torch.sin(torch.deg2rad(a)), z=torch.zeros(n), is_neighbour=torch.rand(n, generator=g) < 0.5,
        sector=None if sector is None else torch.rand(n, sector, generator=g) * 1e4,
        rd_patch=None if patch is None else torch.rand(n, patch, generator=g) * 1e8,
        tau=torch.ones(len(frames)), density=torch.full((len(frames),), 0.057))


@contextlib.contextmanager
def warns_reduced_fp32_matmul():
    """Run the block under ``float32_matmul_precision("medium")`` (TF32 / bf16 GEMMs) and expect
    the inference rewrites' warning that their rounding bounds no longer hold; restores the setting."""
    prev = torch.get_float32_matmul_precision()
    try:
        torch.set_float32_matmul_precision("medium")
        with pytest.warns(RuntimeWarning, match="float32 matmul precision is reduced"):
            yield
    finally:
        torch.set_float32_matmul_precision(prev)
