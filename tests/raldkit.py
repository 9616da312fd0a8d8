"""RaLD's official checkpoint layout written from radarpc's own models, for tests that need official
files without the official code: the inverse key maps, the official ``save_model`` dict and its
pickled ``easydict.EasyDict`` args.

Importable from any test as ``raldkit`` (``pythonpath = ["tests"]`` in pyproject.toml).
"""
from __future__ import annotations

import math
import re
import sys
import types
from pathlib import Path

import torch

from radarpc.models.latent_dit import official_key as dit_official_key
from radarpc.models.vecset import official_key as ae_official_key

__all__ = ["ae_official_state", "dit_official_state", "EasyDict", "SYSTEM_ARGS", "save_official"]


# Inverses of radarpc's key maps (checked by a round trip): radarpc tiny models saved with the
# official key names stand for official checkpoints where no clone is needed.

_AE_TO_OFFICIAL = (
    (r"^embed\.proj\.", "point_embed.mlp."), (r"^static_queries$", "s_latents.weight"),
    (r"^dynamic_queries$", "d_latents.weight"), (r"^query_attn\.", "mix_attn_layer."),
    (r"^encoder_attn\.", "cross_attend_blocks.0."), (r"^encoder_ff\.", "cross_attend_blocks.1."),
    (r"^to_mean\.", "mean_fc."), (r"^to_logvar\.", "logvar_fc."), (r"^from_latents\.", "proj."),
    (r"^blocks\.(\d+)\.attn\.", r"layers.\1.0."), (r"^blocks\.(\d+)\.ff\.", r"layers.\1.1."),
    (r"^decoder_attn\.", "decoder_cross_attn."), (r"^to_logit\.", "to_outputs."),
    (r"\.fc1\.", ".fn.net.0."), (r"\.fc2\.", ".fn.net.2."), (r"\.(to_q|to_kv|to_out)\.", r".fn.\1."),
)
_DIT_TO_OFFICIAL = (
    (r"^radar_encoder\.", "radar_enc."), (r"^radar_tokens\.proj\.", "radar_token_project."),
    (r"^radar_tokens\.pos_range\.", "radar_r_emb."), (r"^radar_tokens\.pos_azimuth\.", "radar_a_emb."),
    (r"^radar_tokens\.pos_elevation\.", "radar_e_emb."), (r"^denoiser\.noise_embed\.fc1\.", "model.map_layer0."),
    (r"^denoiser\.noise_embed\.fc2\.", "model.map_layer1."), (r"^denoiser\.blocks\.", "model.transformer_blocks."),
    (r"^denoiser\.", "model."), (r"\.self_attn\.", ".attn1."), (r"\.cross_attn\.", ".attn2."),
    (r"\.to_out\.", ".to_out.0."), (r"\.ff\.proj\.", ".ff.net.0.proj."), (r"\.ff\.out\.", ".ff.net.2."),
)


def _rename(key: str, rules) -> str:
    for pattern, repl in rules:
        key = re.sub(pattern, repl, key)
    return key


def ae_official_state(model) -> dict[str, torch.Tensor]:
    """A radarpc autoencoder's state dict as the official ``KLAutoEncoder`` holds it."""
    out = {_rename(k, _AE_TO_OFFICIAL): v.clone() for k, v in model.state_dict().items()}
    assert all(ae_official_key(o) == k for o, k in zip(out, model.state_dict()))         # the round trip
    e = (2.0 ** torch.arange(model.cfg.fourier_freqs, dtype=torch.float64) * math.pi).float()
    out["point_embed.basis"] = torch.block_diag(e[None], e[None], e[None])                 # the official buffer
    return out


def dit_official_state(model) -> dict[str, torch.Tensor]:
    """A radarpc diffusion model's state dict as the official ``EDMPrecond`` holds it."""
    out = {_rename(k, _DIT_TO_OFFICIAL): v.clone() for k, v in model.state_dict().items()}
    assert all(dit_official_key(o) == k for o, k in zip(out, model.state_dict()))
    return out


class EasyDict(dict):
    """Pickles byte for byte as ``easydict.EasyDict`` does (the items, and the same keys as
    attributes), without easydict: the type of an official checkpoint's ``args``."""

    __module__ = "easydict"

    def __init__(self, d):
        super().__init__(d)
        self.__dict__.update(d)


SYSTEM_ARGS = {"device": "cuda:3", "seed": 1024, "expname": "tiny", "log_dir": "./result/ckpt/generation",
               "output_dir": "./result/ckpt/generation", "distributed": True, "dist_eval": True, "mode": "train"}


def save_official(path: Path, model: dict, *, ema: dict | None = None, args=None, epoch: int = 99) -> Path:
    """``utils/misc.py`` ``save_model``'s dict (the optimizer and scaler states as the official
    AdamW and GradScaler write them), with ``args`` an EasyDict of the config's system section."""
    args = EasyDict(SYSTEM_ARGS) if args is None else args
    name = next(iter(model))
    optimizer = {"state": {0: {"step": torch.tensor(10.0), "exp_avg": torch.zeros_like(model[name]),
                               "exp_avg_sq": torch.zeros_like(model[name])}},
                 "param_groups": [{"lr": 1e-4, "betas": (0.9, 0.999), "eps": 1e-8, "weight_decay": 0.01,
                                   "amsgrad": False, "foreach": None, "maximize": False, "capturable": False,
                                   "differentiable": False, "fused": None, "params": [0]}]}
    saved = sys.modules.get("easydict")
    sys.modules["easydict"] = types.SimpleNamespace(EasyDict=EasyDict)       # where pickle looks the class up
    try:
        torch.save({"model": model, "model_ema": ema, "optimizer": optimizer, "epoch": epoch,
                    "scaler": {"scale": 65536.0, "growth_factor": 2.0, "backoff_factor": 0.5,
                               "growth_interval": 2000, "_growth_tracker": 0}, "args": args}, path)
    finally:
        if saved is None:
            del sys.modules["easydict"]
        else:
            sys.modules["easydict"] = saved
    return path
