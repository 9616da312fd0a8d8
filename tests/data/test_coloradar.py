"""Tests for radarpc.data.coloradar: reader vs simulator, pairing, transforms, crop, bad input."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from radarpc.data.coloradar import (
    RALD_SPLITS,
    ColoRadar,
    ColoRadarRun,
    collate_coloradar,
    crop_to_frustum,
    frustum_mask,
    lidar_to_radar,
    pair_radar_lidar,
    rald_intensity,
    split_runs,
    upsample_intensity,
)
from radarpc.data.coloradar_format import load_calib
from radarpc.dsp.tdm import radar_cube
from radarpc.io import DataFileError
from radarpc.sensors.coloradar import (
    AWR1843,
    DEFAULT_CALIB,
    ColoRadarCalib,
    HeatmapConfig,
    RadarFOV,
    Transform,
    beam_angles,
)
from radarpc.sim.coloradar_synth import (
    LidarConfig,
    cascade_heatmap,
    lidar_scan,
    radar_scatterers,
    sensor_pose,
    synthesize_tdm_adc,
)
from radarpc.sim.coloradar_writer import frame_generator, run_name, write_coloradar
from radarpc.sim.indoor import make_scene
from testkit import TINY_CALIB as CALIB, TINY_RADAR as RADAR, TINY_KW as KW



@pytest.fixture
def sim_root(colo_root):
    # the session's tiny ColoRadar root (tests/conftest.py): 3 lab runs x 2 radar frames, seed 7; read-only
    return colo_root


def test_reader_agrees_with_simulator(sim_root):
    calib = load_calib(sim_root / "calib")
    assert calib == CALIB
    run = ColoRadarRun(sim_root / "lab_run1")
    assert run.scene == "lab" and run.num_radar_frames == 2 and run.num_lidar_frames == 4
    scene = make_scene("lab", 7, 1)
    t0 = run.pose_timestamps[0]
    # poses: world <- base at the pose timestamps
    for k in (0, 5):
        pos, q = scene.trajectory.pose(float(run.pose_timestamps[k] - t0))
        np.testing.assert_allclose(run.poses[k], np.concatenate([pos, q]), atol=1e-6)
    for i in range(2):
        t = float(run.radar_timestamps[i] - t0)
        pose, vel = sensor_pose(scene, t, CALIB.base_to_single_chip)
        scat = radar_scatterers(scene, t, pose, vel, cfg=RADAR, generator=frame_generator(7, "lab", 1, i, "radar"))
        adc = synthesize_tdm_adc(scat, CALIB.single_chip, cfg=RADAR, generator=frame_generator(7, "lab", 1, i, "adc")).numpy()
        got = run.adc(i)
        assert got.dtype == np.complex64 and got.shape == (3, 4, 8, 128)
        np.testing.assert_array_equal(got.real, adc[..., 0])
        np.testing.assert_array_equal(got.imag, adc[..., 1])
        sc_to_cc = CALIB.base_to_cascade.inverse() @ CALIB.base_to_single_chip
        hm = cascade_heatmap(scat.to_frame(sc_to_cc), CALIB.cascade, cfg=RADAR,
                             generator=frame_generator(7, "lab", 1, i, "heatmap")).numpy()
        np.testing.assert_array_equal(run.heatmap(i), hm)
    for j in range(4):
        t = float(run.lidar_timestamps[j] - t0)
        pose, _ = sensor_pose(scene, t, CALIB.base_to_lidar)
        cloud = lidar_scan(scene, t, pose, cfg=LidarConfig(beams=8, azimuth_steps=128),
                           generator=frame_generator(7, "lab", 1, j, "lidar")).numpy()
        np.testing.assert_array_equal(run.lidar(j, drop_zeros=False), cloud)
        np.testing.assert_array_equal(run.lidar(j), cloud[np.any(cloud[:, :3] != 0, axis=1)])


def test_resume_and_refuse(sim_root, tmp_path):
    import shutil

    copy = shutil.copytree(sim_root, tmp_path / "copy")            # the session root is read-only
    f = copy / "lab_run0" / "single_chip" / "adc_samples" / "data" / "frame_0.bin"
    before = f.read_bytes()
    f.unlink()
    write_coloradar(copy, ["lab"], 3, 2, seed=7, **KW)              # resumes: rewrites the missing file
    assert f.read_bytes() == before
    with pytest.raises(FileExistsError, match="not empty"):
        write_coloradar(copy, ["lab"], 3, 2, seed=8, **KW)
    (tmp_path / "other.txt").write_text("x")
    with pytest.raises(FileExistsError):
        write_coloradar(tmp_path, ["lab"], 1, 1, seed=0, **KW)
    with pytest.raises(ValueError, match="scenes"):
        write_coloradar(tmp_path / "new", ["kitchen"], 1, 1, **KW)


def test_dataset_items_and_splits(sim_root):
    assert [r.name for r in ColoRadar(sim_root, "test").runs] == [run_name("lab", 2)]
    assert [r.name for r in ColoRadar(sim_root, "val").runs] == ["lab_run1"]
    ds = ColoRadar(sim_root, "train")
    assert [r.name for r in ds.runs] == ["lab_run0"] and len(ds) >= 1
    it = ds[0]
    assert it.intensity.shape == (128, 64, 32) and it.intensity.dtype == torch.float32
    assert it.points.ndim == 2 and it.points.shape[1] == 3 and it.points.shape[0] > 0
    assert bool(frustum_mask(it.points).all())
    assert abs(it.radar_time - it.lidar_time) <= 0.05 + 1e-9
    inten, pts, offset, items = collate_coloradar([ds[0], ds[0]])
    assert inten.shape == (2, 128, 64, 32) and offset.tolist() == [it.points.shape[0], 2 * it.points.shape[0]]


def test_every_keeps_every_kth_paired_frame_of_each_run(sim_root):
    full = ColoRadar(sim_root, "all", cube_size=None)
    for k in (1, 2, 3):
        ds = ColoRadar(sim_root, "all", cube_size=None, every=k)
        assert ds.every == k
        # per run: the paired frames at positions 0, k, 2k, ... of the full list
        want = [e for r in range(len(full.runs)) for e in [x for x in full.index if x[0] == r][::k]]
        assert ds.index == want
    assert len(ColoRadar(sim_root, "all", cube_size=None, every=2)) == len(full.runs)   # 2 frames a run
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match=r"every must be a positive integer \(1 keeps every frame\), got"):
            ColoRadar(sim_root, "all", every=bad)


def test_split_rule_and_rald_lists():
    names = [f"lab_run{k}" for k in range(5)] + ["hall_run0", "hall_run1", "solo_run0"]
    assert split_runs(names, "test") == ["hall_run1", "lab_run4"]
    assert split_runs(names, "val") == ["lab_run3"]
    assert split_runs(names, "train") == ["hall_run0", "lab_run0", "lab_run1", "lab_run2", "solo_run0"]
    real = ["2_24_2021_aspen_run10", "2_24_2021_aspen_run11", "2_24_2021_aspen_run3", "12_21_2020_ec_hallways_run4"]
    assert split_runs(real, "test") == ["12_21_2020_ec_hallways_run4", "2_24_2021_aspen_run11"]
    assert split_runs(real, "val") == ["2_24_2021_aspen_run10"]
    assert len(RALD_SPLITS["train"]) == 38 and len(RALD_SPLITS["test"]) == 7
    with pytest.raises(ValueError, match="split"):
        split_runs(names, "dev")


def test_pairing_nearest_timestamp(tmp_path):
    run_dir = tmp_path / "r_run0"
    for rel, ts in (("single_chip/adc_samples/timestamps.txt", [10.00, 10.10, 10.20, 10.90]),
                    ("lidar/timestamps.txt", [9.97, 10.07, 10.12, 10.27, 10.37])):
        (run_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        (run_dir / rel).write_text("\n".join(f"{t:.6f}" for t in ts) + "\n")
    run = ColoRadarRun(run_dir, calib=DEFAULT_CALIB)
    tr, tl = [10.00, 10.10, 10.20, 10.90], [9.97, 10.07, 10.12, 10.27, 10.37]
    for max_dt in (0.05, 0.08, 1.0):                   # brute force: argmin |dt|, dropped when > max_dt
        want = [[i, int(np.argmin([abs(b - a) for b in tl]))] for i, a in enumerate(tr)
                if min(abs(b - a) for b in tl) <= max_dt]
        assert pair_radar_lidar(run, max_dt=max_dt).tolist() == want
    assert pair_radar_lidar(run, max_dt=0.05).tolist() == [[0, 0], [1, 2]]
    (run_dir / "lidar/timestamps.txt").write_text("1.0\n0.5\n")
    run2 = ColoRadarRun(run_dir, calib=DEFAULT_CALIB)
    with pytest.raises(DataFileError, match="decrease"):
        pair_radar_lidar(run2)


def test_lidar_to_radar_hand_made():
    s = math.sqrt(0.5)
    calib = ColoRadarCalib(AWR1843, None, Transform((1.0, 0.0, 0.0), (0.0, 0.0, s, s)),
                           Transform((0.0, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0)), None)
    pts = np.array([[1.0, 2.0, 0.0, 7.0]], dtype=np.float32)          # base (1, 2, 0.5)
    got = lidar_to_radar(pts, calib)
    np.testing.assert_allclose(got, [[2.0, 0.0, 0.5, 7.0]], atol=1e-6)  # R^T (p - t), R = yaw +90


def test_frustum_crop_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-20, 20, (3000, 3)).astype(np.float32)
    fov = RadarFOV(max_range_m=15.0, azimuth_deg=(-60.0, 90.0), elevation_deg=(-20.0, 10.0))
    want = []
    for x, y, z in pts.astype(np.float64):
        r = math.sqrt(x * x + y * y + z * z)
        az, el = math.degrees(math.atan2(y, x)), math.degrees(math.asin(z / r))
        want.append(0 < r <= 15.0 and -60 <= az <= 90 and -20 <= el <= 10)
    np.testing.assert_array_equal(frustum_mask(pts, fov), np.array(want))
    np.testing.assert_array_equal(frustum_mask(torch.from_numpy(pts), fov).numpy(), np.array(want))
    assert crop_to_frustum(pts, fov).shape == (sum(want), 3)


def test_bad_input_errors(sim_root, tmp_path):
    import shutil
    root = tmp_path / "bad"
    shutil.copytree(sim_root, root)
    run = ColoRadarRun(root / "lab_run0")
    f = run.adc_path(1)
    f.write_bytes(f.read_bytes()[:-10])
    with pytest.raises(DataFileError, match=r"frame_1\.bin.*expected 49152 bytes.*found 49142"):
        run.adc(1)
    hm = run.heatmap_path(0)
    arr = np.fromfile(hm, np.float32)
    arr[5] = np.nan
    arr.tofile(hm)
    with pytest.raises(DataFileError, match="heatmap_0.bin.*NaN"):
        run.heatmap(0)
    # simulated root: every scan must have the recorded beams x azimuth steps x 16 bytes
    assert run.lidar_nbytes == 8 * 128 * 16
    good = run.lidar_path(3).read_bytes()
    run.lidar_path(3).write_bytes(good[:-32])              # short by two whole points
    with pytest.raises(DataFileError, match=r"lidar_pointcloud_3\.bin.*expected 16384 bytes.*simulation\.json.*"
                                            r"found 16352 \(truncated\)"):
        run.lidar(3)
    from radarpc.data.summary import check_run
    bad = check_run(ColoRadarRun(root / "lab_run0"))                  # what `radarpc info --check` lists
    assert any("lidar_pointcloud_3.bin" in line and "16352" in line for line in bad)
    run.lidar_path(3).write_bytes(good)
    assert run.lidar(3, drop_zeros=False).shape == (8 * 128, 4)
    # real-data rules (no simulation.json): any whole number of points, empty scans refused
    real = ColoRadarRun(root / "lab_run0", lidar_nbytes=None)
    real.lidar_path(0).write_bytes(b"")
    with pytest.raises(DataFileError, match="lidar_pointcloud_0.bin.*empty"):
        real.lidar(0)
    np.zeros((10, 4), np.float32).tofile(real.lidar_path(1))
    with pytest.raises(DataFileError, match="lidar_pointcloud_1.bin.*empty"):
        real.lidar(1)
    real.lidar_path(2).write_bytes(b"\0" * 20)
    with pytest.raises(DataFileError, match="multiple of 16"):
        real.lidar(2)
    assert real.lidar(3).shape[1] == 4
    with pytest.raises(ValueError, match="lidar_nbytes"):
        ColoRadarRun(root / "lab_run0", lidar_nbytes=20)
    # a NaN ground-truth pose fails the Dataset up front, naming the file
    gtp = root / "lab_run1" / "groundtruth" / "groundtruth_poses.txt"
    lines = gtp.read_text().splitlines()
    lines[2] = " ".join(["nan"] + lines[2].split()[1:])
    gtp.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFileError, match=r"lab_run1/groundtruth/groundtruth_poses\.txt.*NaN"):
        ColoRadar(root, "all", cube_size=None)
    # broken simulator metadata is named
    meta = (root / "simulation.json").read_text()
    (root / "simulation.json").write_text(meta.replace('"beams"', '"nbeams"'))
    with pytest.raises(DataFileError, match=r"simulation\.json.*lidar\.beams"):
        ColoRadarRun(root / "lab_run0")
    (root / "simulation.json").write_text(meta)
    (root / "calib" / "single_chip" / "antenna_cfg.txt").unlink()
    with pytest.raises(DataFileError, match="antenna_cfg.txt.*missing"):
        ColoRadarRun(root / "lab_run0")
    with pytest.raises(DataFileError, match="antenna_cfg.txt"):
        ColoRadar(root, "all")


def test_rald_cube_keeps_its_grid_whatever_the_calib_heatmap(sim_root):
    # calib/single_chip/heatmap_cfg.txt holds the dataset's grid (8 x 64 x 64); RaLD's cube keeps its
    # 128 range x 8 azimuth x 2 elevation bins, identical to the cube of a chip whose heatmap grid is
    # RaLD's (what the calib files held before)
    ds = ColoRadar(sim_root, "all", cube_size=None)
    assert ds.calib.single_chip.heatmap.shape == (8, 64, 64, 2)
    chip = ds.calib.single_chip
    d = chip.element_spacing
    rald_grid = HeatmapConfig(128, 2, 8, chip.waveform.range_bin_width(128), beam_angles(8, d), beam_angles(2, d))
    k, ri, _ = ds.index[0]
    cube = ds.cube(0)
    ref = radar_cube(ds.runs[k].adc(ri), dataclasses.replace(chip, heatmap=rald_grid))
    assert cube.intensity_db.shape == (128, 8, 2)
    torch.testing.assert_close(cube.intensity_db, ref.intensity_db, rtol=0, atol=0)
    torch.testing.assert_close(cube.azimuth_rad, ref.azimuth_rad, rtol=0, atol=0)


def test_upsample_intensity_is_ralds_angle_upsampling():
    chip = AWR1843.replace(num_chirps_per_frame=8)
    rng = np.random.default_rng(0)
    x = (rng.normal(size=(3, 4, 8, 128)) + 1j * rng.normal(size=(3, 4, 8, 128))).astype(np.complex64)
    one = radar_cube(x, chip, n_doppler=8)
    up = upsample_intensity(one.intensity_db, (128, 64, 32))
    assert up.shape == (128, 64, 32)
    torch.testing.assert_close(upsample_intensity(one), up)
    # equal range size: per range bin, RaLD's bilinear (align_corners=True) angle upsampling
    ref = torch.nn.functional.interpolate(one.intensity_db[None], size=(64, 32), mode="bilinear", align_corners=True)[0]
    torch.testing.assert_close(up, ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(up[:, 0, 0], one.intensity_db[:, 0, 0])     # align_corners keeps corners
    torch.testing.assert_close(up[:, -1, -1], one.intensity_db[:, -1, -1])
    batch = upsample_intensity(torch.stack([one.intensity_db, one.intensity_db + 1]), (128, 64, 32))
    torch.testing.assert_close(batch[1], up + 1)


def test_rald_intensity_clips_divides_then_upsamples_by_hand():
    # RaLD's input: clip to [0, 45] dB, divide by 45, then bilinear (align_corners) angle upsampling.
    # One range bin, 2 x 2 angles [[-5, 50], [9, 27]] dB -> [[0, 1], [0.2, 0.6]] -> 3 x 3 by hand:
    db = torch.tensor([[[-5.0, 50.0], [9.0, 27.0]]])                            # (R=1, A=2, E=2)
    want = torch.tensor([[[0.0, 0.5, 1.0], [0.1, 0.45, 0.8], [0.2, 0.4, 0.6]]])
    got = rald_intensity(db, (1, 3, 3))
    torch.testing.assert_close(got, want, rtol=0, atol=1e-6)
    # the order matters: clipping the upsampled dB would give (-5 + 9) / 2 / 45 at [0, 1, 0], not 0.1
    assert float(upsample_intensity(db, (1, 3, 3)).clamp(0, 45)[0, 1, 0] / 45) == pytest.approx(2 / 45)
    # a RadarCube is read through its intensity; the ceiling is a parameter; the default size is RaLD's
    chip = AWR1843.replace(num_chirps_per_frame=8)
    x = np.random.default_rng(0).normal(size=(3, 4, 8, 128)) * (1 + 1j)
    cube = radar_cube(x.astype(np.complex64), chip, n_doppler=8)
    full = rald_intensity(cube)
    assert full.shape == (128, 64, 32) and 0.0 <= float(full.min()) and float(full.max()) <= 1.0
    torch.testing.assert_close(full, upsample_intensity(cube.intensity_db.clamp(0, 45) / 45))
    torch.testing.assert_close(rald_intensity(db, (1, 2, 2), max_db=9.0), torch.tensor([[[0.0, 1.0], [1.0, 1.0]]]))
    with pytest.raises(ValueError, match="max_db"):
        rald_intensity(db, max_db=0.0)


def test_cli_simulate_and_info(sim_root, colo_cli_root, tmp_path, capsys, monkeypatch):
    from radarpc.cli import main

    # the session's `radarpc simulate coloradar --scenes outdoor --runs-per-scene 1 --frames 1 --lidar-beams 4
    # --lidar-azimuth-steps 64 --no-progress` (tests/conftest.py checks its exit code 0); read-only
    out = colo_cli_root[0]
    run = ColoRadarRun(out / "outdoor_run0")
    assert run.num_radar_frames == 1 and run.adc(0).shape == (3, 4, 128, 128)
    assert run.lidar(0, drop_zeros=False).shape == (4 * 64, 4)
    assert main(["simulate", "coloradar", "--out", str(out), "--scenes", "lab", "--frames", "1"]) == 2
    assert "not empty" in capsys.readouterr().err
    png = tmp_path / "info.png"
    assert main(["info", str(sim_root), "--plot", str(png), "--check"]) == 0
    text = capsys.readouterr().out
    assert "lab_run2" in text and "test:" in text and "0 bad" in text
    assert png.stat().st_size > 10_000
    # default plot path: ./info_{root name}.png in the working directory, never inside the root
    monkeypatch.chdir(tmp_path)
    assert main(["info", str(sim_root)]) == 0
    assert main(["info", str(out), "--no-plot"]) == 0
    assert (tmp_path / f"info_{sim_root.name}.png").stat().st_size > 10_000
    assert not (tmp_path / f"info_{out.name}.png").exists()
    assert not list(sim_root.glob("*.png")) and not list(out.glob("*.png"))


def test_short_lidar_timestamps_are_reported(sim_root, tmp_path, capsys):
    # a lidar/timestamps.txt with fewer lines than scan files used to pass `info --check` with
    # "0 bad" while the scans without a line were silently never paired
    import shutil
    from radarpc.cli import main
    from radarpc.data.summary import check_run

    root = tmp_path / "short"
    shutil.copytree(sim_root, root)
    ts = root / "lab_run2" / "lidar" / "timestamps.txt"
    lines = ts.read_text().splitlines()
    n_scans = len(list((root / "lab_run2" / "lidar" / "pointclouds").glob("lidar_pointcloud_*.bin")))
    assert len(lines) == n_scans > 2
    ts.write_text("\n".join(lines[:2]) + "\n")
    want = rf"lab_run2/lidar/timestamps\.txt: 2 timestamp lines but {n_scans} LiDAR scan files in lidar/pointclouds/"
    with pytest.raises(DataFileError, match=want):
        ColoRadar(root, "test", cube_size=None)
    assert len(ColoRadar(root, "train", cube_size=None)) > 0          # other runs still read
    bad = check_run(ColoRadarRun(root / "lab_run2"))
    assert len(bad) == 1 and "2 timestamp lines" in bad[0]
    assert main(["info", str(root), "--check", "--no-plot"]) == 1
    out = capsys.readouterr().out
    assert "1 bad" in out and f"2 timestamp lines but {n_scans} LiDAR scan files" in out
    # more lines than ADC frame files: named too
    (root / "lab_run2" / "lidar" / "timestamps.txt").write_text("\n".join(lines) + "\n")
    run = ColoRadarRun(root / "lab_run2")
    run.adc_path(run.num_radar_frames - 1).unlink()
    with pytest.raises(DataFileError, match=r"adc_samples/timestamps\.txt: \d+ timestamp lines but \d+ "
                                            r"single-chip ADC frame files"):
        run.check_counts()


def test_calib_beside_runs_folder(sim_root, tmp_path):
    # coloradar-library layout: <dir>/kitti/<run>/ and <dir>/calib/
    import shutil
    shutil.copytree(sim_root / "calib", tmp_path / "calib")
    shutil.copytree(sim_root / "lab_run2", tmp_path / "kitti" / "lab_run2")
    ds = ColoRadar(tmp_path / "kitti", "all")
    assert [r.name for r in ds.runs] == ["lab_run2"] and ds.calib == CALIB
    with pytest.raises(DataFileError, match="calib"):
        ColoRadar(tmp_path / "kitti" / "lab_run2" / "lidar", "all")


def test_check_lists_every_run_that_cannot_be_opened(sim_root, tmp_path, capsys):
    # an empty and a decreasing timestamps file in two runs: --check names both, not only the first
    import shutil
    from radarpc.cli import main

    root = tmp_path / "bad_ts"
    shutil.copytree(sim_root, root)
    (root / "lab_run0" / "lidar" / "timestamps.txt").write_text("")
    ts = root / "lab_run1" / "lidar" / "timestamps.txt"
    ts.write_text("\n".join(reversed(ts.read_text().splitlines())) + "\n")
    assert main(["info", str(root), "--check", "--no-plot"]) == 1
    out = capsys.readouterr().out
    assert "lab_run0/lidar/timestamps.txt" in out and "lab_run1/lidar/timestamps.txt" in out
    assert "2 bad" in out
