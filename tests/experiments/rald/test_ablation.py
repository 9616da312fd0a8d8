"""`radarpc experiment rald-ablation` on the session's tiny ColoRadar root: two arms sharing one
stage-1 run (a reconstruction, and a generation by the Table 3(a) model without radar encoder), rows per arm, resume without retraining, the
refusal of a row of another config, and the `radarpc report` table."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from radarpc.cli import main
from radarpc.experiments.rald import ablation
from radarpc.experiments.study.results import read_rows

CONFIGS = Path(__file__).parent / "configs"
QUICK = ("generation: {random_queries: 400, guided_queries: 300, refine_queries: 900, chunk: 256%s}\n"
         "guide: {source: os-cfar}\n")


def _study(tmp_path: Path, root: Path, every: int = 1) -> Path:
    (tmp_path / "gen.yaml").write_text(QUICK % ", num_steps: 2")
    (tmp_path / "recon.yaml").write_text(QUICK % "")
    # the tiny stage 2 conditioned on raw cube patches (Table 3(a)): 4^3-cell patches of its 32 x 16 x 8 cube
    text = (CONFIGS / "rald-tiny.yaml").read_text().replace("name: rald-tiny", "name: rald-tiny-patches")
    (tmp_path / "patches.yaml").write_text(text.replace("  overrides:\n", "  overrides:\n    radar_condition: patches\n"))
    study = tmp_path / "study.yaml"
    study.write_text(
        f"name: tiny-table\ndata: {root}\nsplit: test\nevery: {every}\nemd_points: 64\narms:\n"
        f"  - {{name: ae, label: autoencoder, autoencoder: {CONFIGS / 'rald-ae-tiny.yaml'}, generate: recon.yaml}}\n"
        f"  - {{name: full, label: 'w/o encoder', autoencoder: {CONFIGS / 'rald-ae-tiny.yaml'},\n"
        f"     diffusion: patches.yaml, generate: gen.yaml}}\n")
    return study


def _run(study: Path, out: Path) -> int:
    return main(["experiment", "rald-ablation", str(study), "--out", str(out), "--no-progress"])


class _Stop(Exception):
    """Raised from on_step: a run killed mid-training."""


def _counting(monkeypatch, calls: dict, stop_on: str | None = None) -> None:
    """Count the runner's calls of the train and generate functions (stop at ``stop_on``'s generation)."""
    for name in ("train_autoencoder", "train_diffusion", "generate_run"):
        real = getattr(ablation, name)

        def wrapped(*a, _real=real, _name=name, **k):
            calls.setdefault(_name, []).append(a)
            if _name == "generate_run" and stop_on is not None and Path(a[1]).name == stop_on:
                raise _Stop
            return _real(*a, **k)

        monkeypatch.setattr(ablation, name, wrapped)


def test_two_arms_share_stage_1_resume_and_report(colo_root, tmp_path, monkeypatch, capsys):
    study, out = _study(tmp_path, colo_root), tmp_path / "out"
    # first pass, killed while the second arm generates
    calls: dict = {}
    with monkeypatch.context() as m:
        _counting(m, calls, stop_on="full")
        with pytest.raises(_Stop):
            _run(study, out)
    assert len(calls["train_autoencoder"]) == 2 and len(calls["train_diffusion"]) == 1
    assert calls["train_autoencoder"][0][2] == calls["train_autoencoder"][1][2]    # one stage-1 folder for both
    assert set(read_rows(out, row_format=ablation.RALD_ROW_FORMAT, required=ablation.RALD_ROW_FIELDS)) == {"ae"}
    stage1 = next((out / "stage1").iterdir())
    weights = {p: p.read_bytes() for p in sorted(stage1.rglob("*.safetensors"))}

    # the rerun: the finished arm is reused whole, the second one trains nothing again
    calls = {}
    with monkeypatch.context() as m:
        _counting(m, calls)
        assert _run(study, out) == 0
    assert [Path(c[1]).name for c in calls["generate_run"]] == ["full"]
    assert len(calls["train_autoencoder"]) == 1 and len(calls["train_diffusion"]) == 1
    assert {p: p.read_bytes() for p in sorted(stage1.rglob("*.safetensors"))} == weights
    assert [p.name for p in (out / "stage1").iterdir()] == [stage1.name]
    assert len(list((out / "stage2").iterdir())) == 1
    text = capsys.readouterr().out
    assert "ae: finished (its row is present), reused" in text and "already finished" in text

    rows = read_rows(out, row_format=ablation.RALD_ROW_FORMAT, required=ablation.RALD_ROW_FIELDS)
    assert set(rows) == {"ae", "full"}
    for name, row in rows.items():
        scored = json.loads((out / "preds" / name / "metrics.json").read_text())
        assert row["metrics"]["overall"] == scored["overall"]          # evaluate-points' numbers, as written
        assert row["metrics"]["overall"]["n_frames"] == 2               # the test split's paired frames
        assert row["key"]["data"] == colo_root.name and row["key"]["every"] == 1
        assert row["software"]["radarpc"]
    assert rows["ae"]["arm"]["output"] == "reconstruction" and rows["ae"]["runs"]["stage2"] is None
    assert rows["full"]["arm"]["output"] == "generation" and rows["full"]["runs"]["stage2"]["finished"] is True
    assert rows["full"]["key"]["diffusion"]["model"]["overrides"]["radar_condition"] == "patches"
    # the validation at the best weights, as the stage runs logged it
    for name, stage, folder in (("ae", "stage1", stage1), ("full", "stage2", next((out / "stage2").iterdir()))):
        logged = list(csv.DictReader((folder / "log.csv").read_text().splitlines()))
        best = rows[name]["runs"][stage]["weights_step"]
        row = rows[name]["validation"][stage]
        assert row["step"] == best and row["val_loss"] == pytest.approx(
            float(next(r for r in logged if int(r["step"]) == best)["val_loss"]), rel=1e-12)
    assert rows["ae"]["validation"]["stage2"] is None and "val_radar_gain" in rows["full"]["validation"]["stage2"]

    # a third run does nothing
    calls = {}
    with monkeypatch.context() as m:
        _counting(m, calls)
        assert _run(study, out) == 0
    assert calls == {}

    # --plan lists the arms and their rows; --overwrite is not this study's
    capsys.readouterr()
    assert main(["experiment", "rald-ablation", str(study), "--out", str(out), "--plan"]) == 0
    plan = capsys.readouterr().out
    assert "2 arms, 2 with a row" in plan and f"[1/2] ae: autoencoder; {stage1.parent.name}/{stage1.name} -- row present" in plan
    assert main(["experiment", "rald-ablation", str(study), "--out", str(out), "--overwrite"]) == 2
    assert "--overwrite does not apply to rald-ablation" in capsys.readouterr().err

    # another study folder with --cache naming this one's stage runs: it trains nothing, generates and
    # scores into its own folder, and its rows say the same
    out2, calls = tmp_path / "out2", {}
    with monkeypatch.context() as m:
        _counting(m, calls)
        assert main(["experiment", "rald-ablation", str(study), "--out", str(out2), "--cache", str(out),
                     "--no-progress"]) == 0
    assert [Path(c[2]).parent.parent for c in calls["train_autoencoder"]] == [out, out]
    assert {p: p.read_bytes() for p in sorted(stage1.rglob("*.safetensors"))} == weights
    assert not (out2 / "stage1").exists() and not (out2 / "stage2").exists()
    assert "already finished" in capsys.readouterr().out
    rows2 = read_rows(out2, row_format=ablation.RALD_ROW_FORMAT, required=ablation.RALD_ROW_FIELDS)
    assert set(rows2) == {"ae", "full"} and "--cache" in rows2["full"]["command"]
    for name in rows:
        assert rows2[name]["key"] == rows[name]["key"] and rows2[name]["runs"] == rows[name]["runs"]
        a, b = rows[name]["metrics"]["overall"], rows2[name]["metrics"]["overall"]
        assert (b["n_frames"], b["empty"]) == (a["n_frames"], a["empty"])
        assert b["chamfer_mean"] == (None if a["chamfer_mean"] is None else pytest.approx(a["chamfer_mean"], rel=1e-5))

    # the report: one table row per arm, CD and EMD per scene and over all frames
    assert main(["report", str(out)]) == 0
    report = (out / "report" / "report.md").read_text()
    scene = rows["ae"]["metrics"]["scenes"][0]["scene"]
    assert f"| arm | {scene} CD↓ | {scene} EMD↓ | all CD↓ | all EMD↓ |" in report
    o = rows["full"]["metrics"]["overall"]
    assert f"| w/o encoder | {o['chamfer_mean']:.3f} | {o['emd_mean']:.3f} | {o['chamfer_mean']:.3f} |" in report
    assert report.index("| autoencoder |") < report.index("| w/o encoder |")
    gain = rows["full"]["validation"]["stage2"]["val_radar_gain"]
    assert "| radar check | commit |" in report and f"| {gain:.4f} | `" in report

    # another config of a finished arm is refused, naming the field
    capsys.readouterr()
    assert _run(_study(tmp_path, colo_root, every=2), out) == 2
    err = capsys.readouterr().err
    assert "made by another configuration of arm 'ae'" in err and "every: 1 in the row, 2 in the config" in err


def test_study_config_refusals(tmp_path):
    ae = CONFIGS / "rald-ae-tiny.yaml"
    bad = [
        ("name: x\ndata: d\narms: []\n", "give at least one arm"),
        (f"name: x\ndata: d\narms: [{{name: a, autoencoder: {ae}}}, {{name: a, autoencoder: {ae}}}]\n", "given twice"),
        (f"name: x\ndata: d\narms: [{{name: 'a b', autoencoder: {ae}}}]\n", "use letters, digits"),
        (f"name: x\ndata: d\nevery: 0\narms: [{{name: a, autoencoder: {ae}}}]\n", "every must be an integer >= 1"),
        (f"name: x\ndata: d\narms: [{{name: a, autoencoder: {CONFIGS / 'rald-tiny.yaml'}}}]\n",
         "this field takes stage 'autoencoder'"),
        (f"name: x\ndata: d\nseeds: 2\narms: [{{name: a, autoencoder: {ae}}}]\n", "seeds"),
    ]
    for text, message in bad:
        path = tmp_path / "s.yaml"
        path.write_text(text)
        with pytest.raises(ValueError, match=message):
            ablation.load_rald_ablation(path)
    path.write_text("name: x\ndata: d\narms: [{name: a, autoencoder: missing.yaml}]\n")
    with pytest.raises(FileNotFoundError, match="relative to the study config"):
        ablation.load_rald_ablation(path)


@pytest.mark.parametrize("table", ["table1", "table3", "table4", "table9", "generalization", "seeds"])
def test_shipped_studies_load_with_their_configs(table):
    """Every shipped study reads strictly with every config it names; arms with the same stage-1
    config share one stage-1 folder."""
    cfg, plans = ablation.load_rald_ablation(Path(__file__).parents[3] / "configs" / "rald" / "studies" / f"{table}.yaml")
    assert cfg.name == f"rald-{table}" and cfg.split == "test"
    if table == "table1":
        assert all(p.diffusion is None for p in plans) and len({p.stage1_dir for p in plans}) == 4
    elif table == "table4":
        assert len({p.stage1_dir for p in plans}) == 4 and len({p.stage2_dir for p in plans}) == 4
    elif table == "generalization":
        ae_all, ae_seen, rald_all, rald_seen, tuned = plans
        held_out = {"lab", "outdoor"}
        assert ae_all.autoencoder.scenes is None and rald_all.diffusion.scenes is None
        for p in (ae_seen, rald_seen):
            assert set(p.autoencoder.scenes) == {"hallway", "classroom"}
        assert set(rald_seen.diffusion.scenes) == {"hallway", "classroom"} and set(tuned.diffusion.scenes) == held_out
        assert tuned.init is rald_seen and tuned.stage1_dir == rald_seen.stage1_dir == ae_seen.stage1_dir
        assert rald_all.stage1_dir == ae_all.stage1_dir != ae_seen.stage1_dir
        assert tuned.diffusion.train.max_steps < rald_seen.diffusion.train.max_steps
    else:
        assert len({p.stage1_dir for p in plans}) == 1
    if table == "table3":
        a, b, c = plans
        assert a.diffusion.model.config.radar_condition == "patches"
        assert (b.generate.generation.guided_queries, c.generate.generation.guided_queries) == (0, 700_000)
        assert b.stage2_dir == c.stage2_dir                # one rald-s run, two generations
    if table == "table9":
        assert [p.diffusion.model.config.depth for p in plans] == [2, 3, 4]
    if table == "seeds":
        s0, s1 = plans
        assert (s0.diffusion.train.seed, s1.diffusion.train.seed) == (0, 1) and s0.stage2_dir != s1.stage2_dir


def test_shipped_studies_share_their_reference_run():
    """The reference RaLD-s arm of Tables 3, 4, 9, the seed study and the generalization study is one
    stage-2 run (the same folder name, hence key): trained once and shared through --cache."""
    studies = Path(__file__).parents[3] / "configs" / "rald" / "studies"
    reference = {name: plans[i] for name, i in [("table3", -1), ("table4", -1), ("table9", -1), ("seeds", 0),
                                                ("generalization", 2)]
                 for plans in [ablation.load_rald_ablation(studies / f"{name}.yaml")[1]]}
    assert len({(p.stage1_dir, p.stage2_dir) for p in reference.values()}) == 1
    assert {p.diffusion.loss.p_mean for p in reference.values()} == {0.5}
