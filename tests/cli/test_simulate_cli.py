"""``radarpc simulate``: the summary says what was simulated now and what an earlier run left."""
from __future__ import annotations

import shutil

from radarpc.cli import main
from radarpc.cli.text import plural
from radarpc.data.radial_format import fft_path
from testkit import COLO_CLI_ARGV


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


def test_coloradar_summary_counts_kept_files(colo_cli_root, tmp_path, capsys):
    # the session's one `radarpc simulate coloradar` run (testkit.COLO_CLI_ARGV: one outdoor run, one frame)
    # and what it printed; resumed here on a copy
    root, first = colo_cli_root
    assert f"{root}: 1 scene x 1 run x 1 radar frame (outdoor); " in first      # singular counts
    n = int(first.split("); ")[1].split(" radar frames and LiDAR scans simulated now")[0])
    assert n > 0 and f"{n} radar frames and LiDAR scans simulated now, 0 kept" in first
    out = shutil.copytree(root, tmp_path / "colo")
    argv = COLO_CLI_ARGV + ["--out", str(out)]
    scans = sorted((out / "outdoor_run0" / "lidar" / "pointclouds").glob("*.bin"))
    scans[0].unlink()
    assert main(argv) == 0
    # one file written again: singular
    assert f"1 radar frame or LiDAR scan simulated now, {n - 1} kept" in capsys.readouterr().out


def test_plural():
    assert [plural(n, "sequence") for n in (0, 1, 2)] == ["0 sequences", "1 sequence", "2 sequences"]
    assert plural(1, "CFAR peak") == "1 CFAR peak" and plural(12, "CFAR peak") == "12 CFAR peaks"
    assert plural(1, "radar frame or LiDAR scan", "radar frames and LiDAR scans") == "1 radar frame or LiDAR scan"
    assert plural(3, "radar frame or LiDAR scan", "radar frames and LiDAR scans") == "3 radar frames and LiDAR scans"
