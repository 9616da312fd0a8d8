"""What a user reads before running anything: `--help` (fast, plain text, defaults shown) and the
first error a wrong root, a pickled calibration or an oversized CFAR window gives."""
from __future__ import annotations

import argparse
import subprocess
import sys

import numpy as np
import pytest

from radarpc.cli import build_parser, main


def _all_parsers(parser: argparse.ArgumentParser, name: str = "radarpc"):
    """``(command line, parser)`` of the parser and every sub-command parser below it."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from _all_parsers(sub, f"{name} {sub_name}")


def test_help_imports_no_torch():
    # `radarpc --help` took 1.7 s because every command module imported torch at module level
    code = "import sys; from radarpc.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_help_choices_match_the_library():
    # the parsers use torch-free copies of the library's choice lists
    from radarpc.cli import options
    from radarpc.distributed import DEFAULT_WAIT_S
    from radarpc.models import MODELS
    from radarpc.dsp.beamform import BEAMFORMING_MODES
    from radarpc.dsp.ddma import ENVELOPES
    from radarpc.dsp.pointcloud import CFAR_PRESETS
    from radarpc.experiments.rald.official import WEIGHTS
    from radarpc.experiments.study.config import STUDY_KINDS
    from radarpc.rald.guide import GUIDE_SOURCES
    from radarpc.rald.reconstruct import POSTERIORS
    from radarpc.sensors.radial import RADIAL_SENSORS
    from radarpc.sim.indoor import SCENE_KINDS
    from radarpc.viz import COLOR_BY

    assert options.RADIAL_SENSOR_NAMES == tuple(RADIAL_SENSORS)
    assert options.SCENE_KINDS == SCENE_KINDS
    assert options.CFAR_PRESET_NAMES == tuple(CFAR_PRESETS)
    assert options.BEAMFORMING_MODES == BEAMFORMING_MODES
    assert options.ENVELOPES == ENVELOPES
    assert options.COLOR_BY == COLOR_BY
    assert options.DEFAULT_WAIT_S == DEFAULT_WAIT_S
    assert options.MODEL_NAMES == tuple(MODELS)
    assert options.STUDY_KINDS == tuple(STUDY_KINDS)
    assert options.GUIDE_SOURCES == GUIDE_SOURCES
    assert options.POSTERIORS == POSTERIORS
    assert options.OFFICIAL_RALD_WEIGHTS == WEIGHTS


def test_every_help_is_plain_text_with_defaults():
    parsers = dict(_all_parsers(build_parser()))
    for name in ("radarpc pointcloud", "radarpc show", "radarpc demo", "radarpc info", "radarpc baseline os-cfar",
                 "radarpc evaluate-points", "radarpc simulate radial", "radarpc simulate coloradar"):
        assert name in parsers
    for name, p in parsers.items():
        text = p.format_help()
        assert "``" not in text and ":mod:" not in text and ":func:" not in text, name
        assert not any(line.rstrip().endswith("::") for line in text.splitlines()), name
        assert "seed's" not in text and "seed eq" not in text and "(seed:" not in text, name
        for action in p._actions:                              # every option says what it does
            if action.option_strings and action.help != argparse.SUPPRESS:
                assert action.help, f"{name} {action.option_strings[0]} has no help"
    assert "Examples:" in parsers["radarpc pointcloud"].format_help()
    demo = parsers["radarpc demo"].format_help()
    for opt in ("--sequences", "--frames-per-sequence", "--colo-frames", "--seed", "--device", "--pillars-steps",
                "--fftradnet-steps", "--batch-size"):
        assert opt in demo
    assert "(default 150," in demo and "(default 4," in demo and "(default 6," in demo and "(default 0," in demo
    assert "(default 200," in demo and "(default 60," in demo
    assert "--tiny" in demo and "--data ROOT" in demo
    for name in ("radarpc baseline os-cfar", "radarpc evaluate-points", "radarpc pointcloud", "radarpc generate"):
        split = next(a for a in parsers[name]._actions if "--split" in a.option_strings)
        assert f"default {split.default}" in split.help, name


def test_wrong_layout_names_the_layout(tmp_path, capsys):
    colo, radial = tmp_path / "colo", tmp_path / "radial"
    (colo / "calib").mkdir(parents=True)
    radial.mkdir()
    (radial / "labels.csv").write_text("numSample\n")
    assert main(["pointcloud", str(colo), "--snr", "2", "--out", str(tmp_path / "pc.parquet")]) == 2
    err = capsys.readouterr().err
    assert "this is a ColoRadar root" in err and "`radarpc pointcloud`" in err and "labels.csv is missing" not in err
    assert main(["baseline", "os-cfar", str(radial), "--out", str(tmp_path / "preds")]) == 2
    err = capsys.readouterr().err
    assert "this is a RADIal root" in err and "`radarpc baseline`" in err and "calibration folder" not in err


def test_pickled_calibration_message_names_a_real_way(tmp_path):
    from radarpc.data.radial_format import load_calibration
    from radarpc.io import DataFileError

    path = tmp_path / "CalibrationTable.npy"
    np.save(path, np.array({"Signal": 0}, dtype=object), allow_pickle=True)
    with pytest.raises(DataFileError) as e:
        load_calibration(path)
    msg = str(e.value)
    assert "--trust-pickle" not in msg                      # no command has that flag
    assert "save_calibration" in msg and "calibration.npz" in msg and "trust_pickle=True" in msg


def test_window_larger_than_the_envelope_is_refused(tmp_path, capsys):
    root = tmp_path / "r"
    assert main(["simulate", "radial", "--out", str(root), "--sensor", "tiny", "--sequences", "1",
                 "--frames-per-sequence", "1", "--no-progress"]) == 0
    argv = ["pointcloud", str(root), "--snr", "2", "--quiet", "--out", str(tmp_path / "pc.parquet")]
    assert main(argv + ["--window", "201,201"]) == 2
    err = capsys.readouterr().err
    assert "CFAR window (201, 201) is larger than the 64 x 32 (range x Doppler) RD cube" in err
    assert main(argv + ["--window", "63,31", "--guard", "3,3"]) == 0
