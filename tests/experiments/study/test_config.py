"""The study configs: the shipped ones load and say what the issue asks of them, bad ones are
refused naming the file and the field (as one line from the command), and a config becomes the
grid of runs it describes."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import yaml

from radarpc.cli import main
from radarpc.experiments.study.config import (AXIS_ARMS, AXIS_FEATURES, AblationConfig, DataSpec, DensitySweepConfig,
                                              load_ablation, load_density_sweep, load_study)
from radarpc.experiments.study.grid import density_folder, study_grid
from radarpc.experiments.study.results import run_key
from radarpc.sensors.radial import radial_sensor

CONFIGS = Path(__file__).parents[3] / "configs" / "study"
KIND = {"density-sweep": "density-sweep", "ablation": "ablation", "rd-comparison": "ablation",
        "tiny-sweep": "density-sweep", "tiny-ablation": "ablation", "fps": "fps", "tiny-fps": "fps",
        "density-sweep-short": "density-sweep", "ablation-short": "ablation", "ablation-velocity-short": "ablation",
        "density-sweep-budget-control": "density-sweep", "density-sweep-budget-control-spectral": "density-sweep"}


def test_every_shipped_study_config_is_listed_here():
    assert sorted(p.stem for p in CONFIGS.glob("*.yaml")) == sorted(KIND)


@pytest.mark.parametrize("name", sorted(KIND))
def test_shipped_study_configs_load_and_expand(name):
    cfg = load_study(CONFIGS / f"{name}.yaml", KIND[name])
    if KIND[name] == "fps":                             # rows to time, not runs to train (tests/experiments/study/test_fps.py)
        from radarpc.experiments.study.fps import fps_plan

        ids = [m.id for m in fps_plan(cfg).measurements]
        assert cfg.name == name and len(set(ids)) == len(ids)
        return
    grid = study_grid(cfg)
    assert grid.name == cfg.name == name and grid.kind == KIND[name]
    assert len({r.id for r in grid.runs}) == len(grid.runs)          # one folder per run
    for d in cfg.densities:
        assert d <= radial_sensor(cfg.sensor).n_tx / radial_sensor(cfg.sensor).n_slots


def test_the_shipped_sweep_is_the_issues():
    cfg = load_density_sweep(CONFIGS / "density-sweep.yaml")
    assert cfg.sensor == "radial" and cfg.seeds == 2
    assert len(cfg.densities) >= 5 and cfg.densities[0] <= 0.007 and cfg.densities[-1] >= 0.56
    assert [m.experiment.model.variant for m in cfg.models] == ["pointpillars-s", "spectralpillars-s"]
    assert cfg.models[1].enrich == ("rd3", "sector32") and cfg.models[0].enrich == ()
    assert all(m.input_kind == "points" for m in cfg.models)
    assert cfg.budget.time_limit_min is not None and cfg.budget.time_limit_min <= 20
    assert cfg.data.simulate and cfg.data.drop_cubes                # one seeded command brings the data back
    assert len(study_grid(cfg).runs) == 2 * len(cfg.densities) * 2


def test_the_budget_control_changes_only_the_short_sweeps_budget():
    short = load_density_sweep(CONFIGS / "density-sweep-short.yaml")
    control = load_density_sweep(CONFIGS / "density-sweep-budget-control.yaml")
    assert set(control.densities) == {0.19, 0.564} <= set(short.densities)
    assert control.seeds == 1 <= short.seeds                        # seed 0: the sweep's first seed
    assert control.budget.max_steps == 2 * short.budget.max_steps
    assert control.budget.time_limit_min > short.budget.time_limit_min       # no run is cut short
    assert sorted(control.models, key=lambda m: m.name) == sorted(short.models, key=lambda m: m.name)
    for field in ("sensor", "data", "conversion", "evaluation"):
        assert getattr(control, field) == getattr(short, field), field
    spectral = load_density_sweep(CONFIGS / "density-sweep-budget-control-spectral.yaml")   # its second seed
    assert spectral.models == tuple(m for m in control.models if m.name == "spectralpillars-s") and spectral.seeds == 2
    assert dataclasses.replace(spectral, name=control.name, models=control.models, seeds=control.seeds) == control


def test_the_shipped_ablations_are_the_issues():
    cfg = load_ablation(CONFIGS / "ablation.yaml")
    assert len(cfg.densities) >= 3 and cfg.budget.time_limit_min <= 20
    assert cfg.axes.arms == ("base", "+Ae", "+d", "+Ae+d")
    assert cfg.enrichments.arms == ("none", "rd", "sector", "both")
    assert (cfg.enrichments.rd, cfg.enrichments.sector) == ("rd3", "sector32")
    rd = load_ablation(CONFIGS / "rd-comparison.yaml")
    c = rd.rd_comparison
    assert rd.sensor == "radial-s" and c.dense is not None and c.points.enrich == ("rd3", "sector32")
    assert c.sparse_rd.experiment.model.variant == c.dense.experiment.model.variant == "fftradnet-s"
    assert rd.budget.time_limit_min <= 20


def test_density_folders_keep_every_digit():
    assert density_folder(0.057) == "density-057"
    assert density_folder(0.007) == "density-007"
    assert density_folder(0.0072) == "density-007.2"
    assert density_folder(0.564) == "density-564"
    assert density_folder(0.19) == "density-190"
    assert density_folder(1.0) == "density-1000"
    assert density_folder(None) == "dense"


def test_a_sweep_is_seed_by_seed_dense_first_then_density_by_density():
    cfg = load_study(CONFIGS / "rd-comparison.yaml", "ablation")
    cfg = dataclasses.replace(cfg, densities=(0.05, 0.2), seeds=2)
    ids = [r.id for r in study_grid(cfg).runs]
    assert ids == ["dense/fftradnet-s/seed0",
                   "density-050/sparse-rd-fftradnet-s/seed0", "density-050/spectralpillars-s/seed0",
                   "density-200/sparse-rd-fftradnet-s/seed0", "density-200/spectralpillars-s/seed0",
                   "dense/fftradnet-s/seed1",
                   "density-050/sparse-rd-fftradnet-s/seed1", "density-050/spectralpillars-s/seed1",
                   "density-200/sparse-rd-fftradnet-s/seed1", "density-200/spectralpillars-s/seed1"]
    runs = study_grid(cfg).runs
    assert [r.arm.input for r in runs[:3]] == ["dense", "sparse-rd", "points"]
    # the budget's length and the seed are what each run trains
    assert all(r.experiment(cfg.budget).train.max_steps == 1200 and r.experiment(cfg.budget).train.epochs == 0
               for r in runs)
    assert [r.experiment(cfg.budget).train.seed for r in runs] == [0] * 5 + [1] * 5


def test_ablation_arms_are_model_overrides_and_store_enrichments():
    grid = study_grid(load_ablation(CONFIGS / "tiny-ablation.yaml"))
    arms = {a.name: a for a in grid.arms}
    assert list(arms) == ["axes-base", "axes-Ae", "axes-d", "axes-Ae-d",
                          "enrich-none", "enrich-rd3", "enrich-sector4", "enrich-rd3-sector4"]
    for name, axis in zip(["axes-base", "axes-Ae", "axes-d", "axes-Ae-d"], AXIS_ARMS, strict=True):
        a = arms[name]
        assert a.experiment.model.config.features == AXIS_FEATURES[axis] + ("pillar_offset",)
        assert a.enrich == () and a.group == "axes" and a.input == "points"
    enrich = {n: arms[n] for n in arms if n.startswith("enrich-")}
    assert [a.enrich for a in enrich.values()] == [(), ("rd3",), ("sector4",), ("rd3", "sector4")]
    plain = ("r", "a", "e", "d", "Ae", "pillar_offset")
    assert [a.experiment.model.config.features for a in enrich.values()] == [plain, plain, plain + ("sector",),
                                                                            plain + ("sector",)]
    assert [a.experiment.model.config.n_sector for a in enrich.values()][2:] == [4, 4]
    # +Ae+d on plain points and "none" build the same model on the same store: one run, one key
    keys = {}
    for r in grid.runs:
        keys.setdefault(json.dumps(run_key(grid, r), sort_keys=True), []).append(r.id)
    twins = sorted(ids for ids in keys.values() if len(ids) > 1)
    assert twins == [["density-050/axes-Ae-d/seed0", "density-050/enrich-none/seed0"],
                     ["density-200/axes-Ae-d/seed0", "density-200/enrich-none/seed0"]]


def test_the_velocity_arm_pairs_with_the_short_ablations_doppler_arm():
    # the controlled test of + d: the same data, densities, budget, model and seed, v in place of d
    short, vel = load_ablation(CONFIGS / "ablation-short.yaml"), load_ablation(CONFIGS / "ablation-velocity-short.yaml")
    assert vel.axes.arms == ("+v",) and "+v" not in AXIS_ARMS and set(AXIS_ARMS) < set(AXIS_FEATURES)
    for field in ("sensor", "data", "densities", "budget", "conversion", "evaluation"):
        assert getattr(vel, field) == getattr(short, field), field
    (arm, label, entry), = vel.axes.entries()
    d_entry = next(e for a, _, e in short.axes.entries() if a == "+d")
    assert label == "[r, a, e, v]" and entry.name == "axes-v"
    v_model, d_model = entry.resolved().model.config, d_entry.resolved().model.config
    assert v_model.features == ("r", "a", "e", "v", "pillar_offset")
    assert dataclasses.replace(v_model, features=d_model.features) == d_model
    assert entry.resolved().train == d_entry.resolved().train


def test_run_keys_name_the_data_without_machine_paths(tmp_path):
    cfg = load_density_sweep(CONFIGS / "tiny-sweep.yaml")
    roots = dataclasses.replace(cfg, data=DataSpec(roots=(str(tmp_path / "a" / "sim_x"),)))
    key = run_key(study_grid(roots), study_grid(roots).runs[0])
    assert key["data"] == {"sensor": "tiny", "roots": ["sim_x"]} and str(tmp_path) not in json.dumps(key)
    sim = run_key(study_grid(cfg), study_grid(cfg).runs[0])
    assert sim["data"]["simulate"] == [{"sequences": 3, "frames_per_sequence": 3, "seed": 3, "scenes": "city"}]
    assert sim["density"] == 0.05 and sim["conversion"]["density"] == 0.05 and sim["input"] == "points"


TINY_EXPERIMENT = {"name": "t", "model": {"variant": "pillars-tiny"}, "train": {"epochs": 1, "num_workers": 0}}
BASE = {"name": "s", "sensor": "tiny", "data": {"simulate": [{"sequences": 3, "frames_per_sequence": 1}]},
        "densities": [0.05], "models": [{"experiment": TINY_EXPERIMENT}]}


def _with(**changes):
    d = json.loads(json.dumps(BASE))
    for k, v in changes.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    return d


@pytest.mark.parametrize("d, match", [
    (_with(densitys=[0.1]), r"unknown keys \['densitys'\]"),
    (_with(densities=None), r"missing keys \['densities'\]"),
    (_with(densities=[0.8]), "density 0.8 is unreachable for sensor 'tiny'"),
    (_with(densities=[0.05, 0.05]), "each density once"),
    (_with(densities=[]), "at least one target density"),
    (_with(models=[]), "at least one model"),
    (_with(models=[{"experiment": TINY_EXPERIMENT}, {"experiment": TINY_EXPERIMENT}]), "'pillars-tiny' is given twice"),
    (_with(models=[{"experiment": TINY_EXPERIMENT, "name": "my model"}]), "model name 'my model' must be"),
    (_with(models=[{"experiment": TINY_EXPERIMENT, "enrich": ["rd2"]}]), "rd2"),
    (_with(models=[{"experiment": TINY_EXPERIMENT, "overrides": {"n_pillars": 3}}]), "n_pillars"),
    (_with(models=[{"experiment": {**TINY_EXPERIMENT, "model": {"variant": "fftradnet-tiny"}}}]),
     r"reads \(128, 64, 16\) cubes, sensor 'tiny' makes \(64, 32, 4\)"),
    (_with(reference={"experiment": TINY_EXPERIMENT}), "the dense reference reads RD cubes"),
    (_with(data={"roots": ["a"], "simulate": [{"sequences": 3, "frames_per_sequence": 1}]}), "exactly one of roots"),
    (_with(data={}), "exactly one of roots"),
    (_with(data={"roots": ["x/a", "y/a"]}), "folder names must differ"),
    (_with(data={"roots": ["a"], "drop_cubes": True}), "does not apply to data.roots"),
    (_with(data={"simulate": [{"sequences": 2, "frames_per_sequence": 1}]}), "simulate.sequences must be an integer >= 3"),
    (_with(data={"simulate": [{"sequences": 3, "frames_per_sequence": 1, "scenes": "moon"}]}), "unknown scene preset"),
    (_with(budget={"epochs": 1, "max_steps": 5}), "epochs or max_steps, not both"),
    (_with(budget={"time_limit_min": 0}), "time_limit_min must be > 0"),
    (_with(seeds=0), "seeds must be an integer >= 1"),
    (_with(sensor="radar9"), "unknown sensor 'radar9'"),
    (_with(name="a b"), "study name 'a b' must be"),
    (_with(evaluation={"split": "dev"}), "evaluation.split must be one of"),
    (_with(conversion={"density_mode": "sometimes"}), "sometimes"),
])
def test_bad_sweep_configs_name_the_file_and_field(tmp_path, d, match):
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(ValueError, match=match) as e:
        load_density_sweep(path)
    assert str(path) in str(e.value)


ABLATION = {"name": "a", "sensor": "tiny", "data": BASE["data"], "densities": [0.05]}


@pytest.mark.parametrize("section, match", [
    ({}, "at least one of axes, enrichments and rd_comparison"),
    ({"axes": {"model": {"experiment": TINY_EXPERIMENT}, "arms": ["base", "+x"]}}, "axes.arms: each once"),
    ({"axes": {"model": {"experiment": TINY_EXPERIMENT, "enrich": ["rd3"]}}}, "runs on plain points"),
    ({"axes": {"model": {"experiment": {**TINY_EXPERIMENT, "model": {"variant": "fftradnet-tiny"}}}}},
     "needs a pillar model"),
    ({"enrichments": {"model": {"experiment": {**TINY_EXPERIMENT, "model": {
        "variant": "pillars-tiny", "overrides": {"features": ["r", "a", "e", "sector"]}}}}}}, "already read 'sector'"),
    ({"enrichments": {"model": {"experiment": TINY_EXPERIMENT}, "rd": "sector4"}}, "enrichments.rd must name an RD neighbourhood"),
    ({"rd_comparison": {"points": {"experiment": TINY_EXPERIMENT}, "sparse_rd": {"experiment": TINY_EXPERIMENT}}},
     "rd_comparison.sparse_rd: needs an FFTRadNet"),
])
def test_bad_ablation_configs_are_refused(tmp_path, section, match):
    path = tmp_path / "ablation.yaml"
    path.write_text(yaml.safe_dump({**ABLATION, **section}))
    with pytest.raises(ValueError, match=match):
        load_ablation(path)


def test_experiment_paths_are_relative_to_the_study_file(tmp_path):
    (tmp_path / "exp").mkdir()
    (tmp_path / "exp" / "t.yaml").write_text(yaml.safe_dump(TINY_EXPERIMENT))
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(_with(models=[{"experiment": "exp/t.yaml"}])))
    cfg = load_density_sweep(tmp_path / "s.yaml")
    assert cfg.models[0].experiment.name == "t" and cfg.models[0].name == "pillars-tiny"
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(_with(models=[{"experiment": "exp/none.yaml"}])))
    with pytest.raises(FileNotFoundError, match=r"models\[0\].experiment: 'exp/none.yaml' .* relative to the study"):
        load_density_sweep(tmp_path / "bad.yaml")
    (tmp_path / "exp" / "bad.yaml").write_text("name: t\nmodel: {variant: pillars-tiny}\ntrain: {epoch: 1}\n")
    (tmp_path / "bad2.yaml").write_text(yaml.safe_dump(_with(models=[{"experiment": "exp/bad.yaml"}])))
    with pytest.raises(ValueError, match=r"exp/bad.yaml: train: TrainConfig unknown keys \['epoch'\]"):
        load_density_sweep(tmp_path / "bad2.yaml")


def test_the_command_reports_a_bad_config_in_one_line(tmp_path, capsys):
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(_with(densities=[0.8])))
    assert main(["experiment", "density-sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"radarpc experiment: error: {path}: ") and "unreachable" in err and "\n" not in err
    assert not (tmp_path / "out").exists()
    # a sweep config is not an ablation config
    assert main(["experiment", "ablation", str(path), "--out", str(tmp_path / "out")]) == 2
    assert "AblationConfig unknown keys ['models']" in capsys.readouterr().err


def test_plan_lists_the_runs_and_the_twins(capsys, tmp_path):
    assert main(["experiment", "ablation", str(CONFIGS / "tiny-ablation.yaml"), "--out", str(tmp_path / "o"),
                 "--plan"]) == 0
    out = capsys.readouterr().out
    assert "study 'tiny-ablation' (ablation): 16 runs, 0 finished" in out
    assert "[5/16] density-050/enrich-none/seed0: no enrichment, points -- the same run as " \
           "density-050/axes-Ae-d/seed0, trained once" in out
    assert not (tmp_path / "o").exists()


def test_configs_built_in_python_validate_too():
    cfg = load_density_sweep(CONFIGS / "tiny-sweep.yaml")
    with pytest.raises(ValueError, match="unreachable"):
        dataclasses.replace(cfg, densities=(0.9,))
    assert isinstance(cfg, DensitySweepConfig) and not isinstance(cfg, AblationConfig)
    assert dataclasses.replace(cfg, densities=(0.2, 0.05)).densities == (0.05, 0.2)     # sorted
