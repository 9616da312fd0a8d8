"""Tests of :mod:`radarpc.data.summary` against independent readings of tiny simulated roots."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from radarpc.data import summary
from radarpc.data.coloradar import ColoRadarRun
from radarpc.data.radial import read_labels
from radarpc.data.radial_format import fft_path
from radarpc.io import DataFileError
from radarpc.sensors.radial import TINY


@pytest.fixture
def radial_root(tiny_city_root):
    # the session's TINY root: 3 sequences (train, val, test) x 3 city frames, vehicles in train and test
    return tiny_city_root


@pytest.fixture
def colo_root(colo_hallway_root):
    # the session's 3 runs of one scene (train, val, test), 2 radar frames each, a cheap radar, no cascade
    return colo_hallway_root


def test_summarize_radial_against_labels_csv(radial_root):
    with open(radial_root / "labels.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    frames = {int(r["numSample"]) for r in rows}
    vehicles = [r for r in rows if float(r["radar_R_m"]) >= 0 and int(r["Difficult"]) >= 0]
    s = summary.summarize_radial(radial_root)
    assert s.simulated and s.sensor == TINY and s.n_frames == len(frames) == 9 and s.n_sequences == 3
    assert list(s.split_frames) == ["train", "val", "test"] and s.split_frames == {"train": 3, "val": 3, "test": 3}
    assert s.n_vehicles == len(vehicles)
    assert s.n_empty_frames == len(frames - {int(r["numSample"]) for r in vehicles})
    if vehicles:
        r = [float(v["radar_R_m"]) for v in vehicles]
        assert s.range_m == (min(r), max(r))
    assert summary.summarize_radial(radial_root, read_labels(radial_root / "labels.csv")) == s


def test_first_rd_power_db(radial_root, tmp_path):
    labels = read_labels(radial_root / "labels.csv")
    first = int(np.unique(labels.num_sample)[0])
    cube = np.load(fft_path(radial_root, first))
    num, power = summary.first_rd_power_db(radial_root, labels, TINY)
    assert num == first and power.shape == TINY.rd_shape[:2]
    want = 10 * np.log10((cube.real.astype(np.float64) ** 2 + cube.imag.astype(np.float64) ** 2).mean(2))
    np.testing.assert_allclose(power, want, rtol=0, atol=1e-4)          # float32 powers, in dB
    # a missing cube is skipped; with none readable there is nothing to draw
    import shutil

    copy = shutil.copytree(radial_root, tmp_path / "copy")
    fft_path(copy, first).unlink()
    assert summary.first_rd_power_db(copy, labels, TINY)[0] == int(np.unique(labels.num_sample)[1])
    for p in (copy / "radar_FFT").iterdir():
        p.unlink()
    assert summary.first_rd_power_db(copy, labels, TINY) is None


def test_summarize_coloradar(colo_root):
    calib, runs = summary.open_coloradar_runs(colo_root)
    s = summary.summarize_coloradar(colo_root, calib, runs)
    assert s.simulated and s.scenes == ("hallway",) and [r.name for r in s.runs] == [r.name for r in runs]
    assert s.split_runs == {"train": 1, "val": 1, "test": 1}
    for rs, run in zip(s.runs, runs):
        assert rs.radar_frames == run.num_radar_frames == 2 and rs.lidar_scans == run.num_lidar_frames
        assert rs.heatmaps == 0 and rs.pairs >= 1 and rs.lidar_points[1] <= rs.lidar_points[0]
    assert s.split_pairs == {r.split: r.pairs for r in s.runs}
    assert s.lidar_points == pytest.approx((np.mean([r.lidar_points[0] for r in s.runs]),
                                            np.mean([r.lidar_points[1] for r in s.runs])))


def test_coloradar_view(colo_root):
    calib, runs = summary.open_coloradar_runs(colo_root)
    v = summary.coloradar_view(runs[0], calib)
    assert v.run == runs[0].name and v.heatmap_db is None                   # no cascade in this root
    assert v.lidar_xyz.shape[1] == 3 and 0 < len(v.inside_xyz) <= len(v.lidar_xyz)
    assert np.all(np.linalg.norm(v.inside_xyz, axis=1) <= v.fov.max_range_m + 1e-6)
    assert v.cube_db.shape == (len(v.cube_range_m), len(v.cube_azimuth_deg))


def test_check_runs_lists_bad_files(colo_root, tmp_path):
    import shutil

    root = shutil.copytree(colo_root, tmp_path / "copy")
    calib, runs = summary.open_coloradar_runs(root)
    total, bad = summary.check_runs(runs, progress=False)
    assert total == sum(r.num_radar_frames + r.num_lidar_frames for r in runs) and bad == []
    run = ColoRadarRun(root / runs[1].name)
    p = run.lidar_path(1)
    p.write_bytes(p.read_bytes()[:-32])
    total2, bad = summary.check_runs(runs, progress=False)
    assert total2 == total and len(bad) == 1 and "lidar_pointcloud_1.bin" in bad[0]
    assert summary.check_run(run) == bad
    summary.write_check_list(tmp_path / "bad.txt", bad)
    assert (tmp_path / "bad.txt").read_text() == bad[0] + "\n"
    empty = tmp_path / "empty"
    shutil.copytree(root / "calib", empty / "calib")
    with pytest.raises(DataFileError, match="no run folder"):
        summary.open_coloradar_runs(empty)
