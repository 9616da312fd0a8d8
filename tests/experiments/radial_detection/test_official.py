"""Official FFTRadNet weights and JSON config -> a run folder that `radarpc evaluate` scores."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from radarpc.cli import main
from radarpc.config import load_yaml, save_yaml
from radarpc.experiments.radial_detection.evaluation import load_trained
from radarpc.experiments.radial_detection.official import (import_official_fftradnet, official_to_radarpc,
                                                           radarpc_to_official, read_official_config)
from radarpc.io import DataFileError
from radarpc.models import ModelSpec
from radarpc.models.fftradnet import FFTRadNet, fftradnet_tiny
from radarpc.runs import RunMismatchError
from radarpc.sensors.radial import RADIAL_S
from radarpc.sim.radial_writer import write_radial_dataset
from radarpc.sim.scenes import scene_mix
from radarpc.experiments.radial_detection.config import ExperimentConfig

TINY = fftradnet_tiny().cfg           # radial-s cubes; the official config sets blocks, channels, MIMO, heads
N_CHANNELS = 2 * TINY.n_rx


def _official_config(path: Path, **model) -> Path:
    rng = np.random.default_rng(1)
    doc = {"name": "FFTRadNet_tiny", "seed": 3,
           "model": {"backbone_block": list(TINY.blocks), "channels": list(TINY.channels),
                     "MIMO_output": TINY.mimo_channels, "DetectionHead": "True", "SegmentationHead": "True"} | model,
           "dataset": {"statistics": {"input_mean": rng.normal(0, 2, N_CHANNELS).round(4).tolist(),
                                      "input_std": rng.uniform(1e4, 4e4, N_CHANNELS).round(4).tolist(),
                                      "reg_mean": [0.4048094369863972, 0.3997392847799934],
                                      "reg_std": [0.6968599580482511, 0.6942950877813826]}},
           "losses": {"fct": "PixorLoss", "classification": "FocalLoss", "weight": [1, 100, 100]}}
    path.write_text(json.dumps(doc, indent=1))
    return path


def _official_checkpoint(path: Path, seed: int = 0, **fields) -> dict[str, torch.Tensor]:
    """Random weights of a tiny FFTRadNet saved as the official training script saves them."""
    torch.manual_seed(seed)
    model = fftradnet_tiny(**fields)
    for p in model.parameters():                  # non-trivial everywhere, BatchNorm included
        p.data.normal_(0, 0.3)
    official = radarpc_to_official(model.state_dict())
    torch.save({"epoch": 7, "net_state_dict": official, "optimizer": {"state": {}, "param_groups": []},
                "history": {"train_loss": [1.5, 1.2]}}, path)
    return official


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return write_radial_dataset(tmp_path_factory.mktemp("root") / "root", RADIAL_S, 3, 1, seed=3, progress=False,
                                scenes=scene_mix("city"))


def test_the_imported_run_is_the_official_model_with_its_statistics(root, tmp_path):
    ckpt, conf = tmp_path / "fft.pth", _official_config(tmp_path / "config.json")
    official = _official_checkpoint(ckpt)
    out = import_official_fftradnet(ckpt, conf, root, tmp_path / "run", base=TINY)
    cfg, model, key = load_trained(out)
    assert cfg.model.config == TINY and cfg.name == "FFTRadNet_tiny"
    assert load_yaml(ExperimentConfig, out / "config.yaml") == cfg
    assert key["data"] == str(root.resolve())
    assert key["imported"]["checkpoint_sha256"] == hashlib.sha256(ckpt.read_bytes()).hexdigest()
    assert key["imported"]["official_config_sha256"] == hashlib.sha256(conf.read_bytes()).hexdigest()
    state = model.state_dict()
    for k, v in official_to_radarpc(official).items():
        assert torch.equal(state[k], v), k

    # the official dataset's normalisation, written out independently: concatenate the real and
    # imaginary parts of the receivers, subtract each channel's mean, divide by its std
    stats = json.loads(conf.read_text())["dataset"]["statistics"]
    rng = np.random.default_rng(2)
    cube = (rng.normal(0, 3e4, (2, TINY.n_range, TINY.n_doppler, TINY.n_rx))
            + 1j * rng.normal(0, 3e4, (2, TINY.n_range, TINY.n_doppler, TINY.n_rx))).astype(np.complex64)
    x = np.concatenate([cube.real, cube.imag], axis=3)                      # (B, Nr, Nd, 2 Nrx)
    x = (x - np.float32(stats["input_mean"])) / np.float32(stats["input_std"])
    x = torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2), dtype=np.float32))
    with torch.no_grad():
        got = model(torch.from_numpy(cube))
        want = model.forward_channels(x)
    # the two inputs agree to float32 rounding of one subtraction and one division
    torch.testing.assert_close(got.detection, want.detection, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(got.freespace, want.freespace, rtol=1e-5, atol=1e-5)


def test_import_then_evaluate_from_the_command_line(root, tmp_path, capsys):
    ckpt, conf = tmp_path / "fft.pth", _official_config(tmp_path / "config.json")
    _official_checkpoint(ckpt)
    save_yaml(ExperimentConfig(name="tiny-geometry", model=ModelSpec.matching("fftradnet", TINY)), tmp_path / "tiny.yaml")
    out = tmp_path / "run"
    args = ["import-fftradnet", str(ckpt), "--official-config", str(conf), "--data", str(root), "--out", str(out)]
    assert main(args) == 2                       # RADIal's geometry by default: these weights do not fit
    err = capsys.readouterr().err
    assert str(ckpt) in err and "do not fit" in err and not out.exists()
    args += ["--geometry", str(tmp_path / "tiny.yaml")]
    assert main(args) == 0
    assert f"radarpc evaluate {out}" in capsys.readouterr().out
    assert main(args) == 0                       # the same files again: the same run
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1"]) == 0
    doc = json.loads((out / "eval_test.json").read_text())
    assert doc["metrics"]["n_frames"] == 1
    assert doc["parameters"] == sum(p.numel() for p in FFTRadNet(TINY).parameters())

    _official_checkpoint(ckpt, seed=1)           # other weights in the same folder: refused, then replaced
    with pytest.raises(RunMismatchError):
        import_official_fftradnet(ckpt, conf, root, out, base=TINY)
    import_official_fftradnet(ckpt, conf, root, out, base=TINY, overwrite=True)
    assert not (out / "eval_test.json").exists()            # the scores of the replaced weights go with them
    assert load_trained(out)[2]["imported"]["checkpoint_sha256"] == hashlib.sha256(ckpt.read_bytes()).hexdigest()


@pytest.mark.parametrize("change, message", [
    (lambda d: d["dataset"].pop("statistics"), "'dataset.statistics.input_std'"),
    (lambda d: d["dataset"]["statistics"].update(input_mean=[0.0] * 5), "input_mean must be a list of 32 numbers"),
    (lambda d: d["dataset"]["statistics"].update(input_std=[0.0] * 32), "input_std must be positive"),
    (lambda d: d["dataset"]["statistics"].update(input_std=[float("nan")] * 32), "input_std must hold finite numbers"),
    (lambda d: d["dataset"]["statistics"].update(input_mean=[float("inf")] * 32), "input_mean must hold finite"),
    (lambda d: d["model"].update(SegmentationHead="maybe"), "model.SegmentationHead must be true or false"),
    (lambda d: d["model"].update(DetectionHead="False"), "needs the detection head"),
    (lambda d: d["model"].update(backbone_block=[3, 6, 6]), "model.backbone_block must be a list of 4 integers"),
])
def test_a_malformed_official_config_names_the_file_and_field(tmp_path, change, message):
    conf = _official_config(tmp_path / "config.json")
    doc = json.loads(conf.read_text())
    change(doc)
    conf.write_text(json.dumps(doc))
    with pytest.raises(DataFileError, match="config.json") as e:
        read_official_config(conf)
    assert message in str(e.value)


def test_a_config_that_is_not_json_names_the_file(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(DataFileError, match="bad.json: expected an official FFTRadNet JSON config"):
        read_official_config(tmp_path / "bad.json")


def test_weights_that_do_not_fit_the_config_are_refused(root, tmp_path):
    ckpt = tmp_path / "fft.pth"
    _official_checkpoint(ckpt)
    no_head = _official_config(tmp_path / "nohead.json", SegmentationHead="False")
    with pytest.raises(DataFileError, match=r"(?s)fft\.pth: .*nohead\.json.*Unexpected key.*freespace_head"):
        import_official_fftradnet(ckpt, no_head, root, tmp_path / "run", base=TINY)
    wider = _official_config(tmp_path / "wider.json", MIMO_output=TINY.mimo_channels * 2)
    with pytest.raises(DataFileError, match=r"fft\.pth: its weights do not fit the FFTRadNet that wider\.json"):
        import_official_fftradnet(ckpt, wider, root, tmp_path / "run", base=TINY)
    assert not (tmp_path / "run").exists()


def test_non_finite_or_foreign_weights_are_refused_at_import(root, tmp_path, capsys):
    conf = _official_config(tmp_path / "config.json")
    official = _official_checkpoint(tmp_path / "fft.pth")
    nan = {k: v.clone() for k, v in official.items()}
    nan["FPN.pre_enc.conv.weight"][0, 0, 0, 0] = float("nan")
    torch.save({"net_state_dict": nan}, tmp_path / "nan.pth")
    with pytest.raises(DataFileError, match=r"nan\.pth: non-finite values \(NaN or inf\) in 1 tensor\(s\), "
                                            r"e\.g\. 'pre_encoder\.conv\.weight'"):
        import_official_fftradnet(tmp_path / "nan.pth", conf, root, tmp_path / "run", base=TINY)
    # a state dict of another network: one line from the command, exit 2, nothing written
    torch.save({"encoder.weight": torch.zeros(3), "head.bias": torch.zeros(1)}, tmp_path / "other.pth")
    code = main(["import-fftradnet", str(tmp_path / "other.pth"), "--official-config", str(conf), "--data", str(root),
                 "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "other.pth: not the state dict of an official FFTRadNet: 'encoder.weight' is not a key" in err
    assert not (tmp_path / "run").exists()
