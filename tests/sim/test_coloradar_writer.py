"""The simulated ColoRadar root as a run folder: resume, refusal, overwrite, lock, leftovers."""
from __future__ import annotations

import os
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from radarpc.runs import OutputBusyError, RunMismatchError
from radarpc.sim import coloradar_writer
from radarpc.sim.coloradar_writer import write_coloradar
from testkit import TINY_KW as KW, stalling_writer_script

SCENES, RUNS, FRAMES, SEED = ["lab"], 1, 2, 7


def write(out, **kw) -> Path:
    return write_coloradar(out, SCENES, kw.pop("runs", RUNS), kw.pop("frames", FRAMES), kw.pop("seed", SEED),
                           **KW, **kw)


@pytest.fixture(scope="module")
def ref(tmp_path_factory) -> Path:
    return write(tmp_path_factory.mktemp("colo") / "ref")


def all_files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _count_lidar(monkeypatch) -> list:
    calls = []
    real = coloradar_writer.lidar_scan
    monkeypatch.setattr(coloradar_writer, "lidar_scan", lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


def test_layout_and_manifest(ref):
    settings = json.loads((ref / "simulation.json").read_text())
    assert settings["seed"] == SEED and settings["frames"] == FRAMES and settings["scenes"] == SCENES
    # written like json.dump(..., indent=1) of the settings
    assert (ref / "simulation.json").read_text() == json.dumps(settings, indent=1)
    assert sorted(p.name for p in ref.iterdir()) == ["calib", "lab_run0", "simulation.json"]
    assert not list(ref.rglob("*.tmp")) and not (ref.parent / ".ref.lock").exists()


def test_resume_after_damage_gives_the_identical_root(ref, tmp_path, monkeypatch):
    part = tmp_path / "part"
    shutil.copytree(ref, part)
    run0 = part / "lab_run0"
    (run0 / "single_chip" / "adc_samples" / "data" / "frame_1.bin").unlink()
    hm = run0 / "cascade" / "heatmaps" / "data" / "heatmap_0.bin"
    hm.write_bytes(hm.read_bytes()[:100])                                   # wrong size: redone
    (run0 / "lidar" / "pointclouds" / "lidar_pointcloud_2.bin").unlink()
    lid = run0 / "lidar" / "pointclouds" / "lidar_pointcloud_0.bin"
    lid.write_bytes(lid.read_bytes()[:-16])
    (run0 / "groundtruth" / "timestamps.txt").unlink()
    (part / "calib" / "cascade").joinpath("antenna_cfg.txt").unlink()
    (part / "simulation.json").write_text(json.dumps(json.loads((ref / "simulation.json").read_text())))
    # temp files of a killed job, in the root and deep in a run
    (part / ".simulation.json.k1.tmp").write_text("{")
    (run0 / "lidar" / "pointclouds" / ".lidar_pointcloud_1.bin.k2.tmp").write_bytes(b"\0" * 8)
    untouched = (run0 / "lidar" / "pointclouds" / "lidar_pointcloud_1.bin").stat().st_mtime_ns
    calls = _count_lidar(monkeypatch)
    write(part)
    assert len(calls) == 2                                  # only the two damaged LiDAR scans redone
    assert (run0 / "lidar" / "pointclouds" / "lidar_pointcloud_1.bin").stat().st_mtime_ns == untouched
    assert all_files(part) == all_files(ref)               # leftovers gone, simulation.json rewritten


def test_other_settings_are_refused_without_changing_anything(ref, tmp_path):
    before = all_files(ref)
    with pytest.raises(RunMismatchError, match=r"simulation\.json:seed.*--overwrite"):
        write(ref, seed=SEED + 1)
    with pytest.raises(FileExistsError, match=r"simulation\.json:frames.*--overwrite"):
        write(ref, frames=FRAMES + 1)
    assert all_files(ref) == before
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(RunMismatchError, match=r"simulation\.json \(missing or unreadable\)"):
        write(tmp_path)
    with pytest.raises(ValueError, match="scenes"):
        write_coloradar(tmp_path / "new", ["kitchen"], 1, 1, **KW)


def test_overwrite_replaces_a_run_of_other_settings(ref, tmp_path, monkeypatch):
    fresh = write(tmp_path / "fresh", frames=1)
    other = tmp_path / "other"
    shutil.copytree(ref, other)                              # 2 frames a run: frame_1.bin etc. are stale for 1
    (other / "notes.txt").write_text("mine")
    (other / "lab_run0" / ".frame_0.bin.k.tmp").write_bytes(b"x")
    write(other, frames=1, overwrite=True)
    assert (other / "notes.txt").read_text() == "mine"
    (other / "notes.txt").unlink()
    assert all_files(other) == all_files(fresh)             # stale frames and the leftover are gone
    # overwrite on a matching partial run resumes it (nothing is synthesised again)
    calls = _count_lidar(monkeypatch)
    write(other, frames=1, overwrite=True)
    assert calls == [] and all_files(other) == all_files(fresh)


# A second real process writes the same root and stalls inside the atomic write of its first
# .bin file (its temp file exists), like a job killed mid-write.
_STALLING_WRITER = stalling_writer_script(
    "radarpc.sim.coloradar_writer", ".bin",
    f"from testkit import TINY_KW\nwriter.write_coloradar(sys.argv[1], {SCENES!r}, {RUNS}, {FRAMES}, {SEED}, **TINY_KW)")


def test_second_writer_is_refused_and_a_killed_run_resumes(ref, tmp_path):
    out = tmp_path / "busy"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")]))
    child = subprocess.Popen([sys.executable, "-c", _STALLING_WRITER, str(out)], stdout=subprocess.PIPE, text=True,
                             env=env)
    try:
        assert child.stdout.readline().strip() == "writing"
        assert len(list(out.rglob(".*.tmp"))) == 1
        before = all_files(out)
        with pytest.raises(OutputBusyError, match=rf"pid {child.pid}\) is writing the dataset root .*busy"):
            write(out)
        with pytest.raises(FileExistsError, match="another radarpc process"):     # with overwrite too
            write(out, seed=SEED + 1, overwrite=True)
        assert all_files(out) == before                     # the refused writers touched nothing
    finally:
        child.kill()
        child.wait()
        child.stdout.close()
    write(out)                                              # the kill released the lock
    assert not list(out.rglob("*.tmp")) and not (tmp_path / ".busy.lock").exists()
    assert all_files(out) == all_files(ref)


def test_overwrite_removes_the_runs_of_the_old_simulation(tmp_path):
    # a root of 2 runs per scene overwritten by 1 run per scene holds only the new run, never a
    # mix of two simulations
    from radarpc.data.coloradar import find_runs

    out = tmp_path / "colo"
    # the tiny radar of TINY_KW (8 chirps, a 64 x 16 x 4 cascade): which runs a root holds does not
    # depend on the frame sizes, and the full-size frames took 10 s
    small = dict(KW, lidar_beams=4, lidar_azimuth_steps=16)
    write_coloradar(out, ["lab"], 2, 1, seed=7, **small)
    write_coloradar(out, ["lab"], 1, 1, seed=8, overwrite=True, **small)
    assert find_runs(out) == ["lab_run0"]
