"""``radarpc simulate``: the summary says what was simulated now and what an earlier run left."""
from __future__ import annotations

from radarpc.cli import main
from radarpc.data.radial_format import fft_path


def test_radial_summary_counts_kept_frames(tmp_path, capsys):
    out = tmp_path / "sim"
    argv = ["simulate", "radial", "--out", str(out), "--sensor", "tiny", "--sequences", "2",
            "--frames-per-sequence", "2", "--no-progress"]
    assert main(argv) == 0
    assert "4 simulated now, 0 kept from an earlier run" in capsys.readouterr().out
    fft_path(out, 3).unlink()                                    # as an interrupted run leaves it
    assert main(argv) == 0
    assert "1 simulated now, 3 kept from an earlier run" in capsys.readouterr().out


def test_coloradar_summary_counts_kept_files(tmp_path, capsys):
    out = tmp_path / "colo"
    argv = ["simulate", "coloradar", "--out", str(out), "--scenes", "hallway", "--runs-per-scene", "1",
            "--frames", "2", "--lidar-beams", "4", "--lidar-azimuth-steps", "16", "--no-progress"]
    assert main(argv) == 0
    first = capsys.readouterr().out
    n = int(first.split("); ")[1].split(" radar frames and LiDAR scans simulated now")[0])
    assert n > 0 and f"{n} radar frames and LiDAR scans simulated now, 0 kept" in first
    scans = sorted((out / "hallway_run0" / "lidar" / "pointclouds").glob("*.bin"))
    scans[0].unlink()
    assert main(argv) == 0
    assert f"1 radar frames and LiDAR scans simulated now, {n - 1} kept" in capsys.readouterr().out
