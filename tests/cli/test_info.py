"""Tests of ``radarpc info`` on a tiny hand-made RADIal root (TINY sensor)."""
from __future__ import annotations

import argparse
import csv
import json
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from radarpc.cli import info
from radarpc.data.radial_format import LABEL_COLUMNS, fft_path, freespace_path, simulated_sequence_name
from radarpc.data.summary import summarize_radial
from radarpc.io import DataFileError
from radarpc.data.radial_format import save_calibration
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_calibration import make_calibration


def write_root(root: Path) -> Path:
    """4 sequences x 2 frames (numSample 10q + j); frame j=0 has vehicles at R = 5 + 10q m, j=1 none."""
    (root / "radar_FFT").mkdir(parents=True)
    (root / "radar_Freespace").mkdir()
    rng = np.random.default_rng(0)
    with open(root / "labels.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(LABEL_COLUMNS)
        for q in range(4):
            for j in range(2):
                num = 10 * q + j
                rows = []
                if j == 0:
                    for r, a, d, diff in ((5.0 + 10 * q, -20.0 + q, 2.0, 0), (30.0, 40.0, -1.0, q % 2)):
                        x, y = r * np.cos(np.deg2rad(a)), r * np.sin(np.deg2rad(a))
                        rows.append([num, -1, -1, -1, -1, x, y, 0.0, x, y, r, a, d, 50.0,
                                     simulated_sequence_name(0, q), j, diff])
                else:
                    rows.append([num] + [-1] * 13 + [simulated_sequence_name(0, q), j, -1])
                w.writerows(rows)
                cube = (rng.normal(size=TINY.rd_shape) + 1j * rng.normal(size=TINY.rd_shape))
                np.save(fft_path(root, num), cube.astype(np.complex64))
                m = np.zeros((512, 900), np.uint8)
                m[:100] = 255
                Image.fromarray(m).save(freespace_path(root, num))
    d = TINY.to_dict()
    d.update(seed=0, n_sequences=4, frames_per_sequence=2, radarpc_version="0.1.0")
    (root / "sensor.json").write_text(json.dumps(d))
    save_calibration(root / "calibration.npz", make_calibration(TINY))
    return root


def run(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="radarpc")
    info.add_parser(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(["info", *argv])
    return args.func(args)


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return write_root(tmp_path / "sim")


def test_info_summary_and_plot(root: Path, tmp_path: Path, capsys: pytest.CaptureFixture,
                               monkeypatch: pytest.MonkeyPatch) -> None:
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    assert run([str(root)]) == 0
    out = capsys.readouterr().out
    # 4 sequences: q0, q1 train, q2 val, q3 test (simulated_split with n = 4)
    assert "frames:      8" in out and "sequences:   4" in out
    assert "train 4 frames / 2 seq, val 2 frames / 1 seq, test 2 frames / 1 seq" in out
    assert "vehicles:    8 labels (2 difficult)" in out
    assert "empty:       4 frames without vehicles" in out
    assert "range:       5.00 .. 35.00 m" in out
    assert "azimuth:     -20.00 .. 40.00 deg" in out
    assert "velocity:    -1.00 .. 2.00 m/s" in out
    assert "sensor:      tiny" in out
    assert "warning" not in out
    with Image.open(cwd / "info_sim.png") as im:                 # default: ./info_{root name}.png
        assert im.format == "PNG" and im.size[0] > 400
    assert f"plot:        {cwd / 'info_sim.png'}" in out
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before   # root untouched
    custom = root.parent / "plots" / "s.png"
    assert run([str(root), "--plot", str(custom)]) == 0 and custom.is_file()
    assert not list(custom.parent.glob(".*.tmp"))  # atomic write left no temp file


def test_empty_split_warning(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from radarpc.sim.radial_writer import write_radial_dataset

    out = write_radial_dataset(tmp_path / "two", TINY, 2, 1, 0, progress=False)   # 2 sequences: train only
    assert run([str(out), "--no-plot"]) == 0
    text = capsys.readouterr().out
    assert "warning:     split 'val' is empty (2 sequences;" in text
    assert "warning:     split 'test' is empty" in text and "split 'train' is empty" not in text


def test_summary_object(root: Path) -> None:
    s = summarize_radial(root)
    assert s.simulated and s.n_frames == 8 and s.n_vehicles == 8 and s.n_empty_frames == 4
    assert s.split_frames == {"train": 4, "val": 2, "test": 2}
    assert s.split_sequences == {"train": 2, "val": 1, "test": 1}


def test_check_clean_root(root: Path, capsys: pytest.CaptureFixture) -> None:
    assert run([str(root), "--check", "--no-plot"]) == 0
    out = capsys.readouterr().out
    assert "8 frames checked, 0 problem(s)" in out
    assert not (root / "info.png").exists()


def test_check_lists_missing_and_corrupt(root: Path, tmp_path: Path, capsys: pytest.CaptureFixture,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    fft_path(root, 11).unlink()                                  # missing cube
    b = freespace_path(root, 20).read_bytes()
    freespace_path(root, 20).write_bytes(b[: len(b) // 3])       # corrupt PNG
    skip = tmp_path / "skip.txt"
    assert run([str(root), "--check", "--write-skip", str(skip), "--no-plot"]) == 1
    out = capsys.readouterr().out
    assert "2 problem(s), 2 bad frame(s)" in out
    assert "frame 11:" in out and "fft_000011.npy" in out and "missing" in out
    assert "frame 20:" in out and "freespace_000020.png" in out and "truncated" in out
    assert skip.read_text() == "11\n20\n"
    # --write-skip alone implies --check
    skip.unlink()
    assert run([str(root), "--write-skip", str(skip), "--no-plot"]) == 1 and skip.read_text() == "11\n20\n"
    # the plot still finds a readable cube and the reader skips the listed frames
    from radarpc.data.radial import RADIal

    assert run([str(root)]) == 0
    ds = RADIal(root, "all", skip=skip)
    assert 11 not in ds.frame_ids and len(ds) == 6
    for k in range(len(ds)):
        ds[k]


def test_bad_labels(root: Path, capsys: pytest.CaptureFixture) -> None:
    (root / "labels.csv").write_text("numSample,foo\n1,2\n")
    with pytest.raises(DataFileError, match=r"labels.csv: header .*missing columns"):
        run([str(root)])
    assert run([str(root), "--check"]) == 1
    assert "labels.csv" in capsys.readouterr().out


def test_neither_root_and_coloradar_dispatch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(DataFileError, match="neither a RADIal root"):
        run([str(tmp_path)])
    with pytest.raises(DataFileError, match="missing"):
        run([str(tmp_path / "absent")])
    (tmp_path / "calib").mkdir()
    seen = []
    fake = types.ModuleType("radarpc.cli.info_coloradar")
    fake.info_coloradar = lambda args: seen.append(args.root) or 7
    monkeypatch.setitem(sys.modules, "radarpc.cli.info_coloradar", fake)
    assert run([str(tmp_path)]) == 7 and seen == [str(tmp_path)]


def test_through_radarpc_main(tmp_path: Path, capsys: pytest.CaptureFixture,
                              monkeypatch: pytest.MonkeyPatch) -> None:
    from radarpc.cli import main

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "sim"
    assert main(["simulate", "radial", "--out", str(out), "--sequences", "3", "--frames-per-sequence", "2",
                 "--sensor", "tiny", "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--check"]) == 0
    text = capsys.readouterr().out
    assert "frames:      6" in text and "sequences:   3" in text and "0 problem(s)" in text
    assert "train 2 frames / 1 seq, val 2 frames / 1 seq, test 2 frames / 1 seq" in text
    assert (tmp_path / "info_sim.png").is_file() and not (out / "info.png").exists()
    fft_path(out, 3).write_bytes(b"\x93NUMPY garbage")
    assert main(["info", str(out), "--check", "--no-plot"]) == 1
    assert "frame 3:" in capsys.readouterr().out
    # a folder that is neither layout: one clear line on stderr, exit code 2
    assert main(["info", str(tmp_path)]) == 2
    assert "neither a RADIal root" in capsys.readouterr().err


def test_coloradar_info_and_check(colo_hallway_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    from radarpc.data.summary import open_coloradar_runs, summarize_coloradar

    # a copy of the session's hallway root (3 runs x 2 radar frames, no cascade): this test damages a scan
    root = shutil.copytree(colo_hallway_root, tmp_path / "colo")
    monkeypatch.chdir(tmp_path)
    assert run([str(root), "--check"]) == 0
    out = capsys.readouterr().out.splitlines()
    s = summarize_coloradar(root, *open_coloradar_runs(root))
    assert out[0] == f"ColoRadar root {root} (simulated)" and out[1].startswith("single chip: ADC ")
    assert out[2].startswith("run ") and "pts/scan" in out[2]             # no cascade line
    for line, r in zip(out[3:6], s.runs):
        assert line.split() == [r.name, r.scene, r.split, str(r.radar_frames), "0", str(r.lidar_scans),
                                str(r.pairs), f"{r.duration_s:.1f}", f"{r.lidar_points[0]:.0f}",
                                f"{r.lidar_points[1]:.0f}"]
    assert out[6:10] == ["scenes:      1 (hallway)", "train:       1 run, 2 paired frames",
                         "val:         1 run, 2 paired frames", "test:        1 run, 2 paired frames"]
    assert out[10] == (f"LiDAR:       {s.lidar_points[0]:.0f} points per scan, {s.lidar_points[1]:.0f} inside "
                       f"the radar frustum (mean of sampled scans)")
    assert out[11] == f"plot:        {tmp_path / 'info_colo.png'}" and (tmp_path / "info_colo.png").is_file()
    n_files = sum(r.radar_frames + r.lidar_scans for r in s.runs)
    assert out[12:] == [f"check:       {n_files} files, 0 bad"]
    p = root / s.runs[0].name / "lidar" / "pointclouds" / "lidar_pointcloud_0.bin"
    p.write_bytes(p.read_bytes()[:-32])
    skip = tmp_path / "bad.txt"
    assert run([str(root), "--write-skip", str(skip), "--no-plot"]) == 1
    text = capsys.readouterr().out
    assert f"check:       {n_files} files, 1 bad" in text and "lidar_pointcloud_0.bin" in skip.read_text()
    assert f"skip list:   1 file written to {skip}" in text and "plot:" not in text


def test_a_directory_as_plot_or_skip_list_is_refused_before_work(tiny_root, tmp_path, capsys):
    from radarpc.cli import main

    root = tiny_root                                                # read-only: refused before any work
    d = tmp_path / "figs"
    d.mkdir()
    for args in (["--plot", str(d)], ["--no-plot", "--write-skip", str(d)]):
        capsys.readouterr()
        assert main(["info", str(root), *args]) == 2
        captured = capsys.readouterr()
        assert "is a directory; give a file name" in captured.err and captured.out == ""
