"""Official FFTRadNet weights as a radarpc run folder, so that ``radarpc evaluate`` scores them.

valeoai/RADIal publishes FFTRadNet's trained weights as a ``.pth`` checkpoint and its settings as a
JSON config (``FFTRadNet/config/config_FFTRadNet_192_56.json``): the network sizes under
``model`` and, under ``dataset.statistics``, the per-channel input normalisation (``input_mean``,
``input_std``, real parts then imaginary parts of the 16 receivers) and the regression offsets'
``reg_mean`` / ``reg_std``. The weights alone do not make a usable model: the statistics belong
to them. :func:`import_official_fftradnet` joins the two into a run folder like one
``radarpc train`` writes:

* ``run.json`` -- the key: the resolved :class:`~radarpc.experiments.radial_detection.config.ExperimentConfig`, the
  RADIal root(s) to score by default, and under ``imported`` the two files' paths and SHA-256;
* ``config.yaml`` -- the same config;
* ``best.safetensors`` -- the weights in radarpc's key names, with the input statistics.

The checkpoint is read with ``torch.load(weights_only=True)``
(:func:`load_official_checkpoint`); the bare state dict and the
training script's ``{"net_state_dict": ...}`` layout both load. A rerun with the same files
rewrites the folder; other files in a folder that holds a run are refused unless ``overwrite``,
which also deletes the evaluations of the weights it replaces.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import pickle
from collections.abc import Iterable, Mapping
from pathlib import Path

import torch

from radarpc.config import save_yaml
from radarpc.experiments.radial_detection.config import ExperimentConfig
from radarpc.experiments.radial_detection.task import DataPaths
from radarpc.experiments.radial_detection.train import CONFIG_YAML, run_key
from radarpc.io import DataFileError
from radarpc.models import ModelSpec
from radarpc.models.fftradnet import FFTRadNetConfig
from radarpc.models.targets import TargetConfig
from radarpc.runs import RunFolder
from radarpc.training.checkpoint import load_model_state, save_weights
from radarpc.training.loop import BEST_WEIGHTS

__all__ = ["OfficialConfig", "read_official_config", "official_experiment", "import_official_fftradnet",
           "official_to_radarpc", "radarpc_to_official", "load_official_checkpoint"]


# ---- official state dicts -------------------------------------------------------------------------
# (official prefix, radarpc prefix); the first match rewrites a key, the rest of it is unchanged
_OFFICIAL_PREFIXES = (
    ("FPN.pre_enc.", "pre_encoder."),
    ("FPN.", "backbone."),
    ("RA_decoder.", "decoder."),
    ("detection_header.", "detection_head."),
    ("freespace.0.", "freespace_head.block1."),
    ("freespace.1.", "freespace_head.block2."),
    ("freespace.2.", "freespace_head.out."),
)
_OURS_ONLY = ("input_mean", "input_std")


def _rename(key: str, pairs: Iterable[tuple[str, str]]) -> str | None:
    for a, b in pairs:
        if key.startswith(a):
            return b + key[len(a):]
    return None


def official_to_radarpc(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """An official FFTRadNet state dict (keys ``FPN.*``, ``RA_decoder.*``, ``detection_header.*``,
    ``freespace.*``; a ``module.`` prefix of ``DataParallel`` is dropped) in radarpc's key names."""
    out = {}
    for k, v in state.items():
        k = k.removeprefix("module.")
        new = _rename(k, _OFFICIAL_PREFIXES)
        if new is None:
            raise KeyError(f"{k!r} is not a key of the official FFTRadNet (expected one starting with "
                           f"{', '.join(a for a, _ in _OFFICIAL_PREFIXES)})")
        out[new] = v
    return out


def radarpc_to_official(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Inverse of :func:`official_to_radarpc` (the normalisation buffers, which the official model
    keeps in its JSON config, are left out)."""
    back = [(b, a) for a, b in _OFFICIAL_PREFIXES]
    back.sort(key=lambda p: -len(p[0]))       # "freespace_head.block1." before any shorter prefix
    out = {}
    for k, v in state.items():
        if k in _OURS_ONLY:
            continue
        new = _rename(k, back)
        if new is None:
            raise KeyError(f"{k!r} is not a key of radarpc's FFTRadNet")
        out[new] = v
    return out


def _numpy_scalar_globals() -> list:
    """What unpickling numeric NumPy scalars needs: the official training script stores its metric
    history (``np.float64``) beside the weights. Data constructors only (no callables of the file's
    choosing); the scalar constructor under its NumPy 1 and 2 module names."""
    import numpy as np

    core = getattr(np, "_core", None) or np.core
    names = ("Float64DType", "Float32DType", "Float16DType", "Int64DType", "Int32DType", "BoolDType")
    dtypes = [getattr(np.dtypes, n) for n in names if hasattr(getattr(np, "dtypes", None), n)]
    scalar = core.multiarray.scalar
    return [scalar, (scalar, "numpy.core.multiarray.scalar"), (scalar, "numpy._core.multiarray.scalar"), np.dtype,
            *dtypes]


def load_official_checkpoint(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The network weights of an official FFTRadNet ``.pth`` checkpoint, in radarpc's key names.

    Accepts a bare state dict and the training script's ``{"net_state_dict": ..., "optimizer": ...}``
    layout. The file is read with ``torch.load(weights_only=True)``: tensors, plain containers and
    numeric NumPy scalars (the script's metric history) only. A checkpoint that needs full
    unpickling (arbitrary Python objects) is refused, since unpickling runs code the file chooses.

    Load into a model with ``model.load_state_dict(sd, strict=False)`` (the statistics buffers are
    not in the file; set them with :meth:`FFTRadNet.set_input_statistics`), or use
    ``model.load_state_dict(sd | {"input_mean": ..., "input_std": ...})``.
    """
    path = Path(path)
    try:
        with torch.serialization.safe_globals(_numpy_scalar_globals()):
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise ValueError(
            f"{path}: refusing to load: the checkpoint holds Python objects that only full unpickling can "
            f"rebuild, which can run arbitrary code. radarpc reads checkpoints with torch.load(weights_only=True). "
            f"If you trust the file, re-save its weights alone in a separate Python session: "
            f"torch.save(torch.load(path, weights_only=False)['net_state_dict'], 'weights.pth'). ({e})") from None
    except (RuntimeError, EOFError, OSError) as e:
        if isinstance(e, FileNotFoundError):
            raise
        raise ValueError(f"{path}: not a readable torch checkpoint ({e})") from None
    if isinstance(obj, Mapping) and "net_state_dict" in obj:
        obj = obj["net_state_dict"]
    if not isinstance(obj, Mapping) or not obj or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise ValueError(f"{path}: expected a state dict (name -> tensor) or a dict with 'net_state_dict', "
                         f"got {type(obj).__name__} with keys {list(obj)[:5] if isinstance(obj, Mapping) else '-'}")
    try:
        return official_to_radarpc(obj)
    except KeyError as e:
        raise DataFileError(path, f"not the state dict of an official FFTRadNet: {e.args[0]}") from None


# ---- official configs -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class OfficialConfig:
    """What radarpc takes from an official FFTRadNet JSON config.

    Attributes
    ----------
    name : str
        The config's ``name`` (e.g. ``FFTRadNet_RA_192_56``).
    blocks, channels : tuple of 4 int
        ``model.backbone_block`` and ``model.channels``.
    mimo_channels : int
        ``model.MIMO_output``.
    freespace : bool
        ``model.SegmentationHead``.
    input_mean, input_std : tuple of float
        ``dataset.statistics.input_mean`` / ``input_std``, one per input channel.
    reg_mean, reg_std : tuple of 2 float
        ``dataset.statistics.reg_mean`` / ``reg_std`` (range m, azimuth deg).
    """

    name: str
    blocks: tuple[int, ...]
    channels: tuple[int, ...]
    mimo_channels: int
    freespace: bool
    input_mean: tuple[float, ...]
    input_std: tuple[float, ...]
    reg_mean: tuple[float, float]
    reg_std: tuple[float, float]


def _flag(value: object, where: str, path: Path) -> bool:
    # the official configs write booleans as the strings "True" / "False"
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value in ("True", "False", "true", "false"):
        return value.lower() == "true"
    raise DataFileError(path, f"{where} must be true or false (or the string 'True' / 'False'), got {value!r}")


def _numbers(value: object, where: str, path: Path, n: int | None = None, integer: bool = False) -> tuple:
    kinds = (int,) if integer else (int, float)
    if (not isinstance(value, list) or not value or (n is not None and len(value) != n)
            or not all(isinstance(v, kinds) and not isinstance(v, bool) for v in value)):
        want = f"{n} " if n is not None else ""
        raise DataFileError(path, f"{where} must be a list of {want}{'integers' if integer else 'numbers'}, "
                                  f"got {value!r}")
    if not all(math.isfinite(v) for v in value):
        raise DataFileError(path, f"{where} must hold finite numbers, got {value!r}")
    return tuple(int(v) if integer else float(v) for v in value)


def read_official_config(path: str | os.PathLike) -> OfficialConfig:
    """Read the sizes and statistics of an official FFTRadNet JSON config (see the module docstring).

    Raises
    ------
    DataFileError
        The file is not JSON, or a field is missing or malformed (the message names the field).
    FileNotFoundError
        ``path`` does not exist.
    """
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataFileError(path, f"expected an official FFTRadNet JSON config, could not read it as JSON ({e})") from None

    def get(*keys: str) -> object:
        node: object = raw
        for k in keys:
            if not isinstance(node, dict) or k not in node:
                raise DataFileError(path, f"expected an official FFTRadNet config with '{'.'.join(keys)}' "
                                          f"(as in valeoai/RADIal's config_FFTRadNet_192_56.json)")
            node = node[k]
        return node

    if not _flag(get("model", "DetectionHead"), "model.DetectionHead", path):
        raise DataFileError(path, "model.DetectionHead is False: radarpc scores detections and needs the detection head")
    mimo = get("model", "MIMO_output")
    if not isinstance(mimo, int) or isinstance(mimo, bool) or mimo < 1:
        raise DataFileError(path, f"model.MIMO_output must be a positive integer, got {mimo!r}")
    std = _numbers(get("dataset", "statistics", "input_std"), "dataset.statistics.input_std", path)
    if min(std) <= 0:
        raise DataFileError(path, "dataset.statistics.input_std must be positive in every channel")
    mean = _numbers(get("dataset", "statistics", "input_mean"), "dataset.statistics.input_mean", path, n=len(std))
    name = raw.get("name", path.stem)
    return OfficialConfig(
        name=str(name),
        blocks=_numbers(get("model", "backbone_block"), "model.backbone_block", path, n=4, integer=True),
        channels=_numbers(get("model", "channels"), "model.channels", path, n=4, integer=True),
        mimo_channels=mimo,
        freespace=_flag(get("model", "SegmentationHead"), "model.SegmentationHead", path),
        input_mean=mean,
        input_std=std,
        reg_mean=_numbers(get("dataset", "statistics", "reg_mean"), "dataset.statistics.reg_mean", path, n=2),
        reg_std=_numbers(get("dataset", "statistics", "reg_std"), "dataset.statistics.reg_std", path, n=2),
    )


def official_experiment(official: OfficialConfig, base: FFTRadNetConfig = FFTRadNetConfig()) -> ExperimentConfig:
    """The experiment config of an official FFTRadNet: its sizes on ``base`` (RADIal's cube
    geometry by default), its regression statistics in the targets, RADIal's loss and radarpc's
    training defaults (used only if the run is trained further).

    Raises
    ------
    ValueError
        The sizes do not make an FFTRadNet (:class:`~radarpc.models.fftradnet.FFTRadNetConfig`), or
        the statistics do not have one value per input channel (``2 n_rx``).
    """
    net = dataclasses.replace(base, blocks=official.blocks, channels=official.channels,
                              mimo_channels=official.mimo_channels, freespace=official.freespace)
    if len(official.input_mean) != 2 * net.n_rx:
        raise ValueError(f"{official.name}: {len(official.input_mean)} input statistics, but the model takes "
                         f"{2 * net.n_rx} channels (real and imaginary parts of {net.n_rx} receivers)")
    targets = TargetConfig(reg_mean=official.reg_mean, reg_std=official.reg_std)
    return ExperimentConfig(name=official.name, model=ModelSpec.matching("fftradnet", net), targets=targets)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def import_official_fftradnet(checkpoint: str | os.PathLike, official_config: str | os.PathLike, data: DataPaths,
                              out: str | os.PathLike, *, base: FFTRadNetConfig = FFTRadNetConfig(),
                              overwrite: bool = False) -> Path:
    """Write the run folder ``out`` for an official FFTRadNet checkpoint (see the module docstring).

    Parameters
    ----------
    checkpoint : path-like
        The official ``.pth`` (a state dict, or ``{"net_state_dict": ...}``).
    official_config : path-like
        The official JSON config the weights were trained with (its statistics are the input
        normalisation).
    data : path-like or sequence of path-like
        The RADIal root(s) ``radarpc evaluate`` scores by default (``--data`` overrides it there).
    out : path-like
        The run folder.
    base : FFTRadNetConfig
        Cube geometry (RADIal's by default); the official config sets the sizes on it.
    overwrite : bool
        Replace a folder that holds another run.

    Returns
    -------
    Path of the run folder.

    Raises
    ------
    DataFileError
        The config is malformed, or the checkpoint's tensors do not fit the model its config
        describes (the message names both files).
    ValueError
        The checkpoint is not a readable state dict (:func:`load_official_checkpoint`).
    RunMismatchError
        ``out`` holds another run and ``overwrite`` is False.
    """
    checkpoint, official_config, out = Path(checkpoint), Path(official_config), Path(out)
    official = read_official_config(official_config)
    try:
        cfg = official_experiment(official, base)
    except ValueError as e:
        raise DataFileError(official_config, str(e)) from None
    # the official model keeps its input statistics in the JSON config, radarpc in the weights
    state = load_official_checkpoint(checkpoint) | {"input_mean": torch.tensor(official.input_mean),
                                                    "input_std": torch.tensor(official.input_std)}
    model = cfg.build_model()
    load_model_state(model, state, checkpoint, f"the FFTRadNet that {official_config.name} describes "
                                               f"(is model.SegmentationHead right?)")
    key = run_key(cfg, data) | {"imported": {
        "checkpoint": str(checkpoint.resolve()), "checkpoint_sha256": _sha256(checkpoint),
        "official_config": str(official_config.resolve()), "official_config_sha256": _sha256(official_config)}}
    with RunFolder(out, {"run.json": key}, what="imported FFTRadNet run", indent=2,
                   owned=("run.json", str(BEST_WEIGHTS), CONFIG_YAML, "eval_*", "figures")
                   ).start(overwrite=overwrite) as run:
        save_weights(run.path / BEST_WEIGHTS, model.state_dict(),
                     {"run": key, "epoch": None, "precision": "fp32", "weights": "official"})
        save_yaml(cfg, run.path / CONFIG_YAML)
    return out
