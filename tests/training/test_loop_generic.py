"""The loop as any model uses it: selection direction, schedules, step-counted runs with step-based
validation, frozen submodules, the software record and run keys read through their config type."""
from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch

import radarpc
from radarpc.config import from_dict, to_dict
from radarpc.runs import RunMismatchError, source_commit
from radarpc.training.checkpoint import load_state, load_weights, save_weights, software_record
from radarpc.training.loop import (BEST_WEIGHTS, LAST_CHECKPOINT, LOG_CSV, TrainConfig, fit, frozen_submodules,
                                   scheduled_lr)
from toytask import EncoderHead, FrozenToyTask, ToyTask, assert_same_run, pretrained_encoder_state

QUIET = dict(progress=False, log=lambda s: None)
BASE = dict(batch_size=4, eval_batch_size=4, num_workers=0, precision="fp32", seed=5)   # 6 steps per epoch


class _Kill(Exception):
    pass


def _stop_at(step_to_kill: int):
    def stop(step):
        if step == step_to_kill:
            raise _Kill
    return stop


def _rows(run: Path) -> list[dict[str, str]]:
    with open(run / LOG_CSV, newline="") as f:
        return list(csv.DictReader(f))


# ---- config --------------------------------------------------------------------------------------
def test_config_validation_names_the_bad_values():
    with pytest.raises(ValueError, match=r"select_mode must be one of \('max', 'min'\), got 'lowest'"):
        TrainConfig(select_mode="lowest")
    with pytest.raises(ValueError, match=r"schedule must be one of .*got 'linear'"):
        TrainConfig(schedule="linear")
    with pytest.raises(ValueError, match=r"max_steps=100 counts the run in optimizer steps: set train.epochs to 0 "
                                         r"\(got 30\)"):
        TrainConfig(max_steps=100)
    with pytest.raises(ValueError, match=r"epochs must be >= 1 \(or 0 with train.max_steps > 0\), got 0"):
        TrainConfig(epochs=0)
    with pytest.raises(ValueError, match=r"max_steps must be >= 0"):
        TrainConfig(epochs=0, max_steps=-1)
    with pytest.raises(ValueError, match=r"validate_every must be >= 0.*got -2"):
        TrainConfig(validate_every=-2)
    with pytest.raises(ValueError, match=r"lr_min=0.0001 is where the 'cosine' schedule ends; schedule 'onecycle'"):
        TrainConfig(lr_min=1e-4)
    with pytest.raises(ValueError, match=r"0 <= lr_min <= lr_max"):
        TrainConfig(schedule="cosine", lr_min=1.0)
    with pytest.raises(ValueError, match=r"warmup_steps=10 must be below train.max_steps=10"):
        TrainConfig(epochs=0, max_steps=10, warmup_steps=10)
    with pytest.raises(ValueError, match=r"warmup_steps must be >= 0"):
        TrainConfig(warmup_steps=-1)
    ok = TrainConfig(epochs=0, max_steps=10, warmup_steps=3, schedule="cosine", lr_min=1e-5, validate_every=4,
                     select_mode="min")
    assert ok.total_steps(6) == 10 and TrainConfig(epochs=3).total_steps(6) == 18
    assert ok.warmup(10) == 3.0 and TrainConfig(warmup_fraction=0.25).warmup(10) == 2.5


def test_a_warm_up_as_long_as_an_epoch_counted_run_is_refused_at_the_start(tmp_path):
    cfg = TrainConfig(epochs=1, warmup_steps=6, schedule="constant", **BASE)          # 6 steps in all
    with pytest.raises(ValueError, match=r"warmup_steps=6 must be below the run's 6 steps"):
        fit(ToyTask(), cfg, tmp_path / "run", {"k": 1}, **QUIET)


# ---- schedules -----------------------------------------------------------------------------------
def test_schedules_match_hand_computed_values():
    lr = dict(lr_start=0.1, lr_max=1.0)
    # cosine, T = 10, W = 2, lr_min = 0.01: linear warm-up, then 0.01 + 0.99 (1 + cos(pi p)) / 2
    cos = dict(lr, lr_min=0.01)
    assert scheduled_lr("cosine", 0, 10, 2, **cos) == pytest.approx(0.1, rel=1e-12)
    assert scheduled_lr("cosine", 1, 10, 2, **cos) == pytest.approx(0.55, rel=1e-12)
    assert scheduled_lr("cosine", 2, 10, 2, **cos) == pytest.approx(1.0, rel=1e-12)
    assert scheduled_lr("cosine", 4, 10, 2, **cos) == pytest.approx(0.01 + 0.99 * (1 + math.sqrt(0.5)) / 2, rel=1e-12)
    assert scheduled_lr("cosine", 6, 10, 2, **cos) == pytest.approx(0.505, rel=1e-12)           # p = 1/2
    assert scheduled_lr("cosine", 10, 10, 2, **cos) == pytest.approx(0.01, rel=1e-12)          # one past the end
    assert scheduled_lr("cosine", 1, 10, 2.5, **cos) == pytest.approx(0.1 + 0.9 * 0.4, rel=1e-12)  # fractional W
    assert scheduled_lr("cosine", 0, 10, 0, **cos) == 1.0                                      # no warm-up
    # constant: the same warm-up, then lr_max
    assert scheduled_lr("constant", 1, 10, 2, **lr) == pytest.approx(0.55, rel=1e-12)
    assert [scheduled_lr("constant", s, 10, 2, **lr) for s in (2, 5, 9)] == [1.0, 1.0, 1.0]
    # onecycle, T = 10, W = 3: rises until step a = 2, ends at 0.1 / 1e4 on step 9
    assert scheduled_lr("onecycle", 0, 10, 3, **lr) == pytest.approx(0.1, rel=1e-12)
    assert scheduled_lr("onecycle", 1, 10, 3, **lr) == pytest.approx(0.55, rel=1e-12)
    assert scheduled_lr("onecycle", 2, 10, 3, **lr) == pytest.approx(1.0, rel=1e-12)
    # step 5: p = 3/7, cos(3 pi / 7) = 0.2225209340
    assert scheduled_lr("onecycle", 5, 10, 3, **lr) == pytest.approx(
        1e-5 + (1 - 1e-5) * (1 + 0.2225209340) / 2, rel=1e-9)
    assert scheduled_lr("onecycle", 9, 10, 3, **lr) == pytest.approx(1e-5, rel=1e-12)
    with pytest.raises(ValueError, match="'linear'"):
        scheduled_lr("linear", 0, 10, 2, **lr)
    with pytest.raises(ValueError, match=r"warm-up \(10 steps\)"):
        scheduled_lr("cosine", 0, 10, 10, **lr)


def test_onecycle_equation_is_torchs_schedule():
    p = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.AdamW([p], lr=2.5e-3)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=2.5e-3, total_steps=18, pct_start=0.3,
                                                anneal_strategy="cos", div_factor=10.0, cycle_momentum=False)
    for s in range(18):
        # OneCycleLR derives lr_start as lr_max / div_factor: a few ulp of rounding apart
        assert opt.param_groups[0]["lr"] == pytest.approx(scheduled_lr("onecycle", s, 18, 0.3 * 18, 2.5e-4, 2.5e-3),
                                                          rel=1e-13), s
        opt.step()
        sched.step()


# ---- a regression toy task: lower-is-better loss, step-based validation, cosine, resume ---------
class _LossRecordingTask(ToyTask):
    def __init__(self) -> None:
        super().__init__()
        self.losses: list[float] = []

    def loss(self, model, batch):
        loss, parts = super().loss(model, batch)
        self.losses.append(float(loss.detach()))
        return loss, parts


# 22 steps of 6-step epochs: validation at steps 4, 8, ..., 20 and at the end (22); checkpoints
# every 3 steps, at epoch ends (6, 12, 18) and after each validation
STEPS = TrainConfig(epochs=0, max_steps=22, validate_every=4, checkpoint_every=3, schedule="cosine",
                    lr_start=1e-4, lr_max=5e-3, lr_min=2e-4, warmup_steps=3, select_metric="mse",
                    select_mode="min", **BASE)
# epoch validation in a step-counted run: 14 steps validate at the epoch ends 6 and 12 and at 14
EPOCHS = TrainConfig(epochs=0, max_steps=14, checkpoint_every=4, schedule="constant", lr_start=1e-3,
                     lr_max=4e-3, warmup_steps=2, select_metric="mse", select_mode="min", ema_decay=0.8, **BASE)
RUNS = {"steps": STEPS, "epochs": EPOCHS}


@pytest.fixture(scope="module")
def full_runs(tmp_path_factory):
    """The uninterrupted run of each config, with the training loss of every step."""
    out = {}
    for name, cfg in RUNS.items():
        task = _LossRecordingTask()
        res = fit(task, cfg, tmp_path_factory.mktemp(name) / "run", {"k": name}, **QUIET)
        out[name] = (res, task.losses)
    return out


def test_step_based_validation_rows_schedule_and_best_weights(full_runs):
    res, losses = full_runs["steps"]
    assert len(losses) == 22
    rows = _rows(res.out)
    assert [int(r["step"]) for r in rows] == [4, 8, 12, 16, 20, 22]
    assert [int(r["epoch"]) for r in rows] == [0, 1, 1, 2, 3, 3]             # 6 steps per epoch
    prev = 0
    for r, h in zip(rows, res.history):
        step = int(r["step"])
        # the train means are those of the steps since the previous row, the lr that of the last step
        assert float(r["train_loss"]) == pytest.approx(sum(losses[prev:step]) / (step - prev), rel=1e-12)
        assert float(r["lr"]) == pytest.approx(
            scheduled_lr("cosine", step - 1, 22, 3, STEPS.lr_start, STEPS.lr_max, STEPS.lr_min), rel=1e-12)
        assert float(r["val_mse"]) == h["val_mse"]
        prev = step
    # lower is better: the best is the lowest validation loss, and best.safetensors holds those weights
    val = [h["val_mse"] for h in res.history]
    assert res.best_score == min(val) and res.best_row["val_mse"] == min(val)
    weights, info = load_weights(res.out / BEST_WEIGHTS)
    assert info["step"] == res.best_step == res.best_row["step"] and info["epoch"] == res.best_row["epoch"]
    task = ToyTask()
    model = task.build_model()
    model.load_state_dict(weights)
    model.eval()
    with torch.no_grad():                                            # the loop's batches of 4
        got = task.evaluate(model, [task.collate([task.val_set[i] for i in range(b, b + 4)]) for b in (0, 4)], "cpu")
    assert got["mse"] == pytest.approx(res.best_score, rel=1e-12)
    assert load_state(res.out / LAST_CHECKPOINT).info["finished"]


def test_epoch_validation_in_a_step_counted_run(full_runs):
    res, losses = full_runs["epochs"]
    assert len(losses) == 14
    assert [(r["step"], r["epoch"]) for r in res.history] == [(6, 0), (12, 1), (14, 2)]
    assert [r["lr"] for r in res.history] == [EPOCHS.lr_max] * 3                # constant after the warm-up
    assert res.history[-1]["train_loss"] == pytest.approx(sum(losses[12:]) / 2, rel=1e-12)
    state = load_state(res.out / LAST_CHECKPOINT)
    assert state.info["epoch"] == 2 and state.info["batch_in_epoch"] == 2 and state.info["step"] == 14


@pytest.mark.parametrize("name,kill_at", [("steps", 2), ("steps", 4), ("steps", 7), ("steps", 12),
                                          ("steps", 17), ("steps", 22), ("epochs", 5), ("epochs", 13)])
def test_a_killed_run_resumes_to_the_uninterrupted_one(full_runs, tmp_path, name, kill_at):
    cfg = RUNS[name]
    with pytest.raises(_Kill):
        fit(ToyTask(), cfg, tmp_path / "cut", {"k": name}, **QUIET, on_step=_stop_at(kill_at))
    res = fit(ToyTask(), cfg, tmp_path / "cut", {"k": name}, **QUIET)
    assert 0 <= res.resumed_from_step < kill_at
    assert_same_run(full_runs[name][0].out, tmp_path / "cut")
    assert (res.best_score, res.best_step, res.best_epoch) == (full_runs[name][0].best_score,
                                                               full_runs[name][0].best_step,
                                                               full_runs[name][0].best_epoch)


def test_select_mode_picks_the_direction(tmp_path):
    cfg = TrainConfig(epochs=4, checkpoint_every=50, lr_max=2e-2, lr_start=2e-3, **BASE)
    runs = {}
    for metric, mode in (("mse", "min"), ("r2", "max"), ("mse", "max")):
        c = dataclasses.replace(cfg, select_metric=metric, select_mode=mode)
        runs[metric, mode] = fit(ToyTask(), c, tmp_path / f"{metric}_{mode}", {"k": 1}, **QUIET)
    mse = [h["val_mse"] for h in runs["mse", "min"].history]
    assert len(set(mse)) == 4                                       # four distinct epochs to choose from
    assert runs["mse", "min"].best_epoch == mse.index(min(mse))
    assert runs["mse", "max"].best_epoch == mse.index(max(mse)) != runs["mse", "min"].best_epoch
    # R^2 = 1 - SSE / SST with a fixed SST: its highest is the lowest MSE
    assert runs["r2", "max"].best_epoch == runs["mse", "min"].best_epoch
    assert runs["r2", "max"].best_score == max(h["val_r2"] for h in runs["r2", "max"].history)


# ---- frozen submodules ---------------------------------------------------------------------------
FROZEN = TrainConfig(epochs=2, checkpoint_every=4, lr_start=2e-3, lr_max=2e-2, select_metric="mse",
                     select_mode="min", grad_clip_norm=1.0, **BASE)


def test_frozen_submodule_keeps_its_weights_and_statistics_while_the_rest_trains(tmp_path):
    task = FrozenToyTask()
    logs: list[str] = []
    res = fit(task, FROZEN, tmp_path / "run", {"k": "frozen"}, progress=False, log=logs.append)
    assert any("encoder frozen (72 parameters in eval mode), 178 parameters trained" in m for m in logs), logs
    state = load_state(res.out / LAST_CHECKPOINT)
    pretrained = pretrained_encoder_state()
    for k, v in pretrained.items():                                   # weights and BatchNorm statistics
        assert torch.equal(state.model[f"encoder.{k}"], v), k
    torch.manual_seed(FROZEN.seed)                                    # the head's initial weights, as fit draws them
    init = task.build_model().state_dict()
    assert all(not torch.equal(state.model[k], init[k]) for k in init if k.startswith("head."))
    # only the head's 4 tensors are optimised
    head_shapes = [tuple(p.shape) for p in EncoderHead(0.0).head.parameters()]
    assert len(state.optimizer["param_groups"][0]["params"]) == 4
    assert [tuple(state.optimizer["state"][i]["exp_avg"].shape) for i in range(4)] == head_shapes
    # the best weights hold the frozen part too: they load alone into the model
    best, _ = load_weights(res.out / BEST_WEIGHTS)
    model = EncoderHead(0.0)
    model.load_state_dict(best)                                       # strict
    assert all(torch.equal(model.encoder.state_dict()[k], v) for k, v in pretrained.items())

    # the control: requires_grad alone keeps the weights but not the statistics (train mode)
    control = fit(FrozenToyTask(declare=False), FROZEN, tmp_path / "control", {"k": "control"}, **QUIET)
    c = load_state(control.out / LAST_CHECKPOINT).model
    assert torch.equal(c["encoder.0.weight"], pretrained["0.weight"])
    assert not torch.equal(c["encoder.1.running_mean"], pretrained["1.running_mean"])
    assert int(c["encoder.1.num_batches_tracked"]) == 1000 + 12


def test_a_run_with_a_frozen_part_resumes_exactly(tmp_path):
    cfg = dataclasses.replace(FROZEN, ema_decay=0.9)
    fit(FrozenToyTask(), cfg, tmp_path / "full", {"k": "frozen"}, **QUIET)
    with pytest.raises(_Kill):
        fit(FrozenToyTask(), cfg, tmp_path / "cut", {"k": "frozen"}, **QUIET, on_step=_stop_at(7))
    fit(FrozenToyTask(), cfg, tmp_path / "cut", {"k": "frozen"}, **QUIET)
    assert_same_run(tmp_path / "full", tmp_path / "cut")


def test_frozen_names_are_checked():
    model = EncoderHead(0.0)
    assert frozen_submodules(model) == [model.encoder]
    assert not any(p.requires_grad for p in model.encoder.parameters())
    assert all(p.requires_grad for p in model.head.parameters())
    assert frozen_submodules(ToyTask().build_model()) == []           # no attribute: nothing frozen
    for names, match in (("encoder", "sequence of submodule names, got the string 'encoder'"),
                         (("nope",), "names 'nope', which is not a submodule"),
                         (("",), "names the model itself")):
        m = EncoderHead(0.0)
        m.frozen_submodules = names
        with pytest.raises(ValueError, match=match):
            frozen_submodules(m)


def test_a_model_with_nothing_to_train_is_refused(tmp_path):
    class AllFrozen(FrozenToyTask):
        def build_model(self):
            model = super().build_model()
            model.frozen_submodules = ("encoder", "head")
            return model

    with pytest.raises(ValueError, match="no parameter that requires a gradient"):
        fit(AllFrozen(), FROZEN, tmp_path / "run", {"k": 1}, **QUIET)


# ---- software record -----------------------------------------------------------------------------
def test_software_is_recorded_in_run_json_and_weights_but_not_compared(tmp_path, monkeypatch):
    import radarpc.training.loop as loop

    want = {"radarpc": radarpc.__version__, "commit": source_commit(), "torch": torch.__version__}
    assert software_record() == want
    assert want["commit"] is None or (len(want["commit"]) == 40 and int(want["commit"], 16) >= 0)
    cfg = TrainConfig(epochs=2, checkpoint_every=4, select_metric="mse", select_mode="min", **BASE)
    with pytest.raises(_Kill):
        fit(ToyTask(), cfg, tmp_path / "run", {"k": 1}, **QUIET, on_step=_stop_at(7))
    stored = json.loads((tmp_path / "run" / "run.json").read_text())
    assert stored == {"k": 1, "software": want}
    assert load_weights(tmp_path / "run" / BEST_WEIGHTS)[1]["software"] == want
    # another software resumes the run (recorded, not compared); run.json keeps the first record
    other = {**want, "torch": "0.0.0", "commit": "0" * 40}
    monkeypatch.setattr(loop, "software_record", lambda: dict(other))
    res = fit(ToyTask(), cfg, tmp_path / "run", {"k": 1}, **QUIET)
    assert res.resumed_from_step == 6
    assert json.loads((tmp_path / "run" / "run.json").read_text())["software"] == want
    assert load_weights(tmp_path / "run" / BEST_WEIGHTS)[1]["software"] in (want, other)
    with pytest.raises(ValueError, match="run_key holds 'software'"):
        fit(ToyTask(), cfg, tmp_path / "other", {"k": 1, "software": "x"}, **QUIET)


def test_every_weights_file_records_the_software(tmp_path):
    save_weights(tmp_path / "w.safetensors", {"a": torch.zeros(2)}, {"note": "x"})
    _, info = load_weights(tmp_path / "w.safetensors")
    assert info == {"note": "x", "software": software_record()}
    save_weights(tmp_path / "v.safetensors", {"a": torch.zeros(2)}, {"software": {"radarpc": "old"}})
    assert load_weights(tmp_path / "v.safetensors")[1]["software"] == {"radarpc": "old"}   # the caller's is kept


# ---- a run key stored before a config field existed ----------------------------------------------
@dataclasses.dataclass(frozen=True)
class _ToyConfig:
    epochs: int = 2
    width: int = 16              # "added after the run started": its stored key lacks it


def test_a_run_started_before_a_field_existed_resumes_through_the_config_type(tmp_path):
    cfg = TrainConfig(epochs=2, checkpoint_every=4, select_metric="mse", select_mode="min", **BASE)
    fit(ToyTask(), cfg, tmp_path / "full", {"toy": to_dict(_ToyConfig())}, **QUIET)
    with pytest.raises(_Kill):
        fit(ToyTask(), cfg, tmp_path / "cut", {"toy": {"epochs": 2}}, **QUIET, on_step=_stop_at(7))
    new_key = {"toy": to_dict(_ToyConfig())}
    with pytest.raises(RunMismatchError, match=r"run\.json:toy\.width"):             # compared raw
        fit(ToyTask(), cfg, tmp_path / "cut", new_key, **QUIET)

    def through_config(stored: dict) -> dict:
        return {**stored, "toy": to_dict(from_dict(_ToyConfig, stored["toy"], where="run.json"))}

    res = fit(ToyTask(), cfg, tmp_path / "cut", new_key, **QUIET, canonical_key=through_config)
    assert res.resumed_from_step == 6
    # the best weights written before the resume name the key as it was then
    assert_same_run(tmp_path / "full", tmp_path / "cut", same_key=False)
    # a stored value that differs is still a difference, and one the config type refuses is too
    with pytest.raises(RunMismatchError, match=r"run\.json:toy\.epochs"):
        fit(ToyTask(), cfg, tmp_path / "cut", {"toy": to_dict(_ToyConfig(epochs=3))}, **QUIET,
            canonical_key=through_config)
    stored = json.loads((tmp_path / "cut" / "run.json").read_text())
    (tmp_path / "cut" / "run.json").write_text(json.dumps({**stored, "toy": {"epochs": 2, "depth": 3}}))
    with pytest.raises(RunMismatchError, match=r"not readable as this run's key: run.json: _ToyConfig unknown keys "
                                               r"\['depth'\]"):
        fit(ToyTask(), cfg, tmp_path / "cut", new_key, **QUIET, canonical_key=through_config)
