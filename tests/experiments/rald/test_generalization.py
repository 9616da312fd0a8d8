"""Held-out scenes and fine-tuning (the RaLD paper's Tables 5-8) on the session's tiny ColoRadar
root: the reader's and the stage configs' ``scenes``, ``radarpc train --init``, and a study arm that
fine-tunes another arm's diffusion model."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch

from radarpc.cli import main
from radarpc.config import load_yaml_mapping
from radarpc.data.coloradar import ColoRadar
from radarpc.experiments.rald import ablation
from radarpc.experiments.rald.config import experiment_from_dict, load_experiment
from radarpc.experiments.rald.runs import file_sha256, load_rald, load_rald_ae
from radarpc.experiments.rald.task import AutoencoderTask, DiffusionTask
from radarpc.experiments.study.results import read_rows
from radarpc.training.checkpoint import load_weights, save_weights
from radarpc.training.loop import BEST_WEIGHTS

CONFIGS = Path(__file__).parent / "configs"
AE_YAML, DIT_YAML = CONFIGS / "rald-ae-tiny.yaml", CONFIGS / "rald-tiny.yaml"
QUICK = ("generation: {random_queries: 400, guided_queries: 300, refine_queries: 900, chunk: 256, num_steps: 2}\n"
         "guide: {source: os-cfar}\n")


def _train(*args) -> int:
    return main(["train", *map(str, args), "--no-progress"])


def _writable(root: Path) -> None:
    for d, _, files in os.walk(root):
        os.chmod(d, 0o755)
        for f in files:
            os.chmod(os.path.join(d, f), 0o644)


@pytest.fixture(scope="module")
def two_scene_root(colo_root, tmp_path_factory) -> Path:
    """``colo_root``'s three lab runs and the same runs again as hallway_run0..2: two scene types
    (which runs are read is all these tests look at)."""
    root = tmp_path_factory.mktemp("two_scenes") / "root"
    shutil.copytree(colo_root, root)
    _writable(root)
    for k in range(3):
        shutil.copytree(root / f"lab_run{k}", root / f"hallway_run{k}")
    return root


def _names(ds: ColoRadar) -> list[str]:
    return [r.name for r in ds.runs]


def test_the_reader_keeps_the_runs_of_the_named_scenes(two_scene_root):
    root = two_scene_root
    assert _names(ColoRadar(root, "train", cube_size=None)) == ["hallway_run0", "lab_run0"]
    assert _names(ColoRadar(root, "train", cube_size=None, scenes=["hallway"])) == ["hallway_run0"]
    assert _names(ColoRadar(root, "test", cube_size=None, scenes=["lab"])) == ["lab_run2"]
    assert _names(ColoRadar(root, "val", cube_size=None, scenes=["lab", "hallway"])) == ["hallway_run1", "lab_run1"]
    with pytest.raises(ValueError, match=r"\['outdoor'\] have no run in split 'train' \(its scenes: hallway, lab\)"):
        ColoRadar(root, "train", cube_size=None, scenes=["lab", "outdoor"])
    with pytest.raises(ValueError, match="give at least one"):
        ColoRadar(root, "train", cube_size=None, scenes=[])
    with pytest.raises(ValueError, match="the string 'lab'"):
        ColoRadar(root, "train", cube_size=None, scenes="lab")


def test_a_stage_trains_and_validates_on_its_scenes_only(two_scene_root, rald_ae_run):
    d = load_yaml_mapping(AE_YAML)
    task = AutoencoderTask(experiment_from_dict({**d, "scenes": ["hallway"]}), two_scene_root)
    assert _names(task.train_set.frames) == ["hallway_run0"] and _names(task.val_set.frames) == ["hallway_run1"]
    assert _names(AutoencoderTask(experiment_from_dict(d), two_scene_root).train_set.frames) == ["hallway_run0",
                                                                                                "lab_run0"]
    stage1 = load_rald_ae(rald_ae_run)
    dit = experiment_from_dict({**load_yaml_mapping(DIT_YAML), "scenes": ["lab"]})
    task = DiffusionTask(dit, two_scene_root, stage1.config, stage1.ae)
    assert _names(task.train_set.frames) == ["lab_run0"] and _names(task.val_set.frames) == ["lab_run1"]
    for scenes, message in (([], "non-empty list of scene names"), (["lab", "lab"], "names lab twice"),
                            ([""], "non-empty list of scene names")):
        with pytest.raises(ValueError, match=message):
            experiment_from_dict({**d, "scenes": scenes})
    with pytest.raises(ValueError, match=r"\['classroom'\] have no run in split 'train'"):
        AutoencoderTask(experiment_from_dict({**d, "scenes": ["classroom"]}), two_scene_root)


def _state(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def test_init_starts_a_stage_from_another_runs_weights(rald_run, rald_ae_run, colo_root, tmp_path, capsys):
    ae_run = rald_ae_run
    stage1, start = load_rald_ae(ae_run), load_rald(rald_run)
    # the model a fine-tuning builds is the initial run's, not a fresh one
    cfg = load_experiment(DIT_YAML)
    fresh = _state(DiffusionTask(cfg, colo_root, stage1.config, stage1.ae).build_model().dit)
    tuned = _state(DiffusionTask(cfg, colo_root, stage1.config, stage1.ae, init=start.dit).build_model().dit)
    want = _state(start.dit)
    assert all(torch.equal(tuned[k], want[k]) for k in want)
    assert any(not torch.equal(fresh[k], want[k]) for k in want)
    ae_fresh = _state(AutoencoderTask(load_experiment(AE_YAML), colo_root).build_model())
    ae_tuned = _state(AutoencoderTask(load_experiment(AE_YAML), colo_root, init=stage1.ae).build_model())
    assert all(torch.equal(ae_tuned[k], v) for k, v in _state(stage1.ae).items())
    assert any(not torch.equal(ae_fresh[k], v) for k, v in _state(stage1.ae).items())

    # through `radarpc train --init`: the key records the initial run, a rerun resumes it, another
    # initial run in the same folder is refused
    out = tmp_path / "ft"
    assert _train(DIT_YAML, "--data", colo_root, "--ae", ae_run, "--init", rald_run, "--out", out) == 0
    assert f"fine-tuning from {rald_run}" in capsys.readouterr().out
    key = json.loads((out / "run.json").read_text())
    assert key["init"]["weights_sha256"] == file_sha256(rald_run / BEST_WEIGHTS)
    assert key["init"]["path"] == str(rald_run.resolve()) and key["init"]["run"]["experiment"]["stage"] == "diffusion"
    assert load_rald(out).finished is True
    assert _train(DIT_YAML, "--data", colo_root, "--ae", ae_run, "--init", rald_run, "--out", out) == 0
    assert "already finished" in capsys.readouterr().out
    assert _train(DIT_YAML, "--data", colo_root, "--ae", ae_run, "--out", out) == 2      # not a fresh run's folder
    err = capsys.readouterr().err
    assert f"{out} holds a run fine-tuned from {rald_run.resolve()} (differs in run.json:init)" in err
    twin = tmp_path / "twin"               # the same run and weights in another folder: the same start
    shutil.copytree(rald_run, twin)
    assert _train(DIT_YAML, "--data", colo_root, "--ae", ae_run, "--init", twin, "--out", out) == 0
    assert "already finished" in capsys.readouterr().out
    assert json.loads((out / "run.json").read_text())["init"]["path"] == str(twin.resolve())
    state, info = load_weights(twin / BEST_WEIGHTS)  # other weights there: another start, refused
    save_weights(twin / BEST_WEIGHTS, {k: v + 1e-3 if v.is_floating_point() else v for k, v in state.items()}, info)
    assert _train(DIT_YAML, "--data", colo_root, "--ae", ae_run, "--init", twin, "--out", out) == 2
    assert "differs in run.json:init.weights_sha256" in capsys.readouterr().err
    ae_out = tmp_path / "ae-ft"
    assert _train(AE_YAML, "--data", colo_root, "--init", ae_run, "--out", ae_out) == 0
    assert json.loads((ae_out / "run.json").read_text())["init"]["weights_sha256"] == file_sha256(ae_run / BEST_WEIGHTS)

    # refusals, each one line naming what is wrong
    other_ae = tmp_path / "other-ae"
    shutil.copytree(ae_run, other_ae)
    _writable(other_ae)
    state, info = load_weights(other_ae / BEST_WEIGHTS)
    save_weights(other_ae / BEST_WEIGHTS, {k: v + 1e-3 for k, v in state.items()}, info)
    wide = tmp_path / "wide.yaml"
    wide.write_text(DIT_YAML.read_text().replace("    latent_dim: 8\n", "    latent_dim: 8\n    depth: 3\n"))
    scaled = tmp_path / "scaled.yaml"
    scaled.write_text(DIT_YAML.read_text().replace("max_intensity_db: 45.0", "max_intensity_db: 40.0"))
    cases = [
        ((DIT_YAML, "--data", colo_root, "--ae", ae_run, "--init", tmp_path / "g", "--out", tmp_path / "g"),
         "is the run folder --out itself"),
        ((scaled, "--data", colo_root, "--ae", ae_run, "--init", rald_run, "--out", tmp_path / "h"),
         "that run's radar section differs"),
        ((DIT_YAML, "--data", colo_root, "--ae", other_ae, "--init", rald_run, "--out", tmp_path / "a"),
         "was trained against other autoencoder weights than --ae"),
        ((wide, "--data", colo_root, "--ae", ae_run, "--init", rald_run, "--out", tmp_path / "b"),
         "a fine-tuning starts from the same network"),
        ((DIT_YAML, "--data", colo_root, "--ae", ae_run, "--init", ae_run, "--out", tmp_path / "c"),
         "not a run to fine-tune 'rald-tiny' from:"),
        ((AE_YAML, "--data", colo_root, "--init", rald_run, "--out", tmp_path / "d"), "not an autoencoder run"),
        ((Path(__file__).parents[3] / "configs" / "fftradnet-s.yaml", "--data", colo_root, "--init", rald_run,
          "--out", tmp_path / "e"), "--init names the run a RaLD stage fine-tunes"),
        ((Path(__file__).parents[3] / "configs" / "rpdnet-s.yaml", "--data", colo_root, "--init", rald_run,
          "--out", tmp_path / "f"), "which takes no --init"),
    ]
    for argv, message in cases:
        assert _train(*argv) == 2, message
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not any((tmp_path / n).exists() for n in "abcdefgh")


class _Stop(Exception):
    """Raised from on_step: a run killed mid-training."""


def test_a_killed_fine_tuning_resumes_to_the_uninterrupted_one(rald_run, rald_ae_run, colo_root, tmp_path):
    from radarpc.experiments.rald.train import train_diffusion

    cfg = load_experiment(DIT_YAML)
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    train_diffusion(cfg, colo_root, rald_ae_run, whole, progress=False, init=rald_run, log=lambda s: None)

    def stop_at_3(step: int) -> None:
        if step == 3:
            raise _Stop

    with pytest.raises(_Stop):
        train_diffusion(cfg, colo_root, rald_ae_run, killed, progress=False, init=rald_run, on_step=stop_at_3,
                        log=lambda s: None)
    train_diffusion(cfg, colo_root, rald_ae_run, killed, progress=False, init=rald_run, log=lambda s: None)
    want, got = load_weights(whole / BEST_WEIGHTS)[0], load_weights(killed / BEST_WEIGHTS)[0]
    assert want.keys() == got.keys() and all(torch.equal(want[k], got[k]) for k in want)


def test_a_study_arm_fine_tunes_an_earlier_arm(two_scene_root, tmp_path, capsys):
    (tmp_path / "gen.yaml").write_text(QUICK)
    (tmp_path / "seen.yaml").write_text(DIT_YAML.read_text() + "scenes: [hallway]\n")
    (tmp_path / "ft.yaml").write_text(DIT_YAML.read_text().replace("name: rald-tiny", "name: rald-tiny-ft")
                                      .replace("max_steps: 4", "max_steps: 2") + "scenes: [lab]\n")
    study = tmp_path / "study.yaml"
    arms = (f"  - {{name: base, label: zero-shot, autoencoder: {AE_YAML}, diffusion: seen.yaml, generate: gen.yaml}}\n"
            f"  - {{name: ft, label: fine-tuned, autoencoder: {AE_YAML}, diffusion: ft.yaml, generate: gen.yaml, "
            f"init: base}}\n")
    # the study names a root of the same folder name elsewhere; --data gives the one to use
    study.write_text(f"name: tiny-generalization\ndata: elsewhere/{two_scene_root.name}\nsplit: test\nemd_points: 64\n"
                     f"arms:\n{arms}")
    out = tmp_path / "out"
    assert main(["experiment", "rald-ablation", str(study), "--out", str(out), "--plan"]) == 0
    assert "(fine-tuned from base) -- to run" in capsys.readouterr().out
    argv = ["experiment", "rald-ablation", str(study), "--out", str(out), "--no-progress"]
    assert main(argv + ["--data", str(tmp_path)]) == 2
    assert f"rows name the root {two_scene_root.name!r}" in capsys.readouterr().err
    assert main(argv + ["--data", str(two_scene_root)]) == 0
    assert "fine-tuning from" in capsys.readouterr().out
    rows = read_rows(out, row_format=ablation.RALD_ROW_FORMAT, required=ablation.RALD_ROW_FIELDS)
    assert set(rows) == {"base", "ft"}
    assert rows["ft"]["arm"]["init"] == "base" and rows["ft"]["key"]["init"]["arm"] == "base"
    assert rows["ft"]["arm"]["scenes"] == {"stage1": None, "stage2": ["lab"]}
    assert rows["base"]["arm"]["scenes"] == {"stage1": None, "stage2": ["hallway"]}
    assert {s["scene"] for s in rows["ft"]["metrics"]["scenes"]} == {"hallway", "lab"}     # both scored
    assert rows["ft"]["command"].endswith(f"--data {two_scene_root}")
    _, plans = ablation.load_rald_ablation(study)
    base, ft = plans
    assert ft.stage1_dir == base.stage1_dir and ft.stage2_dir != base.stage2_dir
    key = json.loads((out / ft.stage2_dir / "run.json").read_text())
    assert key["init"]["weights_sha256"] == file_sha256(out / base.stage2_dir / BEST_WEIGHTS)
    assert rows["ft"]["runs"]["stage2"]["steps_done"] == 2
    assert main(["report", str(out)]) == 0
    report = (out / "report" / "report.md").read_text()
    assert "| `ft` | generation | all / lab (from `base`) |" in report
    assert "| `base` | generation | all / hallway |" in report
    assert main(["experiment", "density-sweep", str(study), "--out", str(out), "--data", str(two_scene_root)]) == 2
    assert "--data applies to rald-ablation" in capsys.readouterr().err
    # the study folder moved and its stage runs reused as another study's cache: the fine-tuned arm's
    # key names its initial run's key, whose own stage-1 path moved too; nothing is trained again
    moved = tmp_path / "moved"
    shutil.move(out, moved)
    again = ["experiment", "rald-ablation", str(study), "--out", str(tmp_path / "out2"), "--cache", str(moved),
             "--data", str(two_scene_root), "--no-progress"]
    assert main(again) == 0
    printed = capsys.readouterr().out
    assert printed.count("already finished") == 4 and "fine-tuning from" in printed
    key = json.loads((moved / ft.stage2_dir / "run.json").read_text())
    assert key["init"]["path"] == str((moved / base.stage2_dir).resolve())
    assert "path" not in key["init"]["run"]["ae"]                      # the places under it are not its key


def test_study_init_refusals(tmp_path):
    (tmp_path / "ae2.yaml").write_text(AE_YAML.read_text().replace("name: rald-ae-tiny", "name: rald-ae-tiny-2"))
    base = f"name: x\ndata: d\narms:\n  - {{name: a, autoencoder: {AE_YAML}, diffusion: {DIT_YAML}}}\n"
    (tmp_path / "deeper.yaml").write_text(DIT_YAML.read_text().replace("    latent_dim: 8\n", "    latent_dim: 8\n    depth: 3\n"))
    bad = [
        (base + f"  - {{name: b, autoencoder: {AE_YAML}, diffusion: deeper.yaml, init: a}}\n",
         "a fine-tuning starts from the same network"),
        (base + f"  - {{name: b, autoencoder: {AE_YAML}, diffusion: {DIT_YAML}, init: c}}\n",
         "init: 'c' is not an earlier arm of the study"),
        (f"name: x\ndata: d\narms:\n  - {{name: b, autoencoder: {AE_YAML}, diffusion: {DIT_YAML}, init: a}}\n"
         f"  - {{name: a, autoencoder: {AE_YAML}, diffusion: {DIT_YAML}}}\n", "'a' is not an earlier arm"),
        (base + f"  - {{name: b, autoencoder: {AE_YAML}, init: a}}\n", "a fine-tuning starts from the same stage"),
        (base + f"  - {{name: b, autoencoder: ae2.yaml, diffusion: {DIT_YAML}, init: a}}\n",
         "a fine-tuned diffusion model keeps its autoencoder"),
    ]
    for text, message in bad:
        path = tmp_path / "s.yaml"
        path.write_text(text)
        with pytest.raises(ValueError, match=message):
            ablation.load_rald_ablation(path)
