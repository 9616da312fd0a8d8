"""Training state in safetensors files: weights, optimizer, scheduler, RNG, progress -- no pickle.

A checkpoint is one ``.safetensors`` file, written atomically, so a kill at any moment leaves
either the previous checkpoint or the new one, never a mix:

* tensors ``model.<name>`` (the model's ``state_dict``), ``ema.<name>`` (its exponential moving
  average, when the run keeps one), ``optim.<param index>.<key>`` (the optimizer's per-parameter
  state) and ``scaler.<key>``;
* the safetensors metadata entry ``radarpc`` holds, as JSON, everything else: the optimizer's
  param groups and non-tensor state, the scheduler's ``state_dict``, the progress counters and
  whatever the caller adds (history, best score). JSON writes floats by ``repr``, which parses
  back to the same float64, so a resumed run continues with bit-identical hyper-parameters.

Weights-only files (the best checkpoint, exported models) hold the ``model.`` tensors and the
run's resolved config in the metadata; :func:`load_weights` reads them back.

Every file records the software that wrote it (:func:`software_record`: the radarpc version, the
git commit of its source tree when it runs from a checkout, the torch version): weights files in
their ``info["software"]``, checkpoints in their metadata beside ``info``.
"""
from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save

from radarpc.io import DataFileError, atomic_write
from radarpc.runs import source_commit

__all__ = ["TrainingState", "save_state", "load_state", "read_info", "save_weights", "load_weights",
           "load_model_state",
           "software_record"]

_META_KEY = "radarpc"


@dataclass
class TrainingState:
    """What a checkpoint restores.

    Attributes
    ----------
    model : dict of Tensor
        ``state_dict`` of the (unwrapped) model.
    optimizer : dict
        ``torch.optim.Optimizer.state_dict()``.
    scheduler : dict
        ``LRScheduler.state_dict()`` (JSON-able).
    scaler : dict or None
        ``torch.amp.GradScaler.state_dict()`` when fp16 scaling is on.
    info : dict
        JSON-able progress: epoch, step, running sums, history, best score...
    ema : dict of Tensor or None
        The exponential moving average of ``model`` (same keys), when the run keeps one.
    """

    model: dict[str, torch.Tensor]
    optimizer: dict
    scheduler: dict
    scaler: dict | None
    info: dict[str, Any]
    ema: dict[str, torch.Tensor] | None = None


@functools.lru_cache(maxsize=1)
def _software() -> tuple[tuple[str, str | None], ...]:
    import radarpc

    return (("radarpc", radarpc.__version__), ("commit", source_commit()), ("torch", torch.__version__))


def software_record() -> dict[str, str | None]:
    """The software of this process: ``{"radarpc": version, "commit": ..., "torch": version}``.

    ``commit`` is the git commit of the radarpc source tree when radarpc runs from a git checkout
    (:func:`radarpc.runs.source_commit`), else None. Read once per process, when first asked (a
    training run asks as it starts): the code a process runs is the code it loaded, whatever is
    committed later.
    """
    return dict(_software())


def _contiguous_cpu(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to("cpu").contiguous()


def _write(path: Path, tensors: Mapping[str, torch.Tensor], meta: Mapping[str, Any]) -> Path:
    blob = save({k: _contiguous_cpu(v) for k, v in tensors.items()},
                metadata={_META_KEY: json.dumps(meta, allow_nan=True)})
    with atomic_write(path, "wb") as f:
        f.write(blob)
    return path


def _read(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    from safetensors import safe_open

    try:
        tensors = load_file(str(path))
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
    except (OSError, SafetensorError) as e:
        raise DataFileError(path, f"not a readable safetensors checkpoint ({e})") from e
    if _META_KEY not in meta:
        raise DataFileError(path, f"safetensors file without radarpc metadata (key {_META_KEY!r}); "
                                  "not a checkpoint written by radarpc")
    try:
        return tensors, json.loads(meta[_META_KEY])
    except json.JSONDecodeError as e:
        raise DataFileError(path, f"its radarpc metadata is not valid JSON ({e})") from e


def save_state(path: str | os.PathLike, state: TrainingState) -> Path:
    """Write ``state`` to ``path`` atomically (see the module docstring)."""
    tensors: dict[str, torch.Tensor] = {f"model.{k}": v for k, v in state.model.items()}
    if state.ema is not None:
        tensors.update({f"ema.{k}": v for k, v in state.ema.items()})
    opt_state: dict[str, dict[str, Any]] = {}
    for idx, s in state.optimizer["state"].items():
        plain = {}
        for k, v in s.items():
            if isinstance(v, torch.Tensor):
                tensors[f"optim.{idx}.{k}"] = v
            else:
                plain[k] = v
        opt_state[str(idx)] = plain
    if state.scaler:
        for k, v in state.scaler.items():
            if isinstance(v, torch.Tensor):
                tensors[f"scaler.{k}"] = v
    meta = {
        "kind": "training-state",
        "optimizer": {"param_groups": state.optimizer["param_groups"], "state": opt_state},
        "scheduler": state.scheduler,
        "scaler": {k: v for k, v in state.scaler.items() if not isinstance(v, torch.Tensor)}
        if state.scaler else None,
        "info": state.info,
        "software": software_record(),
    }
    return _write(Path(path), tensors, meta)


def read_info(path: str | os.PathLike) -> tuple[str, dict[str, Any]]:
    """``(kind, info)`` of a file written by :func:`save_state` (``"training-state"``; info: epoch,
    step, finished, history...) or :func:`save_weights` (``"weights"``; info: run key, epoch, step,
    metrics...), read from its metadata alone: no tensor is loaded."""
    from safetensors import safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = (f.metadata() or {}).get(_META_KEY)
        if meta is None:
            raise DataFileError(path, f"safetensors file without radarpc metadata (key {_META_KEY!r})")
        meta = json.loads(meta)
    except (OSError, SafetensorError, json.JSONDecodeError) as e:
        raise DataFileError(path, f"not a readable radarpc checkpoint ({e})") from e
    return str(meta.get("kind")), dict(meta.get("info", {}))


def load_state(path: str | os.PathLike) -> TrainingState:
    """Read a checkpoint written by :func:`save_state`; a damaged file raises ``DataFileError``."""
    path = Path(path)
    tensors, meta = _read(path)
    if meta.get("kind") != "training-state":
        raise DataFileError(path, f"expected a training state (kind 'training-state'), got {meta.get('kind')!r}")
    model = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    opt: dict[int, dict[str, Any]] = {int(i): dict(s) for i, s in meta["optimizer"]["state"].items()}
    scaler = dict(meta["scaler"]) if meta.get("scaler") is not None else None
    ema = {k[len("ema."):]: v for k, v in tensors.items() if k.startswith("ema.")} or None
    for k, v in tensors.items():
        if k.startswith("optim."):
            _, idx, name = k.split(".", 2)
            opt.setdefault(int(idx), {})[name] = v
        elif k.startswith("scaler.") and scaler is not None:
            scaler[k[len("scaler."):]] = v
    optimizer = {"state": opt, "param_groups": meta["optimizer"]["param_groups"]}
    return TrainingState(model=model, optimizer=optimizer, scheduler=meta["scheduler"], scaler=scaler,
                         info=meta["info"], ema=ema)


def save_weights(path: str | os.PathLike, model_state: Mapping[str, torch.Tensor],
                 info: Mapping[str, Any]) -> Path:
    """Write model weights (``state_dict``) and JSON-able ``info`` (e.g. the resolved config).

    ``info`` gains ``"software"`` (:func:`software_record`) unless it has that key already.
    """
    return _write(Path(path), {f"model.{k}": v for k, v in model_state.items()},
                  {"kind": "weights", "info": {**dict(info), "software": info.get("software", software_record())}})


def load_weights(path: str | os.PathLike, map_location: str | torch.device = "cpu"
                 ) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """``(state_dict, info)`` of a file written by :func:`save_weights` or :func:`save_state`."""
    path = Path(path)
    tensors, meta = _read(path)
    if meta.get("kind") not in ("weights", "training-state"):
        raise DataFileError(path, f"expected radarpc weights, got kind {meta.get('kind')!r}")
    state = {k[len("model."):]: v.to(map_location) for k, v in tensors.items() if k.startswith("model.")}
    return state, meta.get("info", {})


def load_model_state(model: torch.nn.Module, state: Mapping[str, torch.Tensor], path: str | os.PathLike,
                     what: str = "the model") -> None:
    """``model.load_state_dict(state)`` for weights read from ``path``, refusing with a
    :class:`DataFileError` that names the file: non-finite values (a diverged or damaged run), and
    weights that do not fit ``model`` (another model's: keys missing or left over, other shapes)."""
    bad = [k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise DataFileError(path, f"non-finite values (NaN or inf) in {len(bad)} tensor(s), e.g. {bad[0]!r}: "
                                  f"a diverged or damaged checkpoint")
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        first = str(e).strip().splitlines()
        detail = "; ".join(line.strip() for line in first[1:3]) or first[0]
        raise DataFileError(path, f"its weights do not fit {what} ({detail})") from None
