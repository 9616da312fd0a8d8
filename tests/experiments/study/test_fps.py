"""The FPS study on the session's radial-s city root: a run writes one row per model, density and
mode, each timed in a fresh process (rates, parameters, frames and points checked against
independent counts), a rerun times nothing again, rows of another config are refused (and timed
again with overwrite), bad configs are refused naming the field, and the report renders the table.

The test times the tiny config's sparse-RD FFTRadNet (plain) and plain pillar model (fast) at one
density, two configs sharing one output (2 processes); its rates mean nothing, but they must be
positive and self-consistent.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import shutil
import statistics
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from PIL import Image

from radarpc.cli import main
from radarpc.data.point_dataset import PointCloudDataset
from radarpc.data.radial import RADIal
from radarpc.experiments.study import fps as fps_module
from radarpc.experiments.study.config import DataSpec, load_fps
from radarpc.experiments.study.fps import FPS_ROW_FORMAT, fps_plan, measurement_key, run_fps
from radarpc.experiments.study.fps_report import write_fps_report
from radarpc.experiments.study.inputs import DONE_SUFFIX, InputsSpec, StudyInputs
from radarpc.machine import cpu_model, isa_flags
from radarpc.models import build_model
from radarpc.models.complexity import MEMORY_METHODS

CONFIGS = Path(__file__).parents[3] / "configs" / "study"
TIMED = {"sparse-rd-fftradnet-tiny": "plain", "pillars-tiny": "fast"}
IDS = ["density-050/sparse-rd-fftradnet-tiny/plain", "density-050/pillars-tiny/fast"]


def tiny_fps(root: Path, name: str, mode: str):
    """The shipped tiny FPS config on ``root`` (the session's radial-s city root: the frames of its
    simulation spec), its model ``name`` at density 0.05 in ``mode``."""
    cfg = load_fps(CONFIGS / "tiny-fps.yaml")
    return dataclasses.replace(cfg, data=DataSpec(roots=(str(root),)), densities=(0.05,),
                               models=tuple(m for m in cfg.models if m.name == name),
                               timing=dataclasses.replace(cfg.timing, modes=(mode,)))


def _rows(out: Path) -> dict[str, dict]:
    return {json.loads(p.read_text())["run"]: json.loads(p.read_text()) for p in (out / "results").glob("*.json")}


@pytest.fixture(scope="module")
def fps_run(radial_s_city_root, tmp_path_factory):
    """Two configs timed into one output: the sparse-RD model plain, then the pillar model fast."""
    base = tmp_path_factory.mktemp("fps")
    cfgs = [tiny_fps(radial_s_city_root, name, mode) for name, mode in TIMED.items()]
    logs: list[str] = []
    outcomes = [run_fps(cfg, base / "out", cache=base / "cache", progress=False, log=logs.append,
                        command="radarpc experiment fps tiny.yaml --out out", config_file="tiny.yaml") for cfg in cfgs]
    return SimpleNamespace(cfgs=cfgs, out=base / "out", cache=base / "cache", logs=logs, outcomes=outcomes,
                           root=radial_s_city_root, base=base)


def test_the_plan_times_a_dense_model_once():
    cfg = load_fps(CONFIGS / "tiny-fps.yaml")
    ids = [m.id for m in fps_plan(cfg).measurements]
    assert ids[:2] == ["dense/fftradnet-tiny/plain", "dense/fftradnet-tiny/fast"]
    assert len(ids) == len(set(ids)) == 2 + 3 * 2 * 2             # dense once; 3 models x 2 densities x 2 modes
    assert "density-200/spectralpillars-tiny/fast" in ids
    shipped = load_fps(CONFIGS / "fps.yaml")
    plan = fps_plan(shipped)
    assert plan.sensors == ["radial", "radial-s"] and len(shipped.densities) == 5
    assert len(plan.measurements) == (2 + 8 * 5) * 2
    assert {m.model.spec.variant for m in plan.measurements} >= {"fftradnet", "pointpillars", "spectralpillars",
                                                                  "fftradnet-s", "pointpillars-s", "spectralpillars-s"}


@pytest.mark.parametrize("k", range(len(IDS)), ids=IDS)
def test_a_run_writes_a_row_per_model_density_and_mode(fps_run, k):
    cfg, out, outcome = fps_run.cfgs[k], fps_run.out, fps_run.outcomes[k]
    rows = _rows(out)
    assert sorted(rows) == sorted(IDS)                   # the second config kept the first one's row
    assert outcome.measured == [IDS[k]] and not outcome.reused
    test_frames = RADIal(fps_run.root, split="test").frame_ids[:cfg.timing.frames]
    inputs = StudyInputs(InputsSpec(cfg.sensor, cfg.data, cfg.conversion), fps_run.cache, progress=False,
                         log=lambda s: None)
    for m in fps_plan(cfg).measurements:
        row = rows[m.id]
        assert row["format"] == FPS_ROW_FORMAT and row["density"] == 0.05 and row["mode"] == m.mode
        assert row["key"] == measurement_key(cfg, m, weights="random", device="cpu", cpu=cpu_model())
        model = build_model(m.model.spec.variant, m.model.spec.overrides)
        assert row["parameters"] == sum(p.numel() for p in model.parameters())
        assert row["frames"] == test_frames                                       # the first test frames
        for path in ("network", "pipeline"):
            meas = row["measurements"][path]
            rate = meas["rate"]
            assert len(rate["sweeps"]) == rate["repeats"] == cfg.timing.repeats and meas["frames"] == len(test_frames)
            assert rate["median"] == statistics.median(rate["sweeps"])
            assert 0 < rate["low"] == min(rate["sweeps"]) <= rate["median"] <= rate["high"] == max(rate["sweeps"])
            assert meas["first_pass_s"] > 0
            assert meas["memory"]["method"] in MEMORY_METHODS and meas["memory"]["working_bytes"] >= 0
        stored, record = inputs.input_of(0, m.need)                               # the cached input, not made again
        assert row["input"]["tau"] == record.tau == json.loads(
            stored.with_name(stored.name + DONE_SUFFIX).read_text())["tau"]
        if m.model.input == "points":
            ds = PointCloudDataset(stored, fps_run.root, "test")
            want = sum(ds[k].points.num_points for k in range(len(test_frames))) / len(test_frames)
            assert row["points_per_frame"] == want
            # the timed extraction computes the stored clouds: the same points a frame
            assert row["pipeline_points_per_frame"] == want
        else:
            sparse = RADIal(stored, split="test")
            want = sum(int((sparse.cube(k).abs().sum(-1) > 0).sum()) for k in range(len(test_frames)))
            assert row["cells_per_frame"] == row["pipeline_cells_per_frame"] == want / len(test_frames)
        mach = row["machine"]
        assert mach["cpu"] == cpu_model() and mach["isa"] == isa_flags() and mach["threads"] == cfg.timing.threads
        assert mach["device"] == "cpu" and len(mach["load_average"]["start"]) == len(mach["load_average"]["end"]) == 3
        assert row["command"] == "radarpc experiment fps tiny.yaml --out out"
    assert any("fresh process" in line for line in fps_run.logs)


def test_a_rerun_reuses_every_row_without_timing(fps_run, monkeypatch):
    before = {p.name: p.stat().st_mtime_ns for p in (fps_run.out / "results").glob("*.json")}

    def no_process(*args, **kwargs):
        raise AssertionError("a finished row was timed again")

    monkeypatch.setattr(fps_module, "_run_worker", no_process)
    for cfg, run_id in zip(fps_run.cfgs, IDS):
        logs: list[str] = []
        again = run_fps(cfg, fps_run.out, cache=fps_run.cache, progress=False, log=logs.append)
        assert again.reused == [run_id] and not again.measured and [r["run"] for r in again.rows] == [run_id]
        assert sum("finished earlier, row reused" in line for line in logs) == 1
    assert {p.name: p.stat().st_mtime_ns for p in (fps_run.out / "results").glob("*.json")} == before


def test_rows_of_another_config_are_refused_and_overwrite_times_them_again(fps_run, tmp_path, monkeypatch):
    out = tmp_path / "out"
    shutil.copytree(fps_run.out / "results", out / "results")
    cfg = fps_run.cfgs[0]
    other = dataclasses.replace(cfg, timing=dataclasses.replace(cfg.timing, repeats=3))
    with pytest.raises(ValueError, match=r"1 row\(s\) were measured with another configuration.*timing\.repeats: 2 in "
                                         r"the row, 3 in the config.*--overwrite"):
        run_fps(other, out, cache=fps_run.cache, progress=False, log=lambda s: None)
    old = _rows(out)
    timed = []

    def canned(job, threads, head, log):
        """The old row's measurements as a worker's result (no process: what is checked is the bookkeeping)."""
        timed.append(job["id"])
        r = old[job["id"]]
        return {"parameters": r["parameters"], "frames": r["frames"], "paths": r["measurements"], "seconds": 1.0,
                "load_average": r["machine"]["load_average"], "machine": r["machine"], "device": "cpu",
                "device_name": None, "threads": threads}

    monkeypatch.setattr(fps_module, "_run_worker", canned)
    again = run_fps(other, out, cache=fps_run.cache, progress=False, overwrite=True, log=lambda s: None)
    assert timed == again.measured == IDS[:1]
    rows = _rows(out)
    assert rows[IDS[0]]["key"]["timing"]["repeats"] == 3 and rows[IDS[1]] == old[IDS[1]]     # the other row kept


@pytest.mark.parametrize("change, message", [
    ({"models": []}, "models: give at least one model"),
    ({"models": [{"variant": "pillars-tiny", "run": "x"}]}, "exactly one of variant .* and run"),
    ({"models": [{"variant": "fftradnet-tiny", "input": "points"}]}, "reads RD cubes; input 'points' needs a pillar"),
    ({"models": [{"variant": "pillars-tiny", "input": "dense"}]}, "reads point clouds; input 'dense' needs an FFTRadNet"),
    ({"models": [{"variant": "fftradnet-tiny", "input": "sideways"}]}, "input must be one of"),
    ({"models": [{"variant": "fftradnet-tiny", "input": "dense", "enrich": ["rd3"]}]}, "dense input reads whole cubes"),
    ({"models": [{"variant": "spectralpillars-s"}]}, "32-wide 'sector' descriptor; enrich needs sectorA"),
    ({"models": [{"variant": "fftradnet"}]}, r"reads \(512, 256, 16\) cubes, sensor 'radial-s' makes"),
    ({"models": [{"variant": "rald-ae-tiny"}]}, "times the detection models"),
    ({"models": [{"variant": "pillars-tiny", "sensor": "radial"}], "data": {"roots": ["r"]}},
     "data.roots are of the study's sensor"),
    ({"data": {"simulate": [{"sequences": 3, "frames_per_sequence": 1, "seed": 0},
                            {"sequences": 3, "frames_per_sequence": 1, "seed": 1}]}}, "one root or one simulation"),
    ({"data": {"simulate": [{"sequences": 3, "frames_per_sequence": 1}], "drop_cubes": True}}, "drop_cubes"),
    ({"timing": {"modes": ["plain", "turbo"]}}, "timing.modes"),
    ({"timing": {"frames": 0}}, "timing.frames must be an integer >= 1"),
    ({"timing": {"threads": 0}}, "timing.threads must be an integer >= 1"),
    ({"timing": {"repeat": 3}}, "unknown keys \\['repeat'\\]"),
    ({"densities": [0.05, 0.05]}, "each density once"),
])
def test_bad_fps_configs_are_refused_naming_the_field(tmp_path, change, message):
    d = yaml.safe_load((CONFIGS / "tiny-fps.yaml").read_text())
    d.update(change)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        load_fps(path)


def test_a_bad_fps_config_is_one_line_from_the_command(tmp_path, capsys):
    d = yaml.safe_load((CONFIGS / "tiny-fps.yaml").read_text())
    d["timing"]["modes"] = ["turbo"]
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    assert main(["experiment", "fps", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and "timing.modes" in err
    assert main(["experiment", "density-sweep", str(CONFIGS / "tiny-sweep.yaml"), "--out", str(tmp_path / "o"),
                 "--overwrite"]) == 2
    assert "--overwrite applies to the fps study" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_run_folder_gives_the_model_and_its_weights(tmp_path):
    import hashlib

    import torch

    from radarpc.config import to_dict
    from radarpc.experiments.radial_detection.config import ExperimentConfig
    from radarpc.experiments.study.fps_worker import _model
    from radarpc.models import ModelSpec
    from radarpc.training.checkpoint import save_weights

    d = yaml.safe_load((CONFIGS / "tiny-fps.yaml").read_text())
    spec = ModelSpec("pillars-tiny", d["models"][2]["overrides"])
    run = tmp_path / "runs" / "pp"
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"experiment": to_dict(ExperimentConfig(name="pp", model=spec))}))
    g = torch.Generator().manual_seed(5)
    state = {k: torch.randn(v.shape, generator=g) if v.is_floating_point() else v
             for k, v in spec.build().state_dict().items()}
    save_weights(run / "best.safetensors", state, {})
    d["models"] = [{"name": "trained", "run": "runs/pp"}]                  # relative to the config's folder
    (tmp_path / "fps.yaml").write_text(yaml.safe_dump(d))
    cfg = load_fps(tmp_path / "fps.yaml")
    m = cfg.models[0]
    assert m.spec.variant == "pillars-tiny" and m.spec.config == spec.config and m.input == "points"
    digest = hashlib.sha256((run / "best.safetensors").read_bytes()).hexdigest()
    key = measurement_key(cfg, fps_plan(cfg).measurements[0], weights=fps_module._weights_id(m), device="cpu",
                          cpu="x")
    assert key["model"] == {"variant": "pillars-tiny", "overrides": spec.overrides, "weights": f"sha256:{digest}"}
    loaded = _model({"model": {"run": m.run, "variant": None, "overrides": {}}, "timing": {"detections_only": True}},
                    torch.device("cpu"))
    assert loaded.freespace_head is None
    for k, v in loaded.state_dict().items():
        assert torch.equal(v, state[k]), k
    d["models"] = [{"run": "runs/pp", "overrides": {"pfn_channels": 8}}]
    (tmp_path / "fps.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(ValueError, match="a run's model is the one it trained; drop overrides"):
        load_fps(tmp_path / "fps.yaml")
    (run / "best.safetensors").unlink()
    d["models"] = [{"run": "runs/pp"}]
    (tmp_path / "fps.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(FileNotFoundError, match="has no best.safetensors"):
        load_fps(tmp_path / "fps.yaml")


def test_the_report_renders_the_table(fps_run, tmp_path):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["report", str(fps_run.out), "--out", str(tmp_path / "report")]) == 0
    text = (tmp_path / "report" / "report.md").read_text()
    assert text.startswith("# FPS study tiny-fps (fps)")
    assert f"radarpc report {fps_run.out} --out {tmp_path / 'report'}" in text
    assert "`radarpc experiment fps tiny.yaml --out out`" in text and cpu_model() in text
    head = ("| model | sensor | input | density | achieved density, tau | input a frame | parameters | network alone, "
            "plain | network alone, fast | with extraction, plain | with extraction, fast |")
    assert head in text
    rows = _rows(fps_run.out)
    lines = text.splitlines()
    for name, mode in TIMED.items():
        row = rows[f"density-050/{name}/{mode}"]

        def cell(p, m, what):                 # the mode not timed is a "-"
            if m != mode:
                return "-"
            r = row["measurements"][p]
            return (f"{r['rate']['median']:.3g} ({r['rate']['low']:.3g}-{r['rate']['high']:.3g})" if what == "rate"
                    else f"{r['memory']['working_bytes'] / 2 ** 20:.1f}")
        cells = [cell(p, m, "rate") for p in ("network", "pipeline") for m in ("plain", "fast")]
        line = next(line for line in lines if line.startswith(f"| {name} | radial-s |") and "| 5 % |" in line)
        assert line.endswith(" | ".join(cells) + " |") and f"{row['parameters']:,}" in line
        mem = next(line for line in lines[lines.index("## working memory of one inference (MB)"):]
                   if line.startswith(f"| {name} | radial-s | 5 % |"))
        working = [cell(p, m, "memory") for p in ("network", "pipeline") for m in ("plain", "fast")]
        assert mem.startswith(f"| {name} | radial-s | 5 % | " + " | ".join(working) + " |")
    assert "![frames/s at batch 1 against density" in text
    with Image.open(tmp_path / "report" / "figures" / "fps.png") as im:
        assert im.size[0] > 800 and im.size[1] > 300
    with pytest.raises(FileNotFoundError, match="no result rows"):
        write_fps_report(tmp_path / "empty")


# the timed pillars-tiny's overrides (configs/study/tiny-fps.yaml)
_TINY = {"pfn_channels": 4, "num_filters": [4, 4, 4], "num_upsample_filters": [4, 2, 2], "detection_widths": [4, 4],
         "freespace_widths": [4, 4]}


def _scored_row(name: str, variant: str, input_: str, sensor: str, density: float, seed: int, f1: float,
                overrides: dict = _TINY) -> dict:
    from radarpc.experiments.study.results import ROW_FORMAT

    return {"format": ROW_FORMAT, "run": f"density-{density * 1000:03.0f}/{name}/seed{seed}",
            "study": {"kind": "density-sweep", "name": "sweep", "config": {"name": "sweep"}},
            "arm": {"name": name, "label": name, "group": "models", "input": input_, "enrich": [], "variant": variant,
                    "order": 0},
            "density": density, "seed": seed,
            "key": {"experiment": {"model": {"variant": variant, "overrides": overrides}}, "data": {"sensor": sensor}},
            "metrics": {"f1_fixed": f1}}


def test_scores_put_a_training_studys_f1_beside_the_frames_per_second(fps_run, tmp_path, capsys):
    sweep = tmp_path / "sweep"
    (sweep / "results").mkdir(parents=True)
    rows = [_scored_row("pp", "pillars-tiny", "points", "radial-s", 0.05, 0, 0.5),
            _scored_row("pp", "pillars-tiny", "points", "radial-s", 0.05, 1, 0.7),
            _scored_row("pp", "pillars-tiny", "points", "radial-s", 0.2, 0, 0.9),       # a density not timed
            _scored_row("pp-r", "pillars-tiny", "points", "radial", 0.05, 0, 0.1),      # another sensor
            _scored_row("pp-rae", "pillars-tiny", "points", "radial-s", 0.05, 0, 0.2,   # other point features
                        {**_TINY, "features": ["r", "a", "e"]}),
            _scored_row("pp-wide", "pillars-tiny", "points", "radial-s", 0.05, 0, 0.3, {})]   # another width
    for row in rows:
        (sweep / "results" / (row["run"].replace("/", "__") + ".json")).write_text(json.dumps(row))
    assert main(["report", str(fps_run.out), "--out", str(tmp_path / "report"), "--scores", str(sweep)]) == 0
    text = (tmp_path / "report" / "report.md").read_text()
    assert f"--scores {sweep}" in text
    block = text[text.index("## F1 beside frames/s"):].split("\n\n")[2].splitlines()
    assert block[0] == "| model | sensor | density | F1 @ 0.2 (runs, study) | frames/s, plain | frames/s, fast |"
    rate = _rows(fps_run.out)["density-050/pillars-tiny/fast"]["measurements"]["pipeline"]["rate"]
    # mean 0.6 and sample standard deviation sqrt(0.02) = 0.141 of the two seeds; the pillar model was timed
    # fast only, with its extraction
    assert block[2:] == [f"| pillars-tiny | radial-s | 5 % | 0.600 ± 0.141 (2, sweep) | - | "
                         f"{rate['median']:.3g} ({rate['low']:.3g}-{rate['high']:.3g}) |"]
    capsys.readouterr()
    # --scores belongs to an FPS report: on a training study it is one line
    assert main(["report", str(sweep), "--scores", str(sweep)]) == 2
    assert "--scores pairs F1 with an FPS study's frames/s" in capsys.readouterr().err
