"""Detection experiments end to end on a tiny simulated radial-s root: shipped configs, a tiny
FFTRadNet and a tiny SpectralPillars that overfit a few frames, and the train / evaluate CLI."""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import runpy
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from radarpc.cli import main
from radarpc.data.augment import SuperposedFrames
from radarpc.config import load_yaml, save_yaml, to_dict
from radarpc.models.fftradnet import fftradnet, fftradnet_s
from radarpc.models.pillars import (pillars_tiny, polar_pointpillars, polar_pointpillars_s, spectralpillars,
                                    spectralpillars_s)
from radarpc.data.point_dataset import PointCloudDataset
from radarpc.pipelines.pointclouds import convert_dataset
from radarpc.sensors.radial import RADIAL_S
from radarpc.sim.radial_writer import write_radial_dataset
from radarpc.sim.scenes import scene_mix
from radarpc.training.checkpoint import load_state, load_weights, save_weights
from radarpc.training.loop import BEST_WEIGHTS, LAST_CHECKPOINT, TrainConfig, fit
import radarpc.experiments.radial_detection.task as radial
from radarpc.experiments.radial_detection.config import ExperimentConfig, experiment_from_dict, load_experiment
from radarpc.experiments.radial_detection.task import RadialDetectionTask, preload_budget_bytes, preload_point_frames
from radarpc.models import MODELS, ModelSpec
from testkit import same_cloud

CONFIGS = Path(__file__).parents[3] / "configs"
FACTORIES = {"fftradnet": fftradnet, "fftradnet-s": fftradnet_s, "pointpillars": polar_pointpillars,
             "pointpillars-s": polar_pointpillars_s, "spectralpillars": spectralpillars,
             "spectralpillars-s": spectralpillars_s}


SCRIPTS = Path(__file__).parents[3] / "docs" / "notebook" / "scripts"
BENCHMARKS = Path(__file__).parents[3] / "benchmarks"


def _run_script(path: Path, *args: str) -> str:
    """Run ``python path args`` in this process: the script's ``__main__`` under that ``sys.argv``
    (without a second interpreter's start and torch import, which it does not depend on); the
    torch thread count it may set is restored. Returns what it printed."""
    argv, threads, out = sys.argv, torch.get_num_threads(), io.StringIO()
    sys.argv = [str(path), *args]
    try:
        with contextlib.redirect_stdout(out):
            runpy.run_path(str(path), run_name="__main__")
    finally:
        sys.argv = argv
        torch.set_num_threads(threads)
    return out.getvalue()


@pytest.mark.parametrize("name", sorted(FACTORIES))
def test_shipped_config_matches_its_factory(name):
    cfg = load_experiment(CONFIGS / f"{name}.yaml")
    assert cfg.name == name and cfg.model.variant == name and MODELS[name] is FACTORIES[name]
    want = FACTORIES[name]().cfg
    assert cfg.model.config == want
    n = sum(p.numel() for p in cfg.model.build(device="meta").parameters())
    if name == "fftradnet":
        assert n == 3_789_940                                    # the official model's count
    elif name in ("pointpillars", "spectralpillars"):
        assert abs(n - 2.4e6) <= 0.05 * 2.4e6                    # the seed's ~2.4M


@pytest.mark.parametrize("path", sorted((CONFIGS / "detection").glob("*.yaml")), ids=lambda p: p.name)
def test_results_configs_load_and_name_a_registered_model(path):
    """The configs behind docs/results rows: each loads and names a registry variant whose
    overrides build (on the meta device)."""
    cfg = load_experiment(path)
    assert cfg.name == path.stem and cfg.model.variant in MODELS
    cfg.model.build(device="meta")


def test_experiment_config_names_one_registered_model():
    with pytest.raises(TypeError, match="model"):
        ExperimentConfig(name="x")
    with pytest.raises(ValueError, match="unknown model variant 'resnet50'; known: fftradnet, "):
        experiment_from_dict({"name": "x", "model": {"variant": "resnet50"}}, where="x.yaml")
    with pytest.raises(ValueError, match=r"x.yaml: .*model 'pillars-tiny': .*'n_pillars'"):
        experiment_from_dict({"name": "x", "model": {"variant": "pillars-tiny", "overrides": {"n_pillars": 3}}},
                             where="x.yaml")
    with pytest.raises(ValueError, match="model.overrides must be a mapping"):
        ModelSpec("pillars-tiny", [1, 2])
    with pytest.raises(ValueError, match="model 'rald-ae-tiny' reads 'lidar' inputs"):   # not a detector
        ExperimentConfig(name="x", model=ModelSpec("rald-ae-tiny"))


def test_overrides_change_the_model_built():
    spec = ModelSpec("pillars-tiny", {"pfn_channels": 12, "features": ["r", "a", "e"]})
    assert spec.config == pillars_tiny(pfn_channels=12, features=("r", "a", "e")).cfg
    assert spec.build().vfe.linear.out_features == 12 and spec.input_kind == "points"
    assert ModelSpec("fftradnet-tiny").input_kind == "rd"
    assert ModelSpec.matching("pillars-tiny", spec.config) == ModelSpec("pillars-tiny", {"pfn_channels": 12,
                                                                                       "features": ["r", "a", "e"]})


@pytest.mark.parametrize("name", ["fftradnet-s", "spectralpillars-s"])
def test_config_written_before_the_registry_reads_as_its_variant(name, tmp_path):
    """A YAML (or run key) with the whole model config in a 'fftradnet:' / 'pillars:' section, as
    radarpc wrote them before the model registry, is read into the same resolved config."""
    family = "fftradnet" if name.startswith("fftradnet") else "pillars"
    old = {"name": name, "fftradnet": None, "pillars": None, "difficult": False,
           family: to_dict(FACTORIES[name](**({"pfn_channels": 48} if family == "pillars" else {})).cfg)}
    cfg = experiment_from_dict(old)
    assert cfg.model.variant == name and not cfg.difficult
    assert cfg.model.overrides == ({"pfn_channels": 48} if family == "pillars" else {})
    renamed = experiment_from_dict(dict(old, name="mine"))            # not a variant's name: the full-size one
    assert renamed.model.variant == ("fftradnet" if family == "fftradnet" else "pointpillars")
    assert renamed.model.config == cfg.model.config
    with pytest.raises(ValueError, match="exactly one of 'fftradnet' and 'pillars'"):
        experiment_from_dict({"name": "x", "fftradnet": None, "pillars": None})


def _city_root(tmp_path_factory, name: str, frames_per_sequence: int, seed: int) -> Path:
    # 3 sequences of radial-s city scenes: one sequence each for train, val and test
    return write_radial_dataset(tmp_path_factory.mktemp(name) / name, RADIAL_S, 3, frames_per_sequence, seed=seed,
                                progress=False, scenes=scene_mix("city"))


def _store_of(root: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pc") / f"{root.name}.parquet"
    convert_dataset(root, out, density=0.057, enrich=("sector32",), progress=False)
    return out


@pytest.fixture
def root(radial_s_city_root):
    return radial_s_city_root                                       # the session's: 3 x 4 frames, 24 vehicles


@pytest.fixture
def store(radial_s_city_store):
    return radial_s_city_store                                      # its 5.7 % sector32 store


def _overfit(cfg: ExperimentConfig, root, store, tmp_path) -> list[dict]:
    task = RadialDetectionTask(cfg, root, store, splits=("all", "all"))
    res = fit(task, cfg.train, tmp_path / cfg.name, {"name": cfg.name}, progress=False, log=lambda s: None)
    return res.history


TINY_TRAIN = TrainConfig(epochs=30, batch_size=4, eval_batch_size=12, num_workers=0, precision="fp32",
                         lr_start=2e-3, lr_max=2e-2, checkpoint_every=1000)
OVERFIT_TRAIN = dataclasses.replace(TINY_TRAIN, epochs=15, batch_size=2)
"""90 steps of 2 frames on the 12 frames of the root (each seen 15 times), one-cycle up to 2e-2."""


def _learned(history: list[dict]) -> None:
    # a run scored on the frames it trains on. The heads start at p = 0.01, so the loss of the
    # first steps is already small on the background; from the first row of the log (the mean
    # over the steps before the first validation) to the last, the loss must halve, its
    # classification term fall 4x, and the F1 at confidence 0.2 leave 0 (untrained, no cell
    # reaches 0.2) for 0.2 or more at a validation in the run's last sixth
    first, last = history[0], history[-1]
    late = [h for h in history if h["step"] > 5 / 6 * last["step"]]
    assert last["train_loss"] < 0.5 * first["train_loss"]
    assert last["train_classification"] < 0.25 * first["train_classification"]
    assert first["val_f1_fixed"] < 0.05 and max(h["val_f1_fixed"] for h in late) >= 0.2


def test_tiny_spectralpillars_overfits(root, store, tmp_path):
    features = ["r", "a", "e", "d", "Ae", "pillar_offset", "sector"]
    cfg = ExperimentConfig(name="sp-tiny", model=ModelSpec("pillars-tiny", {"features": features}), train=OVERFIT_TRAIN)
    _learned(_overfit(cfg, root, store, tmp_path))


def test_tiny_fftradnet_overfits(root, store, tmp_path):
    # validated every 2 epochs: a validation of the 12 cubes costs as much as 4 training steps
    cfg = ExperimentConfig(name="fft-tiny", model=ModelSpec("fftradnet-tiny"),
                           train=dataclasses.replace(OVERFIT_TRAIN, validate_every=12))
    _learned(_overfit(cfg, root, None, tmp_path))


def test_training_preloads_the_point_frames_that_fit(root, store, monkeypatch):
    cfg = ExperimentConfig(name="sp-pre", model=ModelSpec("pillars-tiny"), mirror_probability=0.5, train=TINY_TRAIN)
    held = RadialDetectionTask(cfg, root, store)              # train frames behind the mirroring wrapper
    plain = RadialDetectionTask(cfg, root, store, preload=False)
    assert plain.preloaded_bytes == 0 and held.preloaded_bytes > 0
    stores = [d.store for s in (held.train_set, held.val_set) for d in radial.point_datasets(s)]
    assert len(stores) == 2 and stores[0] is not stores[1]    # each split holds its own frames
    for st in stores:                                         # every item comes from memory
        st.read_row_group = lambda g: pytest.fail(f"row group {g} read from the file")
    for a, b in ((held.train_set, plain.train_set), (held.val_set, plain.val_set)):
        assert len(a) == len(b)
        for i in range(len(a)):
            x, y = a[i], b[i]
            assert x.frame == y.frame and torch.equal(x.labels, y.labels) and same_cloud(x.points, y.points)
    # frames that would not fit stay in the store, and a warning says so
    with pytest.warns(UserWarning, match=r"above the preload budget of 0.00 GiB; they are read from the stores"):
        assert preload_point_frames([plain.train_set], budget_bytes=0) == 0
    assert preload_point_frames([plain.train_set], budget_bytes=2**40) > 0
    # the default budget: a quarter of the memory, shared by the ranks torchrun starts on the machine
    monkeypatch.setattr(radial, "physical_memory_bytes", lambda: 8 * 2**30)
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    assert preload_budget_bytes() == 2**30
    monkeypatch.setattr(radial, "physical_memory_bytes", lambda: None)
    assert preload_budget_bytes() == 0


def test_training_data_benchmark_runs(root, store, tmp_path, monkeypatch):
    # the 4 training frames of the root in 2 batches. The script sets OMP_NUM_THREADS if unset
    # when it starts: set here, it stays as it is, and is put back afterwards
    cfg = ExperimentConfig(name="sp-pre", model=ModelSpec("pillars-tiny"),
                           train=dataclasses.replace(TINY_TRAIN, batch_size=2))
    save_yaml(cfg, tmp_path / "sp.yaml")
    monkeypatch.setenv("OMP_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", str(torch.get_num_threads())))
    out = json.loads(_run_script(BENCHMARKS / "training_data.py", str(tmp_path / "sp.yaml"), "--data", str(root),
                                 "--points", str(store), "--batches", "2", "--threads", "1", "--precision", "fp32"))
    assert out["train_frames"] == 4 and out["batches"] == 2 and out["batch_size"] == 2 and out["preloaded_gib"] > 0
    assert out["file_over_preloaded"] == pytest.approx(out["file_s_per_batch"] / out["preloaded_s_per_batch"])


class _Kill(Exception):
    """Raised from ``on_step`` to stop a run where a kill would."""


def _train_killed_and_resumed(run, cfg: ExperimentConfig, tmp_path: Path) -> None:
    """``run(cfg, out, **kw)`` into ``full`` uninterrupted, and into ``cut`` killed at step 3 (2
    steps an epoch: in epoch 1), then resumed."""
    def stop(step):
        if step == 3:
            raise _Kill

    run(cfg, tmp_path / "full")
    with pytest.raises(_Kill):
        run(cfg, tmp_path / "cut", on_step=stop)
    run(cfg, tmp_path / "cut")


def test_augmented_run_resumes_to_the_same_weights(root, store, tmp_path):
    # the mirrors and rotations are drawn in the loader's worker processes from (seed, epoch,
    # item): a run killed in its second epoch and resumed ends with the weights of an uninterrupted
    # one, and each augmentation reaches the model (the weights differ without it)
    # the 4 frames of the train split in batches of 2
    train = dataclasses.replace(TINY_TRAIN, epochs=2, batch_size=2, eval_batch_size=4, num_workers=2)
    cfg = ExperimentConfig(name="sp-aug", model=ModelSpec("pillars-tiny"), mirror_probability=0.5, rotation_max_deg=2.0,
                           train=train)

    def run(c: ExperimentConfig, out: Path, **kw):
        return fit(RadialDetectionTask(c, root, store, splits=("train", "test")), c.train, out, {"name": c.name},
                   progress=False, log=lambda s: None, **kw)

    _train_killed_and_resumed(run, cfg, tmp_path)
    run(dataclasses.replace(cfg, rotation_max_deg=0.0), tmp_path / "mirror")
    run(dataclasses.replace(cfg, mirror_probability=0.0, rotation_max_deg=0.0), tmp_path / "plain")
    full, cut, mirror, plain = (load_state(tmp_path / d / LAST_CHECKPOINT).model
                                for d in ("full", "cut", "mirror", "plain"))
    assert all(torch.equal(full[k], cut[k]) for k in full)
    assert not all(torch.equal(full[k], mirror[k]) for k in full)
    assert not all(torch.equal(mirror[k], plain[k]) for k in full)


def test_superposed_fftradnet_run_resumes_and_normalises_by_the_recorded_frames(root, store, tmp_path):
    # superposition draws its partners in the loader's workers from (seed, epoch, item): a run
    # killed in its second epoch and resumed ends with the uninterrupted run's weights, the
    # superposed frames reach the model, and the input statistics are those of recorded frames
    # the 4 frames of the train split in batches of 2
    train = dataclasses.replace(TINY_TRAIN, epochs=2, batch_size=2, eval_batch_size=4, num_workers=2)
    cfg = ExperimentConfig(name="fft-sup", model=ModelSpec("fftradnet-tiny"), superpose_probability=0.5, train=train)

    def run(c: ExperimentConfig, out: Path, **kw):
        return fit(RadialDetectionTask(c, root, splits=("train", "test")), c.train, out, {"name": c.name},
                   progress=False, log=lambda s: None, **kw)

    _train_killed_and_resumed(run, cfg, tmp_path)
    run(dataclasses.replace(cfg, superpose_probability=0.0), tmp_path / "plain")
    full, cut, plain = (load_state(tmp_path / d / LAST_CHECKPOINT).model for d in ("full", "cut", "plain"))
    assert all(torch.equal(full[k], cut[k]) for k in full)
    assert not all(torch.equal(full[k], plain[k]) for k in full)
    for k in ("input_mean", "input_std"):
        assert torch.equal(full[k], plain[k])
    task = RadialDetectionTask(dataclasses.replace(cfg, superpose_probability=1.0), root, splits=("all", "all"))
    assert isinstance(task.train_set, SuperposedFrames) and not isinstance(task.val_set, SuperposedFrames)


def test_each_of_several_runs_draws_its_mirrors_from_its_seed(root, store, tmp_path, monkeypatch):
    import radarpc.experiments.radial_detection.train as detection

    seen = []

    def spy(task, train, *a, **k):
        seen.append((train.seed, task.train_set.seed))
        return fitted(task, train, *a, **k)

    fitted = detection.fit
    monkeypatch.setattr(detection, "fit", spy)
    cfg = ExperimentConfig(name="sp-mirror", model=ModelSpec("pillars-tiny"), mirror_probability=0.5,
                           train=dataclasses.replace(TINY_TRAIN, epochs=1, batch_size=4, seed=5))
    detection.train_runs(cfg, root, tmp_path / "runs", points=store, runs=2, progress=False, log=lambda s: None)
    assert seen == [(5, 5), (6, 6)]


def _with_difficult_labels(root: Path, tmp_path: Path) -> tuple[Path, Path, list[dict]]:
    """A copy of ``root`` whose labels.csv marks the vehicles beyond 50 m and every vehicle of the
    first test frame Difficult (RADIal's easy mode then drops those labels and that frame), its
    point store, and the edited label rows of the test split inside the 5-100 m gate."""
    import csv

    from radarpc.data.radial import RADIal

    hard = tmp_path / "hard"
    shutil.copytree(root, hard)
    test = RADIal(root, split="test")
    first = test.frame_ids[0]
    with open(root / "labels.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        if float(r["radar_R_m"]) > 50 or int(r["numSample"]) == first:
            r["Difficult"] = "1" if int(r["Difficult"]) >= 0 else r["Difficult"]
    with open(hard / "labels.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    tested = [r for r in rows if int(r["numSample"]) in set(test.frame_ids) and int(r["Difficult"]) >= 0
              and 5 <= float(r["radar_R_m"]) <= 100]
    assert sum(r["Difficult"] == "1" for r in tested) > 0
    hard_store = tmp_path / "hard.parquet"                       # a store names the root it was made from
    convert_dataset(hard, hard_store, density=0.057, enrich=("sector32",), progress=False)
    return hard, hard_store, tested


def _check_detections_file(path, metrics, root, frames):
    """The per-frame detections file against the metrics computed from the same detections: every
    detection at or above a threshold is a true or a false positive there; its evaluation lists
    every frame, and ``radarpc export`` turns the pair into per-frame arrays holding the same rows."""
    import csv

    from radarpc.eval.detection_files import DETECTION_COLUMNS

    summary = json.loads(path.with_name(path.name.replace("_detections.csv", ".json")).read_text())
    assert summary["frames"] == {"root": [root.name] * len(frames), "numSample": [int(n) for n in frames]}
    assert main(["export", str(path), "--out", str(path.with_suffix(".npz")), "--overwrite"]) == 0
    with np.load(path.with_suffix(".npz")) as z:
        per_frame = dict(zip(z["numSample"].tolist(), np.split(z["detections"], z["offset"][:-1])))

    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == DETECTION_COLUMNS
    rows = rows[1:]
    assert {r[0] for r in rows} <= {root.name} and {int(r[1]) for r in rows} <= set(frames)
    from radarpc.boxes import ra_to_box_xy
    from radarpc.eval.detection import RANGE_GATE_M

    score, r, a = (torch.tensor([float(row[k]) for row in rows], dtype=torch.float64) for k in (2, 3, 4))
    assert bool(((score >= 0.05) & (score <= 1.0)).all())
    near_edge = ra_to_box_xy(r, a)[:, 1]                           # RADIal gates boxes by their near edge
    scored = score[(near_edge >= RANGE_GATE_M[0]) & (near_edge <= RANGE_GATE_M[1])]
    for t, tp, fp in zip(metrics["thresholds"], metrics["tp"], metrics["fp"]):
        assert int((scored > t).sum()) == tp + fp, t               # RADIal: score > t, strictly
    for n in frames:                                                  # (range, azimuth, score) per frame
        want = [[float(x[3]), float(x[4]), float(x[2])] for x in rows if int(x[1]) == int(n)]
        np.testing.assert_array_equal(per_frame[int(n)], np.asarray(want).reshape(-1, 3))


def test_train_and_evaluate_cli(root, store, tmp_path, capsys, monkeypatch):
    cfg = ExperimentConfig(name="sp-tiny", model=ModelSpec("pillars-tiny"),
                           train=dataclasses.replace(TINY_TRAIN, epochs=1, batch_size=2, eval_batch_size=2))
    save_yaml(cfg, tmp_path / "sp.yaml")
    out = tmp_path / "run"
    args = ["train", str(tmp_path / "sp.yaml"), "--data", str(root), "--out", str(out), "--no-progress"]
    assert main(args) == 2
    assert "--points" in capsys.readouterr().err                 # a pillar model needs its point store
    assert main(args + ["--points", str(store)]) == 0
    assert "best validation f1" in capsys.readouterr().out
    assert load_yaml(ExperimentConfig, out / "config.yaml") == cfg
    assert main(args + ["--points", str(store)]) == 0               # finished: nothing to do
    assert "already finished" in capsys.readouterr().out
    assert main(["evaluate", str(out), "--split", "test", "--show", "1", "--fps-frames", "2"]) == 0
    doc = json.loads((out / "eval_test.json").read_text())
    assert doc["split"] == "test" and doc["metrics"]["n_frames"] == 4
    assert doc["parameters"] == sum(p.numel() for p in pillars_tiny().parameters()) and doc["fps_batch1"] > 0
    assert set(doc["metrics"]) >= {"ap", "ar", "f1", "f1_fixed", "range_error_m", "azimuth_error_deg",
                                   "freespace_miou", "fn_fixed", "fn_near_fixed"}
    md = (out / "eval_test.md").read_text()
    assert "| AP | AR | F1 |" in md
    assert f"of the {doc['metrics']['fn_fixed']} labels missed, {doc['metrics']['fn_near_fixed']} have" in md
    first = PointCloudDataset(store, root, split="test").frame_ids[0]       # figures named by RADIal frame
    assert (out / "figures" / f"eval_test_frame{first:06d}.png").stat().st_size > 1000
    assert (out / "figures" / "eval_test_labels.png").stat().st_size > 1000
    assert (out / "figures" / "learning_curve.png").stat().st_size > 1000
    _check_detections_file(out / "eval_test_detections.csv", doc["metrics"], root,
                           PointCloudDataset(store, root, split="test").frame_ids)
    low, high = doc["fps_batch1_range"]
    assert low <= doc["fps_batch1"] <= high and doc["fps_sweeps"] == 5
    # the same weights under bf16 autocast: their own files beside the fp32 ones, scored in bf16
    import radarpc.experiments.radial_detection.evaluation as detection

    seen = []

    def spy(*a, **k):
        seen.append(torch.get_autocast_dtype("cpu") if torch.is_autocast_enabled("cpu") else None)
        return scored(*a, **k)

    scored = detection.evaluate_model
    monkeypatch.setattr(detection, "evaluate_model", spy)
    fp32_doc = (out / "eval_test.json").read_text()
    curve, log = out / "figures" / "learning_curve.png", out / "log.csv"
    drawn = curve.stat().st_mtime_ns
    os.utime(log, ns=(log.stat().st_atime_ns, drawn - 10**9))  # older than the curve, on coarse-mtime file systems too
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1", "--precision", "bf16",
                 "--device", "cpu"]) == 0
    assert curve.stat().st_mtime_ns == drawn                  # the log did not change: not drawn again
    assert seen == [torch.bfloat16]
    bf = json.loads((out / "eval_test_bf16.json").read_text())
    assert bf["precision"] == "bf16" and doc["precision"] == "fp32" and bf["metrics"]["n_frames"] == 4
    assert "bf16 autocast" in (out / "eval_test_bf16.md").read_text().splitlines()[0]
    assert (out / "eval_test.json").read_text() == fp32_doc                      # fp32 files untouched
    with pytest.raises(SystemExit):
        main(["evaluate", str(out), "--precision", "fp16"])
    # RADIal's easy mode, on a copy of the root with Difficult labels (_with_difficult_labels)
    hard, hard_store, tested = _with_difficult_labels(root, tmp_path)
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1", "--data", str(hard), "--points",
                 str(hard_store), "--no-difficult"]) == 0
    easy = json.loads((out / "eval_test_on_hard_easy.json").read_text())
    assert easy["easy"] is True and doc["easy"] is False
    assert easy["metrics"]["n_labels"] == sum(r["Difficult"] == "0" for r in tested) < len(tested)
    assert easy["metrics"]["n_frames"] == 3
    assert "RADIal's easy mode" in (out / "eval_test_on_hard_easy.md").read_text().splitlines()[0]
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1", "--data", str(hard), "--points",
                 str(hard_store)]) == 0                                   # without it: every label
    every = json.loads((out / "eval_test_on_hard.json").read_text())
    assert every["metrics"]["n_labels"] == len(tested) and every["metrics"]["n_frames"] == 4
    # a run trained with difficult: false (its stored config says so) is scored in easy mode unless
    # told --difficult
    easy_run = tmp_path / "easy_run"
    shutil.copytree(out, easy_run, ignore=shutil.ignore_patterns("eval_*", "figures"))
    key = json.loads((easy_run / "run.json").read_text())
    key["experiment"]["difficult"] = False
    (easy_run / "run.json").write_text(json.dumps(key))
    state, info = load_weights(easy_run / "best.safetensors")         # weights carry the key they trained under
    save_weights(easy_run / "best.safetensors", state, {**info, "run": key})
    for flag, stem, n_labels in (([], "eval_test_on_hard_easy", easy["metrics"]["n_labels"]),
                                 (["--difficult"], "eval_test_on_hard", len(tested))):
        assert main(["evaluate", str(easy_run), "--split", "test", "--fps-frames", "1", "--data", str(hard),
                     "--points", str(hard_store), *flag]) == 0
        got = json.loads((easy_run / f"{stem}.json").read_text())
        assert got["easy"] is (not flag) and got["metrics"]["n_labels"] == n_labels
    # averaged over each frame and its mirror image: its own files, scored through MirrorAveraged
    from radarpc.models.mirror import MirrorAveraged

    models = []

    def spy_model(model, *a, **k):
        models.append(model)
        return scored(model, *a, **k)

    monkeypatch.setattr(detection, "evaluate_model", spy_model)
    os.utime(log, ns=(log.stat().st_atime_ns, curve.stat().st_mtime_ns + 1))   # as if training went on
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1", "--mirror-average",
                 "--device", "cpu"]) == 0
    assert curve.stat().st_mtime_ns > log.stat().st_mtime_ns                   # drawn again, from the newer log
    assert len(models) == 1 and isinstance(models[0], MirrorAveraged) and models[0].sectors == (32, 1)
    mi = json.loads((out / "eval_test_mirror.json").read_text())
    assert mi["mirror_average"] is True and doc["mirror_average"] is False and mi["metrics"]["n_frames"] == 4
    assert mi["parameters"] == doc["parameters"]
    assert "mirror image" in (out / "eval_test_mirror.md").read_text().splitlines()[0]
    assert (out / "eval_test.json").read_text() == fp32_doc                      # fp32 files untouched
    # the fast inference copy (exact rewrites): its own files, the same parameters and about the same
    # scores (rounding may move a detection across a threshold: one label of the split at most)
    from radarpc.models.fast.fused_activation import ConvActivation

    models.clear()
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1", "--fast", "--device", "cpu"]) == 0
    assert len(models) == 1 and any(isinstance(m, ConvActivation) for m in models[0].modules())
    fa = json.loads((out / "eval_test_fast.json").read_text())
    assert fa["fast"] is True and doc["fast"] is False and fa["parameters"] == doc["parameters"]
    assert fa["metrics"]["n_frames"] == 4 and fa["fps_batch1"] > 0
    assert abs(fa["metrics"]["fn_fixed"] - doc["metrics"]["fn_fixed"]) <= 1
    assert "fast inference copy" in (out / "eval_test_fast.md").read_text().splitlines()[0]
    assert (out / "eval_test.json").read_text() == fp32_doc
    with pytest.raises(ValueError, match="float32 only"):
        detection.evaluate_run(out, "test", fast=True, precision="bf16")
    # docs/notebook/scripts/mirror_symmetry.py: the split as it is and mirror-averaged score as
    # evaluate scored them, and every frame mirrored is scored too
    ms = json.loads(_run_script(SCRIPTS / "mirror_symmetry.py", str(out)))
    assert ms["frames"] == 4 and set(ms) >= {"as_is", "mirrored", "mirror_averaged"}
    for name, ev in (("as_is", doc), ("mirror_averaged", mi)):
        for m in ("f1", "f1_fixed", "freespace_miou"):
            assert ms[name][m] == pytest.approx(ev["metrics"][m], rel=1e-6, abs=1e-9), (name, m)
    assert ms["mirrored"]["n_labels"] == ms["as_is"]["n_labels"] == doc["metrics"]["n_labels"]
    # an RD-cube model cannot be mirrored: refused, naming the run
    cubes = tmp_path / "cubes"
    shutil.copytree(out, cubes)
    key = json.loads((cubes / "run.json").read_text())
    key["experiment"] = to_dict(ExperimentConfig(name="fft-tiny", model=ModelSpec("fftradnet-tiny"), train=TINY_TRAIN))
    (cubes / "run.json").write_text(json.dumps(key))
    assert main(["evaluate", str(cubes), "--mirror-average"]) == 2
    err = capsys.readouterr().err
    assert str(cubes) in err and "mirror averaging applies to point models" in err
    # the false alarms by cause (docs/notebook/scripts/false_alarms.py, the scene regenerated from
    # the root): as many as the metric's false positives at the same threshold, each given one
    # cause. One epoch leaves every cell below 0.1, so a copy of the run whose head fires
    # everywhere is scored
    eager = tmp_path / "eager"
    shutil.copytree(out, eager)
    state, info = load_weights(eager / BEST_WEIGHTS)
    state["detection_head.clshead.bias"] = torch.full_like(state["detection_head.clshead.bias"], 3.0)
    save_weights(eager / BEST_WEIGHTS, state, info)
    assert main(["evaluate", str(eager), "--split", "test", "--fps-frames", "1", "--device", "cpu"]) == 0
    fp = json.loads((eager / "eval_test.json").read_text())["metrics"]["fp"][0]
    script = SCRIPTS / "false_alarms.py"
    fa = json.loads(_run_script(script, str(eager), "--threshold", "0.1", "--no-progress", "--figure",
                                str(tmp_path / "fa.png")).splitlines()[-1])
    assert fa["false_alarms"] == sum(fa["by_range_m"].values()) == sum(fa["by_cause"].values()) > 0
    # the script's count equals evaluate's false positives (that box positions agree from the
    # first call in a fresh process: tests/models/test_targets_fresh_process.py)
    assert fa["false_alarms"] == fp
    assert fa["by_cause"]["nothing"] < fa["false_alarms"]                           # scatterers under some
    assert (tmp_path / "fa.png").stat().st_size > 1000
    # the same weights in fp32 and under bf16 autocast (docs/notebook/scripts/bf16_detections.py):
    # every detection is paired or reported alone, whatever this CPU's bf16 rounding does to them
    bd = json.loads(_run_script(SCRIPTS / "bf16_detections.py", str(eager), "--frames", "3", "--threads", "1"))
    by_t = bd["by_threshold"]
    assert bd["frames"] == 3 and list(by_t) == ["0.05"] + [f"{k / 10:g}" for k in range(1, 10)]
    for c in by_t.values():               # pairs are one to one: both precisions leave the same number
        assert 0 <= c["frames_same"] <= 3 and c["fp32"] - c["fp32_unpaired"] == c["bf16"] - c["bf16_unpaired"] >= 0
    assert by_t["0.05"]["fp32"] > 0
    # the fp32 counts against the run's first 3 test frames decoded here (as one batch, as the
    # script does: the same arithmetic, so no score can land on the other side of a threshold)
    from radarpc.experiments.radial_detection.evaluation import load_trained
    from radarpc.models.targets import decode_detections
    from radarpc.experiments.radial_detection.task import collate_detection, detection_dataset
    e_cfg, e_model, e_key = load_trained(eager, "cpu")
    e_ds = detection_dataset(e_cfg, e_key["data"], e_key.get("points"), "test")
    with torch.inference_mode():
        batch = collate_detection([e_ds[i] for i in range(3)], cfg=e_cfg)
        scores = decode_detections(e_model(batch.inputs).detection.float(), e_cfg.targets).score
    assert {t: c["fp32"] for t, c in by_t.items()} == {t: int((scores.double() > float(t)).sum()) for t in by_t}
    assert bd["matched"]["pairs"] == by_t["0.05"]["fp32"] - by_t["0.05"]["fp32_unpaired"]
    assert bd["cells"]["cells"] == 3 * 128 * 224 and bd["cells"]["max_logit_diff"] >= 0
    # where the eager run's boxes sit against its labels (docs/notebook/scripts/box_offsets.py): the
    # same labels, misses and near misses at 0.2 as the metrics count
    bo = json.loads(_run_script(SCRIPTS / "box_offsets.py", str(eager), "--figure", str(tmp_path / "box.png")))
    em = json.loads((eager / "eval_test.json").read_text())["metrics"]
    assert bo["labels"] == em["n_labels"] > 0 and bo["labels"] - bo["matched"] == em["fn_fixed"]
    assert bo["near_miss"] == em["fn_near_fixed"] == sum(bo["near_miss_by_axis"].values())
    assert bo["labels"] == bo["matched"] + bo["near_miss"] + bo["far_miss"]
    assert sum(b["labels"] for b in bo["by_range_m"].values()) == bo["labels"]
    assert (tmp_path / "box.png").stat().st_size > 1000
    # a root whose labels the simulator does not regenerate is refused, even where no frame has a
    # false alarm (the one-epoch run: nothing above 0.9)
    moved = tmp_path / "moved"
    shutil.copytree(root, moved)
    rows = (moved / "labels.csv").read_text().splitlines()
    head = rows[0].split(",")
    r_col = head.index("radar_R_m")
    for i, row in enumerate(rows[1:], 1):
        f = row.split(",")
        if float(f[r_col]) > 0:
            f[r_col] = f"{float(f[r_col]) + 0.5:.4f}"
            rows[i] = ",".join(f)
    (moved / "labels.csv").write_text("\n".join(rows) + "\n")
    convert_dataset(moved, tmp_path / "moved.parquet", density=0.057, enrich=("sector32",), progress=False)
    with pytest.raises(SystemExit, match="not written by this simulator version"):
        _run_script(script, str(out), "--data", str(moved), "--points", str(tmp_path / "moved.parquet"),
                    "--threshold", "0.9", "--no-progress")
    # another config in the same folder is refused
    other = dataclasses.replace(cfg, name="other")
    save_yaml(other, tmp_path / "other.yaml")
    assert main(["train", str(tmp_path / "other.yaml"), "--data", str(root), "--points", str(store),
                 "--out", str(out), "--no-progress"]) == 2


@pytest.fixture(scope="module")
def root2(tmp_path_factory):
    return _city_root(tmp_path_factory, "root2", 2, seed=4)         # other scenes, 2 frames a sequence


@pytest.fixture(scope="module")
def store2(root2, tmp_path_factory):
    return _store_of(root2, tmp_path_factory)


def test_several_roots_train_and_evaluate_as_one(root, store, root2, store2, tmp_path, capsys):
    from radarpc.data.augment import MirroredFrames
    from radarpc.data.point_dataset import PointCloudDataset
    from radarpc.experiments.radial_detection.train import run_key
    from radarpc.experiments.radial_detection.task import ConcatFrames, detection_dataset

    cfg = ExperimentConfig(name="sp-tiny", model=ModelSpec("pillars-tiny"),
                           train=dataclasses.replace(TINY_TRAIN, epochs=1, batch_size=2, eval_batch_size=2))
    # the frames of both roots, one after another, each root with its own split
    both = detection_dataset(cfg, [root, root2], [store, store2], "test")
    one, two = PointCloudDataset(store, root, split="test"), PointCloudDataset(store2, root2, split="test")
    assert isinstance(both, ConcatFrames) and (len(one), len(two)) == (4, 2) and len(both) == 6
    for k, want in enumerate([one[i] for i in range(4)] + [two[i] for i in range(2)]):
        got = both[k]
        assert (got.frame, got.sequence) == (want.frame, want.sequence)
        assert torch.equal(got.labels, want.labels) and torch.equal(got.freespace, want.freespace)
    # mirrors draw per root (streams 0 and 1 of the training seed), and the epoch reaches every root
    mirrored = RadialDetectionTask(dataclasses.replace(cfg, mirror_probability=0.5), [root, root2],
                                   [store, store2]).train_set
    assert [(type(d), d.stream) for d in mirrored.datasets] == [(MirroredFrames, 0), (MirroredFrames, 1)]
    mirrored.set_epoch(3)
    assert [d.epoch for d in mirrored.datasets] == [3, 3]
    # one root keeps the run key runs always had; several are stored as lists, in order
    single = run_key(cfg, root, store)
    assert single == run_key(cfg, [root], [store]) and single["data"] == str(Path(root).resolve())
    assert run_key(cfg, [root, root2], [store, store2])["points"] == [str(Path(store).resolve()),
                                                                       str(Path(store2).resolve())]
    # the CLI: train on both, evaluate on both (the stored roots) or on one (given)
    save_yaml(cfg, tmp_path / "sp.yaml")
    out = tmp_path / "run"
    assert main(["train", str(tmp_path / "sp.yaml"), "--data", str(root), str(root2), "--points", str(store),
                 str(store2), "--out", str(out), "--no-progress"]) == 0
    key = json.loads((out / "run.json").read_text())
    assert key["data"] == [str(Path(root).resolve()), str(Path(root2).resolve())]
    log = (out / "log.csv").read_text().splitlines()
    row = dict(zip(log[0].split(","), log[-1].split(",")))
    assert (row["epoch"], row["step"]) == ("0", "3")          # 4 + 2 training frames, batches of 2
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1"]) == 0
    doc = json.loads((out / "eval_test.json").read_text())
    assert doc["metrics"]["n_frames"] == 6 and (doc["data"], doc["points"]) == (key["data"], key["points"])
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1", "--data", str(root2),
                 "--points", str(store2)]) == 0
    # other data than the run's own goes to files named after it, and what was scored is recorded
    other = f"eval_test_on_{Path(root2).name}"
    doc = json.loads((out / f"{other}.json").read_text())
    assert doc["metrics"]["n_frames"] == 2 and (doc["data"], doc["points"]) == (key["data"][1:], key["points"][1:])
    assert f"Scored on `{key['data'][1]}` (points `{key['points'][1]}`)." in (out / f"{other}.md").read_text()
    assert json.loads((out / "eval_test.json").read_text())["metrics"]["n_frames"] == 6   # the run's own, kept
    # the same roots with another store are named after the stores
    copied = tmp_path / "copied.parquet"
    shutil.copyfile(store, copied)
    assert main(["evaluate", str(out), "--split", "test", "--fps-frames", "1", "--data", str(root), str(root2),
                 "--points", str(copied), str(store2)]) == 0
    doc = json.loads((out / f"eval_test_on_copied+{Path(store2).stem}.json").read_text())
    assert doc["metrics"]["n_frames"] == 6 and doc["points"] == [str(copied.resolve()), key["points"][1]]
    capsys.readouterr()
    # bad input: stores that do not pair with the roots, and stores of other point features
    assert main(["train", str(tmp_path / "sp.yaml"), "--data", str(root), str(root2), "--points", str(store),
                 "--out", str(tmp_path / "bad"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "2 dataset roots" in err and "but 1 point stores" in err and "one store per root" in err
    plain = tmp_path / "plain.parquet"
    convert_dataset(root2, plain, density=0.057, progress=False)
    with pytest.raises(ValueError, match=r"point stores of different features.*plain.parquet.*\[\].*\['sector32'\]"):
        detection_dataset(cfg, [root, root2], [store, plain], "test")


def test_classical_row_cli(root, store, tmp_path):
    from radarpc.data.point_dataset import PointCloudDataset, collate_point_frames
    from radarpc.eval.detection import DetectionMetrics
    from radarpc.models.classical import ClassicalConfig, classical_detect

    out = tmp_path / "classical"
    assert main(["baseline", "detect", str(store), "--data", str(root), "--split", "test", "--out", str(out),
                 "--show", "1"]) == 0
    doc = json.loads((out / "eval_test.json").read_text())
    # the same numbers as scoring the detector's output on the test frames directly
    ds = PointCloudDataset(store, root, split="test")
    b = collate_point_frames([ds[i] for i in range(len(ds))])
    want = DetectionMetrics()
    want.update(classical_detect(b.points), b.labels, b.label_offset)
    want = want.compute().to_dict()
    assert doc["metrics"]["n_frames"] == len(ds) == 4 and doc["parameters"] == 0 and doc["fps_batch1"] > 0
    for k in ("ap", "ar", "f1", "f1_fixed"):
        assert doc["metrics"][k] == pytest.approx(want[k], abs=1e-12, nan_ok=True)
    assert load_yaml(ClassicalConfig, out / "classical.yaml") == ClassicalConfig()
    assert (out / "figures" / f"eval_test_frame{ds.frame_ids[0]:06d}.png").stat().st_size > 1000
    _check_detections_file(out / "eval_test_detections.csv", doc["metrics"], root, ds.frame_ids)
    assert (out / "figures" / "eval_test_labels.png").stat().st_size > 1000
    # settings from a file: clusters of a million points never form, so nothing is detected
    save_yaml(ClassicalConfig(min_points=10**6), tmp_path / "c.yaml")
    assert main(["baseline", "detect", str(store), "--data", str(root), "--split", "test", "--out", str(out),
                 "--config", str(tmp_path / "c.yaml")]) == 0
    doc = json.loads((out / "eval_test.json").read_text())
    assert doc["metrics"]["ar"] == 0.0 and load_yaml(ClassicalConfig, out / "classical.yaml").min_points == 10**6
    # RADIal's easy mode on a root with Difficult labels: its own files, flagged, those labels and
    # the all-difficult frame left out; --difficult (the default) scores every label
    hard, hard_store, tested = _with_difficult_labels(root, tmp_path)
    for flag, stem in ((["--no-difficult"], "eval_test_easy"), (["--difficult"], "eval_test")):
        assert main(["baseline", "detect", str(hard_store), "--data", str(hard), "--split", "test",
                     "--out", str(tmp_path / "hard_out"), *flag]) == 0
    easy = json.loads((tmp_path / "hard_out" / "eval_test_easy.json").read_text())
    every = json.loads((tmp_path / "hard_out" / "eval_test.json").read_text())
    assert easy["easy"] is True and every["easy"] is False and doc["easy"] is False
    assert easy["metrics"]["n_labels"] == sum(r["Difficult"] == "0" for r in tested) < len(tested)
    assert every["metrics"]["n_labels"] == len(tested)
    assert easy["metrics"]["n_frames"] == every["metrics"]["n_frames"] - 1


def test_shown_frames_spread_over_the_split():
    from radarpc.experiments.radial_detection.evaluation import _shown

    items = list(range(10))
    picks = lambda k: [i for i, _ in _shown(items, k, lambda batch: batch)]   # noqa: E731
    assert picks(3) == [0, 4, 9]              # round(0), round(4.5) = 4 (even), round(9)
    assert picks(1) == [0]
    assert picks(0) == []
    assert picks(20) == list(range(10))       # more asked than there are: each once
    assert _shown(items, 2, lambda batch: batch) == [(0, [0]), (9, [9])]


def test_evaluate_refuses_what_is_not_the_runs_own_and_says_when_unfinished(root, store, tmp_path, capsys):
    """A run killed in epoch 1 of 2 is scored with a warning and says so in its outputs; weights
    copied in from another run, non-finite weights and a folder in place of the weights are refused
    with one line naming the file."""
    from radarpc.experiments.radial_detection.train import train_runs

    cfg = ExperimentConfig(name="sp-kill", model=ModelSpec("pillars-tiny"),
                           train=dataclasses.replace(TINY_TRAIN, epochs=2, batch_size=4, eval_batch_size=4))
    steps_per_epoch = len(PointCloudDataset(store, root, split="train")) // 4

    def kill(step):
        if step == steps_per_epoch + 1:                  # in epoch 1, after epoch 0's validation
            raise KeyboardInterrupt

    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        train_runs(cfg, root, run, points=store, progress=False, log=lambda s: None, on_step=kill)
    assert main(["evaluate", str(run), "--split", "test", "--fps-frames", "1"]) == 0
    out = capsys.readouterr().out
    assert "warning: the run has not finished" in out and "from epoch 0" in out
    doc = json.loads((run / "eval_test.json").read_text())
    # the kill came before the next checkpoint: the last one is epoch 0's end
    assert doc["training"] == {"weights_epoch": 0, "weights_step": steps_per_epoch, "finished": False,
                               "epochs_done": 1, "steps_done": steps_per_epoch}
    assert "UNFINISHED run" in (run / "eval_test.md").read_text()
    # another run's weights copied in: refused, nothing scored under this run's name
    other = tmp_path / "other"
    train_runs(dataclasses.replace(cfg, name="sp-other", train=dataclasses.replace(cfg.train, epochs=1)), root, other,
               points=store, progress=False, log=lambda s: None)
    best = run / "best.safetensors"
    saved = best.read_bytes()
    shutil.copy(other / "best.safetensors", best)
    assert main(["evaluate", str(run), "--split", "test"]) == 2
    err = capsys.readouterr().err
    assert "best.safetensors: these weights were trained under another run key" in err and "Traceback" not in err
    # non-finite weights
    state, info = load_weights(other / "best.safetensors")
    state = {k: (v.fill_(float("nan")) if v.is_floating_point() else v) for k, v in state.items()}
    best.write_bytes(saved)
    _, own_info = load_weights(best)
    save_weights(best, state, own_info)
    assert main(["evaluate", str(run), "--split", "test"]) == 2
    assert "non-finite values (NaN or inf)" in capsys.readouterr().err
    # a folder in place of the weights
    best.unlink()
    best.mkdir()
    assert main(["evaluate", str(run), "--split", "test"]) == 2
    assert "best.safetensors: is a folder; expected the run's best weights" in capsys.readouterr().err


def test_train_and_evaluate_bad_input_is_one_line(root, store, tmp_path, capsys):
    """Each bad input of `train` / `evaluate` ends in one line naming what is wrong, exit 2."""
    pp = tmp_path / "pp.yaml"
    every = "difficult: true\ntargets: {}\nloss: {}\n"              # all sections given: no notice line
    pp.write_text("name: pp\nmodel: {variant: pillars-tiny}\ntrain: {epochs: 1, batch_size: 4, eval_batch_size: 4, "
                  "num_workers: 0, precision: fp32}\n" + every)
    fft = tmp_path / "fft.yaml"
    fft.write_text("name: fft\nmodel: {variant: fftradnet-tiny}\ntrain: {epochs: 1, num_workers: 0}\n" + every)
    (tmp_path / "empty").mkdir()
    (tmp_path / "afile").write_text("x")

    def one_line(args, *needles):
        code = main(args)
        err = capsys.readouterr().err
        assert code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        for n in needles:
            assert n in err, (n, err)

    out = ["--out", str(tmp_path / "run"), "--no-progress"]
    one_line(["train", str(pp), "--data", str(tmp_path / "missing"), "--points", str(store), *out],
             "missing: dataset root does not exist")
    one_line(["train", str(pp), "--data", str(tmp_path / "afile"), "--points", str(store), *out], "afile: is a file")
    one_line(["train", str(pp), "--data", str(tmp_path / "empty"), "--points", str(store), *out],
             "empty: is an empty folder")
    one_line(["train", str(pp), "--data", str(root), str(root), "--points", str(store), str(store), *out],
             "the same dataset root is given twice")
    one_line(["train", str(fft), "--data", str(root), "--points", str(store), *out],
             "model 'fftradnet-tiny' reads RD cubes, not point stores; drop --points")
    assert not (tmp_path / "run").exists()
    # a finished tiny run, then evaluate's bad input
    assert main(["train", str(pp), "--data", str(root), "--points", str(store), *out]) == 0
    capsys.readouterr()
    # loader processes change nothing a run computes: another count is not another run
    assert main(["train", str(pp), "--data", str(root), "--points", str(store), *out, "--num-workers", "1"]) == 0
    assert "already finished" in capsys.readouterr().out
    run = str(tmp_path / "run")
    for flag, value in (("--fps-frames", "-5"), ("--show", "-1"), ("--show-frames", "-2")):
        one_line(["evaluate", run, flag, value], f"{flag[2:]} must be an integer >= ")
    one_line(["evaluate", run, "--device", "gpu0"], "--device 'gpu0' is not a torch device")
    # a killed evaluation's half-written file is cleared by the next one
    stale = tmp_path / "run" / ".eval_test.json.x1y2.tmp"
    stale.write_text("{")
    assert main(["evaluate", run, "--fps-frames", "0"]) == 0            # 0: scored, not timed
    assert not stale.exists()
    assert np.isnan(json.loads((tmp_path / "run" / "eval_test.json").read_text())["fps_batch1"])
