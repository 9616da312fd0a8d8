"""Every radarpc model, by name: one registry of size variants, and the typed config section that
names one.

:data:`MODELS` is a plain dict of factory functions (DiT's ``DiT_models``): ``MODELS[name](**overrides)``
builds the model, each override replacing one field of the variant's model config. It is what the
CLI and the experiment configs choose from. A model built here has a ``cfg`` (its resolved,
frozen config) and an ``input_kind`` (what its forward takes: ``"rd"`` complex range-Doppler cubes,
``"points"`` a :class:`~radarpc.points.PointCloudBatch`, ``"radar"`` RaLD's radar intensity cube
``(B, range, azimuth, elevation)`` (RaLD's diffusion model and the RPDNet-style baseline), ``"lidar"``
dense ``(B, N, 3)`` LiDAR points and ``(B, Q, 3)`` query points normalised to [-1, 1]).

An experiment names its model with a :class:`ModelSpec`::

    model:
      variant: spectralpillars-s      # a key of MODELS
      overrides:                      # fields of the variant's model config that differ
        pfn_channels: 64

Adding a model means writing its module and factory functions and listing them here.
Inference-only rewrites live in :mod:`radarpc.models.fast`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import torch
from torch import nn

from radarpc.models.fftradnet import fftradnet, fftradnet_s, fftradnet_tiny
from radarpc.models.latent_dit import rald_dit, rald_dit_d12, rald_dit_d18, rald_dit_s, rald_dit_tiny
from radarpc.models.pillars import (pillars_tiny, polar_pointpillars, polar_pointpillars_s, spectralpillars,
                                    spectralpillars_s)
from radarpc.models.rpdnet import rpdnet, rpdnet_s, rpdnet_tiny
from radarpc.models.vecset import rald_ae, rald_ae_s, rald_ae_tiny

__all__ = ["MODELS", "ModelSpec", "build_model"]

MODELS: dict[str, Callable[..., nn.Module]] = {
    "fftradnet": fftradnet,                     # dense RD cubes of the full RADIal sensor
    "fftradnet-s": fftradnet_s,                 # radial-s cubes, trains on 2 CPU cores
    "fftradnet-tiny": fftradnet_tiny,           # tests
    "pointpillars": polar_pointpillars,         # polar-BEV PointPillars on spectral points
    "spectralpillars": spectralpillars,         # ... with the angle-sector descriptor
    "pointpillars-s": polar_pointpillars_s,
    "spectralpillars-s": spectralpillars_s,
    "pillars-tiny": pillars_tiny,               # tests
    "rald-ae": rald_ae,                         # RaLD's LiDAR occupancy autoencoder, official size
    "rald-ae-s": rald_ae_s,                     # ... small, trains on 2 CPU cores
    "rald-ae-tiny": rald_ae_tiny,               # tests
    "rald-dit": rald_dit,                       # RaLD's radar-conditioned latent diffusion, paper size (depth 24)
    "rald-dit-d12": rald_dit_d12,               # ... the seed's depth ablations
    "rald-dit-d18": rald_dit_d18,
    "rald-dit-s": rald_dit_s,                   # trains on 2 CPU cores
    "rald-dit-tiny": rald_dit_tiny,             # tests
    "rpdnet": rpdnet,                           # RaLD's learned baseline: radar cube -> frustum occupancy, GPU size
    "rpdnet-s": rpdnet_s,                       # ... trains on 2 CPU cores
    "rpdnet-tiny": rpdnet_tiny,                 # tests
}
"""Model size variants by name: ``MODELS[name](**overrides) -> nn.Module``."""


def _tuples(v: Any) -> Any:
    # YAML has lists; model configs are frozen dataclasses of tuples
    if isinstance(v, (list, tuple)):
        return tuple(_tuples(x) for x in v)
    return v


def build_model(variant: str, overrides: Mapping[str, Any] | None = None, *,
                device: torch.device | str | None = None) -> nn.Module:
    """``MODELS[variant]`` with ``overrides`` (fresh weights), built on ``device``.

    ``device="meta"`` builds the structure without allocating weights: a cheap way to resolve and
    validate a config, or to count the parameters of a paper-size model.

    Raises
    ------
    ValueError
        ``variant`` is not in :data:`MODELS`, or an override is not a field of its config or has
        a value the config refuses.
    """
    if variant not in MODELS:
        raise ValueError(f"unknown model variant {variant!r}; known: {', '.join(MODELS)}")
    kwargs = {str(k): _tuples(v) for k, v in (overrides or {}).items()}
    try:
        with torch.device(device) if device is not None else contextlib.nullcontext():
            return MODELS[variant](**kwargs)
    except TypeError as e:
        raise ValueError(f"model {variant!r}: overrides {sorted(kwargs)} do not fit its config ({e})") from None
    except ValueError as e:
        raise ValueError(f"model {variant!r}: {e}") from None


@dataclass(frozen=True)
class ModelSpec:
    """The model section of an experiment config: a variant of :data:`MODELS` and its overrides.

    Attributes
    ----------
    variant : str
        A key of :data:`MODELS`.
    overrides : dict
        Fields of the variant's model config that differ from the variant (``{}``: the variant
        as it is). Validated at construction by building the model on the meta device.
    """

    variant: str
    overrides: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.overrides, Mapping):
            raise ValueError(f"model.overrides must be a mapping of config fields, got "
                             f"{type(self.overrides).__name__}")
        structure = build_model(self.variant, self.overrides, device="meta")
        object.__setattr__(self, "overrides", dict(self.overrides))
        # what the structure tells, kept so that no caller builds the model to learn it
        object.__setattr__(self, "_config", structure.cfg)
        object.__setattr__(self, "_input_kind", type(structure).input_kind)

    __hash__ = None          # holds a dict

    @property
    def config(self) -> Any:
        """The resolved model config (e.g. :class:`~radarpc.models.pillars.PillarsConfig`)."""
        return self._config

    @property
    def input_kind(self) -> str:
        """``"rd"`` (complex range-Doppler cubes), ``"points"`` (a point cloud batch), ``"radar"``
        (RaLD's radar intensity cube) or ``"lidar"`` (dense normalised LiDAR points and occupancy
        queries)."""
        return self._input_kind

    def build(self, device: torch.device | str | None = None) -> nn.Module:
        """The model with fresh weights."""
        return build_model(self.variant, self.overrides, device=device)

    @classmethod
    def matching(cls, variant: str, config: Any) -> "ModelSpec":
        """The spec of ``variant`` whose resolved config is ``config``: the fields of ``config``
        that differ from the variant's, as overrides.

        Raises
        ------
        ValueError
            ``config`` is not of the variant's config type.
        """
        base = build_model(variant, device="meta").cfg
        if type(base) is not type(config):
            raise ValueError(f"model {variant!r} takes a {type(base).__name__}, got a {type(config).__name__}")
        changed = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
                   if getattr(config, f.name) != getattr(base, f.name)}
        return cls(variant, json.loads(json.dumps(changed)))

    def replace(self, **overrides: Any) -> "ModelSpec":
        """This spec with more overrides (later ones win)."""
        return dataclasses.replace(self, overrides={**self.overrides, **overrides})
