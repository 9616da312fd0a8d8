"""What several test modules share: the parameters of the simulated roots that ``tests/conftest.py``
builds once per session, tiny ColoRadar simulation settings, a stalling writer, a point-cloud
comparison and point clouds from (range, azimuth) pairs.

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
from radarpc.sim.scenes import scene_mix

__all__ = ["TINY_ROOT", "TINY_CITY_ROOT", "RADIAL_S_CITY_ROOT", "COLO_ROOT", "CHEAP_COLO_KW", "COLO_HALLWAY_ROOT",
           "COLO_CLI_ARGV", "TINY_CASCADE", "TINY_CALIB", "TINY_RADAR", "TINY_KW", "make_cloud", "same_cloud",
           "stalling_writer_script"]

# ---- the session roots of tests/conftest.py --------------------------------------------------------
# Keyword arguments of write_radial_dataset / SimulatedRADIal (the sensor is given apart), so that a
# test can rebuild the same frames on the fly or write a variant of the root.
TINY_ROOT = dict(n_sequences=3, frames_per_sequence=2, seed=0)
"""``tiny_root``: 3 sequences (q000 train, q001 val, q002 test) x 2 frames of the TINY sensor, seed 0,
the default scene mix (no labelled vehicle in these 6 frames)."""
TINY_CITY_ROOT = dict(n_sequences=3, frames_per_sequence=3, seed=3, scenes=scene_mix("city"))
"""``tiny_city_root``: 3 sequences x 3 frames of the TINY sensor, seed 3, city scenes: labelled vehicles
in the train (frames 0-2) and test (frames 6-8) sequences, none in val (frames 3-5)."""
RADIAL_S_CITY_ROOT = dict(n_sequences=3, frames_per_sequence=4, seed=3, scenes=scene_mix("city"))
"""``radial_s_city_root``: 3 sequences x 4 frames of the radial-s sensor, seed 3, city scenes (24 vehicles)."""

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
COLO_ROOT = dict(scenes=["lab"], runs_per_scene=3, frames=2, seed=7)
"""``colo_root``: with :data:`TINY_KW`, 3 runs of the lab (lab_run0 train, lab_run1 val, lab_run2 test) of
2 radar frames (4 LiDAR scans) each, seed 7."""
CHEAP_COLO_KW = dict(calib=dataclasses.replace(DEFAULT_CALIB, cascade=None, base_to_cascade=None),
                     radar=RadarSimConfig(az_step_deg=6.0, el_step_deg=8.0, edges=False, multipath=False,
                                          max_scatterers=200),
                     lidar_beams=16, lidar_azimuth_steps=256, progress=False)
"""Keyword arguments of ``write_coloradar`` for a root without cascade: ColoRadar's own single chip
(128 chirps) fed by a cheap scatterer model, a 16 x 256 LiDAR."""
COLO_HALLWAY_ROOT = dict(scenes=["hallway"], runs_per_scene=3, frames=2, seed=0)
"""``colo_hallway_root``: with :data:`CHEAP_COLO_KW`, 3 hallway runs (train, val, test) of 2 radar frames."""
COLO_CLI_ARGV = ["simulate", "coloradar", "--scenes", "outdoor", "--runs-per-scene", "1", "--frames", "1",
                 "--lidar-beams", "4", "--lidar-azimuth-steps", "64", "--no-progress"]
"""``colo_cli_root``: the ``radarpc simulate coloradar`` command line (without ``--out``): one outdoor run of
one full-size radar frame (the default calibration: single chip and cascade), a 4 x 64 LiDAR."""


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
