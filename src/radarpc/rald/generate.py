"""RaLD's generation: radar cube -> latents (diffusion) -> occupancy of query points -> a dense cloud.

The seed's inference ("CFAR-guided decoding" and "refinement"), as the public RoyAPTX4869/RaLD
code runs it (``engine_generation.py`` ``evaluate``, ``datasets/utils/query_helper.py``
``aug_query_helper``, the evaluation config ``ge_indoor_..._eval.yml``). For one frame:

1. **condition**: the radar tokens ``c = E(cube)``, once (:meth:`LatentDiT.encode_radar`);
2. **sampler**: latents ``z`` by EDM's Heun sampler from seeded noise, every network call with the
   same ``c`` (:func:`radarpc.models.edm.edm_sampler`, 18 steps, 35 calls);
3. **decoding**: the occupancy logit ``l(q) = D(z, q)`` of

   * ``n_r`` random queries, uniform over the normalised grid ``[-1, 1]^3`` (official: 500,000);
   * ``n_g`` CFAR-guided queries (official: 700,000) around the frame's CFAR points ``P``
     (:func:`cfar_guided_queries`): the points themselves, then, while fewer than ``n_g``,
     copies of randomly chosen points moved by ``s u * cell`` per axis, ``u ~ U(-1, 1)^3``,
     ``s`` uniform in ``{1, ..., spread}`` (official spread 2), clipped to the grid; with ``|P| >=
     n_g`` the first ``n_g`` points alone;

   keeping the queries with ``l(q) > 0``, in query order (:func:`decode_occupied`);
4. **refinement** (:func:`refine`): the kept points ``K`` are topped up the same way to
   ``n_f`` queries (official: 500,000, spread 10, one round), the new ones decoded, the occupied
   ones kept; with ``|K| >= n_f`` the first ``n_f`` kept points remain;
5. the kept queries, denormalised and mapped to Cartesian metres in the radar frame
   (:func:`radarpc.rald.voxels.cartesian_points`: polar for RaLD's frustum grid).

The model's frame: an autoencoder reads points in its own frame, the radar frame itself or, with
``mirror_azimuth``, the radar frame mirrored left-right (``y -> -y``: azimuth positive to the
right, the official checkpoints' convention; :class:`radarpc.experiments.rald.config.LidarData`).
The CFAR points (radar frame) are mirrored into that frame before they become guided queries,
and the cloud is mirrored back, so that a cloud is always in the radar frame of the LiDAR truth.

Every step works in the grid's own coordinates (polar ``(r, a, e)`` with cells of 0.05 m, 0.25
deg, 0.5 deg for :data:`~radarpc.rald.frustum.RALD_GRID`; Cartesian metres for a
:class:`~radarpc.rald.voxels.CartesianGrid`) and hands the decoder normalised coordinates.

Where this differs from the official code, and why the output is the same:

* decoding runs in chunks of ``chunk`` queries against the latent tokens computed once: each
  query's logit depends on that query and the latents only (the decoder's cross-attention has
  one softmax per query), so the chunk size changes memory, not the result;
* the decoder's linear maps are multiplied out once per frame
  (:class:`~radarpc.models.vecset.FoldedDecoder`, ``folded_decoder``): the same logits with
  about 35 times fewer FLOPs a query at paper size, rounded differently in float32 (a query
  whose logit lies within float32 rounding of 0 can change sides; ``folded_decoder=False``
  decodes layer by layer);
* refinement decodes only the new queries: the official code decodes the kept points again,
  and a point kept at step 3 has the same logit, so it is kept again;
* randomness is seeded per frame (the official code draws from NumPy's global generator): the
  sampler's initial noise by :class:`~radarpc.models.edm.SeededNoise` of the frame's seed, the
  queries by a CPU :class:`torch.Generator` seeded from it, so a frame's cloud is a function of
  the weights, the cube, the CFAR points, the config and the seed (on one device);
* CFAR points outside the grid are dropped first (the official helper points are cropped to the
  field of view when they are written), and a frame without any gets no guided queries (the
  official code fails there).

The CFAR points themselves come from the caller (:mod:`radarpc.rald.guide`: RaLD's intensity
peaks or radarpc's OS-CFAR baseline).
"""
from __future__ import annotations

import math
import time
import zlib
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch

from radarpc.models.edm import SeededNoise, edm_sampler
from radarpc.rald.frustum import RALD_GRID, FrustumGrid, denormalize, in_frustum, normalize
from radarpc.rald.voxels import CartesianGrid, cartesian_points, grid_coords

__all__ = [
    "STAGES",
    "GenerationConfig",
    "GeneratedCloud",
    "frame_seed",
    "random_queries",
    "spread_queries",
    "cfar_guided_queries",
    "model_frame",
    "decode_occupied",
    "refine",
    "decode_cloud",
    "generate_clouds",
    "generate_cloud",
]

STAGES: tuple[str, ...] = ("condition", "sampler", "decoding", "refinement")
"""The timed stages of a frame's generation, in order."""

Grid = FrustumGrid | CartesianGrid


# ----------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class GenerationConfig:
    """How a cloud is generated from a radar frame, whole (defaults: the official evaluation)."""

    random_queries: int = 500_000   # n_r: uniform over the normalised grid (num_query_points)
    guided_queries: int = 700_000   # n_g: CFAR points, topped up around them (query_aug_num)
    guided_spread: int = 2          # a topped-up query moves by up to guided_spread cells per axis (query_aug_scale)
    refine_queries: int = 500_000   # n_f: kept points, topped up around them (refine_query_aug_num)
    refine_spread: int = 10         # ... by up to refine_spread cells per axis (refine_query_scale)
    refine_rounds: int = 1          # refinements one after the other; 0 = none
    chunk: int = 65_536             # queries per decoder call: bounds the memory, not the result
    num_steps: int = 18             # Heun steps of the sampler (2 num_steps - 1 network calls)
    sigma_min: float = 0.002        # lowest noise level of the sampler
    sigma_max: float = 80.0         # highest noise level
    rho: float = 7.0                # spacing exponent of the noise levels
    seed: int = 0                   # base seed; a frame's seed is frame_seed(seed, run, frame)
    folded_decoder: bool = True     # decode with the autoencoder's folded decoder (same logits, ~35x fewer FLOPs)

    def __post_init__(self) -> None:
        for k in ("random_queries", "guided_queries", "refine_queries", "refine_rounds", "guided_spread",
                  "refine_spread", "chunk", "num_steps", "seed"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise ValueError(f"GenerationConfig.{k} must be an integer >= 0, got {v!r}")
            object.__setattr__(self, k, int(v))
        for k in ("guided_spread", "refine_spread", "chunk"):
            if getattr(self, k) < 1:
                raise ValueError(f"GenerationConfig.{k} must be >= 1, got {getattr(self, k)}")
        if not isinstance(self.folded_decoder, bool):
            raise ValueError(f"GenerationConfig.folded_decoder must be true or false, got {self.folded_decoder!r}")
        if self.random_queries + self.guided_queries < 1:
            raise ValueError("GenerationConfig: random_queries + guided_queries must be >= 1 (nothing to decode)")
        if self.num_steps < 2:
            raise ValueError(f"GenerationConfig.num_steps must be >= 2, got {self.num_steps}")
        for k in ("sigma_min", "sigma_max", "rho"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise ValueError(f"GenerationConfig.{k} must be a finite number > 0, got {v!r}")
            object.__setattr__(self, k, float(v))
        if not self.sigma_min < self.sigma_max:
            raise ValueError(f"GenerationConfig: sigma_min {self.sigma_min} must be below sigma_max {self.sigma_max}")

    def sampler(self) -> dict[str, float]:
        """The keyword settings of :func:`radarpc.models.edm.edm_sampler` (no churn: deterministic)."""
        return dict(num_steps=self.num_steps, sigma_min=self.sigma_min, sigma_max=self.sigma_max, rho=self.rho)


def frame_seed(seed: int, run: str, frame: int) -> int:
    """The seed of radar frame ``frame`` of run ``run``: CRC-32 of ``"{seed}:{run}:{frame}"``.

    A frame's seed depends on the base seed and the frame alone, not on which other frames are
    generated or in what order (a resumed job draws what an uninterrupted one drew).
    """
    return zlib.crc32(f"{int(seed)}:{run}:{int(frame)}".encode())


def _query_generator(seed: int) -> torch.Generator:
    # the queries' own stream, apart from the sampler's noise (SeededNoise seeds with `seed` itself)
    return torch.Generator("cpu").manual_seed((int(seed) * 2654435761 + 0x5EED) % (1 << 63))


# ----------------------------------------------------------------------------------------------
# Queries
# ----------------------------------------------------------------------------------------------

def random_queries(n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``n`` queries uniform over the normalised grid ``[-1, 1]^3``, ``(n, 3)`` float32 (on the
    generator's device, the CPU by default)."""
    dev = generator.device if generator is not None else "cpu"
    return 2.0 * torch.rand((int(n), 3), generator=generator, device=dev) - 1.0


def spread_queries(points: torch.Tensor, n: int, grid: Grid, spread: int,
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """``n`` queries in the grid's coordinates around ``points`` (the official ``aug_query_helper``).

    With ``|P| >= n`` the first ``n`` points; otherwise all points followed by ``n - |P|`` copies
    of points chosen uniformly with replacement, each moved by ``s u * cell`` (``u ~ U(-1, 1)^3``,
    one ``s`` per copy uniform in ``{1, ..., spread}``) and clipped to the grid's box.

    Parameters
    ----------
    points : torch.Tensor, ``(P, 3)``
        In the grid's coordinates (polar for a frustum grid), inside the grid.
    n : int
        Queries wanted.
    grid : FrustumGrid or CartesianGrid
    spread : int
        Largest move, in cells per axis.
    generator : torch.Generator, optional
        Draws the copies (on the CPU).

    Returns
    -------
    torch.Tensor, ``(min(n, |P|) + max(0, n - |P|), 3)`` float64
        Empty when ``points`` is empty.
    """
    p = points.to(torch.float64)
    if p.shape[0] >= n or p.shape[0] == 0:
        return p[:n].clone()
    return torch.cat((p, _moved_copies(p, n - p.shape[0], grid, spread, generator)))


def _moved_copies(p: torch.Tensor, k: int, grid: Grid, spread: int,
                  generator: torch.Generator | None) -> torch.Tensor:
    """``k`` copies of rows of ``p`` ``(P, 3)`` float64, each moved by ``s u * cell`` and clipped."""
    dev = generator.device if generator is not None else p.device
    lo, hi, cell = grid._tensors(dev, torch.float64)
    pick = torch.randint(0, p.shape[0], (k,), generator=generator, device=dev)                   # (k,)
    s = torch.randint(1, int(spread) + 1, (k, 1), generator=generator, device=dev)                # (k, 1)
    u = 2.0 * torch.rand((k, 3), generator=generator, device=dev, dtype=torch.float64) - 1.0     # (k, 3)
    moved = p.to(dev)[pick] + u * s.to(torch.float64) * cell                                      # (k, 3)
    return torch.minimum(torch.maximum(moved, lo), hi).to(p.device)


def cfar_guided_queries(cfar_points, n: int, grid: Grid = RALD_GRID, generator: torch.Generator | None = None,
                        *, spread: int = 2, mirror_azimuth: bool = False) -> torch.Tensor:
    """RaLD's CFAR-guided queries: the CFAR points inside the grid, topped up around them.

    Parameters
    ----------
    cfar_points : array-like or torch.Tensor, ``(P, 3)``
        Cartesian points (metres, radar frame: x forward, y left, z up); those outside the grid
        are dropped.
    n : int
        Queries wanted (official: 700,000).
    grid : FrustumGrid or CartesianGrid
        The occupancy grid the autoencoder was trained on.
    generator : torch.Generator, optional
        Draws the moved copies (on the CPU).
    spread : int
        Largest move in cells per axis (official: 2).
    mirror_azimuth : bool
        The model's frame is the radar frame mirrored left-right (module docstring): the CFAR
        points are mirrored (``y -> -y``) before they are placed in the grid.

    Returns
    -------
    torch.Tensor, ``(min(n, P_in) + max(0, n - P_in), 3)`` float32
        Normalised coordinates (:func:`~radarpc.rald.frustum.normalize`); a guided query lies within
        ``spread`` cells of a CFAR point on every axis and inside the grid. Empty (``(0, 3)``)
        when no CFAR point lies in the grid.
    """
    q = spread_queries(_cfar_in_grid(cfar_points, grid, mirror_azimuth), int(n), grid, spread, generator)   # (n', 3)
    return normalize(grid, q).to(torch.float32)


def model_frame(xyz: torch.Tensor, mirror_azimuth: bool) -> torch.Tensor:
    """Cartesian points ``(..., 3)`` of the radar frame in the model's frame (module docstring):
    unchanged, or ``y`` negated with ``mirror_azimuth``. The map is its own inverse."""
    return xyz * xyz.new_tensor((1.0, -1.0, 1.0)) if mirror_azimuth else xyz


def _cfar_in_grid(cfar_points, grid: Grid, mirror_azimuth: bool = False) -> torch.Tensor:
    """The CFAR points inside the grid, in the grid's coordinates ``(P_in, 3)`` float64 (CPU), taken
    to the model's frame first (:func:`model_frame`)."""
    pts = cfar_points if isinstance(cfar_points, torch.Tensor) else torch.from_numpy(np.asarray(cfar_points))
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"cfar_points must be (P, 3) Cartesian points, got shape {tuple(pts.shape)}")
    pts = model_frame(pts.detach().cpu().to(torch.float64), mirror_azimuth)
    g = grid_coords(grid, pts)                                                    # (P, 3)
    return g[in_frustum(grid, g, coords="polar")]                                 # "polar": the grid's own coordinates


# ----------------------------------------------------------------------------------------------
# Decoding and refinement
# ----------------------------------------------------------------------------------------------

def _device(module: torch.nn.Module) -> torch.device:
    return next(module.parameters()).device


def _check_eval(module: torch.nn.Module, name: str) -> None:
    if module.training:
        raise ValueError(f"{name} is in training mode (stochastic depth would randomise the result); call "
                         f".eval() on it before generating")


def _latent_tokens(ae, latents: torch.Tensor) -> torch.Tensor:
    z = latents if latents.ndim == 3 else latents[None]
    if z.shape[0] != 1:
        raise ValueError(f"decode one frame's latents at a time: (1, M, D) or (M, D), got {tuple(latents.shape)}")
    return ae.latent_tokens(z.to(_device(ae)))                                       # (1, M, C)


def _logit_function(ae, tokens: torch.Tensor, folded: bool):
    """``queries (1, Q, 3) -> logits (1, Q)`` of one frame's tokens: the autoencoder's folded
    decoder (:class:`~radarpc.models.vecset.FoldedDecoder`, built once per frame) where it has one
    and ``folded``, else :meth:`occupancy_logits` per call."""
    if folded and hasattr(ae, "folded_decoder"):
        return ae.folded_decoder(tokens)
    return lambda q: ae.occupancy_logits(tokens, q)


@torch.no_grad()
def _decode_tokens(ae, tokens: torch.Tensor, queries: torch.Tensor, chunk: int,
                   folded: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    kept, logits = [], []
    logit = _logit_function(ae, tokens, folded)
    for q in queries.split(int(chunk)):                                              # (<= chunk, 3)
        q = q.to(tokens.device, torch.float32)
        l = logit(q[None])[0]                                                        # (<= chunk,)
        keep = l > 0
        kept.append(q[keep].cpu())
        logits.append(l[keep].cpu())
    if not kept:
        return queries.new_zeros((0, 3), dtype=torch.float32).cpu(), torch.zeros(0)
    return torch.cat(kept), torch.cat(logits)


@torch.no_grad()
def decode_occupied(ae, latents: torch.Tensor, queries: torch.Tensor,
                    chunk: int = 65_536, *, folded: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The occupied queries of one frame and their logits, ``chunk`` queries per decoder call.

    Parameters
    ----------
    ae : radarpc.models.vecset.VecSetAutoencoder
        In evaluation mode.
    latents : torch.Tensor, ``(1, M, D)`` or ``(M, D)``
        One frame's latents.
    queries : torch.Tensor, ``(Q, 3)``
        Normalised coordinates (any device; moved to the autoencoder's chunk by chunk).
    chunk : int
        Queries per decoder call: the peak memory grows with it (a few ``chunk x width`` float32
        activations), the result does not change (each query's logit depends on that query alone).
    folded : bool
        Decode with the autoencoder's :meth:`~radarpc.models.vecset.VecSetAutoencoder.folded_decoder`
        (the same logits to float32 rounding, about 35 times fewer FLOPs a query at paper
        size); False: :meth:`~radarpc.models.vecset.VecSetAutoencoder.occupancy_logits` layer by layer.

    Returns
    -------
    queries : torch.Tensor, ``(K, 3)`` float32, CPU
        The queries with logit ``> 0``, in their input order.
    logits : torch.Tensor, ``(K,)`` float32, CPU
    """
    _check_eval(ae, "the autoencoder")
    if queries.ndim != 2 or queries.shape[1] != 3:
        raise ValueError(f"queries must be (Q, 3) normalised coordinates, got shape {tuple(queries.shape)}")
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    return _decode_tokens(ae, _latent_tokens(ae, latents), queries, chunk, folded)


@torch.no_grad()
def refine(ae, latents: torch.Tensor, occupied: torch.Tensor, logits: torch.Tensor, grid: Grid = RALD_GRID, *,
           n: int = 500_000, spread: int = 10, rounds: int = 1, chunk: int = 65_536,
           generator: torch.Generator | None = None, tokens: torch.Tensor | None = None,
           folded: bool = True) -> tuple[torch.Tensor, torch.Tensor, int]:
    """RaLD's refinement: more queries around the occupied ones, the occupied of those added.

    Each round: with ``K = |occupied| >= n`` the first ``n`` occupied points remain; otherwise
    ``n - K`` copies of occupied points moved by up to ``spread`` cells per axis
    (:func:`spread_queries`) are decoded and the occupied ones appended.

    Parameters
    ----------
    ae, latents, chunk
        As :func:`decode_occupied`.
    occupied : torch.Tensor, ``(K, 3)``
        Normalised occupied queries (from :func:`decode_occupied`).
    logits : torch.Tensor, ``(K,)``
        Their logits.
    grid : FrustumGrid or CartesianGrid
    n, spread, rounds : int
        Queries per round (official 500,000), largest move in cells (official 10), rounds
        (official 1).
    generator : torch.Generator, optional
        Draws the moved copies (CPU).
    tokens : torch.Tensor, optional
        ``ae.latent_tokens(latents)`` when the caller has them already.
    folded : bool
        As :func:`decode_occupied`.

    Returns
    -------
    occupied : torch.Tensor, ``(K', 3)`` float32, CPU
    logits : torch.Tensor, ``(K',)`` float32, CPU
    n_decoded : int
        Queries decoded by the refinement.
    """
    _check_eval(ae, "the autoencoder")
    if tokens is None:
        tokens = _latent_tokens(ae, latents)
    occ, lg = occupied.detach().cpu().to(torch.float32), logits.detach().cpu().to(torch.float32)
    n_decoded = 0
    for _ in range(int(rounds)):
        k = occ.shape[0]
        if k == 0:
            break
        if k >= n:
            occ, lg = occ[:n], lg[:n]
            continue
        new = _moved_copies(denormalize(grid, occ.to(torch.float64)), n - k, grid, spread, generator)   # (n - k, 3)
        q = normalize(grid, new).to(torch.float32)
        kept, kept_logits = _decode_tokens(ae, tokens, q, chunk, folded)
        n_decoded += q.shape[0]
        occ, lg = torch.cat((occ, kept)), torch.cat((lg, kept_logits))
    return occ, lg, n_decoded


# ----------------------------------------------------------------------------------------------
# A frame's cloud
# ----------------------------------------------------------------------------------------------

@dataclass
class GeneratedCloud:
    """One frame's generated cloud and how it was made."""

    points: np.ndarray                                           # (N, 3) float32, Cartesian metres, radar frame
    seconds: dict[str, float] = field(default_factory=dict)      # per stage of STAGES
    n_queries: dict[str, int] = field(default_factory=dict)      # decoded: random, guided, refinement
    n_cfar_points: int = 0                                       # CFAR points inside the grid
    n_occupied: int = 0                                          # occupied queries before the refinement
    seed: int = 0                                                # the frame's seed
    stages: tuple[str, ...] = STAGES                             # the timed stages, in order (the record's columns)
    latents: torch.Tensor | None = None                          # (M, D) float32 CPU: the sampled latents

    @property
    def empty(self) -> bool:
        """No query decoded as occupied: the cloud has no point."""
        return self.points.shape[0] == 0

    @property
    def warning(self) -> str | None:
        """A one-line warning for an empty cloud (None otherwise)."""
        if not self.empty:
            return None
        n = sum(self.n_queries.values())
        return (f"empty decoding: none of the {n:,} queries decoded as occupied (logit > 0), the cloud has no "
                f"point (seed {self.seed}, {self.n_cfar_points:,} CFAR points in the grid)")

    def record(self) -> dict[str, object]:
        """The flat per-frame record (for a CSV): counts, seed, seconds per stage."""
        out: dict[str, object] = {"n_points": int(self.points.shape[0]), "empty": self.empty, "seed": self.seed,
                                  "n_cfar_points": self.n_cfar_points, "n_occupied": self.n_occupied}
        out.update({f"queries_{k}": v for k, v in self.n_queries.items()})
        out.update({f"seconds_{k}": self.seconds.get(k, 0.0) for k in self.stages})
        return out


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _check_frames(cubes: torch.Tensor, cfar_points: Sequence, seeds: Sequence[int]) -> None:
    if cubes.ndim != 4:
        raise ValueError(f"cubes must be (B, R, A, E) normalised intensity cubes, got shape {tuple(cubes.shape)}")
    if len(cfar_points) != cubes.shape[0] or len(seeds) != cubes.shape[0]:
        raise ValueError(f"{cubes.shape[0]} cubes need as many CFAR point sets and seeds, got {len(cfar_points)} "
                         f"and {len(seeds)}")


@torch.no_grad()
def generate_clouds(ae, dit, cubes: torch.Tensor, cfar_points: Sequence, cfg: GenerationConfig,
                    seeds: Sequence[int], *, grid: Grid = RALD_GRID,
                    mirror_azimuth: bool = False) -> list[GeneratedCloud]:
    """Clouds of a batch of frames (see the module docstring): one sampler run for the batch, then
    each frame's decoding and refinement.

    Parameters
    ----------
    ae : radarpc.models.vecset.VecSetAutoencoder
        The autoencoder whose latents ``dit`` generates, in evaluation mode.
    dit : radarpc.models.latent_dit.LatentDiT
        In evaluation mode.
    cubes : torch.Tensor, ``(B, R, A, E)``
        Radar cubes as the diffusion model reads them (RaLD: intensity clipped to 0..45 dB and
        divided by 45, 128 x 64 x 32); moved to the model's device.
    cfar_points : sequence of B arrays ``(P_b, 3)``
        Each frame's CFAR points, Cartesian metres in the radar frame (may be empty).
    cfg : GenerationConfig
    seeds : sequence of B ints
        Each frame's seed (:func:`frame_seed`): its initial noise and its queries. A frame's cloud
        does not depend on the other frames of the batch.
    grid : FrustumGrid or CartesianGrid
        The occupancy grid the autoencoder was trained on (default RaLD's frustum grid).
    mirror_azimuth : bool
        The autoencoder's frame is the radar frame mirrored left-right (module docstring; the
        official checkpoints'): CFAR points go in mirrored, the clouds come out in the radar frame.

    Returns
    -------
    list of GeneratedCloud
        Per frame; ``seconds["condition"]`` and ``seconds["sampler"]`` are the batch's divided by
        ``B``, decoding and refinement the frame's own. An empty cloud is flagged
        (:attr:`GeneratedCloud.empty`, :attr:`GeneratedCloud.warning`), never dropped.
    """
    _check_eval(ae, "the autoencoder")
    _check_eval(dit, "the diffusion model")
    _check_frames(cubes, cfar_points, seeds)
    b = cubes.shape[0]
    dev = _device(dit)

    _sync(dev)
    t0 = time.perf_counter()
    condition = dit.encode_radar(cubes.to(dev, torch.float32))                            # (B, T, W)
    _sync(dev)
    t1 = time.perf_counter()
    rnd = SeededNoise([int(s) for s in seeds], dev)
    noise = rnd.randn((b, dit.cfg.n_latents, dit.cfg.latent_dim))                         # (B, M, D)
    latents = edm_sampler(dit, noise, condition, randn_like=rnd.randn_like, **cfg.sampler())   # (B, M, D)
    _sync(dev)
    t2 = time.perf_counter()

    out = []
    for i in range(b):
        out.append(decode_cloud(ae, latents[i:i + 1], cfar_points[i], cfg, int(seeds[i]), grid=grid,
                                mirror_azimuth=mirror_azimuth))
        out[-1].latents = latents[i].detach().to("cpu", torch.float32)
        out[-1].seconds = {"condition": (t1 - t0) / b, "sampler": (t2 - t1) / b, **out[-1].seconds}
    return out


@torch.no_grad()
def decode_cloud(ae, latents: torch.Tensor, cfar_points, cfg: GenerationConfig, seed: int, *,
                 grid: Grid = RALD_GRID, mirror_azimuth: bool = False) -> GeneratedCloud:
    """One frame's cloud from its latents: steps 3 to 5 of the module docstring (random and guided
    queries decoded in chunks, the refinement, Cartesian points in the radar frame).

    Parameters
    ----------
    ae : radarpc.models.vecset.VecSetAutoencoder
        In evaluation mode.
    latents : torch.Tensor, ``(1, M, D)`` or ``(M, D)``
        The frame's latents (sampled by the diffusion model, or encoded from its LiDAR:
        :mod:`radarpc.rald.reconstruct`).
    cfar_points : array-like, ``(P, 3)``
        Cartesian guide points of the frame, radar frame.
    cfg : GenerationConfig
        Its query counts, spreads, refinement and chunk (the sampler's fields are not read).
    seed : int
        The frame's seed (:func:`frame_seed`): the queries' draws.
    grid, mirror_azimuth
        As :func:`generate_clouds`.

    Returns
    -------
    GeneratedCloud
        With ``seconds["decoding"]`` and ``seconds["refinement"]``.
    """
    _check_eval(ae, "the autoencoder")
    dev = _device(ae)
    gen = _query_generator(seed)
    _sync(dev)
    t0 = time.perf_counter()
    q_random = random_queries(cfg.random_queries, gen)                                    # (n_r, 3)
    seeds = _cfar_in_grid(cfar_points, grid, mirror_azimuth)                              # (P_in, 3) model frame
    q_guided = normalize(grid, spread_queries(seeds, cfg.guided_queries, grid, cfg.guided_spread,
                                              gen)).to(torch.float32)                    # (n_g, 3)
    tokens = ae.latent_tokens(latents.to(dev))                                            # (1, M, C)
    occ, logits = _decode_tokens(ae, tokens, torch.cat((q_random, q_guided)), cfg.chunk,
                                 cfg.folded_decoder)                                    # (K, 3), (K,)
    _sync(dev)
    t1 = time.perf_counter()
    n_first = occ.shape[0]
    occ, logits, n_refine = refine(ae, latents, occ, logits, grid, n=cfg.refine_queries, spread=cfg.refine_spread,
                                   rounds=cfg.refine_rounds, chunk=cfg.chunk, generator=gen, tokens=tokens,
                                   folded=cfg.folded_decoder)
    _sync(dev)
    t2 = time.perf_counter()
    xyz = model_frame(cartesian_points(grid, occ.to(torch.float64)), mirror_azimuth)     # (N, 3) radar frame
    points = xyz.to(torch.float32).numpy()
    return GeneratedCloud(points=np.ascontiguousarray(points, dtype=np.float32),
                          seconds={"decoding": t1 - t0, "refinement": t2 - t1},
                          n_queries={"random": int(q_random.shape[0]), "guided": int(q_guided.shape[0]),
                                     "refinement": int(n_refine)},
                          n_cfar_points=int(seeds.shape[0]), n_occupied=int(n_first), seed=seed)


def generate_cloud(ae, dit, cube: torch.Tensor, cfar_points, cfg: GenerationConfig, seed: int, *,
                   grid: Grid = RALD_GRID, mirror_azimuth: bool = False) -> GeneratedCloud:
    """One frame's cloud (:func:`generate_clouds` of a batch of one).

    Parameters
    ----------
    cube : torch.Tensor, ``(R, A, E)`` or ``(1, R, A, E)``
        The radar cube as the diffusion model reads it.
    cfar_points : array-like, ``(P, 3)``
        Cartesian CFAR points of the frame.
    seed : int
        The frame's seed (:func:`frame_seed`).
    grid, mirror_azimuth
        As :func:`generate_clouds`.
    """
    x = cube if cube.ndim == 4 else cube[None]
    return generate_clouds(ae, dit, x, [cfar_points], cfg, [int(seed)], grid=grid, mirror_azimuth=mirror_azimuth)[0]
