"""RaLD's autoencoder reconstruction: a frame's LiDAR -> latents (encoder) -> occupancy of query points
-> a dense cloud.

The cloud the diffusion model would give if it sampled the very latents the autoencoder encodes
from the LiDAR truth: the upper bound of what generation can reach with this autoencoder (the
seed's "reconstruction" rows, Tables 1, 4 and 5). For one frame:

1. **encoding**: the encoder's input ``P`` (``(N, 3)`` LiDAR points in the model's coordinates, drawn
   by the caller as the autoencoder's training draws them) gives the posterior ``mu, log sigma^2``
   (:meth:`~radarpc.models.vecset.VecSetAutoencoder.encode`), and the latents are

   * ``z = mu + sigma eps`` with ``eps ~ N(0, I)`` seeded by the frame's seed (``posterior:
     sample``, the default): what the official evaluation decodes (``engine_ae.py`` ``evaluate``
     calls the model, whose ``encode`` always returns ``posterior.sample()``), and what stage 2
     trains the diffusion model to generate (:class:`~radarpc.experiments.rald.task.RaldStage2`);
   * ``z = mu`` (``posterior: mean``): the autoencoder's own best guess, as radarpc's stage-1
     validation decodes it;

2. **decoding**, **refinement** and the Cartesian output exactly as generation's
   (:func:`radarpc.rald.generate.decode_cloud`: random and guided queries decoded in chunks, the
   refinement around the occupied ones, the kept queries as Cartesian metres in the radar frame),
   so that a reconstruction and a generation of the same settings differ only in their latents.

The official evaluation of the autoencoder decodes 500,000 random queries and nothing else:
``GenerationConfig(random_queries=500_000, guided_queries=0, refine_rounds=0)`` reproduces it
(``radarpc generate AE_RUN --guide none --config C`` with ``generation: {refine_rounds: 0}`` in
``C``); the defaults decode as generation does (random, guided and refinement queries), which is
the bound generation's own decoding can reach. The official evaluation scores the cloud against
the 10,000 points it encoded; ``radarpc evaluate-points`` scores it against the frame's whole
LiDAR in the field of view, as it scores every method.

Randomness is seeded per frame (the official code draws from NumPy's global generator): the
encoder's points by :func:`points_generator`, the posterior's ``eps`` by a stream of its own, the
queries as generation draws them, all from the frame's seed
(:func:`radarpc.rald.generate.frame_seed`), so a frame's cloud is a function of the weights, the
LiDAR, the guide points, the settings and the seed (on one device).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from radarpc.rald.frustum import RALD_GRID, FrustumGrid
from radarpc.rald.generate import GeneratedCloud, GenerationConfig, decode_cloud
from radarpc.rald.voxels import CartesianGrid

__all__ = ["POSTERIORS", "RECONSTRUCTION_STAGES", "ReconstructionConfig", "points_generator", "encode_latents",
           "reconstruct_cloud"]

POSTERIORS: tuple[str, ...] = ("sample", "mean")
"""Which latents of the posterior are decoded: a seeded sample (the official evaluation's) or the mean."""

RECONSTRUCTION_STAGES: tuple[str, ...] = ("encoding", "decoding", "refinement")
"""The timed stages of a frame's reconstruction, in order."""

_POINTS_STREAM, _POSTERIOR_STREAM = 1, 2


@dataclass(frozen=True)
class ReconstructionConfig:
    """What a reconstruction decodes besides generation's query settings."""

    posterior: str = "sample"       # "sample": z = mu + sigma eps (official); "mean": z = mu

    def __post_init__(self) -> None:
        if self.posterior not in POSTERIORS:
            raise ValueError(f"ReconstructionConfig.posterior must be one of {', '.join(POSTERIORS)}, "
                             f"got {self.posterior!r}")


def _generator(seed: int, stream: int) -> torch.Generator:
    state = np.random.SeedSequence([int(seed), int(stream)]).generate_state(2, np.uint32)
    return torch.Generator("cpu").manual_seed(int(state[0]) << 32 | int(state[1]))


def points_generator(seed: int) -> torch.Generator:
    """The CPU generator that draws a frame's encoder points, from the frame's seed (a stream apart
    from the posterior's noise and the queries')."""
    return _generator(seed, _POINTS_STREAM)


@torch.no_grad()
def encode_latents(ae, points: torch.Tensor, seed: int, posterior: str = "sample") -> torch.Tensor:
    """One frame's latents ``(1, M, D)`` of its encoder points (step 1 of the module docstring).

    Parameters
    ----------
    ae : radarpc.models.vecset.VecSetAutoencoder
        In evaluation mode.
    points : torch.Tensor, ``(N, 3)`` or ``(1, N, 3)``
        The LiDAR points in the model's coordinates ``[-1, 1]``.
    seed : int
        The frame's seed: ``eps`` of a sample is drawn from it (on the CPU, so the same on every device).
    posterior : str
        ``"sample"`` or ``"mean"``.
    """
    if posterior not in POSTERIORS:
        raise ValueError(f"posterior must be one of {', '.join(POSTERIORS)}, got {posterior!r}")
    if ae.training:
        raise ValueError("the autoencoder is in training mode (stochastic depth would randomise the result); call "
                         ".eval() on it before reconstructing")
    p = points if points.ndim == 3 else points[None]
    if p.shape[0] != 1:
        raise ValueError(f"encode one frame's points at a time: (N, 3) or (1, N, 3), got {tuple(points.shape)}")
    dev = next(ae.parameters()).device
    mean, logvar = ae.encode(p.to(dev, torch.float32))                                       # (1, M, D) each
    if posterior == "mean":
        return mean
    eps = torch.randn(mean.shape, generator=_generator(seed, _POSTERIOR_STREAM), dtype=mean.dtype)   # (1, M, D)
    return ae.sample(mean, logvar, eps.to(dev))                                              # (1, M, D)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.no_grad()
def reconstruct_cloud(ae, points: torch.Tensor, cfar_points, cfg: GenerationConfig, seed: int, *,
                      posterior: str = "sample", grid: FrustumGrid | CartesianGrid = RALD_GRID,
                      mirror_azimuth: bool = False) -> GeneratedCloud:
    """One frame's reconstruction (see the module docstring).

    Parameters
    ----------
    ae : radarpc.models.vecset.VecSetAutoencoder
        In evaluation mode.
    points : torch.Tensor, ``(N, 3)``
        The frame's encoder points, model coordinates (as the autoencoder's training draws them).
    cfar_points : array-like, ``(P, 3)``
        Cartesian guide points of the frame (radar frame; may be empty).
    cfg : GenerationConfig
        Query counts, spreads, refinement, chunk (the sampler's fields are not read).
    seed : int
        The frame's seed (:func:`radarpc.rald.generate.frame_seed`).
    posterior : str
        ``"sample"`` (official) or ``"mean"``.
    grid, mirror_azimuth
        As :func:`radarpc.rald.generate.generate_clouds`.

    Returns
    -------
    GeneratedCloud
        Timed per :data:`RECONSTRUCTION_STAGES`; an empty cloud is flagged, never dropped.
    """
    dev = next(ae.parameters()).device
    _sync(dev)
    t0 = time.perf_counter()
    latents = encode_latents(ae, points, seed, posterior)                                    # (1, M, D)
    _sync(dev)
    t1 = time.perf_counter()
    out = decode_cloud(ae, latents, cfar_points, cfg, int(seed), grid=grid, mirror_azimuth=mirror_azimuth)
    out.seconds = {"encoding": t1 - t0, **out.seconds}
    out.stages = RECONSTRUCTION_STAGES
    return out
