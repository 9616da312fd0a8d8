"""Tests of the training loop on a toy task: schedule, exact resume, best checkpoint, logs, DDP."""
from __future__ import annotations

import csv
import dataclasses
import math
import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from radarpc.distributed import DistEnv
from radarpc.runs import RunMismatchError
from radarpc.training.checkpoint import load_state, load_weights, save_state
from radarpc.training.loop import (BEST_WEIGHTS, LAST_CHECKPOINT, LOG_CSV, TrainConfig, ema_decay_at, epoch_batches,
                                   fit)
from toytask import ToyTask, assert_same_run

CFG = TrainConfig(epochs=3, batch_size=4, eval_batch_size=4, num_workers=0, checkpoint_every=2,
                  precision="fp32", seed=5, select_metric="mse", select_mode="min")
KEY = {"model": "toy", "train": {"epochs": 3}}


def _final(out: Path) -> dict[str, torch.Tensor]:
    return load_state(out / LAST_CHECKPOINT).model


def test_epoch_batches_cover_a_permutation_and_split_over_ranks():
    one = epoch_batches(10, 4, seed=3, epoch=1)
    assert [len(b) for b in one] == [4, 4]                           # the tail of 2 is dropped
    assert len(set(sum(one, []))) == 8 and set(sum(one, [])) <= set(range(10))
    assert epoch_batches(10, 4, 3, 1) == one and epoch_batches(10, 4, 3, 2) != one
    r0 = epoch_batches(10, 4, 3, 1, DistEnv(0, 2, 0))
    r1 = epoch_batches(10, 4, 3, 1, DistEnv(1, 2, 1))
    assert [a + b for a, b in zip(r0, r1)] == one                     # global batch b is the same items
    with pytest.raises(ValueError, match="multiple of the number of ranks"):
        epoch_batches(10, 3, 0, 0, DistEnv(0, 2, 0))
    with pytest.raises(ValueError, match="fewer than one batch"):
        epoch_batches(3, 4, 0, 0)


def test_config_validation():
    with pytest.raises(ValueError, match="precision must be one of"):
        TrainConfig(precision="half")
    with pytest.raises(ValueError, match="lr_start <= lr_max"):
        TrainConfig(lr_start=1e-2, lr_max=1e-3)
    with pytest.raises(ValueError, match=r"ema_decay must be in \[0, 1\)"):
        TrainConfig(ema_decay=1.0)


def test_schedule_logs_and_best_checkpoint(tmp_path):
    res = fit(ToyTask(), CFG, tmp_path / "run", KEY, progress=False, log=lambda s: None)
    assert len(res.history) == 3 and res.best_epoch in (0, 1, 2)
    assert res.best_score == min(r["val_mse"] for r in res.history)        # lower is better
    assert res.best_row is res.history[res.best_epoch] and res.best_step == 6 * (res.best_epoch + 1)
    with open(tmp_path / "run" / LOG_CSV, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["epoch"]) for r in rows] == [0, 1, 2]
    assert [float(r["val_mse"]) for r in rows] == [r["val_mse"] for r in res.history]
    # OneCycle: 6 steps per epoch, 18 in all; the lr after the last step is the annealed minimum
    # lr_max / (div_factor * final_div_factor) = lr_start / 1e4
    assert int(rows[-1]["step"]) == 18
    assert float(rows[-1]["lr"]) == pytest.approx(CFG.lr_start / 1e4, rel=1e-9)
    weights, info = load_weights(tmp_path / "run" / BEST_WEIGHTS)
    assert info["run"] == KEY and info["epoch"] == res.best_epoch and info["step"] == res.best_step
    assert set(weights) == set(ToyTask().build_model().state_dict())
    # a finished run returns at once; another key is refused
    again = fit(ToyTask(), CFG, tmp_path / "run", KEY, progress=False, log=lambda s: None)
    assert again.history == res.history and again.resumed_from_step == 18
    with pytest.raises(RunMismatchError):
        fit(ToyTask(), CFG, tmp_path / "run", {"model": "other"}, progress=False, log=lambda s: None)


class _Kill(Exception):
    pass


@pytest.mark.parametrize("kill_at", [1, 5, 6, 13])
def test_interrupted_run_resumes_to_the_same_weights(tmp_path, kill_at):
    full = fit(ToyTask(), CFG, tmp_path / "full", KEY, progress=False, log=lambda s: None)

    def stop(step):
        if step == kill_at:
            raise _Kill

    with pytest.raises(_Kill):
        fit(ToyTask(), CFG, tmp_path / "cut", KEY, progress=False, log=lambda s: None, on_step=stop)
    res = fit(ToyTask(), CFG, tmp_path / "cut", KEY, progress=False, log=lambda s: None)
    # from the last checkpoint before the kill (the epoch ends, 6 and 12, are multiples of 2 too)
    assert res.resumed_from_step == (kill_at - 1) // CFG.checkpoint_every * CFG.checkpoint_every
    assert_same_run(tmp_path / "full", tmp_path / "cut")
    assert [r["val_mse"] for r in res.history] == [r["val_mse"] for r in full.history]


def test_auto_precision_is_kept_when_a_run_resumes_on_another_machine(tmp_path, monkeypatch):
    """"auto" is bf16 on a CPU with native bf16 and fp32 elsewhere: a run started on the first and
    resumed on the second goes on in bf16 and ends as an uninterrupted bf16 run."""
    import radarpc.training.loop as loop

    auto = dataclasses.replace(CFG, precision="auto")
    monkeypatch.setattr(loop, "cpu_has_native_bf16", lambda: True)
    full = fit(ToyTask(), auto, tmp_path / "full", KEY, progress=False, log=lambda s: None)

    def stop(step):
        if step == 7:
            raise _Kill

    with pytest.raises(_Kill):
        fit(ToyTask(), auto, tmp_path / "cut", KEY, progress=False, log=lambda s: None, on_step=stop)
    monkeypatch.setattr(loop, "cpu_has_native_bf16", lambda: False)       # "another machine"
    logs: list[str] = []
    res = fit(ToyTask(), auto, tmp_path / "cut", KEY, progress=False, log=logs.append)
    assert any("resuming in bf16" in m and "would mean fp32" in m for m in logs), logs
    a, b = _final(tmp_path / "full"), _final(tmp_path / "cut")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert [r["val_mse"] for r in res.history] == [r["val_mse"] for r in full.history]
    assert load_state(tmp_path / "cut" / LAST_CHECKPOINT).info["precision"] == "bf16"
    assert load_weights(tmp_path / "cut" / BEST_WEIGHTS)[1]["precision"] == "bf16"
    # and the bf16 run is not the fp32 run: the precision did change the weights
    fp32 = fit(ToyTask(), CFG, tmp_path / "fp32", KEY, progress=False, log=lambda s: None)
    c = _final(fp32.out)
    assert not all(torch.equal(a[k], c[k]) for k in a)


class _ModelTypeToyTask(ToyTask):
    """Records the type of the module each training step runs."""

    def __init__(self) -> None:
        super().__init__(dropout=0.0)      # compiled dropout draws from Inductor's RNG, not eager's
        self.types: set[type] = set()

    def loss(self, model, batch):
        self.types.add(type(model))
        return super().loss(model, batch)


def test_compiled_training_runs_the_compiled_module_and_ends_at_the_eager_weights(tmp_path):
    eager_task, compiled_task = _ModelTypeToyTask(), _ModelTypeToyTask()
    eager = fit(eager_task, CFG, tmp_path / "eager", KEY, progress=False, log=lambda s: None)
    compiled = fit(compiled_task, dataclasses.replace(CFG, compile=True), tmp_path / "compiled", KEY,
                   progress=False, log=lambda s: None)
    assert compiled_task.types == {torch._dynamo.eval_frame.OptimizedModule}
    assert eager_task.types == {torch.nn.Sequential}
    a, b = _final(eager.out), _final(compiled.out)
    assert set(b) == set(a)                      # checkpoints hold the plain module's keys
    # The two differ only by rounding (Inductor fuses and reorders fp32 sums): each of the 18
    # AdamW steps moves a weight by about lr <= 2.5e-3 times m / sqrt(v), a ratio that a
    # relative gradient change d alters by about d. Weights move by ~1e-2 in all (checked), so
    # 1e-4 separates rounding from a different training.
    torch.manual_seed(CFG.seed)                  # as fit seeds before it builds the model
    init = ToyTask().build_model().state_dict()
    assert max(float((a[k] - init[k]).abs().max()) for k in a) > 1e-2
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=0, atol=1e-4)
    for r, s in zip(eager.history, compiled.history):
        assert s["val_mse"] == pytest.approx(r["val_mse"], rel=1e-3)


class _RecordingToyTask(ToyTask):
    """Keeps the weights each training step starts from."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[dict[str, torch.Tensor]] = []

    def loss(self, model, batch):
        self.seen.append({k: v.detach().clone() for k, v in model.state_dict().items()})
        return super().loss(model, batch)


def test_weight_average_follows_its_equation_and_is_what_validation_scores(tmp_path):
    # the decay ramp, by hand: (1 + n) / (10 + n) until it reaches ema_decay
    assert ema_decay_at(1, 0.999) == pytest.approx(2 / 11)
    assert ema_decay_at(90, 0.999) == pytest.approx(91 / 100)
    assert ema_decay_at(10**6, 0.999) == 0.999 and ema_decay_at(50, 0.5) == 0.5
    with pytest.raises(ValueError, match="1-based"):
        ema_decay_at(0, 0.9)

    cfg = dataclasses.replace(CFG, ema_decay=0.9)
    task = _RecordingToyTask()
    res = fit(task, cfg, tmp_path / "run", KEY, progress=False, log=lambda s: None)
    state = load_state(tmp_path / "run" / LAST_CHECKPOINT)
    # theta after step n is what step n + 1 starts from; the last step's is the checkpoint's model
    thetas = task.seen[1:] + [state.model]
    assert len(thetas) == 18
    expected = {k: v.double() for k, v in task.seen[0].items()}     # the average starts at theta_0
    for n, theta in enumerate(thetas, start=1):
        beta = min(0.9, (1 + n) / (10 + n))
        expected = {k: beta * v + (1 - beta) * theta[k].double() for k, v in expected.items()}
    # 18 float32 lerps, each rounding to half an ulp: 1e-5 of the weights' scale is far above it
    scale = max(float(v.abs().max()) for v in expected.values())
    for k, v in expected.items():
        torch.testing.assert_close(state.ema[k].double(), v, rtol=0, atol=1e-5 * scale)
    assert not all(torch.equal(state.ema[k], state.model[k]) for k in state.model)
    # validation scored the average, and the best weights are the average at the best epoch
    best, info = load_weights(tmp_path / "run" / BEST_WEIGHTS)
    assert info["weights"] == "ema" and info["epoch"] == res.best_epoch
    model = task.build_model()
    model.eval()
    val = [task.collate([task.val_set[i] for i in range(len(task.val_set))])]
    for weights, epoch in ((state.ema, -1), (best, res.best_epoch)):
        model.load_state_dict(weights)
        with torch.no_grad():
            score = task.evaluate(model, val, "cpu")["mse"]
        assert res.history[epoch]["val_mse"] == pytest.approx(score, rel=1e-6)


def test_interrupted_run_resumes_to_the_same_weight_average(tmp_path):
    cfg = dataclasses.replace(CFG, ema_decay=0.9)
    fit(ToyTask(), cfg, tmp_path / "full", KEY, progress=False, log=lambda s: None)

    def stop(step):
        if step == 7:
            raise _Kill

    with pytest.raises(_Kill):
        fit(ToyTask(), cfg, tmp_path / "cut", KEY, progress=False, log=lambda s: None, on_step=stop)
    fit(ToyTask(), cfg, tmp_path / "cut", KEY, progress=False, log=lambda s: None)
    assert_same_run(tmp_path / "full", tmp_path / "cut")            # the average included
    # a checkpoint without an average cannot resume as a run that keeps one
    with pytest.raises(_Kill):
        fit(ToyTask(), CFG, tmp_path / "plain", KEY, progress=False, log=lambda s: None, on_step=stop)
    with pytest.raises(ValueError, match=r"holds no weight average, but train.ema_decay is 0.9"):
        fit(ToyTask(), cfg, tmp_path / "plain", KEY, progress=False, log=lambda s: None)


def test_run_started_in_fp16_is_refused_on_a_cpu_with_the_reason(tmp_path):
    def stop(step):
        if step == 3:
            raise _Kill

    with pytest.raises(_Kill):
        fit(ToyTask(), CFG, tmp_path / "run", KEY, progress=False, log=lambda s: None, on_step=stop)
    last = tmp_path / "run" / LAST_CHECKPOINT
    state = load_state(last)
    state.info["precision"] = "fp16"                   # as a checkpoint written by a CUDA run
    save_state(last, state)
    with pytest.raises(ValueError, match=r"run started in fp16 and cannot resume on cpu.*needs a CUDA device"):
        fit(ToyTask(), CFG, tmp_path / "run", KEY, progress=False, log=lambda s: None)


def test_killed_process_resumes_to_the_same_weights(tmp_path):
    """SIGKILL at an arbitrary moment (after the first checkpoint exists), then a rerun in a new
    process, against an uninterrupted run (run here: where it runs changes nothing it computes)."""
    cfg = TrainConfig(epochs=8, batch_size=4, num_workers=0, checkpoint_every=3, precision="fp32", seed=5,
                      select_metric="mse", select_mode="min")
    script = textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(Path(__file__).parents[1])!r})
        from radarpc.training.loop import TrainConfig, fit
        from toytask import ToyTask
        cfg = TrainConfig(**{dataclasses.asdict(cfg)!r})
        slow = (lambda step: time.sleep(0.01)) if sys.argv[2] == "slow" else None
        fit(ToyTask(), cfg, sys.argv[1], {{"k": 1}}, progress=False, log=lambda s: None, on_step=slow)
    """)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    fit(ToyTask(), cfg, tmp_path / "full", {"k": 1}, progress=False, log=lambda s: None)
    p = subprocess.Popen([sys.executable, "-c", script, str(tmp_path / "cut"), "slow"], env=env)
    last = tmp_path / "cut" / LAST_CHECKPOINT
    t0 = time.monotonic()
    while not last.is_file() and time.monotonic() - t0 < 120 and p.poll() is None:
        time.sleep(0.02)
    time.sleep(0.15)
    p.kill()
    p.wait()
    assert last.is_file()
    subprocess.run([sys.executable, "-c", script, str(tmp_path / "cut"), "fast"], check=True, env=env)
    assert_same_run(tmp_path / "full", tmp_path / "cut")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank: int, world: int, port: int, out: str, queue) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank),
                      MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.set_num_threads(1)
    cfg = TrainConfig(epochs=1, batch_size=8, num_workers=0, precision="fp32", seed=5, select_metric="mse",
                      select_mode="min")
    res = fit(ToyTask(n_train=8, dropout=0.0), cfg, out, {"k": "ddp"}, progress=False, log=lambda s: None)
    queue.put((rank, res.history[0]["train_loss"]))
    torch.distributed.destroy_process_group()


def test_ddp_gloo_matches_single_process_first_step(tmp_path):
    cfg = TrainConfig(epochs=1, batch_size=8, num_workers=0, precision="fp32", seed=5, select_metric="mse",
                      select_mode="min")
    single = fit(ToyTask(n_train=8, dropout=0.0), cfg, tmp_path / "single", {"k": "ddp"}, progress=False, log=lambda s: None)
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    port = _free_port()
    procs = [ctx.Process(target=_ddp_worker, args=(r, 2, port, str(tmp_path / "ddp"), q)) for r in range(2)]
    for p in procs:
        p.start()
    got = dict(q.get(timeout=180) for _ in procs)
    for p in procs:
        p.join(180)               # as long as the queue's wait: a starved machine (nice 19 beside training) took > 60 s
        assert p.exitcode == 0, f"rank process {p.name}: exit code {p.exitcode} (None: still running after 180 s)"
    # no dropout here: ranks draw their own random streams. One step: the mean over ranks of each rank's 4-item mean is the 8-item mean, up to the
    # rounding of two float32 sums of 8 squared errors each (relative 2^-24 * 8 per sum)
    want = single.history[0]["train_loss"]
    assert got[0] == got[1]
    assert math.isclose(got[0], want, rel_tol=16 * 2 ** -24 * 8)
    assert (tmp_path / "ddp" / BEST_WEIGHTS).is_file()


def test_a_checkpoint_of_another_model_is_refused_naming_the_file(tmp_path):
    """``checkpoints/last.safetensors`` swapped for another model's: the rerun says which file does
    not fit, instead of load_state_dict's traceback."""
    import shutil

    from radarpc.io import DataFileError

    class WiderToy(ToyTask):
        def build_model(self):
            return torch.nn.Sequential(torch.nn.Linear(6, 32), torch.nn.GELU(), torch.nn.Dropout(0.2), torch.nn.Linear(32, 2))

    one = dataclasses.replace(CFG, epochs=1)
    fit(ToyTask(), one, tmp_path / "run", KEY, progress=False, log=lambda s: None)
    fit(WiderToy(), one, tmp_path / "wide", KEY, progress=False, log=lambda s: None)
    shutil.copy(tmp_path / "wide" / LAST_CHECKPOINT, tmp_path / "run" / LAST_CHECKPOINT)
    with pytest.raises(DataFileError, match=r"last\.safetensors: its weights do not fit this run's model "
                                            r"\(another model's checkpoint\?.*size mismatch"):
        fit(ToyTask(), one, tmp_path / "run", KEY, progress=False, log=lambda s: None)


def test_log_lines_print_on_their_own_line_above_the_progress_bar(tmp_path):
    """With the bar and the log on one terminal (stdout and stderr the same stream), each log line
    starts at column 0 of a line the bar was cleared from, not after the bar's text."""
    import contextlib
    import io
    import re

    term = io.StringIO()
    with contextlib.redirect_stdout(term), contextlib.redirect_stderr(term):
        fit(ToyTask(), CFG, tmp_path / "run", KEY, progress=True, log=print)
    text = term.getvalue()
    logs = list(re.finditer(r"epoch \d: loss", text))
    assert len(logs) == CFG.epochs and "train run" in text             # the bar was drawn as well
    for m in logs:
        line = text[:m.start()].rsplit("\n", 1)[-1]                    # this terminal line before the log
        *drawn, cleared, tail = line.split("\r")
        assert tail == "", f"the log line follows {tail!r} on its terminal line"
        assert cleared.strip() == "" and any(s.strip() for s in drawn), \
            f"the bar {drawn!r} was not cleared ({cleared!r}) before the log line"
