"""``radarpc simulate``: the summary says what was simulated now and what an earlier run left."""
from __future__ import annotations

from radarpc.cli import main
from radarpc.cli.text import plural
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


def test_radial_summary_of_one_sequence_of_one_frame_is_singular(tmp_path, capsys):
    out = tmp_path / "one"
    assert main(["simulate", "radial", "--out", str(out), "--sensor", "tiny", "--sequences", "1",
                 "--frames-per-sequence", "1", "--no-progress"]) == 0
    assert f"{out}: 1 frame (1 sequence x 1) of sensor 'tiny'" in capsys.readouterr().out


def test_coloradar_summary_counts_kept_files(tmp_path, capsys):
    out = tmp_path / "colo"
    argv = ["simulate", "coloradar", "--out", str(out), "--scenes", "hallway", "--runs-per-scene", "1",
            "--frames", "2", "--lidar-beams", "4", "--lidar-azimuth-steps", "16", "--no-progress"]
    assert main(argv) == 0
    first = capsys.readouterr().out
    assert f"{out}: 1 scene x 1 run x 2 radar frames (hallway); " in first
    n = int(first.split("); ")[1].split(" radar frames and LiDAR scans simulated now")[0])
    assert n > 0 and f"{n} radar frames and LiDAR scans simulated now, 0 kept" in first
    scans = sorted((out / "hallway_run0" / "lidar" / "pointclouds").glob("*.bin"))
    scans[0].unlink()
    assert main(argv) == 0
    # one file written again: singular
    assert f"1 radar frame or LiDAR scan simulated now, {n - 1} kept" in capsys.readouterr().out


def test_plural():
    assert [plural(n, "sequence") for n in (0, 1, 2)] == ["0 sequences", "1 sequence", "2 sequences"]
    assert plural(1, "CFAR peak") == "1 CFAR peak" and plural(12, "CFAR peak") == "12 CFAR peaks"
    assert plural(1, "radar frame or LiDAR scan", "radar frames and LiDAR scans") == "1 radar frame or LiDAR scan"
    assert plural(3, "radar frame or LiDAR scan", "radar frames and LiDAR scans") == "3 radar frames and LiDAR scans"
