"""Polar PointPillars and SpectralPillars: spectral point clouds -> range-azimuth pillars -> BEV
backbone -> the common detection and freespace heads.

The seed's point-cloud branch (Sec. 3.1), in OpenPCDet's vocabulary:

1. :class:`PillarVFE` bins every point into a pillar of a polar range-azimuth grid (256 x 448 at
   full size, 0.4023 m x 0.4 deg over 0..103 m and -89.6..+89.6 deg), decorates it with its
   offsets to the pillar centre, and encodes it with a PointNet layer (linear -> BatchNorm ->
   GELU); a max over each pillar's points gives the pillar's feature.
2. :class:`PointPillarScatter` places the pillar features on the BEV pseudo-image
   ``(B, C, 256, 448)`` (empty pillars are zero).
3. :class:`BaseBEVBackbone`: strided conv blocks at 1/2, 1/4, 1/8 of the grid, each upsampled back
   to 1/2 (128 x 224, the detection map) and concatenated; thinner and deeper than OpenPCDet's
   PointPillars (channels 32/64/128 instead of 64/128/256, 6 convs per block instead of 4/6/6),
   GELU instead of ReLU, as the seed describes (about 2.4M parameters with the heads).
4. :class:`~radarpc.models.heads.DetectionHead` and :class:`~radarpc.models.heads.FreespaceHead`,
   the heads every radarpc detector shares; the size variants run the freespace head on the
   128 x 224 map and resize its logits (``freespace_upsample_logits``), half the official order's
   work, with no official weights to keep.

Point features are named in :attr:`PillarsConfig.features`, so the seed's axis ablations
(``r a e`` + ``Ae`` / ``d`` / both) and enrichment ablations are config changes:

* ``r``: range, m (``range_m``);
* ``a``: azimuth, deg, left positive (``azimuth_deg``);
* ``e``: elevation, deg (``elevation_deg``);
* ``d``: consolidated Doppler index (``doppler_bin``, the seed's ``d_j``): the radial velocity
  modulo one DDMA slot (16 bins, 2.43 m/s on ``radial``), so it wraps many times over the span;
* ``v``: radial velocity, m/s, receding positive, from the resolved full-axis Doppler bin
  (``velocity_mps``; not a seed axis: the unwrapped counterpart of ``d``);
* ``Ae``: angle-spectrum amplitude (``amplitude``, eq. 7), as ``log(1 + Ae)``;
* ``pillar_offset`` (2 values): ``r - r_c`` (m) and ``a - a_c`` (deg) to the pillar centre;
* ``sector`` (``n_sector`` values): angle-sector maxima (``sector``, eq. 10), as ``log(1 + x)``;
* ``rd_patch`` (``n_patch`` values): RD-envelope neighbourhood (``rd_patch``), as ``log(1 + x)``;
* ``neighbour``: 1 for a point added by the RD-neighbourhood enrichment (``is_neighbour``).

(fields of :class:`~radarpc.points.PointCloudBatch` in brackets.)

Amplitudes and powers span orders of magnitude, hence the ``log(1 + x)``. Every feature is then
standardised by a BatchNorm without affine parameters (its running mean and variance are the
training data's statistics, saved with the weights), so that no scale has to be set by hand.

Pillarisation is vectorised (no Python loop over points or pillars) and device-agnostic; points
outside the grid are dropped, and a pillar keeps all its points (OpenPCDet caps them at 32 to pad
a dense tensor; the max over an offset-indexed scatter needs no cap).

Size variants are plain factory functions (listed in :data:`radarpc.models.MODELS`): :func:`polar_pointpillars`
and :func:`spectralpillars` (full size), their ``_s`` variants for ``radial-s``, and
:func:`pillars_tiny` for tests.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models.heads import DETECTION_SHAPE, FREESPACE_SHAPE, DetectionHead, FreespaceHead, HeadOutput
from radarpc.points import PointCloudBatch, offset2batch

__all__ = [
    "POINT_FEATURES",
    "LOG_FEATURES",
    "PillarsConfig",
    "PointPillars",
    "PillarVFE",
    "PointPillarScatter",
    "BaseBEVBackbone",
    "pillar_coords",
    "point_features",
    "polar_pointpillars",
    "spectralpillars",
    "polar_pointpillars_s",
    "spectralpillars_s",
    "pillars_tiny",
]

POINT_FEATURES: tuple[str, ...] = ("r", "a", "e", "d", "v", "Ae", "pillar_offset", "sector", "rd_patch",
                                   "neighbour")
"""Every point feature a pillar model can take (see the module docstring)."""
LOG_FEATURES: tuple[str, ...] = ("Ae", "sector", "rd_patch")
"""Amplitude and power features, which enter as ``log(1 + x)``."""

RANGE_MAX_M = DETECTION_SHAPE[0] * 4 * 0.201171875   # 103.0 m: the detection map's 128 rows of 0.8047 m
AZIMUTH_MAX_DEG = DETECTION_SHAPE[1] / 2 * 0.8       # 89.6 deg: its 224 columns of 0.8 deg


# ----------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PillarsConfig:
    """A polar PointPillars / SpectralPillars model, whole.

    The BEV grid is ``grid[0]`` range cells over ``[0, range_max_m)`` by ``grid[1]`` azimuth cells
    over ``[-azimuth_max_deg, azimuth_max_deg)``; the backbone's first stride brings it to the
    128 x 224 detection map (``grid = (128 * s, 224 * s)`` with ``s = layer_strides[0]``).
    """

    features: tuple[str, ...] = ("r", "a", "e", "d", "Ae", "pillar_offset")   # point features, in order
    n_sector: int = 32                                   # width of "sector" (n_az_sec * n_el_sec)
    n_patch: int = 9                                     # width of "rd_patch" (n * n)
    grid: tuple[int, int] = (256, 448)                   # pillars: range cells, azimuth cells
    range_max_m: float = RANGE_MAX_M                     # far edge of the grid
    azimuth_max_deg: float = AZIMUTH_MAX_DEG             # the grid spans +-azimuth_max_deg
    pfn_channels: int = 64                               # PointNet width = pseudo-image channels
    layer_nums: tuple[int, ...] = (5, 5, 5)              # convs after each block's strided conv
    layer_strides: tuple[int, ...] = (2, 2, 2)           # stride of each block's first conv
    num_filters: tuple[int, ...] = (32, 64, 128)         # channels of each block
    upsample_strides: tuple[int, ...] = (1, 2, 4)        # each block's output back to block 0's scale
    num_upsample_filters: tuple[int, ...] = (128, 64, 64)   # their channels; the sum feeds the heads
    detection_widths: tuple[int, int] = (144, 96)        # DetectionHead conv widths (the official head's)
    freespace: bool = True                               # with the freespace head
    freespace_widths: tuple[int, int] = (128, 64)        # FreespaceHead block widths (the official head's)
    freespace_upsample_logits: bool = False              # FreespaceHead on the 128 x 224 map, logits resized
                                                         # (the size variants' choice; False: the official order)

    def __post_init__(self) -> None:
        feats = tuple(self.features.split(",")) if isinstance(self.features, str) else tuple(self.features)
        feats = tuple(str(f).strip() for f in feats)
        object.__setattr__(self, "features", feats)
        unknown = [f for f in feats if f not in POINT_FEATURES]
        if unknown:
            raise ValueError(f"PillarsConfig.features: unknown feature(s) {unknown}; known: {list(POINT_FEATURES)}")
        if not feats:
            raise ValueError(f"PillarsConfig.features: give at least one of {list(POINT_FEATURES)}")
        if len(set(feats)) != len(feats):
            raise ValueError(f"PillarsConfig.features: each feature may be given once, got {list(feats)}")
        for k in ("grid", "layer_nums", "layer_strides", "num_filters", "upsample_strides", "num_upsample_filters",
                  "detection_widths", "freespace_widths"):
            object.__setattr__(self, k, tuple(int(v) for v in getattr(self, k)))
        for k in ("freespace", "freespace_upsample_logits"):
            if not isinstance(getattr(self, k), bool):
                raise ValueError(f"PillarsConfig.{k} must be true or false, got {getattr(self, k)!r}")
        for k in ("n_sector", "n_patch", "pfn_channels"):
            if int(getattr(self, k)) < 1:
                raise ValueError(f"PillarsConfig.{k} must be >= 1, got {getattr(self, k)}")
        for k in ("detection_widths", "freespace_widths"):
            if len(getattr(self, k)) != 2 or min(getattr(self, k)) < 1:
                raise ValueError(f"PillarsConfig.{k} must be two positive channel counts, got {getattr(self, k)}")
        if len(self.grid) != 2 or min(self.grid) < 1:
            raise ValueError(f"PillarsConfig.grid must be two positive cell counts (range, azimuth), got {self.grid}")
        if not (self.range_max_m > 0 and 0 < self.azimuth_max_deg <= 180):
            raise ValueError(f"PillarsConfig: range_max_m must be > 0 and azimuth_max_deg in (0, 180], "
                             f"got {self.range_max_m}, {self.azimuth_max_deg}")
        n = len(self.layer_nums)
        lists = {k: getattr(self, k) for k in ("layer_strides", "num_filters", "upsample_strides",
                                               "num_upsample_filters")}
        if n == 0 or any(len(v) != n for v in lists.values()):
            raise ValueError(f"PillarsConfig: layer_nums, layer_strides, num_filters, upsample_strides and "
                             f"num_upsample_filters need one entry per block, got {self.layer_nums} and {lists}")
        if min(self.layer_strides + self.num_filters + self.upsample_strides + self.num_upsample_filters) < 1 \
                or min(self.layer_nums) < 0:
            raise ValueError(f"PillarsConfig: strides and channels must be >= 1 and layer_nums >= 0, got "
                             f"{self.layer_nums} and {lists}")
        total = 1
        for s, u in zip(self.layer_strides, self.upsample_strides):
            total *= s
            if total != self.layer_strides[0] * u:
                raise ValueError(f"PillarsConfig: block strides {self.layer_strides} and upsample strides "
                                 f"{self.upsample_strides} must bring every block back to the first block's scale")
        if any(g % total for g in self.grid):
            raise ValueError(f"PillarsConfig: grid {self.grid} is not divisible by the blocks' total stride {total}")
        s0 = self.layer_strides[0]
        want = (DETECTION_SHAPE[0] * s0, DETECTION_SHAPE[1] * s0)
        if self.grid != want:
            raise ValueError(f"PillarsConfig: grid {self.grid} with first stride {s0} does not give the "
                             f"{DETECTION_SHAPE[0]} x {DETECTION_SHAPE[1]} detection map; use grid {want}")

    @property
    def cell(self) -> tuple[float, float]:
        """Pillar size: (range m, azimuth deg)."""
        return self.range_max_m / self.grid[0], 2 * self.azimuth_max_deg / self.grid[1]

    @property
    def in_channels(self) -> int:
        """Width of the decorated point feature vector."""
        width = {"pillar_offset": 2, "sector": self.n_sector, "rd_patch": self.n_patch}
        return sum(width.get(f, 1) for f in self.features)

    @property
    def out_channels(self) -> int:
        """Channels of the backbone's 128 x 224 map (the heads' input)."""
        return sum(self.num_upsample_filters)


# ----------------------------------------------------------------------------------------------
# Model
# ----------------------------------------------------------------------------------------------

class PointPillars(nn.Module):
    """Polar PointPillars (SpectralPillars with the enrichment features).

    ``forward(points)`` takes an offset-batched :class:`~radarpc.points.PointCloudBatch` of ``B``
    frames and returns a :class:`~radarpc.models.heads.HeadOutput`: ``detection``
    ``(B, 3, 128, 224)`` (probability, range and azimuth offsets) and ``freespace``
    ``(B, 1, 256, 224)`` logits (None without the freespace head).
    """

    input_kind = "points"                   # forward takes a PointCloudBatch

    def __init__(self, cfg: PillarsConfig):
        super().__init__()
        self.cfg = cfg
        self.vfe = PillarVFE(cfg)
        self.scatter = PointPillarScatter(cfg)
        self.backbone = BaseBEVBackbone(cfg)
        self.detection_head = DetectionHead(cfg.out_channels, widths=cfg.detection_widths)
        self.freespace_head = (FreespaceHead(cfg.out_channels, FREESPACE_SHAPE, cfg.freespace_widths,
                                             upsample_logits=cfg.freespace_upsample_logits)
                               if cfg.freespace else None)

    def bev(self, points: PointCloudBatch) -> torch.Tensor:
        """The backbone's range-azimuth map ``(B, out_channels, 128, 224)``."""
        pillar_features, coords = self.vfe(points)                    # (P, C), (P, 3)
        canvas = self.scatter(pillar_features, coords, len(points))   # (B, C, 256, 448)
        return self.backbone(canvas)                                  # (B, C_out, 128, 224)

    def forward(self, points: PointCloudBatch) -> HeadOutput:
        x = self.bev(points)
        det = self.detection_head(x)                                  # (B, 3, 128, 224)
        free = self.freespace_head(x) if self.freespace_head is not None else None   # (B, 1, 256, 224)
        return HeadOutput(det, free)


# ----------------------------------------------------------------------------------------------
# Pillarisation and the pillar encoder
# ----------------------------------------------------------------------------------------------

def pillar_coords(points: PointCloudBatch, cfg: PillarsConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Pillar of every point: ``i_r = floor(r / dr)``, ``i_a = floor((a + a_max) / da)``.

    Returns
    -------
    keep : BoolTensor ``(N,)``
        Points inside the grid (``0 <= r < range_max_m``, ``|a| < azimuth_max_deg``); the others
        belong to no pillar.
    coords : LongTensor ``(N_keep, 3)``
        ``(frame, i_r, i_a)`` of the kept points, in point order.
    """
    dr, da = cfg.cell
    i_r = torch.floor(points.range_m / dr).long()                                  # (N,)
    i_a = torch.floor((points.azimuth_deg + cfg.azimuth_max_deg) / da).long()      # (N,)
    keep = (i_r >= 0) & (i_r < cfg.grid[0]) & (i_a >= 0) & (i_a < cfg.grid[1])
    b = offset2batch(points.offset)                                                # (N,)
    return keep, torch.stack([b[keep], i_r[keep], i_a[keep]], dim=1)


def point_features(points: PointCloudBatch, keep: torch.Tensor, coords: torch.Tensor,
                   cfg: PillarsConfig) -> torch.Tensor:
    """The decorated features ``(N_keep, cfg.in_channels)`` of the kept points, in
    ``cfg.features`` order (before standardisation).

    Raises
    ------
    ValueError
        A selected enrichment is missing from ``points`` or has another width than the config's.
    """
    dr, da = cfg.cell
    cols = []
    for name in cfg.features:
        if name == "pillar_offset":
            r_c = (coords[:, 1].to(points.range_m.dtype) + 0.5) * dr               # pillar centre
            a_c = (coords[:, 2].to(points.azimuth_deg.dtype) + 0.5) * da - cfg.azimuth_max_deg
            cols += [points.range_m[keep] - r_c, points.azimuth_deg[keep] - a_c]
            continue
        if name in ("sector", "rd_patch"):
            x = getattr(points, name)
            width = cfg.n_sector if name == "sector" else cfg.n_patch
            if x is None:
                raise ValueError(f"the model takes the point feature {name!r} but the point cloud has none "
                                 f"(make the store with the matching enrichment, or drop {name!r} from features)")
            if x.shape[1] != width:
                raise ValueError(f"point feature {name!r} has width {x.shape[1]} but the model was built for "
                                 f"{width} (PillarsConfig.n_{'sector' if name == 'sector' else 'patch'})")
            cols += list(torch.log1p(x[keep]).unbind(1))
            continue
        x = {"r": points.range_m, "a": points.azimuth_deg, "e": points.elevation_deg, "d": points.doppler_bin,
             "v": points.velocity_mps, "Ae": points.amplitude, "neighbour": points.is_neighbour}[name][keep].to(points.range_m.dtype)
        cols.append(torch.log1p(x) if name in LOG_FEATURES else x)
    return torch.stack(cols, dim=1)                                                # (N_keep, F)


class PillarVFE(nn.Module):
    """Pillar feature net: points -> pillar features.

    Each kept point's decorated features (:func:`point_features`) are standardised (BatchNorm,
    no affine), encoded by one PointNet layer ``GELU(BN(W x))``, and max-pooled over its pillar.

    ``forward(points)`` returns ``(pillar_features (P, C), coords (P, 3))`` with ``coords``
    ``(frame, i_r, i_a)`` of each non-empty pillar, ``C = cfg.pfn_channels``.
    """

    def __init__(self, cfg: PillarsConfig):
        super().__init__()
        self.cfg = cfg
        self.input_norm = nn.BatchNorm1d(cfg.in_channels, affine=False)
        self.linear = nn.Linear(cfg.in_channels, cfg.pfn_channels, bias=False)
        self.norm = nn.BatchNorm1d(cfg.pfn_channels)

    def forward(self, points: PointCloudBatch) -> tuple[torch.Tensor, torch.Tensor]:
        keep, coords = pillar_coords(points, self.cfg)                       # (N,), (N', 3)
        x = point_features(points, keep, coords, self.cfg)                   # (N', F)
        x = F.gelu(_norm(self.norm, self.linear(_norm(self.input_norm, x))))   # (N', C)
        # one pillar per distinct (frame, i_r, i_a); the max over its points is its feature
        g0, g1 = self.cfg.grid
        key = (coords[:, 0] * g0 + coords[:, 1]) * g1 + coords[:, 2]         # (N',)
        pillars, inverse = torch.unique(key, return_inverse=True)            # (P,), (N',)
        feats = x.new_zeros(pillars.numel(), x.shape[1]).scatter_reduce(
            0, inverse[:, None].expand_as(x), x, reduce="amax", include_self=False)   # (P, C)
        pillar_xy = torch.stack([pillars // (g0 * g1), pillars // g1 % g0, pillars % g1], dim=1)   # (P, 3)
        return feats, pillar_xy


def _norm(bn: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``bn(x)`` over points, using the running statistics when a training batch holds fewer than
    two points (batch statistics need two; a batch of empty frames holds none)."""
    if isinstance(bn, nn.BatchNorm1d) and bn.training and x.shape[0] < 2:
        return F.batch_norm(x, bn.running_mean, bn.running_var, bn.weight, bn.bias, False, 0.0, bn.eps)
    return bn(x)


class PointPillarScatter(nn.Module):
    """Pillar features -> BEV pseudo-image ``(B, C, grid[0], grid[1])``; cells without a pillar are 0.

    The canvas is laid out channels-last (each cell's ``C`` features contiguous), the layout the
    CPU convolutions prefer; its shape and values are those of a contiguous ``(B, C, H, W)`` tensor.
    """

    def __init__(self, cfg: PillarsConfig):
        super().__init__()
        self.grid = cfg.grid
        self.channels = cfg.pfn_channels

    def forward(self, pillar_features: torch.Tensor, coords: torch.Tensor, batch_size: int) -> torch.Tensor:
        g0, g1 = self.grid
        canvas = pillar_features.new_zeros(batch_size * g0 * g1, self.channels)               # (B H W, C)
        canvas.index_copy_(0, (coords[:, 0] * g0 + coords[:, 1]) * g1 + coords[:, 2], pillar_features)
        return canvas.view(batch_size, g0, g1, self.channels).permute(0, 3, 1, 2)            # (B, C, H, W)


# ----------------------------------------------------------------------------------------------
# BEV backbone
# ----------------------------------------------------------------------------------------------

def _conv_bn_gelu(c_in: int, c_out: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.GELU()]


class BaseBEVBackbone(nn.Module):
    """Multi-scale BEV backbone: ``len(layer_nums)`` blocks, each a strided conv then
    ``layer_nums[i]`` convs (3 x 3, BN, GELU); each block's output is upsampled to the first
    block's scale (transposed conv, kernel = stride) and the results are concatenated.

    Shapes: ``(B, pfn_channels, H, W)`` -> ``(B, sum(num_upsample_filters), H / s0, W / s0)``.
    """

    def __init__(self, cfg: PillarsConfig):
        super().__init__()
        c_in = [cfg.pfn_channels, *cfg.num_filters[:-1]]
        self.blocks = nn.ModuleList(
            nn.Sequential(*_conv_bn_gelu(ci, co, s), *[m for _ in range(n) for m in _conv_bn_gelu(co, co)])
            for ci, co, s, n in zip(c_in, cfg.num_filters, cfg.layer_strides, cfg.layer_nums))
        self.deblocks = nn.ModuleList(
            nn.Sequential(nn.ConvTranspose2d(ci, co, u, stride=u, bias=False), nn.BatchNorm2d(co), nn.GELU())
            for ci, co, u in zip(cfg.num_filters, cfg.num_upsample_filters, cfg.upsample_strides))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        ups = []
        for block, deblock in zip(self.blocks, self.deblocks):
            x = block(x)                                       # (B, C_i, H / 2^(i+1), W / 2^(i+1))
            ups.append(deblock(x))                             # (B, U_i, H / 2, W / 2)
        return torch.cat(ups, dim=1)                           # (B, sum U_i, H / 2, W / 2)


# ----------------------------------------------------------------------------------------------
# Size variants
# ----------------------------------------------------------------------------------------------

SPECTRAL_FEATURES = ("r", "a", "e", "d", "Ae", "pillar_offset", "sector")


# The freespace head convolves the 128 x 224 map and resizes its logits: half the official head's
# work, which is most of a pillar model's (docs/results/detection.md, same mIoU when trained so).
_HEADS = dict(freespace_upsample_logits=True)


def polar_pointpillars(**overrides) -> PointPillars:
    """Full size (~2.4M parameters): 256 x 448 pillars, features ``r a e d Ae`` + offsets."""
    return PointPillars(PillarsConfig(**{**_HEADS, **overrides}))


def spectralpillars(**overrides) -> PointPillars:
    """Full size SpectralPillars: ``polar_pointpillars`` plus the 32-sector angle descriptor; the
    RD-neighbourhood points come with the data (a store made with ``--enrich rd3,sector32``)."""
    return PointPillars(PillarsConfig(**{**_HEADS, "features": SPECTRAL_FEATURES, **overrides}))


# The heads run at the full 128 x 224 map, where a 3 x 3 conv costs 29k positions per channel
# pair: they, not the backbone, set the training time on a CPU, hence 16/8.
_SMALL = dict(grid=(128, 224), pfn_channels=32, layer_nums=(2, 3, 3), layer_strides=(1, 2, 2),
              num_filters=(16, 32, 64), upsample_strides=(1, 2, 4), num_upsample_filters=(16, 8, 8),
              detection_widths=(16, 16), freespace_widths=(8, 8), **_HEADS)


def polar_pointpillars_s(**overrides) -> PointPillars:
    """For ``radial-s`` on CPUs: 128 x 224 pillars (0.80 m, one ``radial-s`` range bin, x 0.8 deg),
    a 32-channel backbone output and 16/8-channel heads, so it trains on 2 CPU cores."""
    return PointPillars(PillarsConfig(**{**_SMALL, **overrides}))


def spectralpillars_s(**overrides) -> PointPillars:
    """:func:`polar_pointpillars_s` with the angle-sector descriptor."""
    return PointPillars(PillarsConfig(**{**_SMALL, "features": SPECTRAL_FEATURES, **overrides}))


def pillars_tiny(**overrides) -> PointPillars:
    """For tests: 128 x 224 pillars, 8 pillar channels, one conv per block, 8-channel heads."""
    return PointPillars(PillarsConfig(**{**_SMALL, "pfn_channels": 8, "layer_nums": (0, 1, 1),
                                         "num_filters": (8, 8, 8), "num_upsample_filters": (8, 4, 4),
                                         "detection_widths": (8, 8), "freespace_widths": (8, 8), **overrides}))
