"""RaLD's experiment configs: the shipped ones load, bad files end in one line naming the file and
the field before any data is read, and stored keys read through the config types."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from radarpc.cli import main
from radarpc.config import to_dict
from radarpc.experiments.rald.config import (AUTOENCODER_METRICS, AutoencoderExperiment, DiffusionExperiment,
                                             LidarData, canonical_key, experiment_from_dict, load_experiment)
from radarpc.models import ModelSpec
from radarpc.rald.frustum import RALD_CELL, FrustumGrid
from radarpc.rald.voxels import RALD_VOXEL, CartesianGrid
from radarpc.training.loop import TrainConfig

CONFIGS = Path(__file__).parents[3] / "configs"
TEST_CONFIGS = Path(__file__).parent / "configs"
AE = "name: x\nstage: autoencoder\nmodel: {variant: rald-ae-tiny}\ntrain: {epochs: 1, select_metric: loss, select_mode: min}\n"
DIT = "name: x\nstage: diffusion\nmodel: {variant: rald-dit-tiny}\ntrain: {epochs: 1, select_metric: loss, select_mode: min}\n"


def test_shipped_and_test_configs_load():
    ae = load_experiment(CONFIGS / "rald-ae-s.yaml")
    assert isinstance(ae, AutoencoderExperiment) and ae.name == "rald-ae-s" and ae.model.variant == "rald-ae-s"
    assert (ae.data.points, ae.data.queries, ae.data.n_occupied, ae.data.partition) == (10_000, 10_000, 625, "frustum")
    assert ae.train.select_metric == "loss" and ae.train.select_mode == "min"
    dit = load_experiment(CONFIGS / "rald-s.yaml")
    assert isinstance(dit, DiffusionExperiment) and dit.model.variant == "rald-dit-s"
    assert dit.radar.max_intensity_db == 45.0 and (dit.loss.p_mean, dit.loss.p_std) == (-1.2, 1.2)
    # the -s pair fits: the diffusion model generates the autoencoder's latents
    a, d = ae.model.config, dit.model.config
    assert (a.n_latents, a.latent_dim) == (d.n_latents, d.latent_dim)
    tiny_ae, tiny = load_experiment(TEST_CONFIGS / "rald-ae-tiny.yaml"), load_experiment(TEST_CONFIGS / "rald-tiny.yaml")
    assert (tiny_ae.model.config.n_latents, tiny_ae.model.config.latent_dim) == (tiny.model.config.n_latents,
                                                                             tiny.model.config.latent_dim)


def test_defaults_are_ralds_and_the_grid_is_the_partitions():
    d = LidarData()
    assert (d.points, d.queries, d.occupied_fraction, d.n_occupied) == (10_000, 10_000, 0.0625, 625)
    g = d.grid()
    assert isinstance(g, FrustumGrid) and g.cell == RALD_CELL and g.shape == (318, 720, 80)
    v = LidarData(partition="cartesian").grid()
    assert isinstance(v, CartesianGrid) and v.cell == RALD_VOXEL
    assert LidarData(cell=(0.2, 2, 4)).grid().shape == (80, 90, 10)
    assert LidarData(queries=7, occupied_fraction=0.3).n_occupied == 2            # floor(2.1)


def test_model_coordinates_by_hand_and_the_official_convention():
    # radarpc's: azimuth left-positive, the range over the field of view in whole cells (0 .. 15.9 m)
    ours = LidarData()
    left = torch.tensor([[7.95 * math.cos(math.radians(30)), 7.95 * math.sin(math.radians(30)), 0.0]],
                        dtype=torch.float64)
    torch.testing.assert_close(ours.to_model(left), torch.tensor([[0.0, 1 / 3, 0.0]], dtype=torch.float64))
    # the official checkpoints': pc_range to 15.8 m (316 cells), azimuth right-positive
    official = LidarData(max_range_m=15.8, mirror_azimuth=True)
    assert official.grid().shape == (316, 720, 80) and official.grid().range_m == (0.0, 15.8)
    p = left * 7.9 / 7.95                                                  # r = 7.9 m, the official span's centre
    torch.testing.assert_close(official.to_model(p), torch.tensor([[0.0, -1 / 3, 0.0]], dtype=torch.float64))
    up = torch.tensor([[15.8 * math.cos(math.radians(20)), 0.0, 15.8 * math.sin(math.radians(20))]],
                      dtype=torch.float64)                                 # the official grid's far top corner
    torch.testing.assert_close(official.to_model(up), torch.tensor([[1.0, 0.0, 1.0]], dtype=torch.float64))
    for d in (ours, official):
        torch.testing.assert_close(d.to_radar(d.to_model(left)), left)
    torch.testing.assert_close(official.model_frame(official.model_frame(left)), left)


@pytest.mark.parametrize("text, message", [
    (AE.replace("stage: autoencoder\n", ""), "no 'stage'"),
    (AE.replace("autoencoder", "decoder"), "stage must be one of autoencoder, diffusion (the RaLD training stage), "
                                           "got 'decoder'"),
    (AE.replace("rald-ae-tiny", "rald-dit-tiny"), "stage 'autoencoder' trains a model that reads 'lidar' inputs, "
                                                  "but model 'rald-dit-tiny' reads 'radar'; it is a diffusion model "
                                                  "(stage: diffusion)"),
    (DIT.replace("rald-dit-tiny", "pillars-tiny"), "model 'pillars-tiny' reads 'points'; it is not a RaLD model"),
    (AE + "data: {pointz: 5}\n", "data: LidarData unknown keys ['pointz']"),
    (AE + "data: {points: many}\n", "data: points: expected an integer, got 'many' (a string)"),
    (AE + "data: {points: 0}\n", "data.points must be an integer >= 1, got 0"),
    (AE + "data: {queries: 10, occupied_fraction: 0.05}\n", "10 queries x occupied_fraction 0.05 gives 0 occupied"),
    (AE + "data: {occupied_fraction: 1.0}\n", "data.occupied_fraction must be in (0, 1), got 1.0"),
    (AE + "data: {partition: cartesian, max_range_m: 15.8}\n", "data.max_range_m is the frustum grid's far edge; "
                                                              "partition 'cartesian' covers the field of view"),
    (AE + "data: {max_range_m: 15.83}\n", "data: partition 'frustum' with cell None and max_range_m 15.83: "
                                         "FrustumGrid.range_m span 15.83 is not a whole number of cells of 0.05"),
    (AE + "data: {max_range_m: -1.0}\n", "data.max_range_m must be a finite range > 0 (metres), got -1.0"),
    (AE + "data: {mirror_azimuth: 1}\n", "data: mirror_azimuth: expected true or false, got 1"),
    (AE + "data: {partition: octree}\n", "data.partition must be one of ['frustum', 'cartesian'], got 'octree'"),
    (AE + "data: {cell: [0.05, 0.25]}\n", "data: cell: expected a list of 3 values, got 2"),
    (AE + "data: {cell: [0.05, -0.25, 0.5]}\n", "data: partition 'frustum' with cell (0.05, -0.25, 0.5): cell must be 3 "
                                                 "positive sizes"),
    (AE.replace("{variant: rald-ae-tiny}", "{variant: rald-ae-tiny, overrides: {query_type: fps}}")
     + "data: {points: 16}\n", "query_type 'fps' picks n_latents=32 of the input points, but data.points is 16"),
    (AE.replace("select_metric: loss", "select_metric: f1"),
     "train.select_metric 'f1' is not a validation metric of the autoencoder stage; one of loss, bce, kl, iou, "
     "accuracy, recall"),
    (AE.replace("select_mode: min", "select_mode: max"), "train.select_mode 'max': loss is better when lower; "
                                                         "set select_mode: min"),
    (DIT.replace("select_metric: loss", "select_metric: iou"), "not a validation metric of the diffusion stage; one of loss"),
    (DIT + "radar: {max_intensity_db: -3}\n", "radar.max_intensity_db must be a finite number > 0, got -3"),
    (DIT + "loss: {p_std: 0}\n", "loss.p_std must be a finite number > 0, got 0"),
    (DIT + "data: {points: 5}\n", "DiffusionExperiment unknown keys ['data']"),
    (AE + "radar: {}\n", "AutoencoderExperiment unknown keys ['radar']"),
    ("name: x\nstage: diffusion\nmodel: {variant: rald-dit-tiny}\n", "no 'train'"),
])
def test_bad_configs(tmp_path, capsys, text, message):
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as e:
        load_experiment(path)
    assert message in str(e.value) and str(path) in str(e.value)
    # the command line: one line naming the file, exit 2, no traceback, nothing trained
    code = main(["train", str(path), "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "run"),
                 "--no-progress"])
    err = capsys.readouterr().err
    # (a config without a stage is a detection experiment to the command line, which says what is missing)
    cli = {"no 'stage'": "(a RaLD experiment config names its stage: autoencoder or diffusion)"}.get(message, message)
    assert code == 2 and "Traceback" not in err and str(path) in err and cli in err
    assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run").exists()


def test_left_out_sections_are_named_in_a_notice(tmp_path):
    said = []
    (tmp_path / "ae.yaml").write_text(AE)
    (tmp_path / "dit.yaml").write_text(DIT + "radar: {}\n")
    load_experiment(tmp_path / "ae.yaml", notice=said.append)
    load_experiment(tmp_path / "dit.yaml", notice=said.append)
    assert said == [f"{tmp_path / 'ae.yaml'}: data not given, so RaLD's defaults apply",
                    f"{tmp_path / 'dit.yaml'}: loss not given, so RaLD's defaults apply"]


def test_experiments_refuse_what_they_cannot_train():
    with pytest.raises(ValueError, match="stage 'diffusion' given to the autoencoder stage's config"):
        AutoencoderExperiment("x", ModelSpec("rald-ae-tiny"), stage="diffusion",
                              train=TrainConfig(select_metric="loss", select_mode="min"))
    with pytest.raises(ValueError, match="model must be a ModelSpec"):
        DiffusionExperiment("x", "rald-dit-tiny", train=TrainConfig(select_metric="loss", select_mode="min"))
    # every metric validation reports, in the direction it improves
    for metric, mode in AUTOENCODER_METRICS.items():
        AutoencoderExperiment("x", ModelSpec("rald-ae-tiny"), train=TrainConfig(select_metric=metric, select_mode=mode))


def test_a_detection_config_with_a_rald_model_names_the_stage_key(tmp_path, capsys):
    path = tmp_path / "cfg.yaml"
    path.write_text("name: x\nmodel: {variant: rald-ae-tiny}\ntrain: {epochs: 1}\n")
    assert main(["train", str(path), "--data", str(tmp_path), "--out", str(tmp_path / "run")]) == 2
    assert "a RaLD experiment config names its stage: autoencoder or diffusion" in capsys.readouterr().err


def test_canonical_key_reads_stored_keys_through_the_types(tmp_path):
    (tmp_path / "ae.yaml").write_text(AE)
    (tmp_path / "dit.yaml").write_text(DIT)
    ae, dit = load_experiment(tmp_path / "ae.yaml"), load_experiment(tmp_path / "dit.yaml")
    ae_key = {"experiment": to_dict(ae), "data": "/r"}
    key = {"experiment": to_dict(dit), "data": "/r", "ae": {"path": "ae", "run": ae_key, "weights_sha256": "00"}}
    # a key written before fields existed (the data section, train.ema_decay) reads as today's
    old_ae = {"experiment": {k: v for k, v in to_dict(ae).items() if k != "data"}, "data": "/r"}
    del old_ae["experiment"]["train"]["ema_decay"]
    old = {**key, "ae": {**key["ae"], "run": old_ae}}
    assert canonical_key(old) == key
    # the loader processes do not count; the stage-1 key inside keeps its own
    other = canonical_key(key, num_workers=7)
    assert other["experiment"]["train"]["num_workers"] == 7
    assert other["ae"]["run"]["experiment"]["train"]["num_workers"] == ae.train.num_workers
    assert canonical_key({"experiment": {"stage": "nope"}}) == {"experiment": {"stage": "nope"}}   # compared raw
    assert experiment_from_dict(key["experiment"]).model.variant == "rald-dit-tiny"
