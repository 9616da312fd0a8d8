"""Simulated roots and point stores shared by the whole test session, each built once, on first use,
in pytest's session temporary folder (once per pytest-xdist worker: the README runs ``-n 2 --dist
loadfile``, each file's tests in one worker).

Every fixture here is **read-only** for tests: a test that damages, resumes or extends a root works on
its own copy (``shutil.copytree(root, tmp_path / "copy")``) or writes its own root. Each root checks at
the end of the session that no test changed it (its files, their sizes and modification times), so a
test that writes into a shared root fails instead of silently changing what later tests read.

The simulation parameters live in :mod:`testkit` (``TINY_ROOT``, ``TINY_CITY_ROOT``, ...), so that a
test can rebuild the same frames on the fly (``SimulatedRADIal(TINY, **TINY_ROOT, split="all")``) or
write a variant of a root.
"""
from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import pytest

from testkit import (CHEAP_COLO_KW, COLO_CLI_ARGV, COLO_HALLWAY_ROOT, COLO_ROOT, RADIAL_S_CITY_ROOT, TINY_CITY_ROOT,
                     TINY_KW, TINY_ROOT)


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime_ns) of every file under ``root``, by relative path."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


@contextlib.contextmanager
def _read_only(root: Path):
    """Yield ``root``; afterwards fail if any file under it was added, removed or rewritten."""
    before = _snapshot(root)
    yield root
    after = _snapshot(root)
    if after != before:
        changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
        pytest.fail(f"a test changed the shared session root {root} (read-only; copy it first): {changed[:10]}")


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory) -> Path:
    """RADIal root of the TINY sensor (64 range x 32 Doppler x 8 Rx, 4 Tx): 3 sequences (q000 train,
    q001 val, q002 test) x 2 frames (numSample 0-5), seed 0, the default scene mix (no labelled
    vehicle in these frames), every output of the release (.npy cubes, freespace, camera, laser).
    ``testkit.TINY_ROOT`` holds its parameters."""
    from radarpc.sensors.radial import TINY
    from radarpc.sim.radial_writer import write_radial_dataset

    root = write_radial_dataset(tmp_path_factory.mktemp("tiny") / "root", TINY, **TINY_ROOT, progress=False)
    with _read_only(root):
        yield root


@pytest.fixture(scope="session")
def tiny_city_root(tmp_path_factory) -> Path:
    """RADIal root of the TINY sensor: 3 sequences x 3 frames (numSample 0-8), seed 3, city scenes, every
    output. Labelled vehicles in the train (frames 0-2) and test (6-8) sequences, none in val (3-5).
    ``testkit.TINY_CITY_ROOT`` holds its parameters."""
    from radarpc.sensors.radial import TINY
    from radarpc.sim.radial_writer import write_radial_dataset

    root = write_radial_dataset(tmp_path_factory.mktemp("tiny_city") / "root", TINY, **TINY_CITY_ROOT,
                                progress=False)
    with _read_only(root):
        yield root


@pytest.fixture(scope="session")
def tiny_city_store(tiny_city_root, tmp_path_factory) -> Path:
    """Point store (path) of every frame of :func:`tiny_city_root` at the fixed threshold tau = 1.5 (low,
    so that frames hold points) with the 4-wide angle-sector descriptor (``enrich=("sector4",)``; the
    TINY calibration grid is 61 x 5 directions), the other settings at their defaults."""
    from radarpc.pipelines.pointclouds import convert_dataset

    out = tmp_path_factory.mktemp("tiny_city_store") / "pc.parquet"
    convert_dataset(tiny_city_root, out, tau=1.5, enrich=("sector4",), progress=False)
    with _read_only(out.parent):
        yield out


@pytest.fixture(scope="session")
def radial_s_city_root(tmp_path_factory) -> Path:
    """RADIal root of the radial-s sensor: 3 sequences (train, val, test) x 4 frames, seed 3, city scenes
    (24 labelled vehicles), every output. ``testkit.RADIAL_S_CITY_ROOT`` holds its parameters; the
    detection experiments' tiny runs train on it."""
    from radarpc.sensors.radial import RADIAL_S
    from radarpc.sim.radial_writer import write_radial_dataset

    root = write_radial_dataset(tmp_path_factory.mktemp("radial_s_city") / "root", RADIAL_S, **RADIAL_S_CITY_ROOT,
                                progress=False)
    with _read_only(root):
        yield root


@pytest.fixture(scope="session")
def radial_s_city_store(radial_s_city_root, tmp_path_factory) -> Path:
    """Point store (path) of every frame of :func:`radial_s_city_root` at RADIal's density 0.057 (per
    frame) with the 32-wide angle-sector descriptor (``enrich=("sector32",)``), the SpectralPillars input."""
    from radarpc.pipelines.pointclouds import convert_dataset

    out = tmp_path_factory.mktemp("radial_s_city_store") / "pc.parquet"
    convert_dataset(radial_s_city_root, out, density=0.057, enrich=("sector32",), progress=False)
    with _read_only(out.parent):
        yield out


@pytest.fixture(scope="session")
def colo_root(tmp_path_factory) -> Path:
    """ColoRadar root of ``testkit.TINY_KW`` sizes (single chip of 8 chirps, a 64 x 16 x 4 cascade
    heatmap, an 8 x 128 LiDAR, ``TINY_RADAR`` scatterers): 3 lab runs (lab_run0 train, lab_run1 val,
    lab_run2 test) of 2 radar frames and 4 LiDAR scans each, seed 7. ``testkit.COLO_ROOT`` holds the
    simulation's arguments."""
    from radarpc.sim.coloradar_writer import write_coloradar

    root = write_coloradar(tmp_path_factory.mktemp("colo") / "sim", **COLO_ROOT, **TINY_KW)
    with _read_only(root):
        yield root


@pytest.fixture(scope="session")
def colo_hallway_root(tmp_path_factory) -> Path:
    """ColoRadar root without cascade (``testkit.CHEAP_COLO_KW``: ColoRadar's own single chip, 128 chirps,
    fed by a cheap scatterer model; a 16 x 256 LiDAR): 3 hallway runs (hallway_run0 train, hallway_run1
    val, hallway_run2 test) of 2 radar frames each, seed 0 (``testkit.COLO_HALLWAY_ROOT``). The root the
    OS-CFAR baseline and the point-set metrics run on."""
    from radarpc.sim.coloradar_writer import write_coloradar

    root = write_coloradar(tmp_path_factory.mktemp("colo_hallway") / "sim", **COLO_HALLWAY_ROOT, **CHEAP_COLO_KW)
    with _read_only(root):
        yield root


@pytest.fixture(scope="session")
def colo_cli_root(tmp_path_factory) -> tuple[Path, str]:
    """``(root, stdout)`` of one ``radarpc simulate coloradar`` run end to end through
    :func:`radarpc.cli.main` (``testkit.COLO_CLI_ARGV``: one outdoor run of one full-size radar frame, a
    4 x 64 LiDAR, seed 0); the command's exit code 0 is checked here."""
    from radarpc.cli import main

    root = tmp_path_factory.mktemp("colo_cli") / "cli"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(COLO_CLI_ARGV + ["--out", str(root)])
    assert code == 0, f"radarpc {' '.join(COLO_CLI_ARGV)} --out {root} exited with {code}"
    with _read_only(root):
        yield root, out.getvalue()


RALD_CONFIGS = Path(__file__).parent / "experiments" / "rald" / "configs"
"""The tiny RaLD stage configs (``rald-ae-tiny.yaml``, ``rald-tiny.yaml``: 4 steps each)."""


def _train_quietly(*argv) -> None:
    from radarpc.cli import main

    argv = ["train", *map(str, argv), "--no-progress"]
    with contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    assert code == 0, f"radarpc {' '.join(argv)} exited with {code}"


@pytest.fixture(scope="session")
def rald_ae_run(colo_root, tmp_path_factory) -> Path:
    """A finished RaLD stage-1 run (``rald-ae-tiny.yaml``, 4 steps) on ``colo_root``, trained through
    ``radarpc train``."""
    out = tmp_path_factory.mktemp("rald_ae") / "ae"
    _train_quietly(RALD_CONFIGS / "rald-ae-tiny.yaml", "--data", colo_root, "--out", out)
    with _read_only(out):
        yield out


@pytest.fixture(scope="session")
def rald_run(colo_root, rald_ae_run, tmp_path_factory) -> Path:
    """A finished RaLD stage-2 run (``rald-tiny.yaml``, 4 steps) against :func:`rald_ae_run`, trained
    through ``radarpc train``."""
    out = tmp_path_factory.mktemp("rald_dit") / "rald"
    _train_quietly(RALD_CONFIGS / "rald-tiny.yaml", "--data", colo_root, "--ae", rald_ae_run, "--out", out)
    with _read_only(out):
        yield out


@pytest.fixture(scope="session")
def rald_ae_overfit(colo_hallway_root):
    """``(config, state_dict, oscfar_chamfer)``: the tiny autoencoder overfit on frame 0 of
    :func:`colo_hallway_root`'s train split (hallway_run0: 1,856 LiDAR points in the field of view): 512
    points and 4,096 queries (6.25 % occupied) per step, new queries every step, frustum cells of
    0.2 m x 2 deg x 4 deg, 300 AdamW steps at 1e-3 from ``torch.manual_seed(0)`` (so
    ``torch.manual_seed(0); task.build_model()`` rebuilds its starting weights); and OS-CFAR's Chamfer
    distance on that frame, tuned on that very frame over 72 settings (its best case), the mark the
    autoencoder's reconstruction must beat. Tests load the state into a model of their own."""
    import torch

    from radarpc.rald.oscfar_baseline import CubeAxes, TuningGrid, tune_oscfar

    from radarpc.experiments.rald.config import AutoencoderExperiment, LidarData
    from radarpc.experiments.rald.task import AutoencoderTask
    from radarpc.models import ModelSpec
    from radarpc.training.loop import TrainConfig

    cfg = AutoencoderExperiment("t", ModelSpec("rald-ae-tiny"),
                                data=LidarData(points=512, queries=4096, occupied_fraction=0.0625, cell=(0.2, 2.0, 4.0)),
                                train=TrainConfig(select_metric="loss", select_mode="min"))
    task = AutoencoderTask(cfg, colo_hallway_root)
    torch.manual_seed(0)
    model = task.build_model()
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.0)
    for step in range(300):
        task.train_set.set_epoch(step)
        loss, _ = task.loss(model, task.collate([task.train_set[0]]))
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
    frames = task.train_set.frames
    cube = frames.cube(0)
    axes = CubeAxes.from_radians(cube.range_m, cube.azimuth_rad, cube.elevation_rad)
    grid_search = TuningGrid(windows=((9, 3, 3), (17, 7, 3)), guards=((3, 1, 1), (5, 3, 1)), ranks=(0.5, 0.75))
    oscfar = tune_oscfar([(cube.intensity_db, frames.lidar_points(0))], axes, grid_search).best_chamfer
    return cfg, {k: v.detach().clone() for k, v in model.state_dict().items()}, oscfar


def pytest_configure(config):
    """Under pytest-xdist (the README runs ``-n 2``) each worker takes its share of the cores: its
    torch, its BLAS and the processes its tests start (through ``OMP_NUM_THREADS``). Two workers
    that each spin every core's threads would wait on each other."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        import torch
        from threadpoolctl import threadpool_limits

        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        share = max(1, cores // int(workers))
        torch.set_num_threads(share)
        threadpool_limits(share)
        os.environ.setdefault("OMP_NUM_THREADS", str(share))
