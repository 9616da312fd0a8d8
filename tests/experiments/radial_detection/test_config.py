"""The detection experiment's config: bad files end in one line naming the file and the field,
before any data is read or any training starts."""
from __future__ import annotations

import pytest

from radarpc.cli import main
from radarpc.experiments.radial_detection.config import load_experiment, validation_metrics

GOOD = "name: x\nmodel: {variant: pillars-tiny}\ntrain: {epochs: 1}\n"


@pytest.mark.parametrize("text, message", [
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: null\n", "train: expected a mapping of TrainConfig fields, got null"),
    ("name: x\npillars: resnet50\ntrain: {epochs: 1}\n", "pillars: expected a mapping of model config fields, got str"),
    ("name: x\nmodel: {variant: resnet50}\ntrain: {epochs: 1}\n", "unknown model variant 'resnet50'"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {epochs: '1'}\n", "train: epochs: expected an integer, got '1'"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {batch_size: '4'}\n", "train: batch_size: expected an integer"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {epochs: true}\n", "train: epochs: expected an integer, got true"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {epochs: 1.7}\n", "train: epochs: expected an integer, got 1.7"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {lr_max: .inf}\n", "train: lr_max: expected finite numbers, got inf"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {lr_max: '0.01'}\n", "train: lr_max: expected a number, got '0.01'"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {seed: 1180591620717411303424}\n", "train: seed: 1180591620717411303424 is out of range"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {select_metric: accuracy}\n",
     "train.select_metric 'accuracy' is not a validation metric of this experiment; one of ap, ar, f1"),
    ("name: x\nmodel: {variant: pillars-tiny}\n", "no 'train'"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {num_workers: 1000000}\n",
     "train.num_workers=1000000: at most 256 loader processes"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntargets: {n_range: 64}\ntrain: {epochs: 1}\n",
     "targets: n_range x n_azimuth = 64 x 224, but the models' detection map is 128 x 224"),
    ("name: x\ntrain: {epochs: 1}\n", "no 'model'"),
    ("name: x\nmodel: {variant: pillars-tiny}\ntrain: {epochs: 1}\ntrain: {epochs: 2}\n", "found the key 'train' twice"),
    ("name: x\nmodel: {variant: pillars-tiny, overrides: {pfn_channels: 8.5}}\ntrain: {epochs: 1}\n", "pfn_channels"),
])
def test_bad_experiment_configs(tmp_path, capsys, text, message):
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        load_experiment(path)
    # the command line: one line naming the file, exit 2, no traceback, nothing trained
    code = main(["train", str(path), "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "run"), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and str(path) in err
    assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run").exists()


def test_left_out_sections_are_named_in_a_notice(tmp_path):
    (tmp_path / "cfg.yaml").write_text(GOOD)
    said = []
    cfg = load_experiment(tmp_path / "cfg.yaml", notice=said.append)
    assert cfg.difficult and said == [f"{tmp_path / 'cfg.yaml'}: difficult, targets, loss not given, so the defaults "
                                      f"apply (difficult: true, every label trains and scores)"]
    (tmp_path / "full.yaml").write_text(GOOD + "difficult: false\ntargets: {}\nloss: {}\n")
    said.clear()
    load_experiment(tmp_path / "full.yaml", notice=said.append)
    assert said == []


def test_validation_metrics_are_what_validation_reports():
    # the names the task's evaluate returns: the report's float scores, plus freespace with its head
    assert {"f1", "ap", "ar", "f1_fixed", "range_error_m", "azimuth_error_deg"} <= set(validation_metrics(False))
    assert "freespace_miou" not in validation_metrics(False) and "freespace_miou" in validation_metrics(True)
    assert "n_labels" not in validation_metrics(True) and "thresholds" not in validation_metrics(True)
