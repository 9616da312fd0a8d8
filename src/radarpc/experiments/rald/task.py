"""RaLD's two stages as tasks of the training loop: datasets, collate, loss and validation.

Both stages read a ColoRadar-layout root (:class:`radarpc.data.coloradar.ColoRadar`: real or
simulated) split by runs, and the LiDAR of each frame in the radar frame, cropped to the radar's
field of view.

**Stage 1**, :class:`AutoencoderTask` (as RaLD's ``engine_ae.py`` with its dataset's view-cone
mode):

* the LiDAR points in the model's frame (:meth:`LidarData.model_frame`: the radar frame, mirrored
  left-right with ``data.mirror_azimuth``);
* the occupancy of a frame: the cells of the partition's grid (:meth:`LidarData.grid`, RaLD's
  frustum cells or Cartesian voxels) that hold at least one of the frame's LiDAR points, all of
  them (:func:`radarpc.rald.voxels.voxelize_points`);
* the encoder's input: ``data.points`` of the LiDAR points in the model's coordinates (the grid's
  coordinates mapped to ``[-1, 1]`` per axis, :meth:`LidarData.to_model`), drawn
  without replacement (RaLD's ``sampling``); a frame with fewer points gives all of them plus
  draws with replacement up to ``data.points`` (RaLD refuses such a frame);
* the queries: ``n_occ = floor(queries * occupied_fraction)`` in occupied cells (cells drawn
  uniformly with replacement among the occupied ones), the rest in empty cells (drawn uniformly
  with replacement among the empty ones), each uniform inside its cell, labelled 1 and 0
  (:func:`radarpc.rald.frustum.sample_queries`; RaLD's ``transform_voxels_to_query_points``,
  625 of 10,000 occupied);
* the loss: ``L = 0.1 mean_{occupied} BCE + 1.0 mean_{empty} BCE + 1e-3 KL`` with the model
  config's weights (:func:`radarpc.models.vecset.occupancy_loss`, :func:`~radarpc.models.vecset.kl_divergence`);
* validation: the same kind of queries, fixed per frame, decoded from the posterior mean; per frame
  the loss, its BCE and KL terms, and with the logits thresholded at 0 the IoU of the predicted
  and true occupied queries, the accuracy and the recall (the share of occupied queries
  predicted occupied: RaLD's validation ``iou``, whose queries are all occupied), averaged over the
  frames.

**Stage 2**, :class:`DiffusionTask` (as RaLD's ``engine_generation.py``): the model is
:class:`RaldStage2`, the stage-1 autoencoder (frozen: :data:`radarpc.training.loop.FROZEN_ATTR`)
beside the diffusion model it trains.

* the input: the frame's radar cube (:meth:`radarpc.data.coloradar.ColoRadar.cube`) as RaLD
  normalises it, intensity clipped to ``[0, 45]`` dB, divided by 45, then upsampled to the model's
  ``radar_shape`` (:func:`radarpc.data.coloradar.rald_intensity`);
* the target: a sample ``z = mu + sigma eps`` of the frozen autoencoder's posterior for the frame's
  LiDAR points (resampled as in stage 1, with the stage-1 run's ``data``), as the official
  ``vae.encode`` returns it;
* the loss: EDM's (:func:`radarpc.models.edm.edm_loss`), the radar condition encoded once per item
  and step;
* validation: the same loss on the validation frames; the loop seeds the global RNG before each
  validation, so the noise levels, the noise and the posterior samples are the same every time.

Every random draw of an item (the points kept, the queries) comes from a generator seeded by
``(train.seed, epoch, index)`` for training items and ``(train.seed, index)`` for validation
items: an item is the same whatever the loader's worker processes, and a resumed run draws what
an uninterrupted one does.
"""
from __future__ import annotations

import copy
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from radarpc.data.coloradar import ColoRadar, rald_intensity
from radarpc.experiments.rald.config import AutoencoderExperiment, DiffusionExperiment, LidarData
from radarpc.models.edm import edm_loss, edm_loss_weight, edm_sigma_steps
from radarpc.models.latent_dit import LatentDiT
from radarpc.models.vecset import VecSetAutoencoder, kl_divergence, occupancy_loss
from radarpc.rald.frustum import sample_queries
from radarpc.rald.voxels import model_coords, voxelize_points

__all__ = ["resample_points", "AutoencoderBatch", "DiffusionBatch", "AutoencoderFrames", "DiffusionFrames",
           "RaldStage2", "AutoencoderTask", "DiffusionTask", "occupancy_scores", "evaluate_autoencoder",
           "evaluate_diffusion", "check_latents_match", "radar_swap_pairs", "RADAR_SWAP_FRAMES"]

_TRAIN_STREAM = 0x7472                     # "tr": the draws of training items
_VAL_STREAM = 0x76616C                     # "val": the draws of validation items


def _generator(seed: int, stream: int, epoch: int, index: int) -> torch.Generator:
    state = np.random.SeedSequence([int(seed), stream, int(epoch), int(index)]).generate_state(2, np.uint32)
    return torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))


def resample_points(points: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``n`` of the points ``(M, 3)``: drawn without replacement when ``M >= n`` (RaLD's sampling),
    else all ``M`` in random order followed by ``n - M`` drawn with replacement.

    Raises
    ------
    ValueError
        No point, or ``n < 1``.
    """
    m = int(points.shape[0])
    if m == 0 or n < 1:
        raise ValueError(f"resample_points: need at least one point and n >= 1, got {m} points and n={n}")
    perm = torch.randperm(m, generator=generator)
    if m >= n:
        return points[perm[:n]]
    extra = torch.randint(0, m, (n - m,), generator=generator)
    return points[torch.cat((perm, extra))]


# ---- batches ----------------------------------------------------------------------------------------

@dataclass
class AutoencoderBatch:
    """Stage 1's collated batch: encoder points ``(B, N, 3)``, queries ``(B, Q, 3)`` (both in the
    model's ``[-1, 1]`` coordinates) and their labels ``(B, Q)`` (bool, True: occupied)."""

    points: torch.Tensor
    queries: torch.Tensor
    occupied: torch.Tensor

    def to(self, device: torch.device) -> "AutoencoderBatch":
        return AutoencoderBatch(self.points.to(device), self.queries.to(device), self.occupied.to(device))


@dataclass
class DiffusionBatch:
    """Stage 2's collated batch: normalised radar cubes ``(B, R, A, E)`` and the LiDAR points the
    frozen autoencoder encodes ``(B, N, 3)`` (model coordinates)."""

    radar: torch.Tensor
    points: torch.Tensor

    def to(self, device: torch.device) -> "DiffusionBatch":
        return DiffusionBatch(self.radar.to(device), self.points.to(device))


def _collate_autoencoder(items: list) -> AutoencoderBatch:
    return AutoencoderBatch(*(torch.stack(t) for t in zip(*items)))


def _collate_diffusion(items: list) -> DiffusionBatch:
    return DiffusionBatch(*(torch.stack(t) for t in zip(*items)))


# ---- datasets ---------------------------------------------------------------------------------------

class _Frames(Dataset):
    """The paired frames of a split with the seeding of the module docstring."""

    def __init__(self, root: str | os.PathLike, split: str, seed: int, training: bool, data: LidarData,
                 scenes: tuple[str, ...] | None = None):
        self.frames = ColoRadar(root, split, cube_size=None, scenes=scenes)
        if len(self.frames) == 0:
            raise ValueError(f"{root}: split {split!r} has no paired radar / LiDAR frame (runs of this split"
                             + (f" and scenes {list(scenes)}" if scenes is not None else "")
                             + f": {', '.join(r.name for r in self.frames.runs) or 'none'})")
        self.data = data
        self.grid = data.grid(self.frames.fov)
        self.seed = int(seed)
        self.training = training
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.frames)

    def set_epoch(self, epoch: int) -> None:
        """Training items draw anew each epoch (validation items never change)."""
        self.epoch = int(epoch)

    def _rng(self, i: int) -> torch.Generator:
        return (_generator(self.seed, _TRAIN_STREAM, self.epoch, i) if self.training
                else _generator(self.seed, _VAL_STREAM, 0, i))

    def _lidar(self, i: int) -> torch.Tensor:
        """The frame's LiDAR points ``(M, 3)`` cropped to the field of view, in the model's frame
        (:meth:`LidarData.model_frame`: the radar frame, mirrored with ``mirror_azimuth``), metres."""
        return self.data.model_frame(torch.from_numpy(self.frames.lidar_points(i)))


class AutoencoderFrames(_Frames):
    """Stage 1's items: ``(points (N, 3), queries (Q, 3), occupied (Q,))`` of each frame of a split
    (see the module docstring)."""

    def __init__(self, root: str | os.PathLike, split: str, data: LidarData, *, seed: int = 0,
                 training: bool = True, scenes: tuple[str, ...] | None = None):
        super().__init__(root, split, seed, training, data, scenes)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        g = self._rng(i)
        xyz = self._lidar(i)                                                  # (M, 3) metres, model frame
        occ = voxelize_points(self.grid, xyz)                                 # every point's cell
        points = model_coords(self.grid, resample_points(xyz, self.data.points, g)).to(torch.float32)  # (N, 3)
        queries, occupied = sample_queries(occ, self.data.queries, self.data.occupied_fraction, generator=g)
        return points, queries, occupied                                      # (N, 3), (Q, 3), (Q,)


class DiffusionFrames(_Frames):
    """Stage 2's items: ``(radar (R, A, E), points (N, 3))`` of each frame of a split: the radar
    cube as RaLD normalises it and the LiDAR points as stage 1 (``data``) reads them."""

    def __init__(self, root: str | os.PathLike, split: str, data: LidarData, radar_shape: tuple[int, int, int],
                 max_intensity_db: float, *, seed: int = 0, training: bool = True,
                 scenes: tuple[str, ...] | None = None):
        super().__init__(root, split, seed, training, data, scenes)
        self.radar_shape = tuple(radar_shape)
        self.max_intensity_db = float(max_intensity_db)

    def radar(self, i: int) -> torch.Tensor:
        """Frame ``i``'s radar cube ``(R, A, E)`` as RaLD normalises it."""
        return rald_intensity(self.frames.cube(i), self.radar_shape, max_db=self.max_intensity_db)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        g = self._rng(i)
        radar = self.radar(i)                                                                      # (R, A, E)
        xyz = resample_points(self._lidar(i), self.data.points, g)
        return radar, model_coords(self.grid, xyz).to(torch.float32)                                # (N, 3)


# ---- stage 2's model --------------------------------------------------------------------------------

def check_latents_match(ae: VecSetAutoencoder, dit: LatentDiT, where: str) -> None:
    """Refuse a diffusion model whose latents ``(n_latents, latent_dim)`` are not the autoencoder's."""
    a, d = ae.cfg, dit.cfg
    if (a.n_latents, a.latent_dim) != (d.n_latents, d.latent_dim):
        raise ValueError(f"{where}: the diffusion model generates {d.n_latents} latents of {d.latent_dim}, but the "
                         f"autoencoder's are {a.n_latents} of {a.latent_dim}; give the diffusion model "
                         f"overrides n_latents: {a.n_latents}, latent_dim: {a.latent_dim}")


class RaldStage2(nn.Module):
    """What stage 2 trains: the diffusion model beside the frozen stage-1 autoencoder.

    ``forward(radar (B, R, A, E), points (B, N, 3))`` returns EDM's loss (a scalar) on the latents
    of ``points`` (a posterior sample of the autoencoder), conditioned on ``radar``: the loss runs
    inside ``forward`` so that DistributedDataParallel sees the whole computation.

    Its state dict holds ``autoencoder.<key>`` (:class:`~radarpc.models.vecset.VecSetAutoencoder`)
    and ``dit.<key>`` (:class:`~radarpc.models.latent_dit.LatentDiT`): a stage-2 run's
    ``best.safetensors`` is the whole pair.
    """

    frozen_submodules = ("autoencoder",)     # the loop freezes it (radarpc.training.loop.FROZEN_ATTR)
    input_kind = "radar"

    def __init__(self, autoencoder: VecSetAutoencoder, dit: LatentDiT, *, p_mean: float = -1.2,
                 p_std: float = 1.2):
        super().__init__()
        check_latents_match(autoencoder, dit, "RaldStage2")
        self.autoencoder = autoencoder
        self.dit = dit
        # the radar encoder's 3-D convolutions in channels-last layout: the same maths, and on CPUs their
        # backward pass 3-4 times faster than in the default layout (oneDNN's slow path there)
        self.dit.radar_encoder.to(memory_format=torch.channels_last_3d)
        self.p_mean = float(p_mean)          # ln(sigma) ~ N(p_mean, p_std^2) in training
        self.p_std = float(p_std)

    @torch.no_grad()
    def latents(self, points: torch.Tensor) -> torch.Tensor:
        """``z = mu + sigma eps`` ``(B, M, D)`` of the autoencoder's posterior for ``points``
        (``eps`` from the global RNG), the official training target."""
        mean, logvar = self.autoencoder.encode(points)                        # (B, M, D) each
        return self.autoencoder.sample(mean, logvar).float()                  # (B, M, D)

    def forward(self, radar: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        z = self.latents(points)                                              # (B, M, D)
        condition = self.dit.encode_radar(radar)                              # (B, T, W), once per item
        return edm_loss(self.dit, z, condition, P_mean=self.p_mean, P_std=self.p_std,
                        sigma_data=self.dit.cfg.sigma_data)

    @torch.no_grad()
    def condition_check(self, radar: torch.Tensor, other_radar: torch.Tensor, points: torch.Tensor,
                        sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-frame EDM losses ``(B,)`` of the frames' latents at noise levels ``sigma (B,)``, with
        their own radar and with ``other_radar`` (other frames' cubes), the same latents and noise:
        the difference says how much the radar condition lowers the loss, about 0 when the model
        has learned only the latents' prior. The latents and the noise come from the global RNG."""
        z = self.latents(points)                                              # (B, M, D)
        sigma = sigma.to(device=z.device, dtype=z.dtype).reshape(-1, 1, 1)    # (B, 1, 1)
        weight = edm_loss_weight(sigma, self.dit.cfg.sigma_data)             # (B, 1, 1)
        x = z + torch.randn_like(z) * sigma                                   # (B, M, D)

        def loss(cube: torch.Tensor) -> torch.Tensor:
            denoised = self.dit(x, sigma.flatten(), self.dit.encode_radar(cube))
            return (weight * (denoised - z) ** 2).mean((1, 2))                # (B,)

        return loss(radar), loss(other_radar)


# ---- validation -------------------------------------------------------------------------------------

def occupancy_scores(logits: torch.Tensor, occupied: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-frame scores ``(B,)`` of logits ``(B, Q)`` thresholded at 0 against labels ``(B, Q)``:
    ``iou = |P & O| / |P | O|`` (1 when both are empty), ``accuracy`` (share of queries right) and
    ``recall = |P & O| / |O|`` (1 when no query is occupied)."""
    pred = logits > 0
    occ = occupied.to(torch.bool)
    inter = (pred & occ).sum(1).double()
    union = (pred | occ).sum(1).double()
    n_occ = occ.sum(1).double()
    return {"iou": torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(inter)),
            "accuracy": (pred == occ).double().mean(1),
            "recall": torch.where(n_occ > 0, inter / n_occ.clamp_min(1), torch.ones_like(inter))}


@torch.no_grad()
def evaluate_autoencoder(model: nn.Module, batches: Iterable[AutoencoderBatch], device: torch.device
                         ) -> dict[str, float]:
    """Stage 1's validation metrics (:data:`~radarpc.experiments.rald.config.AUTOENCODER_METRICS`),
    each the mean over frames of its per-frame value; the latents are the posterior means."""
    cfg = model.cfg
    sums: dict[str, float] = {}
    n = 0
    for batch in batches:
        batch = batch.to(device)
        mean, logvar = model.encode(batch.points)                             # (B, M, D) each
        logits = model.decode(mean, batch.queries).float()                   # (B, Q)
        kl = kl_divergence(mean.float(), logvar.float())                      # (B,)
        bce = torch.stack([occupancy_loss(logits[b:b + 1], batch.occupied[b:b + 1], cfg.occupied_weight,
                                          cfg.empty_weight) for b in range(logits.shape[0])])   # (B,)
        per_frame = {"loss": bce + cfg.kl_weight * kl, "bce": bce, "kl": kl,
                     **occupancy_scores(logits, batch.occupied)}
        for k, v in per_frame.items():
            sums[k] = sums.get(k, 0.0) + float(v.double().sum())
        n += logits.shape[0]
    return {k: v / max(n, 1) for k, v in sums.items()}


RADAR_SWAP_FRAMES = 72
"""Validation frames of stage 2's radar check (:func:`radar_swap_pairs`): four at each of the
sampler's 18 noise levels."""


def radar_swap_pairs(n: int, count: int = RADAR_SWAP_FRAMES) -> list[tuple[int, int]]:
    """``(frame, other frame)`` index pairs for stage 2's radar check: up to ``count`` frames evenly
    spread over ``n``, each with the frame ``n // 2`` positions on (modulo ``n``), in a split ordered
    by run another run's, so another place's radar."""
    if n < 2:
        return []
    frames = np.unique(np.linspace(0, n - 1, min(count, n)).round().astype(int))
    return [(int(i), int((i + n // 2) % n)) for i in frames]


@torch.no_grad()
def evaluate_diffusion(model: nn.Module, batches: Iterable[DiffusionBatch], device: torch.device,
                       swaps: Iterable[tuple[DiffusionBatch, torch.Tensor]] = ()) -> dict[str, float]:
    """Stage 2's validation (:data:`~radarpc.experiments.rald.config.DIFFUSION_METRICS`), with the
    noise of the caller's RNG state.

    ``loss``: EDM's loss over the frames of ``batches`` (their mean), noise levels drawn as in
    training. With ``swaps``, batches of frames each beside another frame's radar cube
    ``(B, R, A, E)``, the radar check at the noise levels generation visits (the Heun sampler's 18,
    :func:`~radarpc.models.edm.edm_sigma_steps`, frame ``k`` of the check at level ``k mod 18``):
    ``loss_other_radar``, the loss of those frames conditioned on the other radar, and
    ``radar_gain``, its excess over the loss of the same frames, latents, levels and noise with their
    own radar. Training's noise levels (``ln sigma ~ N(-1.2, 1.2^2)``) sit mostly where the noisy
    latents alone still tell one scene from another; the sampler's first steps do not.
    """
    stage2 = getattr(model, "module", model)                                  # a DDP wrapper's module
    total, n = 0.0, 0
    for batch in batches:
        batch = batch.to(device)
        total += float(stage2(batch.radar, batch.points)) * batch.radar.shape[0]
        n += batch.radar.shape[0]
    metrics = {"loss": total / n} if n else {}
    levels = edm_sigma_steps(device=device)[:-1]                              # (18,) without the final 0
    own_sum, other_sum, m = 0.0, 0.0, 0
    for batch, other_radar in swaps:
        batch = batch.to(device)
        k = torch.arange(m, m + batch.radar.shape[0], device=device) % len(levels)
        own, other = stage2.condition_check(batch.radar, other_radar.to(device), batch.points, levels[k])
        own_sum += float(own.double().sum())
        other_sum += float(other.double().sum())
        m += own.shape[0]
    if m:
        metrics["loss_other_radar"] = other_sum / m
        metrics["radar_gain"] = (other_sum - own_sum) / m
    return metrics


# ---- the tasks --------------------------------------------------------------------------------------

class AutoencoderTask:
    """The loop's :class:`~radarpc.training.loop.Task` for RaLD's stage 1.

    Parameters
    ----------
    cfg : AutoencoderExperiment
    data : path-like
        A ColoRadar-layout root.
    splits : (str, str)
        Training and validation splits (:func:`radarpc.data.coloradar.split_runs`).
    init : VecSetAutoencoder, optional
        Weights to start from (fine-tuning; :meth:`build_model` copies them); None: fresh ones.
    """

    def __init__(self, cfg: AutoencoderExperiment, data: str | os.PathLike,
                 splits: tuple[str, str] = ("train", "val"), init: VecSetAutoencoder | None = None) -> None:
        self.cfg = cfg
        self.root = Path(data)
        self._init = None if init is None else {k: v.detach().cpu().clone() for k, v in init.state_dict().items()}
        kw = dict(seed=cfg.train.seed, scenes=cfg.scenes)
        self.train_set = AutoencoderFrames(data, splits[0], cfg.data, training=True, **kw)
        self.val_set = AutoencoderFrames(data, splits[1], cfg.data, training=False, **kw)

    def build_model(self) -> VecSetAutoencoder:
        model = self.cfg.build_model()
        if self._init is not None:
            model.load_state_dict(self._init)
        return model

    def collate(self, items: list) -> AutoencoderBatch:
        return _collate_autoencoder(items)

    def to_device(self, batch: AutoencoderBatch, device: torch.device) -> AutoencoderBatch:
        return batch.to(device)

    def loss(self, model: nn.Module, batch: AutoencoderBatch) -> tuple[torch.Tensor, dict[str, float]]:
        mc = self.cfg.model.config
        logits, kl = model(batch.points, batch.queries)                       # (B, Q), (B,)
        bce = occupancy_loss(logits.float(), batch.occupied, mc.occupied_weight, mc.empty_weight)
        kl = kl.float().mean()
        return bce + mc.kl_weight * kl, {"bce": float(bce.detach()), "kl": float(kl.detach())}

    def evaluate(self, model: nn.Module, batches: Iterable, device: torch.device) -> dict[str, float]:
        return evaluate_autoencoder(model, batches, device)


class DiffusionTask:
    """The loop's :class:`~radarpc.training.loop.Task` for RaLD's stage 2.

    Parameters
    ----------
    cfg : DiffusionExperiment
    data : path-like
        A ColoRadar-layout root.
    ae_config : AutoencoderExperiment
        The stage-1 run's config: its ``data`` (points per frame, partition) shapes the target.
    autoencoder : VecSetAutoencoder
        The stage-1 weights; :meth:`build_model` freezes a copy beside a fresh diffusion model.
    splits : (str, str)
        Training and validation splits.
    init : LatentDiT, optional
        Diffusion weights to start from (fine-tuning; :meth:`build_model` copies them); None: fresh ones.

    Raises
    ------
    ValueError
        The diffusion model's latents are not the autoencoder's.
    """

    def __init__(self, cfg: DiffusionExperiment, data: str | os.PathLike, ae_config: AutoencoderExperiment,
                 autoencoder: VecSetAutoencoder, splits: tuple[str, str] = ("train", "val"),
                 init: LatentDiT | None = None) -> None:
        self.cfg = cfg
        self._init = None if init is None else {k: v.detach().cpu().clone() for k, v in init.state_dict().items()}
        self.ae_config = ae_config
        self.root = Path(data)
        check_latents_match(autoencoder, cfg.model.build(device="meta"), f"experiment {cfg.name!r}")
        self._autoencoder = copy.deepcopy(autoencoder).cpu()
        shape = cfg.model.config.radar_shape
        kw = dict(radar_shape=shape, max_intensity_db=cfg.radar.max_intensity_db, seed=cfg.train.seed,
                  scenes=cfg.scenes)
        self.train_set = DiffusionFrames(data, splits[0], ae_config.data, training=True, **kw)
        self.val_set = DiffusionFrames(data, splits[1], ae_config.data, training=False, **kw)

    def build_model(self) -> RaldStage2:
        dit = self.cfg.build_model()
        if self._init is not None:
            dit.load_state_dict(self._init)
        return RaldStage2(copy.deepcopy(self._autoencoder), dit, p_mean=self.cfg.loss.p_mean, p_std=self.cfg.loss.p_std)

    def collate(self, items: list) -> DiffusionBatch:
        return _collate_diffusion(items)

    def to_device(self, batch: DiffusionBatch, device: torch.device) -> DiffusionBatch:
        return batch.to(device)

    def loss(self, model: nn.Module, batch: DiffusionBatch) -> tuple[torch.Tensor, dict[str, float]]:
        return model(batch.radar, batch.points), {}

    def evaluate(self, model: nn.Module, batches: Iterable, device: torch.device) -> dict[str, float]:
        return evaluate_diffusion(model, batches, device, self._radar_swaps(batches))

    def _radar_swaps(self, batches: Iterable) -> Iterator[tuple[DiffusionBatch, torch.Tensor]]:
        """The radar check's batches (:func:`radar_swap_pairs` of the validation frames), as large as
        the loop's validation batches."""
        pairs = radar_swap_pairs(len(self.val_set))
        size = getattr(batches, "batch_size", None) or 1
        for k in range(0, len(pairs), size):
            chunk = pairs[k:k + size]
            batch = self.collate([self.val_set[i] for i, _ in chunk])
            yield batch, torch.stack([self.val_set.radar(j) for _, j in chunk])
