"""RaLD's two stages trained under DDP as a torchrun user runs them: ``radarpc train`` on 2 gloo
ranks (CPU), stage 1 (the autoencoder) and then stage 2 (the diffusion model against the stage-1
run, frozen), each 2 optimizer steps of the tiny configs on the session's tiny ColoRadar root.

What can be derived exactly, and is checked:

* **each step's gradient** -- a rank's loss draws its random numbers (stage 1: the posterior
  sample ``eps``; stage 2: the posterior sample, the noise level and the noise) from the global
  RNG, which the loop seeds per rank from ``(train.seed, rank, step)`` at every checkpoint (here
  after every step, each followed by a validation); everything else of an item (the points kept,
  the queries) comes from a generator of its own, and the items of global batch ``b`` are split
  over the ranks by :func:`~radarpc.training.loop.epoch_batches`. So rank ``r``'s loss ``L_r``
  and gradient ``g_r`` at step ``s`` are recomputed here in one process, from the weights the
  ranks held before the step (the initial ones built as the loop builds them, then those recorded
  after step ``s - 1``), on rank ``r``'s items, with the global RNG seeded as the loop seeds rank
  ``r``: the same float32 operations on the same inputs (one thread on both sides), hence the same
  bits. DDP multiplies each rank's gradient by 1/2 and sums the two (a power-of-two scaling
  commutes with rounding, and ``a + b`` rounds as ``b + a``), so the gradient the optimizer sees on
  every rank is ``fl(g_0 + g_1) / 2`` bit for bit, clipped as the loop clips it: compared with
  ``==``. (At stage 2's first step only the zero-initialised output layer has a gradient; the
  second step's reaches every trained parameter.);
* **each step's loss** -- ``log.csv``'s rows (one per step) hold the mean over the ranks of their
  float32 losses, summed in float64 (exact): ``(L_0 + L_1) / 2`` exactly;
* **the same objective as one process** -- both losses are means over items of equal size (stage
  1: BCE means over the occupied and over the empty queries, ``floor(queries * occupied_fraction)``
  occupied in every frame, and the KL mean; stage 2: EDM's mean over equal latents), so with each
  item's random draws as its rank drew them the single-process loss of the whole global batch is
  ``(L_0 + L_1) / 2``, up to the float32 rounding of its sums (see :func:`_sum_tolerance`);
* **identical weights** -- after the last step both ranks hold the same trainable weights, bit for
  bit; stage 2's best weights (rank 0's) hold the frozen autoencoder unchanged and the weight
  average of those common weights, as the loop's update gives it;
* **rank 0 alone writes** -- each rank is given its own ``--out`` (as on two nodes without a shared
  file system); rank 0's holds the run (``run.json``, ``config.yaml``, ``best.safetensors``,
  ``log.csv``, the last checkpoint), rank 1's is never created. Both ranks' stage 2 reads rank 0's
  stage-1 run.
"""
from __future__ import annotations

import contextlib
import csv
import io
import os
import socket
import time
import traceback
from pathlib import Path
from queue import Empty

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp
import yaml

from radarpc.distributed import DistEnv
from radarpc.experiments.rald.config import load_experiment
from radarpc.experiments.rald.runs import load_rald_ae
from radarpc.experiments.rald.task import AutoencoderTask, DiffusionTask
from radarpc.models.edm import edm_loss_weight
from radarpc.training.checkpoint import load_weights
from radarpc.training.loop import (BEST_WEIGHTS, LAST_CHECKPOINT, LOG_CSV, ema_decay_at, epoch_batches,
                                   frozen_submodules)

CONFIGS = Path(__file__).parent / "configs"
WORLD = 2
STEPS = 2
DDP_STRIDES = "Grad strides do not match bucket view strides"
"""DDP's one warning in stage 2, harmless: the radar encoder's 3-D convolution weights are in
channels-last layout, and where it is the same memory as the default layout (one input channel, or
a 1 x 1 x 1 kernel) autograd gives their gradients the default strides; only the strides of size-1
dimensions differ, which DDP compares literally. It copies the gradients into its buckets all the
same (the gradients are checked bit for bit)."""
TIMEOUT_S = 900              # spawn start-up and 2 x 2 steps: seconds alone, minutes on a starved machine


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(src: Path, dst: Path) -> Path:
    """``src`` cut to :data:`STEPS` steps with a validation (a log row) after every step."""
    mapping = yaml.safe_load(src.read_text())
    mapping["train"].update(max_steps=STEPS, validate_every=1, checkpoint_every=STEPS)
    assert mapping["train"]["batch_size"] == WORLD            # one item per rank (the reference draws per item)
    dst.write_text(yaml.safe_dump(mapping, sort_keys=False))
    return dst


def _flat(tensors) -> np.ndarray:
    return torch.cat([t.detach().reshape(-1) for t in tensors]).numpy().copy()


def _rank_main(rank: int, port: int, argvs: list[list[str]], queue) -> None:
    """One torchrun rank: ``radarpc train`` for each argv, the optimizer's gradients (before each
    step) and parameters (after it) recorded through torch's global optimizer hooks."""
    from torch.optim.optimizer import register_optimizer_step_post_hook, register_optimizer_step_pre_hook

    from radarpc.cli import main

    os.environ.update(RANK=str(rank), WORLD_SIZE=str(WORLD), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    steps: list[dict] = []

    def before(opt, args, kwargs):
        steps.append({"grad": _flat(p.grad for g in opt.param_groups for p in g["params"])})

    def after(opt, args, kwargs):
        steps[-1]["params"] = _flat(p for g in opt.param_groups for p in g["params"])

    register_optimizer_step_pre_hook(before)
    register_optimizer_step_post_hook(after)
    runs = []
    try:
        for argv in argvs:
            steps = []
            out, err = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = main(argv)
            runs.append({"code": code, "stdout": out.getvalue(), "stderr": err.getvalue(), "steps": steps})
            if code != 0:
                break
        queue.put((rank, runs, None))
    except BaseException:
        queue.put((rank, runs, traceback.format_exc()))
    finally:
        if torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()


@pytest.fixture(scope="module")
def ddp_runs(colo_root, tmp_path_factory):
    """``(folder, runs)``: both stages trained on 2 gloo ranks, rank ``r`` into ``folder/rank{r}``
    (``ae``, then ``rald`` against rank 0's ``ae``); ``runs[r]`` is rank ``r``'s list of the two
    trainings (exit code, output, per-step gradients and parameters)."""
    folder = tmp_path_factory.mktemp("rald_ddp")
    ae_cfg = _config(CONFIGS / "rald-ae-tiny.yaml", folder / "rald-ae-ddp.yaml")
    dit_cfg = _config(CONFIGS / "rald-tiny.yaml", folder / "rald-ddp.yaml")

    def argvs(r: int) -> list[list[str]]:
        out = folder / f"rank{r}"
        return [["train", str(ae_cfg), "--data", str(colo_root), "--out", str(out / "ae"), "--no-progress"],
                ["train", str(dit_cfg), "--data", str(colo_root), "--ae", str(folder / "rank0" / "ae"),
                 "--out", str(out / "rald"), "--no-progress"]]

    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    port = _free_port()
    procs = [ctx.Process(target=_rank_main, args=(r, port, argvs(r), queue)) for r in range(WORLD)]
    for p in procs:
        p.start()
    got: dict[int, list] = {}
    deadline = time.monotonic() + TIMEOUT_S
    try:
        while len(got) < WORLD:
            try:
                rank, runs, error = queue.get(timeout=5)
            except Empty:       # a rank that died without a word (killed, crashed) fails the test at once
                died = [(p.name, p.exitcode) for p in procs if p.exitcode not in (None, 0)]
                assert not died, f"rank processes died: {died}"
                assert time.monotonic() < deadline, f"the ranks did not finish in {TIMEOUT_S} s"
                continue
            assert error is None, f"rank {rank} failed:\n{error}"
            for run in runs:
                assert run["code"] == 0, f"rank {rank}: radarpc train exited with {run['code']}:\n{run['stderr']}"
            got[rank] = runs
    finally:
        for p in procs:         # the other rank of a failed one waits in a collective: not for long
            p.join(TIMEOUT_S if len(got) == WORLD else 5)
            if p.exitcode is None:
                p.kill()
                p.join()
    for r in range(WORLD):
        assert len(got[r]) == 2 and all(len(run["steps"]) == STEPS for run in got[r])
    assert all(p.exitcode == 0 for p in procs), [p.exitcode for p in procs]
    return folder, got


# ---- the single-process reference ------------------------------------------------------------------

def _seed_as_rank(seed: int, rank: int, step: int) -> None:
    """The loop's seeding of rank ``rank``'s global RNG at ``step`` (its module docstring: from
    ``(seed, rank, step)``, at the start and at every checkpoint, which follows every validation),
    as :func:`radarpc.training.loop._reseed` does it."""
    torch.manual_seed(int(np.random.SeedSequence([seed, rank, step]).generate_state(1)[0]))


@contextlib.contextmanager
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)            # as the ranks: the same reduction order in every kernel
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _reference(task, cfg, run: dict, draws) -> tuple[list[dict], list[str], np.ndarray]:
    """``(steps, names, initial)``: per optimizer step ``s`` (0-based), from the weights the ranks
    held before it (the initial model built as the loop builds it, then the weights after step
    ``s - 1`` of ``run``, rank 0's training), ``{"losses": [L_0, L_1], "grad": the gradient the
    optimizer sees (the mean of the ranks', clipped), "single": the single-process loss of the
    whole global batch with each item's random numbers as its rank drew them}``; and the names and
    initial values of the trained parameters. ``draws(model, batch, ranks, step)`` is the loss of ``batch`` with item
    ``i``'s random numbers drawn as rank ``ranks[i]`` draws them at ``step``."""
    seed, batch_size = cfg.train.seed, cfg.train.batch_size
    torch.manual_seed(seed)
    model = task.build_model()
    frozen = frozen_submodules(model)
    model.train()
    for m in frozen:
        m.eval()
    trainable = [p for p in model.parameters() if p.requires_grad]
    names = [n for n, p in model.named_parameters() if p.requires_grad]
    initial = _flat(trainable)
    n_train = len(task.train_set)
    per_epoch = len(epoch_batches(n_train, batch_size, seed, 0))
    steps = []
    for s in range(STEPS):
        if s > 0:
            torch.nn.utils.vector_to_parameters(torch.from_numpy(run["steps"][s - 1]["params"]), trainable)
        epoch, b = divmod(s, per_epoch)
        task.train_set.set_epoch(epoch)
        losses, grads, items = [], [], []
        for r in range(WORLD):
            mine = epoch_batches(n_train, batch_size, seed, epoch, DistEnv(r, WORLD, r))[b]
            items += mine
            batch = task.collate([task.train_set[i] for i in mine])
            _seed_as_rank(seed, r, s)
            loss, _ = task.loss(model, batch)
            losses.append(float(loss.detach()))
            grads.append(torch.autograd.grad(loss, trainable))
            with torch.no_grad():            # the draws reproduced outside the model: the rank's loss, bit for bit
                assert float(draws(model, batch, [r], s)) == losses[-1], f"step {s + 1}, rank {r}: other draws"
        for p, g0, g1 in zip(trainable, *grads):
            p.grad = (g0 + g1) / 2
        if cfg.train.grad_clip_norm > 0:
            torch.nn.utils.clip_grad_norm_(trainable, cfg.train.grad_clip_norm)
        with torch.no_grad():
            single = float(draws(model, task.collate([task.train_set[i] for i in items]), list(range(WORLD)), s))
        steps.append({"losses": losses, "grad": _flat(p.grad for p in trainable), "single": single})
    return steps, names, initial


def _draw(shapes: list[tuple[int, ...]], ranks: list[int], seed: int, step: int) -> list[torch.Tensor]:
    """The global RNG's first draws of each rank at ``step`` (of ``shapes``, one item each, in
    order), each shape's draws concatenated over ``ranks`` along the batch dimension."""
    per_rank = []
    for r in ranks:
        _seed_as_rank(seed, r, step)
        per_rank.append([torch.randn(s) for s in shapes])
    return [torch.cat(ts) for ts in zip(*per_rank)]


def _sum_tolerance(n_terms: int) -> float:
    """Relative bound on how far the single-process loss of a batch of ``n_terms`` non-negative
    loss terms may be from the mean of the ranks' losses over their halves, when every term is the
    same bits on both sides (the network's per-item outputs are: its matrix products sum the same
    way per row whatever the batch size): float32 recursive summation is within ``(k - 1) u`` of
    the exact sum of ``k`` non-negative terms (``u = 2^-24``), so ``(n - 1) u`` for the batch's
    sum and ``(n / 2 - 1) u`` for each rank's, plus a few roundings of the loss's weighted
    combination; ``4 n u`` bounds them all."""
    return 4 * n_terms * 2.0 ** -24


def _log_rows(out: Path) -> list[dict[str, str]]:
    with open(out / LOG_CSV, newline="") as f:
        return list(csv.DictReader(f))


def _check_run(out: Path, other: Path, runs, steps: list[dict], n_terms: int, name: str) -> None:
    """Rank 0 alone wrote; per step, the logged loss is the ranks' mean, the single-process loss
    of the global batch equals it (:func:`_sum_tolerance`) and each rank's optimizer saw the
    reference gradient; the ranks end with the same weights."""
    for f in ("run.json", "config.yaml", BEST_WEIGHTS, LAST_CHECKPOINT, LOG_CSV):
        assert (out / f).is_file(), f"{name}: rank 0 wrote no {f}"
    assert not other.exists(), f"{name}: rank 1 wrote {sorted(p.name for p in other.rglob('*'))}"
    rows = _log_rows(out)
    assert [int(r["step"]) for r in rows] == list(range(1, STEPS + 1))
    for s, (row, want) in enumerate(zip(rows, steps)):
        mean = (want["losses"][0] + want["losses"][1]) / 2
        assert float(row["train_loss"]) == mean, f"{name}: step {s + 1}'s logged loss"
        assert want["single"] == pytest.approx(mean, rel=_sum_tolerance(n_terms), abs=0), f"{name}: step {s + 1}"
        for r in range(WORLD):
            np.testing.assert_array_equal(runs[r]["steps"][s]["grad"], want["grad"],
                                          err_msg=f"{name}: rank {r}'s gradient at step {s + 1}")
    np.testing.assert_array_equal(runs[0]["steps"][-1]["params"], runs[1]["steps"][-1]["params"],
                                  err_msg=f"{name}: the ranks' final weights")
    for r in range(WORLD):                  # pytest's warnings-as-errors does not reach the ranks
        said = [line for line in runs[r]["stderr"].splitlines() if "Warning" in line and DDP_STRIDES not in line]
        assert not said, f"{name}: rank {r} warned: {said}"
    assert not np.array_equal(runs[0]["steps"][-1]["params"], runs[0]["steps"][0]["params"])    # they trained


def test_stage_1_trains_under_ddp_as_one_process(ddp_runs, colo_root):
    folder, got = ddp_runs
    cfg = load_experiment(folder / "rald-ae-ddp.yaml")
    task = AutoencoderTask(cfg, colo_root)
    mc = cfg.model.config
    shape = (1, mc.n_latents, mc.latent_dim)

    def draws(model, batch, ranks, step):
        eps, = _draw([shape], ranks, cfg.train.seed, step)          # the posterior sample's eps
        return task.loss(lambda points, queries: model(points, queries, noise=eps), batch)[0]

    with _one_thread():
        steps, _, _ = _reference(task, cfg, got[0][0], draws)
    # the terms of the whole batch's sums: the queries' BCE terms and the latents' KL terms
    n_terms = WORLD * (cfg.data.queries + mc.n_latents * mc.latent_dim)
    _check_run(folder / "rank0" / "ae", folder / "rank1" / "ae", [got[r][0] for r in range(WORLD)], steps, n_terms,
               "stage 1")


def test_stage_2_trains_under_ddp_as_one_process(ddp_runs, colo_root):
    folder, got = ddp_runs
    cfg = load_experiment(folder / "rald-ddp.yaml")
    stage1 = load_rald_ae(folder / "rank0" / "ae")
    task = DiffusionTask(cfg, colo_root, stage1.config, stage1.ae)
    dc = cfg.model.config
    latents = (1, dc.n_latents, dc.latent_dim)

    def draws(model, batch, ranks, step):
        # RaldStage2.forward's draws in order: the posterior sample's eps, ln(sigma)'s normal, the noise
        eps, rnd, noise = _draw([latents, (1, 1, 1), latents], ranks, cfg.train.seed, step)
        mean, logvar = model.autoencoder.encode(batch.points)
        with torch.no_grad():
            z = model.autoencoder.sample(mean, logvar, eps).float()                    # (B, M, D)
        # each item's radar condition alone, as its rank computes it: oneDNN's 3-D convolutions sum in
        # another order for a batch of 2 than for one item (the transformers' products do not)
        condition = torch.cat([model.dit.encode_radar(batch.radar[i:i + 1]) for i in range(len(ranks))])
        sigma = (rnd * cfg.loss.p_std + cfg.loss.p_mean).exp()                          # (B, 1, 1)
        weight = edm_loss_weight(sigma, dc.sigma_data)
        denoised = model.dit(z + noise * sigma, sigma.flatten(), condition)            # (B, M, D)
        return (weight * (denoised - z) ** 2).mean()

    with _one_thread():
        steps, names, initial = _reference(task, cfg, got[0][1], draws)
    _check_run(folder / "rank0" / "rald", folder / "rank1" / "rald", [got[r][1] for r in range(WORLD)], steps,
               WORLD * dc.n_latents * dc.latent_dim, "stage 2")
    # rank 0's best weights: the frozen autoencoder as stage 1 left it, and the weight average of the
    # ranks' common weights at the best step (the loop's update, from the initial weights)
    best, info = load_weights(folder / "rank0" / "rald" / BEST_WEIGHTS)
    ae_best, _ = load_weights(folder / "rank0" / "ae" / BEST_WEIGHTS)
    for k, v in ae_best.items():
        assert torch.equal(best[f"autoencoder.{k}"], v), k
    assert info["weights"] == "ema" and info["step"] in range(1, STEPS + 1)
    average = torch.from_numpy(initial)
    for n in range(1, info["step"] + 1):
        average.lerp_(torch.from_numpy(got[0][1]["steps"][n - 1]["params"]), 1.0 - ema_decay_at(n, cfg.train.ema_decay))
    np.testing.assert_array_equal(_flat(best[k] for k in names), average.numpy())
