"""A tiny regression task for the training-loop tests (importable by spawned DDP workers)."""
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
    """Linear model with dropout (so the RNG state matters on resume), MSE loss, score = -MSE."""

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
        err, n = 0.0, 0
        for x, y in batches:
            x, y = x.to(device), y.to(device)
            err += float(((model(x) - y) ** 2).sum())
            n += y.numel()
        return {"f1": -err / n, "mse": err / n}
