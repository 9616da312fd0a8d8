"""RaLD's two stages trained through `radarpc train` on the session's tiny ColoRadar root: run
folders, the frozen autoencoder, resume, the --ae errors and the loaders' checks."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from radarpc.cli import main
from radarpc.experiments.rald.config import load_experiment
from radarpc.experiments.rald.runs import (ae_reference, autoencoder_run_key, diffusion_run_key, file_sha256,
                                           load_rald, load_rald_ae)
from radarpc.experiments.rald.generation import stage1_notice
from radarpc.experiments.rald.train import train_diffusion
from radarpc.io import DataFileError
from radarpc.models.latent_dit import LatentDiT
from radarpc.models.vecset import VecSetAutoencoder
from radarpc.runs import RunMismatchError
from radarpc.training.checkpoint import load_state, load_weights, read_info, save_weights
from radarpc.training.loop import BEST_WEIGHTS, LAST_CHECKPOINT

CONFIGS = Path(__file__).parent / "configs"
AE_YAML, DIT_YAML = CONFIGS / "rald-ae-tiny.yaml", CONFIGS / "rald-tiny.yaml"


class _Stop(Exception):
    pass


def _train(*args: str) -> int:
    return main(["train", *map(str, args), "--no-progress"])


@pytest.fixture(scope="module")
def ae_run(rald_ae_run) -> Path:
    """A finished stage-1 run of the tiny autoencoder on ``colo_root`` (the session's, read-only)."""
    return rald_ae_run


def _weights(path: Path, prefix: str = "") -> dict[str, torch.Tensor]:
    state, _ = load_weights(path)
    return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


def test_stage_1_run_folder_and_loader(ae_run, colo_root):
    for name in ("config.yaml", "run.json", "best.safetensors", "checkpoints/last.safetensors", "log.csv"):
        assert (ae_run / name).is_file(), name
    cfg = load_experiment(AE_YAML)
    key = json.loads((ae_run / "run.json").read_text())
    assert {k: v for k, v in key.items() if k != "software"} == autoencoder_run_key(cfg, colo_root)
    assert load_experiment(ae_run / "config.yaml") == cfg
    run = load_rald_ae(ae_run)
    assert isinstance(run.ae, VecSetAutoencoder) and not run.ae.training and run.config == cfg
    assert run.finished is True and run.status["weights_step"] in (2, 4) and run.grid.shape == (318, 720, 80)
    header = (ae_run / "log.csv").read_text().splitlines()[0].split(",")
    assert {"val_loss", "val_bce", "val_kl", "val_iou", "val_accuracy", "val_recall", "train_bce"} <= set(header)
    for k, v in _weights(ae_run / BEST_WEIGHTS).items():
        torch.testing.assert_close(run.ae.state_dict()[k], v, rtol=0, atol=0)


def test_stage_2_freezes_the_autoencoder_and_records_it(rald_run, ae_run, colo_root):
    ae = _weights(ae_run / BEST_WEIGHTS)
    # the frozen autoencoder, bit for bit, in the best weights and the last checkpoint
    for state in (_weights(rald_run / BEST_WEIGHTS, "autoencoder."),
                  {k[len("autoencoder."):]: v for k, v in load_state(rald_run / LAST_CHECKPOINT).model.items()
                   if k.startswith("autoencoder.")}):
        assert state.keys() == ae.keys()
        assert all(torch.equal(state[k], ae[k]) for k in ae)
    # ... and none of its parameters in the optimizer: its state holds the diffusion model's alone
    cfg = load_experiment(DIT_YAML)
    n_dit = len(list(cfg.build_model().parameters()))
    opt = load_state(rald_run / LAST_CHECKPOINT).optimizer
    assert len(opt["param_groups"][0]["params"]) == n_dit and len(opt["state"]) == n_dit
    # the run key names the stage-1 run: its path, key and weights
    key = json.loads((rald_run / "run.json").read_text())
    ae_key = {k: v for k, v in json.loads((ae_run / "run.json").read_text()).items() if k != "software"}
    assert key["ae"] == {"path": str(ae_run.resolve()), "run": ae_key,
                         "weights_sha256": file_sha256(ae_run / BEST_WEIGHTS)}
    assert {k: v for k, v in key.items() if k != "software"} == diffusion_run_key(cfg, colo_root, key["ae"])
    # the loader: both networks in eval mode, the stored autoencoder the stage-1 run's
    run = load_rald(rald_run)
    assert isinstance(run.dit, LatentDiT) and not run.dit.training and not run.ae.training
    assert run.config == cfg and run.ae_config == load_experiment(AE_YAML) and run.ae_dir == ae_run.resolve()
    assert run.ae_status == "same" and run.finished is True and run.grid.shape == (318, 720, 80)
    assert all(torch.equal(run.ae.state_dict()[k], v) for k, v in ae.items())
    header = (rald_run / "log.csv").read_text().splitlines()[0].split(",")
    assert "val_loss" in header and "train_loss" in header


def test_stage_2_resumes_to_the_uninterrupted_run(rald_run, ae_run, colo_root, tmp_path, capsys):
    out = tmp_path / "rald"
    cfg = load_experiment(DIT_YAML)

    def stop_at_3(step: int) -> None:
        if step == 3:
            raise _Stop

    with pytest.raises(_Stop):
        train_diffusion(cfg, colo_root, ae_run, out, progress=False, on_step=stop_at_3)
    # killed after step 3 of 4: the weights so far are flagged as an unfinished run's
    assert load_rald(out).finished is False and read_info(out / LAST_CHECKPOINT)[1]["step"] == 2
    assert _train(DIT_YAML, "--data", colo_root, "--ae", ae_run, "--out", out) == 0
    assert "resuming at epoch" in capsys.readouterr().out
    assert load_rald(out).finished is True
    want, got = _weights(rald_run / BEST_WEIGHTS), _weights(out / BEST_WEIGHTS)
    assert want.keys() == got.keys() and all(torch.equal(want[k], got[k]) for k in want)
    rows = [[c for i, c in enumerate(line.split(",")) if i != 3] for line in (out / "log.csv").read_text().splitlines()]
    ref = [[c for i, c in enumerate(line.split(",")) if i != 3] for line in (rald_run / "log.csv").read_text().splitlines()]
    assert rows == ref                                                   # (column 3: training time)


def test_a_changed_autoencoder_is_refused_on_resume(rald_run, ae_run, colo_root, tmp_path, capsys):
    ae = tmp_path / "ae"
    shutil.copytree(ae_run, ae)
    out = tmp_path / "rald"
    shutil.copytree(rald_run, out)
    key = json.loads((out / "run.json").read_text())
    key["ae"] = ae_reference(ae, out)                                    # as if trained against the copy
    (out / "run.json").write_text(json.dumps(key))
    state, info = load_weights(out / BEST_WEIGHTS)
    save_weights(out / BEST_WEIGHTS, state, {**info, "run": {k: v for k, v in key.items() if k != "software"}})
    assert load_rald(out).ae_status == "same"
    # the stage-1 weights change (retrained, or copied over): same tensors, other file
    state, info = load_weights(ae / BEST_WEIGHTS)
    save_weights(ae / BEST_WEIGHTS, {k: v + 1e-3 for k, v in state.items()}, info)
    assert load_rald(out).ae_status == "changed"
    assert _train(DIT_YAML, "--data", colo_root, "--ae", ae, "--out", out) == 2
    err = capsys.readouterr().err
    assert "does not hold a run with these settings (differs in run.json:ae.weights_sha256)" in err
    with pytest.raises(RunMismatchError, match="ae.weights_sha256"):
        train_diffusion(load_experiment(DIT_YAML), colo_root, ae, out, progress=False)
    assert stage1_notice(out, ae, "changed").endswith(f"its stage-1 folder {ae} holds another run or other weights "
                                                      f"now; the autoencoder stored with the run (the one the "
                                                      f"diffusion model was trained on) is used")
    shutil.rmtree(ae)
    run = load_rald(out)                                                 # the stored autoencoder still loads
    assert run.ae_status == "missing" and run.ae_dir.resolve() == ae.resolve()
    # what generation says of it: not there, not "holds no run" (a stage-2 run moved alone lands here)
    assert f"{run.ae_dir} is not there or holds no finished stage-1 run (moved apart from this run?)" in \
        stage1_notice(out, run.ae_dir, run.ae_status)
    with pytest.raises(ValueError, match="ae_status must be 'changed' or 'missing', got 'same'"):
        stage1_notice(out, ae, "same")



def test_moved_runs_resume_and_record_their_new_place(rald_run, ae_run, colo_root, tmp_path, capsys):
    # a study folder moved (or its stage runs copied into a shared cache): the stage-1 run is the
    # same run with the same weights, only elsewhere
    ae, out = tmp_path / "moved" / "ae", tmp_path / "moved" / "rald"
    shutil.copytree(ae_run, ae)
    shutil.copytree(rald_run, out)
    old = json.loads((out / "run.json").read_text())
    assert _train(DIT_YAML, "--data", colo_root, "--ae", ae, "--out", out) == 0
    assert f"{out}: already finished" in capsys.readouterr().out
    key = json.loads((out / "run.json").read_text())
    assert key["ae"]["path"] == str(ae.resolve())                         # the locator follows the run
    assert {k: v for k, v in key["ae"].items() if k != "path"} == {k: v for k, v in old["ae"].items() if k != "path"}
    assert key["software"] == old["software"]                             # the records kept as found
    run = load_rald(out)                 # its weights still carry the old place in their run key
    assert run.ae_dir == ae.resolve() and run.ae_status == "same" and run.finished is True
    want, got = _weights(rald_run / BEST_WEIGHTS), _weights(out / BEST_WEIGHTS)
    assert all(torch.equal(want[k], got[k]) for k in want)                # nothing retrained

def test_ae_option_errors(ae_run, rald_run, colo_root, tmp_path, capsys):
    cases = [
        ((AE_YAML, "--data", colo_root, "--ae", ae_run, "--out", tmp_path / "a"),
         "is stage 1 (stage: autoencoder): it trains the autoencoder and takes no --ae"),
        ((DIT_YAML, "--data", colo_root, "--out", tmp_path / "b"),
         "is stage 2 (stage: diffusion): give the stage-1 autoencoder run it trains against, --ae RUN"),
        ((DIT_YAML, "--data", colo_root, "--ae", tmp_path, "--out", tmp_path / "c"),
         f"{tmp_path}: no RaLD training run here (no run.json)"),
        ((DIT_YAML, "--data", colo_root, "--ae", rald_run, "--out", tmp_path / "d"),
         "a RaLD diffusion run, not an autoencoder run (its diffusion model and frozen autoencoder load with "
         "load_rald)"),
        ((Path(__file__).parents[3] / "configs" / "fftradnet-s.yaml", "--data", colo_root, "--ae", ae_run, "--out",
          tmp_path / "e"), "is a detection experiment (it has no 'stage')"),
        ((AE_YAML, "--data", colo_root, "--points", tmp_path / "p.parquet", "--out", tmp_path / "f"),
         "--points is a detection experiment's point store"),
        ((AE_YAML, "--data", colo_root, "--runs", "2", "--out", tmp_path / "g"),
         "--runs 2: RaLD experiments train one run per folder"),
        ((AE_YAML, "--data", colo_root, colo_root, "--out", tmp_path / "h"), "a RaLD experiment reads one ColoRadar "
                                                                             "root (its runs give the splits), got 2"),
        ((DIT_YAML, "--data", colo_root, "--ae", ae_run, "--model", "rald-ae-tiny", "--out", tmp_path / "i"),
         "stage 'diffusion' trains a model that reads 'radar' inputs, but model 'rald-ae-tiny' reads 'lidar'"),
    ]
    for argv, message in cases:
        assert _train(*argv) == 2, message
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not any((tmp_path / n).exists() for n in "abcdefghi")


def test_loaders_refuse_what_is_not_the_runs_own(ae_run, rald_run, tmp_path):
    # another run's weights copied in
    run = tmp_path / "ae"
    shutil.copytree(ae_run, run)
    state, info = load_weights(run / BEST_WEIGHTS)
    foreign = {**info["run"], "data": str(tmp_path / "another_root")}
    save_weights(run / BEST_WEIGHTS, state, {**info, "run": foreign})
    with pytest.raises(DataFileError, match="trained under another run key"):
        load_rald_ae(run)
    # non-finite weights
    bad = dict(state)
    k = next(iter(bad))
    bad[k] = torch.full_like(bad[k], float("nan"))
    save_weights(run / BEST_WEIGHTS, bad, info)
    with pytest.raises(DataFileError, match="non-finite values"):
        load_rald_ae(run)
    # another model's weights under the right key
    save_weights(run / BEST_WEIGHTS, _weights(rald_run / BEST_WEIGHTS), info)
    with pytest.raises(DataFileError, match="its weights do not fit autoencoder 'rald-ae-tiny'"):
        load_rald_ae(run)
    # the wrong stage, no run, no weights yet, a detection run
    with pytest.raises(DataFileError, match="a RaLD autoencoder run, not a diffusion run"):
        load_rald(ae_run)
    with pytest.raises(FileNotFoundError, match="no RaLD training run here"):
        load_rald(tmp_path)
    (run / BEST_WEIGHTS).unlink()
    with pytest.raises(FileNotFoundError, match="no best.safetensors yet"):
        load_rald_ae(run)
    (tmp_path / "det").mkdir()
    (tmp_path / "det" / "run.json").write_text(json.dumps({"experiment": {"name": "x", "model": {}}}))
    with pytest.raises(DataFileError, match="a detection training run, not a RaLD one"):
        load_rald_ae(tmp_path / "det")


def test_an_imported_layout_resolves_its_relative_autoencoder(ae_run, rald_run, tmp_path):
    # an official import writes OUT/ae (the stage-1 run) and OUT (stage 2) whose key says "path": "ae"
    out = tmp_path / "official"
    shutil.copytree(ae_run, out / "ae")
    ref = ae_reference(out / "ae", out)
    assert ref["path"] == "ae"
    stored = json.loads((rald_run / "run.json").read_text())
    key = {"experiment": stored["experiment"], "data": stored["data"], "ae": ref}
    (out / "run.json").write_text(json.dumps(key))
    state, info = load_weights(rald_run / BEST_WEIGHTS)
    save_weights(out / BEST_WEIGHTS, state, {"run": key, "epoch": None, "precision": "fp32", "weights": "official"})
    moved = tmp_path / "elsewhere"
    out.rename(moved)                                                    # the folder moves whole
    run = load_rald(moved)
    assert run.ae_dir == moved / "ae" and run.ae_status == "same" and run.finished is None
    assert all(torch.equal(run.dit.state_dict()[k], v) for k, v in _weights(rald_run / BEST_WEIGHTS, "dit.").items())
