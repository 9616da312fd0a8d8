"""Tiny regression tasks for the training-loop tests (importable by spawned DDP workers).

:class:`ToyTask` scores its validation set with the mean squared error (lower is better, select it
with ``select_mode="min"``) and the coefficient of determination R^2 (higher is better).
:class:`FrozenToyTask` is the same regression through a pretrained, frozen encoder with a
BatchNorm layer, as the second stage of a latent diffusion model holds its first-stage autoencoder.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.utils.data import Dataset


class Pairs(Dataset):
    """``n`` fixed pairs ``(x, y = x @ W + noise)`` from a seeded generator."""

    def __init__(self, n: int, seed: int) -> None:
        g = torch.Generator().manual_seed(seed)
        self.x = torch.randn(n, 6, generator=g)
        w = torch.randn(6, 2, generator=torch.Generator().manual_seed(99))
        self.y = self.x @ w + 0.05 * torch.randn(n, 2, generator=g)

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, i: int):
        return self.x[i], self.y[i]


class ToyTask:
    """Linear model with dropout (so the RNG state matters on resume), MSE loss; validation gives
    ``mse`` (lower is better) and ``r2`` (higher is better)."""

    def __init__(self, n_train: int = 24, n_val: int = 8, dropout: float = 0.2) -> None:
        self.dropout = dropout
        self.train_set = Pairs(n_train, 1)
        self.val_set = Pairs(n_val, 2)

    def build_model(self) -> nn.Module:
        return nn.Sequential(nn.Linear(6, 16), nn.GELU(), nn.Dropout(self.dropout), nn.Linear(16, 2))

    def collate(self, items):
        return torch.stack([a for a, _ in items]), torch.stack([b for _, b in items])

    def to_device(self, batch, device):
        return tuple(t.to(device) for t in batch)

    def loss(self, model, batch):
        x, y = batch
        mse = ((model(x) - y) ** 2).mean()
        return mse, {"mse": float(mse.detach())}

    def evaluate(self, model, batches, device):
        preds, targets = [], []
        for x, y in batches:
            preds.append(model(x.to(device)).double())
            targets.append(y.to(device).double())
        p, y = torch.cat(preds), torch.cat(targets)
        sse = float(((p - y) ** 2).sum())
        sst = float(((y - y.mean(dim=0)) ** 2).sum())
        return {"mse": sse / y.numel(), "r2": 1.0 - sse / sst}


def pretrained_encoder_state() -> dict[str, torch.Tensor]:
    """The "pretrained" weights of :class:`EncoderHead`'s encoder (Linear 6 -> 8, BatchNorm1d(8)),
    BatchNorm statistics included, drawn from their own generator."""
    g = torch.Generator().manual_seed(123)
    return {"0.weight": 0.4 * torch.randn(8, 6, generator=g), "0.bias": 0.1 * torch.randn(8, generator=g),
            "1.weight": 1.0 + 0.1 * torch.randn(8, generator=g), "1.bias": 0.1 * torch.randn(8, generator=g),
            "1.running_mean": 0.2 * torch.randn(8, generator=g),
            "1.running_var": 0.5 + torch.rand(8, generator=g),
            "1.num_batches_tracked": torch.tensor(1000)}


class EncoderHead(nn.Module):
    """A frozen encoder (named in ``frozen_submodules``) and a head with dropout that trains."""

    frozen_submodules = ("encoder",)

    def __init__(self, dropout: float) -> None:
        super().__init__()
        self.encoder = nn.Sequential(nn.Linear(6, 8), nn.BatchNorm1d(8))
        self.head = nn.Sequential(nn.Linear(8, 16), nn.GELU(), nn.Dropout(dropout), nn.Linear(16, 2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.encoder(x))


class FrozenToyTask(ToyTask):
    """:class:`ToyTask` through :class:`EncoderHead` with the pretrained encoder.

    ``declare=False`` is the control: the encoder's parameters are set not to require gradients
    but the model does not name it in ``frozen_submodules``, so it trains in train mode and its
    BatchNorm statistics move.
    """

    def __init__(self, declare: bool = True, **kwargs) -> None:
        super().__init__(**kwargs)
        self.declare = declare

    def build_model(self) -> nn.Module:
        model = EncoderHead(self.dropout)
        model.encoder.load_state_dict(pretrained_encoder_state())
        if not self.declare:
            model.frozen_submodules = ()
            model.encoder.requires_grad_(False)
        return model


def _log_rows(run) -> list[dict[str, str]]:
    import csv

    with open(run / "log.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k != "train_time_s"} for row in csv.DictReader(f)]


def assert_same_run(a, b, same_key: bool = True) -> None:
    """Two finished run folders hold the same training: last checkpoint (weights, weight average,
    optimizer and scheduler state, progress), log and best weights, bit for bit; only the
    training times (a measurement) may differ, and without ``same_key`` the run key that the
    best weights' metadata records."""
    from radarpc.training.checkpoint import load_state, load_weights

    sa, sb = (load_state(r / "checkpoints" / "last.safetensors") for r in (a, b))
    assert sa.model.keys() == sb.model.keys() and all(torch.equal(sa.model[k], sb.model[k]) for k in sa.model)
    assert (sa.ema is None) == (sb.ema is None)
    if sa.ema is not None:
        assert all(torch.equal(sa.ema[k], sb.ema[k]) for k in sa.ema)
    assert sa.optimizer["param_groups"] == sb.optimizer["param_groups"]
    assert sa.optimizer["state"].keys() == sb.optimizer["state"].keys()
    for i, state in sa.optimizer["state"].items():
        assert state.keys() == sb.optimizer["state"][i].keys()
        for k, v in state.items():
            w = sb.optimizer["state"][i][k]
            assert torch.equal(v, w) if isinstance(v, torch.Tensor) else v == w, (i, k)
    assert sa.scheduler == sb.scheduler

    def timeless(info):
        return {**info, "history": [{k: v for k, v in r.items() if k != "train_time_s"} for r in info["history"]]}

    assert timeless(sa.info) == timeless(sb.info)
    assert _log_rows(a) == _log_rows(b)
    (wa, ia), (wb, ib) = (load_weights(r / "best.safetensors") for r in (a, b))
    if not same_key:
        ia, ib = ({k: v for k, v in i.items() if k != "run"} for i in (ia, ib))
    assert ia == ib and wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
