"""A study's runs on the session's tiny city root: a finished run is reused and not trained again,
a killed study ends as an uninterrupted one, the result rows alone resume it elsewhere, a row of
another config is refused, the time limit stops a run, and the inputs are made once and cached.

The tiny sweep trains ``pillars-tiny`` for 2 epochs of 1 step (3 training frames, batch 2) at two
densities; its scores mean nothing, but its weights and rows are compared exactly.
"""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from radarpc.cli import main
from radarpc.experiments.radial_detection.config import experiment_from_dict
from radarpc.experiments.study.config import Budget, DataSpec, SimulateSpec, load_density_sweep
from radarpc.experiments.study.grid import Arm, Grid, GridRun, study_grid
from radarpc.experiments.study.inputs import DONE_SUFFIX, StudyInputs
from radarpc.experiments.study.report import write_report
from radarpc.experiments.study.results import plain_json, read_rows
from radarpc.experiments.study.runner import run_grid
from radarpc.data.pointstore import PointStore
from radarpc.runs import read_json
from radarpc.training.checkpoint import load_weights

CONFIGS = Path(__file__).parents[3] / "configs" / "study"
RUN1, RUN2 = "density-050/pillars-tiny/seed0", "density-200/pillars-tiny/seed0"


def tiny_sweep(root: Path, densities=(0.05, 0.2), **changes):
    """The shipped tiny sweep on ``root`` (the session's tiny city root: the same frames as its
    simulation spec), 2 epochs of 1 step."""
    cfg = load_density_sweep(CONFIGS / "tiny-sweep.yaml")
    return dataclasses.replace(cfg, data=DataSpec(roots=(str(root),)), densities=tuple(densities),
                               budget=Budget(epochs=2), **changes)


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return load_weights(path)[0]


def _tables(report: Path) -> list[str]:
    """The report's score and input tables (the lines between the first table and the runs table)."""
    text = report.read_text()
    body = text[text.index("### F1 @ 0.2"):text.index("### runs")]
    return [line for line in body.splitlines() if line.startswith("|")]


@pytest.fixture(scope="module")
def sweep(tiny_city_root, tmp_path_factory):
    """The tiny sweep finished in two commands: the density 0.05 alone, then both densities
    (through ``radarpc experiment``)."""
    base = tmp_path_factory.mktemp("sweep")
    out = base / "out"
    logs1: list[str] = []
    run_grid(study_grid(tiny_sweep(tiny_city_root, (0.05,))), out, progress=False, log=logs1.append)
    first = out / RUN1
    before = {p.relative_to(first): p.stat().st_mtime_ns for p in first.rglob("*") if p.is_file()}
    d = yaml.safe_load((CONFIGS / "tiny-sweep.yaml").read_text())
    d.update(data={"roots": [str(tiny_city_root)]}, budget={"epochs": 2})
    config = base / "sweep.yaml"
    config.write_text(yaml.safe_dump(d))
    return SimpleNamespace(out=out, base=base, config=config, logs1=logs1, before=before, root=tiny_city_root)


@pytest.fixture(scope="module")
def finished(sweep):
    """The second command of :func:`sweep`, its stdout."""
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["experiment", "density-sweep", str(sweep.config), "--out", str(sweep.out), "--no-progress"])
    assert code == 0
    return buf.getvalue()


def test_a_finished_run_is_reused_and_not_trained_again(sweep, finished):
    assert f"[1/1] {RUN1}: training pillars-tiny" in "\n".join(sweep.logs1)
    assert f"[1/2] {RUN1}: finished earlier, result row reused" in finished
    assert f"[2/2] {RUN2}: training pillars-tiny" in finished
    assert "1 trained now, 1 reused" in finished
    first = sweep.out / RUN1
    after = {p.relative_to(first): p.stat().st_mtime_ns for p in first.rglob("*") if p.is_file()}
    assert after == sweep.before                           # not a file of the finished run touched
    rows = read_rows(sweep.out)
    assert sorted(rows) == [RUN1, RUN2]
    row = rows[RUN2]
    # what a row records: the command, the config file, the commit, density and tau, metrics, times
    assert row["command"] == (f"radarpc experiment density-sweep {sweep.config} --out {sweep.out}")
    assert row["study"]["config_file"] == str(sweep.config) and row["study"]["kind"] == "density-sweep"
    assert set(row["software"]) == {"radarpc", "commit", "torch"}
    assert row["density"] == 0.2 and row["seed"] == 0 and row["arm"]["name"] == "pillars-tiny"
    store = PointStore(next((sweep.out / "cache" / "points").glob("*-200-plain-*.parquet")))
    assert row["inputs"] == [{"root": sweep.root.name, "tau": store.metadata.tau,
                              "achieved_density": store.metadata.achieved_density,
                              "peak_density": store.metadata.peak_density, "seconds": row["inputs"][0]["seconds"]}]
    assert 0.15 < row["inputs"][0]["achieved_density"] < 0.25           # per-dataset tau for the target 0.2
    evaluation = read_json(sweep.out / RUN2 / "eval_test.json")
    assert row["metrics"]["f1_fixed"] == evaluation["metrics"]["f1_fixed"]
    assert row["metrics"]["freespace_miou"] == pytest.approx(evaluation["metrics"]["freespace_miou"], abs=0)
    assert row["training"]["steps_done"] == 2 and row["training"]["finished"] is True
    assert row["training"]["cut_at_time_limit"] is False and row["evaluation"]["split"] == "test"
    assert row["evaluation"]["fps_batch1"] is None                     # fps_frames 0: not timed
    assert experiment_from_dict(row["key"]["experiment"]).train.epochs == 2
    assert "weights" not in json.dumps(row["key"]) or "best validation" in json.dumps(row["key"])
    assert not list((sweep.out / "results").glob("*.safetensors"))


def test_a_killed_study_ends_as_an_uninterrupted_one(sweep, finished, tmp_path):
    grid = study_grid(tiny_sweep(sweep.root))
    out = tmp_path / "killed"
    # the study killed in its second run: its first finished (as in the fixture), the second not
    (out / "results").mkdir(parents=True)
    shutil.copy(sweep.out / "results" / (RUN1.replace("/", "__") + ".json"), out / "results")
    shutil.copytree(sweep.out / RUN1, out / RUN1)

    def kill(run: GridRun, step: int) -> None:
        if run.id == RUN2 and step == 2:                  # the last step, after the epoch-0 checkpoint
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_grid(grid, out, progress=False, log=lambda s: None, on_step=kill, cache=sweep.out / "cache")
    assert sorted(read_rows(out)) == [RUN1]               # the killed run has no row
    logs: list[str] = []
    outcome = run_grid(grid, out, progress=False, log=logs.append, cache=sweep.out / "cache")
    assert outcome.trained == [RUN2] and outcome.reused == [RUN1]
    assert any("resuming at epoch 1, step 1 of 2" in line for line in logs)
    for run in (RUN1, RUN2):
        a, b = _weights(sweep.out / run / "best.safetensors"), _weights(out / run / "best.safetensors")
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
        assert read_rows(out)[run]["metrics"] == read_rows(sweep.out)[run]["metrics"]
    assert _tables(write_report(out, log=lambda s: None)) == _tables(write_report(sweep.out, log=lambda s: None))


def test_the_rows_alone_resume_the_study_elsewhere(sweep, finished, tmp_path):
    out = tmp_path / "elsewhere"
    shutil.copytree(sweep.out / "results", out / "results")
    called = []
    outcome = run_grid(study_grid(tiny_sweep(sweep.root)), out, progress=False, log=lambda s: None,
                       on_step=lambda run, step: called.append(run.id))
    assert outcome.trained == [] and outcome.reused == [RUN1, RUN2] and called == []
    assert sorted(p.name for p in out.iterdir()) == ["results", "study.json"]     # no input made, no run folder
    assert _tables(write_report(out, log=lambda s: None)) == _tables(write_report(sweep.out, log=lambda s: None))


def test_a_row_of_another_config_of_the_run_is_refused(sweep, finished, tmp_path, capsys):
    out = tmp_path / "other"
    shutil.copytree(sweep.out / "results", out / "results")
    longer = study_grid(dataclasses.replace(tiny_sweep(sweep.root), budget=Budget(epochs=3)))
    with pytest.raises(ValueError, match=r"2 result row\(s\) were made by another configuration") as e:
        run_grid(longer, out, progress=False, log=lambda s: None)
    assert f"{RUN1}: experiment.train.epochs: 2 in the row, 3 in the config" in str(e.value)
    assert "Remove those rows" in str(e.value)
    assert sorted(p.name for p in out.iterdir()) == ["results"]                  # refused before any work
    # from the command: one line
    d = yaml.safe_load(sweep.config.read_text())
    d["budget"] = {"epochs": 3}
    (tmp_path / "longer.yaml").write_text(yaml.safe_dump(d))
    assert main(["experiment", "density-sweep", str(tmp_path / "longer.yaml"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("radarpc experiment: error: ") and err.count("\n") == 1


def _ablation_of_the_sweeps_model(root: Path, arms=("base", "+Ae+d"), enrichments=()) -> dict:
    """An ablation config whose ``+Ae+d`` arm (and enrichment arm ``none``) is the tiny sweep's
    pillars-tiny run at 0.05 (same experiment, data, budget, seed and scoring); its base arm is not."""
    experiment = yaml.safe_load((CONFIGS / "tiny-sweep.yaml").read_text())["models"][0]["experiment"]
    d = {"name": "tiny-axes", "sensor": "tiny", "data": {"roots": [str(root)]}, "densities": [0.05],
         "budget": {"epochs": 2}, "conversion": {"density_mode": "per-dataset"}, "evaluation": {"fps_frames": 0},
         "axes": {"model": {"experiment": experiment}, "arms": list(arms)}}
    if enrichments:
        d["enrichments"] = {"model": {"experiment": experiment}, "arms": list(enrichments)}
    return d


def _grid(d: dict) -> Grid:
    from radarpc.config import from_dict
    from radarpc.experiments.study.config import AblationConfig

    return study_grid(from_dict(AblationConfig, d))


def test_another_studys_row_of_the_same_run_is_reused_and_names_its_origin(sweep, finished, tmp_path, capsys):
    d = _ablation_of_the_sweeps_model(sweep.root)
    grid, out = _grid(d), tmp_path / "axes"
    # --plan says which run is taken from the sweep, and trains nothing
    (tmp_path / "axes.yaml").write_text(yaml.safe_dump(d))
    assert main(["experiment", "ablation", str(tmp_path / "axes.yaml"), "--out", str(out), "--reuse",
                 str(sweep.out), "--plan"]) == 0
    plan = capsys.readouterr().out
    assert "2 runs, 0 finished, 1 to take from --reuse" in plan
    assert (f"density-050/axes-Ae-d/seed0: [r, a, e, d, Ae], points -- the same run as tiny-sweep:{RUN1} "
            f"({sweep.out}), its row reused") in plan
    assert "density-050/axes-base/seed0: [r, a, e], points -- to train" in plan
    assert not out.exists()
    # the run: the base arm trains, the +Ae+d arm takes the sweep's row
    logs: list[str] = []
    outcome = run_grid(grid, out, progress=False, log=logs.append, cache=sweep.out / "cache", reuse=[sweep.out],
                       command="the command", config_file="axes.yaml")
    assert outcome.trained == ["density-050/axes-base/seed0"] and outcome.reused == ["density-050/axes-Ae-d/seed0"]
    assert any(line.startswith(f"--reuse {sweep.out}: 1 run(s) of this study not finished here") for line in logs)
    assert any("0 finished (result rows in" in line and "1 taken from --reuse, 1 to train" in line for line in logs)
    assert any(f"the same run as tiny-sweep:{RUN1}" in line for line in logs)
    assert not (out / "density-050" / "axes-Ae-d").exists()             # not trained
    source, row = read_rows(sweep.out)[RUN1], read_rows(out)["density-050/axes-Ae-d/seed0"]
    assert row["metrics"] == source["metrics"] and row["key"] == source["key"] and row["inputs"] == source["inputs"]
    assert row["software"] == source["software"] and row["times"]["finished_at"] == source["times"]["finished_at"]
    assert row["times"]["reused_at"] >= source["times"]["finished_at"]
    assert row["study"]["name"] == "tiny-axes" and row["command"] == "the command"
    assert row["same_as"] == f"tiny-sweep:{RUN1}" and row["arm"]["group"] == "axes"
    assert row["reused_from"] == {"study": "tiny-sweep", "kind": "density-sweep",
                                  "config_file": source["study"]["config_file"],
                                  "command": source["command"], "run": RUN1, "key": source["key"]}
    # a rerun without --reuse finds it finished; the report marks where it came from
    again = run_grid(grid, out, progress=False, log=lambda s: None, cache=sweep.out / "cache")
    assert again.trained == [] and len(again.reused) == 2
    report = write_report(out, log=lambda s: None).read_text()
    assert f"| `density-050/axes-Ae-d/seed0` (= `tiny-sweep:{RUN1}`) |" in report
    from radarpc.experiments.study.fps_report import collect_scores

    at_5 = {k: dict(v) for k, v in collect_scores([sweep.out, out]).items() if k[-1] == 0.05}
    assert len(at_5) == 2                           # the base arm (other point features) is another model
    assert {"tiny-sweep": [source["metrics"]["f1_fixed"]]} in at_5.values()      # not again under tiny-axes
    # a row taken from a row that was itself taken names the run that trained
    chained = read_rows(out)
    chained_grid = _grid({**d, "name": "tiny-axes-2"})
    from radarpc.experiments.study.runner import rows_elsewhere

    hit = rows_elsewhere(chained_grid, [out], {})
    assert sorted(hit) == ["density-050/axes-Ae-d/seed0", "density-050/axes-base/seed0"]
    assert hit["density-050/axes-Ae-d/seed0"]["row"] == chained["density-050/axes-Ae-d/seed0"]
    out2 = tmp_path / "axes2"
    run_grid(chained_grid, out2, progress=False, log=lambda s: None, reuse=[out])
    assert read_rows(out2)["density-050/axes-Ae-d/seed0"]["same_as"] == f"tiny-sweep:{RUN1}"
    assert read_rows(out2)["density-050/axes-base/seed0"]["same_as"] == "tiny-axes:density-050/axes-base/seed0"


def test_rows_taken_from_reuse_are_written_before_the_first_training(sweep, finished, tmp_path):
    """The base arm comes first in the grid and trains; a stop in its first step keeps the +Ae+d
    arm's row taken from the sweep, and the rerun trains only the base arm."""
    grid, out = _grid(_ablation_of_the_sweeps_model(sweep.root)), tmp_path / "stopped"
    assert [r.id for r in grid.runs] == ["density-050/axes-base/seed0", "density-050/axes-Ae-d/seed0"]

    def stop(run: GridRun, step: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_grid(grid, out, progress=False, log=lambda s: None, cache=sweep.out / "cache", reuse=[sweep.out],
                 on_step=stop)
    assert sorted(read_rows(out)) == ["density-050/axes-Ae-d/seed0"]
    outcome = run_grid(grid, out, progress=False, log=lambda s: None, cache=sweep.out / "cache")
    assert outcome.trained == ["density-050/axes-base/seed0"] and outcome.reused == ["density-050/axes-Ae-d/seed0"]


def test_a_finished_arm_of_the_same_run_wins_over_reuse(sweep, finished, tmp_path):
    """The +Ae+d arm trained here: its enrichment twin "none" takes this study's row, not the sweep's."""
    from radarpc.experiments.study.runner import rows_elsewhere

    d = _ablation_of_the_sweeps_model(sweep.root, arms=("+Ae+d",), enrichments=("none",))
    grid, out = _grid(d), tmp_path / "own"
    source = read_rows(sweep.out)[RUN1]
    (out / "results").mkdir(parents=True)
    own = {**source, "run": "density-050/axes-Ae-d/seed0", "metrics": {**source["metrics"], "f1_fixed": 0.123},
           "study": {**source["study"], "name": "tiny-axes", "kind": "ablation"}}
    (out / "results" / "density-050__axes-Ae-d__seed0.json").write_text(json.dumps(own))
    assert rows_elsewhere(grid, [sweep.out], {"density-050/axes-Ae-d/seed0": own}) == {}
    outcome = run_grid(grid, out, progress=False, log=lambda s: None, reuse=[sweep.out])
    assert outcome.trained == [] and outcome.reused == ["density-050/axes-Ae-d/seed0", "density-050/enrich-none/seed0"]
    twin = read_rows(out)["density-050/enrich-none/seed0"]
    assert twin["metrics"]["f1_fixed"] == 0.123 and twin["same_as"] == "density-050/axes-Ae-d/seed0"
    # a run trained once counts once where F1 is paired with frames/s (two arms here; --reuse rows)
    from radarpc.experiments.study.fps_report import collect_scores

    assert list(collect_scores([out]).values()) == [[("tiny-axes", [0.123])]]


def test_a_reused_row_must_have_the_runs_key(sweep, finished, tmp_path):
    """Rows that differ in the key are not taken (another seed, root, split); one that differs only by a
    raised time limit is, unless that limit cut it."""
    from radarpc.experiments.study.runner import rows_elsewhere

    grid = _grid(_ablation_of_the_sweeps_model(sweep.root))              # no time limit
    row = read_rows(sweep.out)[RUN1]
    key = row["key"]
    experiment = key["experiment"]

    def taken(changed: dict) -> list[str]:
        other = tmp_path / f"other{len(list(tmp_path.iterdir()))}"
        (other / "results").mkdir(parents=True)
        (other / "results" / (RUN1.replace("/", "__") + ".json")).write_text(json.dumps(changed))
        return sorted(rows_elsewhere(grid, [other], {}))

    assert taken(row) == ["density-050/axes-Ae-d/seed0"]
    assert taken({**row, "key": {**key, "time_limit_min": 5.0}}) == ["density-050/axes-Ae-d/seed0"]
    assert taken({**row, "key": {**key, "time_limit_min": 5.0},
                  "training": {**row["training"], "cut_at_time_limit": True}}) == []
    assert taken({**row, "seed": 1, "key": {**key, "experiment": {
        **experiment, "train": {**experiment["train"], "seed": 1}}}}) == []
    assert taken({**row, "key": {**key, "experiment": {                 # the key's seed, not only the row's
        **experiment, "train": {**experiment["train"], "seed": 1}}}}) == []
    assert taken({**row, "key": {**key, "data": {**key["data"], "roots": ["another-root"]}}}) == []
    assert taken({**row, "key": {**key, "evaluation": {**key["evaluation"], "split": "val"}}}) == []
    # the same network named otherwise (the variant's own value as an override, another experiment name)
    # is the same run; another network, or an unknown variant, is not
    def model(spec: dict, **train) -> dict:
        return {**row, "key": {**key, "experiment": {**experiment, "name": "another-name", "model": spec,
                                                     "train": {**experiment["train"], **train}}}}

    ours = experiment["model"]["overrides"]
    assert experiment["model"]["variant"] == "pillars-tiny" and "layer_nums" not in ours
    same = {"variant": "pillars-tiny", "overrides": {**ours, "layer_nums": [0, 1, 1]}}     # pillars_tiny's own
    assert taken(model(same)) == ["density-050/axes-Ae-d/seed0"]
    assert taken(model({**same, "overrides": {**ours, "layer_nums": [1, 1, 1]}})) == []
    assert taken(model(same, lr_max=0.5)) == []
    assert taken(model({"variant": "no-such-model", "overrides": {}})) == []


def test_a_row_of_the_same_network_named_otherwise_is_reused_and_resumes(sweep, finished, tmp_path):
    """The row carries this study's key (its own check accepts it on every later start) and keeps the
    key the run that trained stored."""
    grid, out = _grid(_ablation_of_the_sweeps_model(sweep.root)), tmp_path / "named-otherwise"
    source = read_rows(sweep.out)[RUN1]
    experiment = source["key"]["experiment"]
    spelled = {**experiment, "name": "another-name", "model": {
        **experiment["model"], "overrides": {**experiment["model"]["overrides"], "layer_nums": [0, 1, 1]}}}
    other = tmp_path / "other"
    (other / "results").mkdir(parents=True)
    (other / "results" / (RUN1.replace("/", "__") + ".json")).write_text(
        json.dumps({**source, "key": {**source["key"], "experiment": spelled}}))

    def stop(run: GridRun, step: int) -> None:
        raise KeyboardInterrupt

    for reuse in ([other], []):                 # the second start reads its own rows only
        with pytest.raises(KeyboardInterrupt):  # got as far as training the base arm
            run_grid(grid, out, progress=False, log=lambda s: None, cache=sweep.out / "cache", reuse=reuse,
                     on_step=stop)
    row = read_rows(out)["density-050/axes-Ae-d/seed0"]
    assert row["key"] == source["key"] and row["reused_from"]["key"]["experiment"] == spelled
    assert row["metrics"] == source["metrics"]


def test_two_spellings_of_one_network_have_one_identity():
    from radarpc.experiments.study.results import network_identity
    from radarpc.models.pillars import SPECTRAL_FEATURES

    spectral = network_identity({"variant": "spectralpillars-s", "overrides": {}})
    assert spectral == network_identity({"variant": "pointpillars-s", "overrides": {"features": list(SPECTRAL_FEATURES)}})
    assert spectral["class"] == "radarpc.models.pillars.PointPillars"
    assert spectral != network_identity({"variant": "pointpillars-s", "overrides": {}})
    assert spectral != network_identity({"variant": "spectralpillars", "overrides": {}})       # the full size
    assert network_identity({"variant": "no-such-model", "overrides": {}}) is None
    assert network_identity({"variant": "pointpillars-s", "overrides": {"no_such_field": 1}}) is None


def test_a_reuse_folder_without_rows_is_refused_before_any_work(sweep, tmp_path, capsys):
    grid = _grid(_ablation_of_the_sweeps_model(sweep.root))
    with pytest.raises(FileNotFoundError, match=r"--reuse .*typo: no result rows of a training study there"):
        run_grid(grid, tmp_path / "axes", progress=False, log=lambda s: None, reuse=[tmp_path / "typo"])
    assert not (tmp_path / "axes" / "results").exists()
    assert main(["experiment", "fps", str(CONFIGS / "tiny-sweep.yaml"), "--out", str(tmp_path / "f"),
                 "--reuse", str(tmp_path)]) == 2
    assert "--reuse applies to the density-sweep and ablation studies" in capsys.readouterr().err


def test_the_time_limit_stops_a_run_and_its_row_says_so(sweep, finished, tmp_path, monkeypatch):
    import radarpc.experiments.study.runner as runner

    clock = iter(range(0, 10**6, 40))               # each reading 40 s later: step 1 at 40 s, step 2 at 80 s

    monkeypatch.setattr(runner, "time", SimpleNamespace(perf_counter=lambda: float(next(clock))))
    cfg = dataclasses.replace(tiny_sweep(sweep.root, (0.05,)), budget=Budget(epochs=2, time_limit_min=1.0))
    logs: list[str] = []
    outcome = run_grid(study_grid(cfg), tmp_path / "cut", progress=False, log=logs.append,
                       cache=sweep.out / "cache")
    row = outcome.rows[0]
    assert any("stopped at the time limit of 1 min, at step 2" in line for line in logs)
    assert row["training"]["cut_at_time_limit"] is True and row["training"]["finished"] is False
    assert row["training"]["weights_step"] == 1 and row["key"]["time_limit_min"] == 1.0
    # a raised limit: the cut run trains on from its folder to the end; then, under a higher limit
    # still, its row (not cut) is the same run's and is reused; a lowered limit is refused
    raised = dataclasses.replace(cfg, budget=Budget(epochs=2, time_limit_min=10.0))
    logs.clear()
    outcome = run_grid(study_grid(raised), tmp_path / "cut", progress=False, log=logs.append,
                       cache=sweep.out / "cache")
    row = outcome.rows[0]
    assert outcome.trained == [row["run"]]
    assert any("cut by the earlier time limit of 1 min; it trains on under this one, from its run folder" in line
               for line in logs)
    assert any("resuming" in line for line in logs)                  # from the cut run's checkpoint
    assert row["training"]["finished"] is True and row["training"]["cut_at_time_limit"] is False
    assert row["key"]["time_limit_min"] == 10.0
    # the same weights and scores as the run the fixture trained without a limit
    a, b = _weights(sweep.out / RUN1 / "best.safetensors"), _weights(tmp_path / "cut" / RUN1 / "best.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert row["metrics"] == read_rows(sweep.out)[RUN1]["metrics"]
    for limit in (20.0, None):                                       # higher still, or none
        logs.clear()
        higher = dataclasses.replace(cfg, budget=Budget(epochs=2, time_limit_min=limit))
        again = run_grid(study_grid(higher), tmp_path / "cut", progress=False, log=logs.append,
                         cache=sweep.out / "cache")
        assert again.reused == [row["run"]] and again.rows == [row]
        assert any("under a time limit of 10 min that did not cut it" in line for line in logs)
    with pytest.raises(ValueError, match=r"time_limit_min"):
        run_grid(study_grid(dataclasses.replace(cfg, budget=Budget(epochs=2, time_limit_min=5.0))), tmp_path / "cut",
                 progress=False, log=lambda s: None, cache=sweep.out / "cache")
    # a limit reached before the first validation leaves nothing to score: said, not scored
    clock2 = iter(range(0, 10**6, 100))
    monkeypatch.setattr(runner, "time", SimpleNamespace(perf_counter=lambda: float(next(clock2))))
    with pytest.raises(ValueError, match="before its first validation: no weights to score"):
        run_grid(study_grid(cfg), tmp_path / "cut_early", progress=False, log=lambda s: None,
                 cache=sweep.out / "cache")


def test_a_second_study_on_the_same_output_is_refused(sweep, finished):
    from radarpc.runs import OutputBusyError, OutputLock

    with OutputLock(sweep.out, "study output"):
        with pytest.raises(OutputBusyError, match="study output"):
            run_grid(study_grid(tiny_sweep(sweep.root)), sweep.out, progress=False, log=lambda s: None)


def _grid_of(arms: list[Arm], root: Path | None, densities=(0.1,), simulate=None, drop=False) -> Grid:
    cfg = load_density_sweep(CONFIGS / "tiny-sweep.yaml")
    data = DataSpec(simulate=simulate, drop_cubes=drop) if simulate else DataSpec(roots=(str(root),))
    runs = tuple(GridRun(a, None if a.input == "dense" else d, 0) for a in arms for d in densities)
    return Grid("density-sweep", "inputs", "tiny", data, cfg.conversion, cfg.budget, cfg.evaluation,
                tuple(densities), tuple(arms), runs, {})


def _arm(name: str, input: str, enrich=()) -> Arm:
    variant = "pillars-tiny" if input == "points" else "fftradnet-tiny"
    cfg = experiment_from_dict({"name": name, "model": {"variant": variant}, "train": {"epochs": 1}})
    return Arm(name, name, "models", cfg, input, tuple(enrich))


def test_inputs_are_made_once_and_found_by_content(tiny_city_root, tmp_path, monkeypatch):
    arms = [_arm("pp", "points"), _arm("sp", "points", ("rd3", "sector4")), _arm("srd", "sparse-rd"),
            _arm("fft", "dense")]
    grid = _grid_of(arms, tiny_city_root)
    logs: list[str] = []
    inputs = StudyInputs(grid, tmp_path / "cache", progress=False, log=logs.append)
    inputs.prepare(grid.runs)
    got = {r.arm.name: inputs.for_run(r) for r in grid.runs}
    data, points, records = got["pp"]
    assert data == [tiny_city_root] and len(points) == 1 and points[0].suffix == ".parquet"
    meta = PointStore(points[0]).metadata
    assert meta.density_mode == "per-dataset" and meta.target_density == 0.1 and meta.enrich == ()
    assert records[0].tau == meta.tau and records[0].achieved_density == meta.achieved_density
    assert PointStore(got["sp"][1][0]).metadata.enrich == ("rd3", "sector4")
    srd_data, srd_points, srd_records = got["srd"]
    manifest = read_json(srd_data[0] / "sparse_rd.json")
    assert srd_points is None and manifest["complete"] is True and srd_records[0].tau == manifest["tau"]
    assert srd_records[0].achieved_density == pytest.approx(manifest["mean_density"])
    assert got["fft"][0] == [tiny_city_root] and got["fft"][1] is None
    # a second study on the same cache opens nothing it has: each output reused, and said so
    import radarpc.pipelines.pointclouds as pointclouds
    import radarpc.pipelines.sparse_rd as sparse_rd

    def refuse(*a, **k):
        raise AssertionError("converted again")

    monkeypatch.setattr(pointclouds, "convert_dataset", refuse)
    monkeypatch.setattr(sparse_rd, "write_sparse_rd", refuse)
    logs2: list[str] = []
    again = StudyInputs(grid, tmp_path / "cache", progress=False, log=logs2.append)
    again.prepare(grid.runs)
    assert [again.for_run(r)[:2] for r in grid.runs] == [v[:2] for v in got.values()]
    assert sum(line.startswith("reused point store") for line in logs2) == 2
    assert sum(line.startswith("reused sparse-RD root") for line in logs2) == 1


def test_dropped_cubes_are_simulated_again_when_needed(tmp_path):
    spec = SimulateSpec(sequences=3, frames_per_sequence=1, seed=5, scenes="city")
    grid = _grid_of([_arm("pp", "points")], None, densities=(0.1,), simulate=(spec,), drop=True)
    logs: list[str] = []
    inputs = StudyInputs(grid, tmp_path / "cache", progress=False, log=logs.append)
    root = inputs.root(0, cubes=True)
    cube = next((root / "radar_FFT").glob("fft_*.npy"))
    original = cube.read_bytes()
    inputs.prepare(grid.runs)
    assert not (root / "radar_FFT").exists() and any("deleted the RD cubes" in line for line in logs)
    assert read_json(root.with_name(root.name + DONE_SUFFIX))["cubes"] is False
    data, points, _ = inputs.for_run(grid.runs[0])                 # the store is made: no cube needed
    assert data == [root] and points[0].is_file() and not (root / "radar_FFT").exists()
    # another density needs the cubes: simulated again, the same bytes
    more = _grid_of([_arm("pp", "points")], None, densities=(0.2,), simulate=(spec,), drop=True)
    logs2: list[str] = []
    StudyInputs(more, tmp_path / "cache", progress=False, log=logs2.append).prepare(more.runs)
    assert any(line.startswith("simulating again the dropped cubes") for line in logs2)
    assert not (root / "radar_FFT").exists()                          # dropped again once made
    fresh = StudyInputs(more, tmp_path / "cache2", progress=False, log=lambda s: None).root(0, cubes=True)
    assert (fresh / "radar_FFT" / cube.name).read_bytes() == original


def _narrow(variant: str) -> dict:
    """A tiny experiment (1 step of batch 2, the narrowest pillar model): the study's machinery,
    not what the model learns."""
    overrides = ({"pfn_channels": 4, "num_filters": [4, 4, 4], "num_upsample_filters": [4, 2, 2],
                  "detection_widths": [4, 4], "freespace_widths": [4, 4]} if variant == "pillars-tiny" else {})
    return {"name": variant, "model": {"variant": variant, "overrides": overrides},
            "train": {"epochs": 1, "batch_size": 2, "eval_batch_size": 4, "num_workers": 0, "precision": "fp32"}}


def test_two_arms_of_one_run_train_once(tiny_city_root, tmp_path):
    from radarpc.config import from_dict
    from radarpc.experiments.study.config import AblationConfig

    cfg = from_dict(AblationConfig, {
        "name": "twins", "sensor": "tiny", "data": {"roots": [str(tiny_city_root)]}, "densities": [0.05],
        "budget": {"max_steps": 1}, "evaluation": {"fps_frames": 0},
        "axes": {"model": {"experiment": _narrow("pillars-tiny")}, "arms": ["+Ae+d"]},
        "enrichments": {"model": {"experiment": _narrow("pillars-tiny")}, "arms": ["none"]}})
    logs: list[str] = []
    outcome = run_grid(study_grid(cfg), tmp_path / "out", progress=False, log=logs.append)
    assert outcome.trained == ["density-050/axes-Ae-d/seed0"] and outcome.reused == ["density-050/enrich-none/seed0"]
    assert any("the same run as density-050/axes-Ae-d/seed0" in line for line in logs)
    rows = read_rows(tmp_path / "out")
    twin = rows["density-050/enrich-none/seed0"]
    assert twin["same_as"] == "density-050/axes-Ae-d/seed0" and twin["arm"]["group"] == "enrichments"
    assert twin["metrics"] == rows["density-050/axes-Ae-d/seed0"]["metrics"]
    assert not (tmp_path / "out" / "density-050" / "enrich-none").exists()
    # and the rerun finds both finished; the report marks the twin
    again = run_grid(study_grid(cfg), tmp_path / "out", progress=False, log=lambda s: None)
    assert again.trained == [] and len(again.reused) == 2
    text = write_report(tmp_path / "out", log=lambda s: None).read_text()
    assert "| `density-050/enrich-none/seed0` (= `density-050/axes-Ae-d/seed0`) |" in text
    assert "## point axes (the spectral point-cloud paper's Fig. 5)" in text
    assert "## spectral enrichments (the paper's Fig. 6)" in text


def test_a_sparse_rd_fftradnet_run(radial_s_city_root, tmp_path):
    """The sparse-RD arm trains an FFTRadNet on the cache's masked root (the dense benchmark is the
    same code on the roots themselves: its key and data are checked in the grid tests)."""
    from radarpc.config import from_dict
    from radarpc.experiments.study.config import AblationConfig

    cfg = from_dict(AblationConfig, {
        "name": "rd", "sensor": "radial-s", "data": {"roots": [str(radial_s_city_root)]}, "densities": [0.1],
        "budget": {"max_steps": 1}, "evaluation": {"fps_frames": 0},
        "rd_comparison": {"points": {"experiment": _narrow("pillars-tiny"), "name": "sp"},
                          "sparse_rd": {"experiment": _narrow("fftradnet-tiny"), "name": "srd"}}})
    full = study_grid(cfg)
    grid = dataclasses.replace(full, runs=tuple(r for r in full.runs if r.arm.input == "sparse-rd"))
    out = tmp_path / "out"
    outcome = run_grid(grid, out, progress=False, log=lambda s: None)
    assert outcome.trained == ["density-100/srd/seed0"]
    srd = read_json(out / "density-100" / "srd" / "seed0" / "run.json")
    sparse_root = Path(srd["data"])
    assert sparse_root.parent == out / "cache" / "sparse-rd" and (sparse_root / "sparse_rd.json").is_file()
    row = read_rows(out)["density-100/srd/seed0"]
    assert row["inputs"][0]["tau"] == read_json(sparse_root / "sparse_rd.json")["tau"]
    assert row["key"]["input"] == "sparse-rd" and row["key"]["conversion"]["density"] == 0.1
    assert row["metrics"] == plain_json(read_json(out / "density-100" / "srd" / "seed0" / "eval_test.json")["metrics"])
    dense = [r for r in full.runs if r.arm.input == "dense"]
    assert dense == []                                  # no dense arm given: none in the grid
