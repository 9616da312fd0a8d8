"""The occupancy baseline's config: the shipped and test configs load, bad files end in one line
naming the file and the field before any data is read."""
from __future__ import annotations

from pathlib import Path

import pytest

from radarpc.cli import main
from radarpc.config import to_dict
from radarpc.experiments.rald.config import load_experiment as load_rald_experiment
from radarpc.experiments.rpdnet.config import (DEFAULT_CELL, OccupancyExperiment, OccupancyTarget, canonical_key,
                                               load_experiment)

CONFIGS = Path(__file__).parents[3] / "configs"
TEST_CONFIGS = Path(__file__).parent / "configs"
OCC = ("name: x\nstage: occupancy\nmodel: {variant: rpdnet-tiny}\ntarget: {cell: [0.5, 11.25, 5.0]}\n"
       "train: {epochs: 1, select_metric: iou, select_mode: max}\n")


def test_shipped_and_test_configs_load():
    cfg = load_experiment(CONFIGS / "rpdnet-s.yaml")
    assert isinstance(cfg, OccupancyExperiment) and cfg.model.variant == "rpdnet-s" and cfg.stage == "occupancy"
    assert cfg.target.cell == DEFAULT_CELL and cfg.target.grid().shape == cfg.model.config.out_shape == (64, 32, 16)
    assert cfg.radar.max_intensity_db == 45.0 and cfg.model.config.radar_shape == (128, 64, 32)
    assert (cfg.train.select_metric, cfg.train.select_mode) == ("iou", "max")
    tiny = load_experiment(TEST_CONFIGS / "rpdnet-tiny.yaml")
    assert tiny.target.grid().shape == tiny.model.config.out_shape == (32, 16, 8)


def test_default_grid_by_hand():
    """AWR1843's field of view, 0..15.863 m, +-90 deg, +-20 deg, in cells of 0.25 m x 5.625 deg x
    2.5 deg: ceil(63.45) = 64 range cells (to 16 m), 180 / 5.625 = 32, 40 / 2.5 = 16."""
    g = OccupancyTarget().grid()
    assert g.shape == (64, 32, 16) and g.range_m == (0.0, 16.0) and g.azimuth_deg == (-90.0, 90.0)
    assert g.elevation_deg == (-20.0, 20.0)


@pytest.mark.parametrize("text, message", [
    (OCC.replace("rpdnet-tiny", "rald-dit-tiny"), "stage 'occupancy' trains a radar-to-occupancy network (rpdnet, "
                                                  "rpdnet-s, rpdnet-tiny), but model 'rald-dit-tiny' is a "
                                                  "LatentDiTConfig model"),
    (OCC.replace("[0.5, 11.25, 5.0]", "[0.25, 5.625, 2.5]"),
     "target.cell [0.25, 5.625, 2.5] cuts the field of view into 64 x 32 x 16 cells, but model 'rpdnet-tiny' "
     "writes 32 x 16 x 8 (radar_shape / out_stride)"),
    (OCC.replace("[0.5, 11.25, 5.0]", "[0.5, -11.25, 5.0]"), "target.cell must be 3 sizes > 0"),
    (OCC.replace("}\ntrain", ", occupied_weight: 0}\ntrain"), "target.occupied_weight must be a finite number > 0, got 0"),
    (OCC.replace("select_metric: iou", "select_metric: f2"),
     "train.select_metric 'f2' is not a validation metric of the occupancy baseline; one of loss, iou, precision, "
     "recall, f1"),
    (OCC.replace("select_mode: max", "select_mode: min"), "train.select_mode 'min': iou is better when higher"),
    (OCC + "data: {points: 5}\n", "OccupancyExperiment unknown keys ['data']"),
    (OCC + "radar: {max_intensity_db: 0}\n", "radar.max_intensity_db must be a finite number > 0, got 0"),
    ("name: x\nstage: occupancy\nmodel: {variant: rpdnet-tiny}\n", "no 'train'"),
])
def test_bad_configs(tmp_path, capsys, text, message):
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as e:
        load_experiment(path)
    assert message in str(e.value) and str(path) in str(e.value)
    code = main(["train", str(path), "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "run"),
                 "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and str(path) in err and message in err
    assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run").exists()


def test_options_of_other_experiments_are_refused(tmp_path, capsys):
    path = tmp_path / "cfg.yaml"
    path.write_text(OCC)
    for extra, what in ((["--ae", str(tmp_path)], "--ae"), (["--points", "x.parquet"], "--points"),
                        (["--runs", "2"], "--runs 2")):
        assert main(["train", str(path), "--data", str(tmp_path), "--out", str(tmp_path / "run"), *extra]) == 2
        err = capsys.readouterr().err
        assert "is the occupancy baseline (stage: occupancy), which takes no " + what in err
    assert not (tmp_path / "run").exists()


def test_a_radar_to_occupancy_model_is_refused_by_the_diffusion_stage(tmp_path):
    path = tmp_path / "dit.yaml"
    path.write_text("name: x\nstage: diffusion\nmodel: {variant: rpdnet-tiny}\n"
                    "train: {epochs: 1, select_metric: loss, select_mode: min}\n")
    with pytest.raises(ValueError, match="model 'rpdnet-tiny' is a RPDNetConfig model .a radar-to-occupancy network "
                                         "trains with stage: occupancy."):
        load_rald_experiment(path)


def test_canonical_key_reads_stored_keys_through_the_types():
    cfg = load_experiment(TEST_CONFIGS / "rpdnet-tiny.yaml")
    stored = to_dict(cfg)
    del stored["target"]["occupied_weight"]                    # a key stored before the field existed
    key = canonical_key({"experiment": stored, "data": "/r"}, num_workers=3)
    assert key["experiment"]["target"]["occupied_weight"] == 4.0 and key["experiment"]["train"]["num_workers"] == 3
