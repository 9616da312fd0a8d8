"""``radarpc simulate radial`` flags of the release's other modalities: --cube-format, --no-camera,
--no-laser."""
from __future__ import annotations

import json

import pytest

from radarpc.cli import main
from radarpc.data.radial_format import camera_path, fft_path, laser_pcl_path


def test_flags(tmp_path, capsys):
    out = tmp_path / "sim"
    argv = ["simulate", "radial", "--out", str(out), "--sensor", "tiny", "--sequences", "1",
            "--frames-per-sequence", "2", "--no-progress", "--cube-format", "npz", "--no-laser"]
    assert main(argv) == 0
    assert "2 simulated now" in capsys.readouterr().out
    assert fft_path(out, 1, ".npz").is_file() and not fft_path(out, 1).exists()
    assert camera_path(out, 1).is_file() and not laser_pcl_path(out, 1).exists()
    assert json.loads((out / "outputs.json").read_text()) == {"cube_format": "npz", "camera": True,
                                                              "laser_PCL": False}
    # the outputs are part of the run's key: other ones are refused without --overwrite
    assert main(argv[:-3] + ["--no-camera"]) == 2
    assert "outputs.json" in capsys.readouterr().err
    out2 = tmp_path / "bare"
    assert main(["simulate", "radial", "--out", str(out2), "--sensor", "tiny", "--sequences", "1",
                 "--frames-per-sequence", "1", "--no-progress", "--no-camera", "--no-laser"]) == 0
    assert fft_path(out2, 0).is_file() and not (out2 / "camera").exists() and not (out2 / "laser_PCL").exists()


def test_bad_cube_format(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "radial", "--out", "x", "--cube-format", "npy.gz"])
    assert "invalid choice: 'npy.gz'" in capsys.readouterr().err
