"""Official RaLD checkpoints (RoyAPTX4869/RaLD) read into radarpc's models, without unpickling code.

The official training scripts (``main_ae.py``, ``main_generation.py``) save ``checkpoint-N.pth``
with ``utils/misc.py`` ``save_model``: a dict of

* ``model``: the network's state dict (a ``KLAutoEncoder`` or an ``EDMPrecond``);
* ``model_ema``: the same keys, the parameters replaced by their exponential moving average (the
  buffers copied from ``model``), or None;
* ``optimizer``, ``scaler``, ``epoch``: the training state;
* ``args``: the ``system`` section of the YAML config, an ``easydict.EasyDict`` (device, seed,
  experiment name, output and log folders, mode). It holds no network size.

**Reading.** :func:`read_official_checkpoint` opens the file with ``torch.load(weights_only=True)``,
which builds tensors and plain containers only. Two more data types are allowed, because the
checkpoints pickle their ``args`` as one of them: ``easydict.EasyDict`` (rebuilt as a plain ordered
dict; an EasyDict's attributes repeat its items) and ``argparse.Namespace`` (3DShape2VecSet's
scripts). Anything else that a file asks to construct is refused, with the file and that global
named; nothing the file names is imported or run. A bare state dict loads too.

**Sizes.** A state dict fixes every size of both networks except the attention heads, which no
tensor shape records (every official factory uses 8: :data:`OFFICIAL_HEADS`), and, for the
diffusion model, the number of latents (the autoencoder's). :func:`convert_official_autoencoder`
and :func:`convert_official_diffusion` infer the model config from the tensor shapes, check it
against a network name in ``args`` where there is one, rename the keys
(:func:`radarpc.models.vecset.official_key`, :func:`radarpc.models.latent_dit.official_key`) and
check the result against the radarpc model of that config key by key and shape by shape, so that
the state dict of another network, or of the other stage, is refused before any weight is used.

:func:`read_official_rald` reads both stages' files, :func:`import_official_rald` writes them as
a RaLD run folder (what ``radarpc import-rald`` calls).

**As a run.** :func:`import_official_rald` writes ``OUT/ae``, a stage-1 run folder, and ``OUT``, a
stage-2 run folder against it, in the format :mod:`radarpc.experiments.rald.runs` loads
(:func:`~radarpc.experiments.rald.runs.load_rald`): ``run.json``, ``config.yaml`` and
``best.safetensors`` each. The stage-1 config's ``data`` is the official one,
:data:`OFFICIAL_LIDAR_DATA`: the official code normalises range over its ``pc_range`` of
0..15.8 m and takes azimuth as ``-atan2(y, x)`` (right positive), so the autoencoder reads and
decodes points in the radar frame mirrored left-right over a grid ending at 15.8 m; the
generation maps its clouds back to radarpc's radar frame. Both keys hold ``"imported"``: each
official file (resolved path), its SHA-256, the weights taken from it (``"model_ema"``,
``"model"`` or ``"state dict"``), its epoch and args, and the choice asked for (``"ema"`` or
``"model"``).

**Which weights.** ``weights="ema"`` (the default) takes ``model_ema`` where the file has it and
``model`` otherwise; ``weights="model"`` always takes ``model``. The official evaluation
(``main_generation.py`` and ``main_ae.py`` in ``mode: eval``) scores ``model``: its EMA switch,
``train.use_ema``, is off in the published configs. The info of the result says which was used.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import pickle
import re
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from radarpc.config import save_yaml, to_dict
from radarpc.experiments.rald.config import AutoencoderExperiment, DiffusionExperiment, LidarData
from radarpc.experiments.rald.runs import ae_reference, autoencoder_run_key, diffusion_run_key
from radarpc.experiments.rald.task import RaldStage2
from radarpc.experiments.rald.train import CONFIG_YAML
from radarpc.io import DataFileError, atomic_write
from radarpc.models import ModelSpec
from radarpc.models.latent_dit import LatentDiT, LatentDiTConfig
from radarpc.models.latent_dit import official_key as dit_official_key
from radarpc.models.vecset import VecSetAEConfig, VecSetAutoencoder
from radarpc.models.vecset import official_key as ae_official_key
from radarpc.runs import RunFolder, check_writable
from radarpc.training.checkpoint import save_weights
from radarpc.training.loop import BEST_WEIGHTS, TrainConfig

__all__ = [
    "OFFICIAL_HEADS",
    "OFFICIAL_GROUPS",
    "WEIGHTS",
    "OfficialCheckpoint",
    "OfficialRaLD",
    "read_official_checkpoint",
    "convert_official_autoencoder",
    "convert_official_diffusion",
    "read_official_rald",
    "OFFICIAL_LIDAR_DATA",
    "AE_FOLDER",
    "import_official_rald",
]

OFFICIAL_HEADS = 8
"""Attention heads of every official factory (``create_autoencoder``: ``heads=8``; ``EDMPrecond``:
``n_heads=8``). No tensor shape records them: pass ``heads=`` for a network built otherwise."""

OFFICIAL_GROUPS = 32
"""GroupNorm groups of the official radar encoder (``Normalize``: ``num_groups=32``, fixed)."""

WEIGHTS = ("ema", "model")
"""Which weights of a checkpoint to take: ``"ema"`` (``model_ema`` where present) or ``"model"``."""

# The only classes a checkpoint's pickle may construct besides tensors and plain containers: the
# pickled args. An EasyDict is a dict subclass whose attributes repeat its items; it is rebuilt as
# an OrderedDict (the one dict type whose instance the weights-only unpickler lets a pickle both
# fill and give attributes), so no EasyDict code, nor easydict itself, is needed.
_ARGS_TYPES: list = [argparse.Namespace, (OrderedDict, "easydict.EasyDict")]


# ---- reading a checkpoint ---------------------------------------------------------------------

@dataclass(frozen=True)
class OfficialCheckpoint:
    """One official checkpoint, read.

    Attributes
    ----------
    path : Path
        The file.
    state : dict of str to Tensor
        The network's state dict in the official key names, float32 (a ``module.`` prefix of
        ``DistributedDataParallel`` removed).
    weights : str
        Which weights ``state`` holds: ``"model_ema"``, ``"model"`` or ``"state dict"`` (a bare
        state dict file).
    epoch : int or None
        The checkpoint's ``epoch``.
    args : dict or None
        The checkpoint's ``args`` as plain JSON-able values.
    """

    path: Path
    state: dict
    weights: str
    epoch: int | None
    args: dict | None


def _plain(value: Any) -> Any:
    """A JSON-able copy of pickled args (dicts, Namespaces, lists and scalars)."""
    if isinstance(value, argparse.Namespace):
        value = vars(value)
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if value is None or isinstance(value, (str, bool, int)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, torch.Tensor):
        return f"tensor{tuple(value.shape)}"
    return repr(value)


def _refusal(path: Path, error: pickle.UnpicklingError) -> DataFileError:
    text = str(error)
    detail = re.search(r"WeightsUnpickler error:\s*([^\n]+)", text)
    detail = detail.group(1).strip() if detail else text.strip().splitlines()[0]
    if detail.startswith("Unsupported operand"):          # bytes that are no pickle torch.save writes
        return DataFileError(path, f"not a readable torch checkpoint ({detail})")
    found = re.search(r"GLOBAL ([\w.]+)", detail)
    what = (f"it asks to construct {found.group(1)}" if found
            else f"it asks for more than tensors and plain containers ({detail})")
    return DataFileError(
        path, f"refusing to read it: {what}, which radarpc does not unpickle (unpickling runs code the file "
              f"chooses). Official RaLD checkpoints hold tensors, plain containers and their args (an EasyDict "
              f"or a Namespace) only. If you trust the file, save its state dicts alone in a separate Python "
              f"session: ck = torch.load(path, weights_only=False); "
              f"torch.save({{'model': ck['model'], 'model_ema': ck.get('model_ema')}}, 'weights.pth')")


def read_official_checkpoint(path: str | os.PathLike, *, weights: str = "ema") -> OfficialCheckpoint:
    """Read an official RaLD checkpoint (``save_model``'s dict) or a bare state dict.

    Parameters
    ----------
    path : path-like
        ``checkpoint-N.pth`` of either stage, or a file holding a state dict alone.
    weights : {"ema", "model"}
        ``"ema"``: ``model_ema`` where the file has it, else ``model``; ``"model"``: ``model``.

    Returns
    -------
    OfficialCheckpoint

    Raises
    ------
    DataFileError
        The file is missing or not a torch checkpoint; it asks to construct an object other than
        tensors, plain containers and the args types (the message names that global; nothing is
        run); or it holds no state dict of tensors.
    """
    path = Path(path)
    if weights not in WEIGHTS:
        raise ValueError(f"weights must be one of {list(WEIGHTS)}, got {weights!r}")
    if not path.is_file():
        raise DataFileError(path, "expected an official RaLD checkpoint (.pth), found no such file")
    try:
        with torch.serialization.safe_globals(_ARGS_TYPES):
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise _refusal(path, e) from None
    except (RuntimeError, EOFError, OSError, ValueError) as e:
        raise DataFileError(path, f"not a readable torch checkpoint ({str(e).strip().splitlines()[0]})") from None

    epoch = args = None
    if isinstance(obj, Mapping) and isinstance(obj.get("model"), Mapping):
        ema = obj.get("model_ema")
        if weights == "ema" and isinstance(ema, Mapping) and ema:
            state, used = ema, "model_ema"
        else:
            state, used = obj["model"], "model"
        epoch = obj.get("epoch") if isinstance(obj.get("epoch"), int) else None
        args = _plain(obj["args"]) if obj.get("args") is not None else None
        if args is not None and not isinstance(args, dict):
            args = {"args": args}
    elif isinstance(obj, Mapping) and obj and all(isinstance(v, torch.Tensor) for v in obj.values()):
        state, used = obj, "state dict"
    else:
        keys = list(obj)[:6] if isinstance(obj, Mapping) else "-"
        raise DataFileError(path, f"expected an official RaLD checkpoint (a dict with 'model', as utils/misc.py "
                                  f"save_model writes) or a state dict, found a {type(obj).__name__} with keys {keys}")
    bad = [k for k, v in state.items() if not isinstance(v, torch.Tensor)]
    if bad or not state:
        raise DataFileError(path, f"'{used}' must map names to tensors; "
                                  + (f"{bad[0]!r} is a {type(state[bad[0]]).__name__}" if bad else "it is empty"))
    if all(str(k).startswith("module.") for k in state):
        state = {str(k)[len("module."):]: v for k, v in state.items()}
    state = {str(k): v.detach().to(torch.float32) if v.is_floating_point() else v.detach()
             for k, v in state.items()}
    return OfficialCheckpoint(path=path, state=state, weights=used, epoch=epoch, args=args)


# ---- sizes and keys ---------------------------------------------------------------------------

def _network(state: Mapping[str, torch.Tensor]) -> str | None:
    if "point_embed.mlp.weight" in state:
        return "the autoencoder (KLAutoEncoder)"
    if any(k.startswith("model.transformer_blocks.") for k in state) or "model.proj_in.weight" in state:
        return "the diffusion model (EDMPrecond)"
    return None


def _tensor(state: Mapping[str, torch.Tensor], key: str, path: Path, what: str, ndim: int) -> torch.Tensor:
    if key not in state:
        other = _network(state)
        hint = (f": it is the state dict of {other}; were the autoencoder and the diffusion files swapped?"
                if other and what not in other else f" (its keys start {sorted(state)[:3]})")
        raise DataFileError(path, f"not the state dict of an official {what}: no {key!r}{hint}")
    t = state[key]
    if t.ndim != ndim:
        raise DataFileError(path, f"{key!r} has shape {tuple(t.shape)}, an official {what} has {ndim} dimensions there")
    return t


def _count(state: Mapping[str, torch.Tensor], pattern: str) -> int:
    """How many consecutive indices ``i = 0, 1, ...`` have ``pattern.format(i)`` in ``state``."""
    n = 0
    while pattern.format(n) in state:
        n += 1
    return n


def _names_in_args(args: Mapping | None) -> list[str]:
    """Network names an official config records: ``model`` (3DShape2VecSet's scripts),
    ``lidar_ae.name`` and ``ar_model.name`` (a whole RaLD config)."""
    if not isinstance(args, Mapping):
        return []
    names = [args.get("model")]
    for section in ("lidar_ae", "ar_model"):
        if isinstance(args.get(section), Mapping):
            names.append(args[section].get("name"))
    return [n for n in names if isinstance(n, str)]


def _refuse_unfit(path: Path, what: str, cfg: Any, checks: Mapping[str, tuple[Any, Any]]) -> None:
    wrong = [f"{k} {named} (the weights: {held})" for k, (named, held) in checks.items()
             if named is not None and named != held]
    if wrong:
        raise DataFileError(path, f"the args name a {what} that the weights are not: {', '.join(wrong)}")


def _finite(state: Mapping[str, torch.Tensor], path: Path) -> None:
    bad = [k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise DataFileError(path, f"non-finite values (NaN or inf) in {len(bad)} tensor(s), e.g. {bad[0]!r}: "
                                  f"a diverged or damaged checkpoint")


def _mapped(state: Mapping[str, torch.Tensor], path: Path, what: str, rename, spec: ModelSpec
            ) -> dict[str, torch.Tensor]:
    """``state`` in radarpc's key names, checked against ``spec``'s model key by key and shape by shape."""
    out: dict[str, torch.Tensor] = {}
    origin: dict[str, str] = {}
    for key, value in state.items():
        new = rename(key)
        if new is None:
            continue
        if new in out:
            raise DataFileError(path, f"{key!r} and {origin[new]!r} both map onto {new!r}: not an official {what}")
        out[new], origin[new] = value.contiguous(), key
    want = {k: tuple(v.shape) for k, v in spec.build(device="meta").state_dict().items()}
    missing = sorted(k for k in want if k not in out)
    unexpected = sorted(origin[k] for k in out if k not in want)
    shapes = sorted(f"{origin[k]} {tuple(out[k].shape)} (expected {want[k]})"
                    for k in out if k in want and tuple(out[k].shape) != want[k])
    if missing or unexpected or shapes:
        parts = [f"{len(missing)} missing (radarpc names), e.g. {missing[:4]}" if missing else "",
                 f"{len(unexpected)} unexpected, e.g. {unexpected[:4]}" if unexpected else "",
                 f"{len(shapes)} of other shapes, e.g. {shapes[:3]}" if shapes else ""]
        raise DataFileError(path, f"its tensors do not make the official {what} their sizes describe "
                                  f"({spec.variant} {spec.overrides}): " + "; ".join(p for p in parts if p))
    return out


def _fourier_basis(n_freqs: int) -> torch.Tensor:
    """The official ``PointEmbed.basis`` ``(3, 3F)``: ``pi 2^k`` on a block diagonal (one block per axis)."""
    e = (2.0 ** torch.arange(n_freqs, dtype=torch.float64) * math.pi).to(torch.float32)
    return torch.block_diag(e[None], e[None], e[None])


def convert_official_autoencoder(state: Mapping[str, torch.Tensor], path: str | os.PathLike, *,
                                 heads: int = OFFICIAL_HEADS, n_latents: int = 512,
                                 args: Mapping | None = None) -> tuple[dict[str, torch.Tensor], ModelSpec]:
    """An official ``KLAutoEncoder`` state dict as radarpc's :class:`~radarpc.models.vecset.VecSetAutoencoder`.

    The sizes come from the shapes: width ``C`` and Fourier frequencies ``F`` from
    ``point_embed.mlp.weight`` ``(C, 6F + 3)``, the query type from the query tensors present
    (``s_latents`` and ``d_latents``: hybrid, ``latents``: static, none: point queries), ``M`` from
    their rows, ``D`` from ``mean_fc``, the depth from the ``layers.i`` present, the attention's
    inner width from ``to_q`` (split into ``heads``) and the feed-forward multiplier from ``net.0``.

    Parameters
    ----------
    state : mapping
        The official state dict (:attr:`OfficialCheckpoint.state`).
    path : path-like
        The file it came from (named in errors).
    heads : int
        Attention heads of the latent blocks (:data:`OFFICIAL_HEADS`; not recorded by any shape).
    n_latents : int
        ``M`` for point (FPS) queries, whose count no tensor records; ignored otherwise.
    args : mapping, optional
        The checkpoint's args: a network name there (``model``, ``lidar_ae.name``, e.g.
        ``kl_d512_m512_l32_mix``) must agree with the shapes.

    Returns
    -------
    (state, spec) : (dict of str to Tensor, ModelSpec)
        The weights in radarpc's names, and the ``rald-ae`` spec that builds their model.

    Raises
    ------
    DataFileError
        Not an official autoencoder's state dict (keys missing or left over, other shapes, the
        other stage's), non-finite values, a ``point_embed.basis`` other than the official
        frequencies, or args naming other sizes.
    """
    path, what = Path(path), "autoencoder (KLAutoEncoder)"
    embed = _tensor(state, "point_embed.mlp.weight", path, what, 2)                 # (C, 6F + 3)
    width, n_feat = embed.shape
    if (n_feat - 3) % 6 or n_feat < 9:
        raise DataFileError(path, f"point_embed.mlp.weight has {n_feat} inputs; the official embedding has 6 F + 3")
    n_freqs = (n_feat - 3) // 6
    if "point_embed.basis" in state:
        basis = state["point_embed.basis"]
        if tuple(basis.shape) != (3, 3 * n_freqs) or not torch.equal(basis, _fourier_basis(n_freqs)):
            raise DataFileError(path, "point_embed.basis is not the official frequencies pi 2^k, k = 0.."
                                      f"{n_freqs - 1} (radarpc computes them; other ones would embed points otherwise)")
    if "s_latents.weight" in state or "d_latents.weight" in state:
        query_type = "hybrid"
        n_latents = _tensor(state, "s_latents.weight", path, what, 2).shape[0]
    elif "latents.weight" in state:
        query_type = "static"
        n_latents = _tensor(state, "latents.weight", path, what, 2).shape[0]
    else:
        query_type = "fps"
    latent_dim = _tensor(state, "mean_fc.weight", path, what, 2).shape[0]
    depth = _count(state, "layers.{}.0.norm.weight")
    if depth:
        inner = _tensor(state, "layers.0.0.fn.to_q.weight", path, what, 2).shape[0]
    elif query_type == "hybrid":
        inner = _tensor(state, "mix_attn_layer.fn.to_q.weight", path, what, 2).shape[0]
    else:
        inner = heads * 64                       # no multi-head attention at all: the head width is moot
    if inner % heads:
        raise DataFileError(path, f"the attention's inner width {inner} does not split into heads={heads}")
    ff = _tensor(state, "cross_attend_blocks.1.fn.net.0.weight", path, what, 2).shape[0]
    if ff % (2 * width):
        raise DataFileError(path, f"cross_attend_blocks.1.fn.net.0.weight has {ff} rows, not a multiple of 2 x {width}")
    try:
        cfg = VecSetAEConfig(width=width, depth=depth, heads=heads, head_dim=inner // heads, n_latents=n_latents,
                             latent_dim=latent_dim, fourier_freqs=n_freqs, ff_mult=ff // (2 * width),
                             query_type=query_type)
    except ValueError as e:
        raise DataFileError(path, f"its sizes make no radarpc autoencoder ({e})") from None
    for name in _names_in_args(args):
        m = re.fullmatch(r"kl_d(\d+)_m(\d+)_l(\d+)(_mix|_learn)?", name)
        if m:
            named_type = {"_mix": "hybrid", "_learn": "static", None: "fps"}[m.group(4)]
            _refuse_unfit(path, f"autoencoder ({name})", cfg, {
                "width": (int(m.group(1)), width), "latents": (int(m.group(2)), n_latents),
                "latent dims": (int(m.group(3)), latent_dim), "query type": (named_type, query_type)})
    _finite(state, path)
    spec = ModelSpec.matching("rald-ae", cfg)
    return _mapped(state, path, what, ae_official_key, spec), spec


def convert_official_diffusion(state: Mapping[str, torch.Tensor], path: str | os.PathLike, *,
                               heads: int = OFFICIAL_HEADS, n_latents: int = 512,
                               args: Mapping | None = None) -> tuple[dict[str, torch.Tensor], ModelSpec]:
    """An official ``EDMPrecond`` state dict (radar encoder inside, ``unfreeze_radar_enc: true``) as
    radarpc's :class:`~radarpc.models.latent_dit.LatentDiT`.

    The sizes come from the shapes: width ``W`` and latent dims ``D`` from ``model.proj_in.weight``
    ``(W, D)``, the depth from the ``model.transformer_blocks.i`` present, the noise features from
    ``model.map_layer0``, the feed-forward multiplier from ``ff.net.0.proj``; the radar encoder's
    base width, level multipliers, residual blocks, attention and output channels from
    ``radar_enc.*``; the condition grid from the three radar embeddings, and the radar cube
    ``grid x 2^(levels - 1)`` per axis.

    Parameters
    ----------
    state : mapping
        The official state dict (:attr:`OfficialCheckpoint.state`).
    path : path-like
        The file it came from (named in errors).
    heads : int
        Attention heads (:data:`OFFICIAL_HEADS`; not recorded by any shape).
    n_latents : int
        ``M``, latents per frame: the autoencoder's (no tensor of the diffusion model records it).
    args : mapping, optional
        The checkpoint's args: a network name there (``model``, ``ar_model.name``, e.g.
        ``kl_d512_m512_l32_d24_edm``) must agree with the shapes.

    Returns
    -------
    (state, spec) : (dict of str to Tensor, ModelSpec)
        The weights in radarpc's names, and the ``rald-dit`` spec that builds their model.

    Raises
    ------
    DataFileError
        Not an official diffusion model's state dict (or one trained with the radar encoder
        outside the network, or on more than the intensity channel), non-finite values, or args
        naming other sizes.
    """
    path, what = Path(path), "diffusion model (EDMPrecond)"
    proj_in = _tensor(state, "model.proj_in.weight", path, what, 2)                  # (W, D)
    width, latent_dim = proj_in.shape
    depth = _count(state, "model.transformer_blocks.{}.norm1.linear.weight")
    noise_channels = _tensor(state, "model.map_layer0.weight", path, what, 2).shape[1]
    ff = (_tensor(state, "model.transformer_blocks.0.ff.net.0.proj.weight", path, what, 2).shape[0]
          if depth else 8 * width)
    if ff % (2 * width):
        raise DataFileError(path, f"ff.net.0.proj.weight has {ff} rows, not a multiple of 2 x {width}")
    if width % heads:
        raise DataFileError(path, f"the width {width} does not split into heads={heads}")
    if "radar_enc.conv_in.weight" not in state:
        if "radar_token_project.weight" in state:
            raise DataFileError(path, "this diffusion model was trained without its radar encoder inside (the official "
                                      "use_radar_enc without unfreeze_radar_enc, a separate frozen radar autoencoder, "
                                      "or the raw cube as tokens); radarpc's LatentDiT holds its radar encoder, as the "
                                      "published configs do (unfreeze_radar_enc: true)")
        _tensor(state, "radar_enc.conv_in.weight", path, what, 5)
    conv_in = _tensor(state, "radar_enc.conv_in.weight", path, what, 5)               # (ch, in, 3, 3, 3)
    channels, in_channels = conv_in.shape[:2]
    if in_channels != 1:
        raise DataFileError(path, f"its radar encoder reads {in_channels} channels; the official model (and radarpc) "
                                  f"reads the intensity channel only")
    levels = _count(state, "radar_enc.down.{}.block.0.conv1.weight")
    res_blocks = _count(state, "radar_enc.down.0.block.{}.conv1.weight")
    outs = [state[f"radar_enc.down.{i}.block.0.conv1.weight"].shape[0] for i in range(levels)]
    if not levels or any(c % channels for c in outs):
        raise DataFileError(path, f"its radar encoder levels have widths {outs}, not multiples of its base width "
                                  f"{channels}")
    grid = tuple(_tensor(state, f"radar_{a}_emb.weight", path, what, 2).shape[0] for a in "rae")
    try:
        cfg = LatentDiTConfig(
            n_latents=n_latents, latent_dim=latent_dim, width=width, heads=heads, depth=depth,
            noise_channels=noise_channels, ff_mult=ff // (2 * width),
            radar_shape=tuple(g * 2 ** (levels - 1) for g in grid), enc_channels=channels,
            enc_ch_mult=tuple(c // channels for c in outs), enc_res_blocks=res_blocks,
            enc_z_channels=_tensor(state, "radar_enc.conv_out.weight", path, what, 5).shape[0],
            enc_groups=OFFICIAL_GROUPS, enc_attention=f"radar_enc.down.{levels - 1}.attn.0.q.weight" in state)
    except ValueError as e:
        raise DataFileError(path, f"its sizes make no radarpc diffusion model ({e})") from None
    for name in _names_in_args(args):
        m = re.fullmatch(r"kl_d(\d+)_m(\d+)_l(\d+)(?:_d(\d+))?_edm", name)
        if m:
            _refuse_unfit(path, f"diffusion model ({name})", cfg, {
                "latents": (int(m.group(2)), n_latents), "latent dims": (int(m.group(3)), latent_dim),
                "depth": (int(m.group(4) or 12), depth)})
    _finite(state, path)
    spec = ModelSpec.matching("rald-dit", cfg)
    return _mapped(state, path, what, dit_official_key, spec), spec


# ---- both stages ------------------------------------------------------------------------------

@dataclass(frozen=True)
class OfficialRaLD:
    """Both official stages in radarpc's terms (:func:`read_official_rald`).

    Attributes
    ----------
    ae_state, dit_state : dict of str to Tensor
        The weights in radarpc's key names (float32).
    ae_spec, dit_spec : ModelSpec
        The ``rald-ae`` and ``rald-dit`` specs of their models.
    info : dict
        JSON-able, per stage (``"autoencoder"``, ``"diffusion"``): ``file``, ``sha256``,
        ``weights`` (``"model_ema"``, ``"model"`` or ``"state dict"``), ``epoch``, ``args`` and
        ``parameters``.
    """

    ae_state: dict
    ae_spec: ModelSpec
    dit_state: dict
    dit_spec: ModelSpec
    info: dict

    def build(self, device: torch.device | str | None = None) -> tuple[VecSetAutoencoder, LatentDiT]:
        """The two models with these weights, in evaluation mode."""
        ae, dit = self.ae_spec.build(device=device), self.dit_spec.build(device=device)
        ae.load_state_dict(self.ae_state)
        dit.load_state_dict(self.dit_state)
        return ae.eval(), dit.eval()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _info(ck: OfficialCheckpoint, state: Mapping[str, torch.Tensor]) -> dict:
    return {"file": str(ck.path), "sha256": _sha256(ck.path), "weights": ck.weights, "epoch": ck.epoch,
            "args": ck.args, "parameters": int(sum(v.numel() for v in state.values()))}


def read_official_rald(ae_path: str | os.PathLike, gen_path: str | os.PathLike, *, weights: str = "ema",
                       ae_heads: int = OFFICIAL_HEADS, dit_heads: int = OFFICIAL_HEADS) -> OfficialRaLD:
    """Read the official autoencoder and diffusion checkpoints as radarpc weights and model specs.

    Parameters
    ----------
    ae_path : path-like
        The autoencoder's ``checkpoint-N.pth`` (``main_ae.py``; ``lidar_ae.ckpt`` of a generation
        config), or its bare state dict.
    gen_path : path-like
        The generation model's ``checkpoint-N.pth`` (``main_generation.py``), or its bare state dict.
    weights : {"ema", "model"}
        ``"ema"``: each file's ``model_ema`` where it has one, else ``model``; ``"model"``: the
        weights the official evaluation scores.
    ae_heads, dit_heads : int
        Attention heads (:data:`OFFICIAL_HEADS`, what every official factory builds).

    Returns
    -------
    OfficialRaLD
        ``ae_state, ae_spec, dit_state, dit_spec, info``; :meth:`OfficialRaLD.build` makes the models.

    Raises
    ------
    DataFileError
        A file that is unreadable, asks to unpickle anything but data, holds the other stage's or
        another network's weights, non-finite values, or a diffusion model whose latents do not
        have the autoencoder's dimension.
    """
    ae_ck = read_official_checkpoint(ae_path, weights=weights)
    ae_state, ae_spec = convert_official_autoencoder(ae_ck.state, ae_ck.path, heads=ae_heads, args=ae_ck.args)
    gen_ck = read_official_checkpoint(gen_path, weights=weights)
    dit_state, dit_spec = convert_official_diffusion(gen_ck.state, gen_ck.path, heads=dit_heads,
                                                     n_latents=ae_spec.config.n_latents, args=gen_ck.args)
    if dit_spec.config.latent_dim != ae_spec.config.latent_dim:
        raise DataFileError(gen_ck.path, f"its latents have {dit_spec.config.latent_dim} dimensions, but the "
                                         f"autoencoder's ({ae_ck.path}) have {ae_spec.config.latent_dim}: not a pair")
    info = {"autoencoder": _info(ae_ck, ae_state), "diffusion": _info(gen_ck, dit_state)}
    return OfficialRaLD(ae_state=ae_state, ae_spec=ae_spec, dit_state=dit_state, dit_spec=dit_spec, info=info)


# ---- as a run folder --------------------------------------------------------------------------

OFFICIAL_LIDAR_DATA = LidarData(max_range_m=15.8, mirror_azimuth=True)
"""The official autoencoder's data (``configs/ae/*.yml``): 10,000 points and queries per frame,
6.25 % occupied, frustum cells of 0.05 m x 0.25 deg x 0.5 deg over ``pc_range`` 0..15.8 m,
+-90 deg, +-20 deg, in the official frame, whose azimuth is ``-atan2(y, x)`` (right positive)."""

AE_FOLDER = "ae"
"""The stage-1 run folder inside an imported run folder."""

_SELECT = TrainConfig(select_metric="loss", select_mode="min")   # the stages' validation metric (no training here)


def _provenance(info: Mapping[str, Any]) -> dict:
    return {"file": str(Path(info["file"]).resolve()), "sha256": info["sha256"], "weights": info["weights"],
            "epoch": info["epoch"], "args": info["args"]}


def import_official_rald(ae_path: str | os.PathLike, gen_path: str | os.PathLike, out: str | os.PathLike, *,
                         weights: str = "ema", data: str | os.PathLike | None = None, overwrite: bool = False,
                         ae_heads: int = OFFICIAL_HEADS, dit_heads: int = OFFICIAL_HEADS) -> Path:
    """Write the official checkpoints as a RaLD run folder ``out`` (stage 2) with ``out/ae`` (stage 1).

    See the module docstring ("As a run"). ``load_rald(out)`` then gives the official models, and
    ``radarpc generate out`` their clouds.

    Parameters
    ----------
    ae_path, gen_path : path-like
        The official autoencoder and generation checkpoints (:func:`read_official_rald`).
    out : path-like
        The run folder.
    weights : {"ema", "model"}
        ``"ema"``: each file's ``model_ema`` where it has one (the default), ``"model"``: ``model``.
    data : path-like, optional
        A ColoRadar root the keys name as the run's data (what ``radarpc generate`` reads when not
        given ``--data``); None: the keys name no root.
    overwrite : bool
        Replace a folder that holds anything else (another run, another import).
    ae_heads, dit_heads : int
        Attention heads (:data:`OFFICIAL_HEADS`).

    Returns
    -------
    Path of the run folder.

    Raises
    ------
    DataFileError
        A checkpoint is unreadable or not an official network of its stage (:func:`read_official_rald`).
    FileNotFoundError, ValueError
        ``data`` is not a ColoRadar root.
    RunMismatchError
        ``out`` holds anything but this import, and ``overwrite`` is False.
    PermissionError
        ``out`` cannot be written (checked first).
    """
    if weights not in WEIGHTS:
        raise ValueError(f"weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
    check_writable(out, "imported RaLD run")                 # before the checkpoints are read
    if data is not None:
        from radarpc.data.coloradar import ColoRadar

        ColoRadar(data, "all", cube_size=None)              # a ColoRadar root, or the reader's error naming it
    official = read_official_rald(ae_path, gen_path, weights=weights, ae_heads=ae_heads, dit_heads=dit_heads)
    ae_cfg = AutoencoderExperiment(name="rald-official-ae", model=official.ae_spec, data=OFFICIAL_LIDAR_DATA,
                                   train=_SELECT)
    dit_cfg = DiffusionExperiment(name="rald-official", model=official.dit_spec, train=_SELECT)
    ae_prov, dit_prov = (_provenance(official.info[k]) for k in ("autoencoder", "diffusion"))
    ae_key = autoencoder_run_key(ae_cfg, data) | {"imported": {"weights": weights, "autoencoder": ae_prov}}
    imported = {"weights": weights, "autoencoder": ae_prov, "diffusion": dit_prov}
    # what identifies the import before the stage-1 weights (whose hash the full key holds) exist
    head = {"experiment": to_dict(dit_cfg), "data": ae_key["data"], "imported": imported}
    out = Path(out)
    ae_dir = out / AE_FOLDER
    ae, dit = official.build()
    with RunFolder(out, {"run.json": head}, what="imported RaLD run", indent=2,
                   owned=("run.json", str(BEST_WEIGHTS), CONFIG_YAML, AE_FOLDER)
                   ).start(overwrite=overwrite, resume=False) as run:
        ae_dir.mkdir()
        save_weights(ae_dir / BEST_WEIGHTS, ae.state_dict(),
                     {"run": ae_key, "epoch": None, "precision": "fp32", "weights": "official"})
        save_yaml(ae_cfg, ae_dir / CONFIG_YAML)
        with atomic_write(ae_dir / "run.json", "w") as f:
            json.dump(ae_key, f, indent=2)
        key = diffusion_run_key(dit_cfg, data, ae_reference(ae_dir, out)) | {"imported": imported}
        save_weights(out / BEST_WEIGHTS, RaldStage2(ae, dit).state_dict(),
                     {"run": key, "epoch": None, "precision": "fp32", "weights": "official"})
        save_yaml(dit_cfg, out / CONFIG_YAML)
        run.write_manifest("run.json", key)                  # last: the folder is a stage-2 run from here on
    return out
