"""The learned baseline of RaLD's Table 2: a supervised radar-to-occupancy network, RPDNet-style.

The seed compares RaLD with RPDNet (cheng2022novel), a GAN that maps the radar spectrum to a dense
high-resolution point cloud with a convolutional generator. What radarpc keeps of it is what the
seed says of it: a convolutional network reads the radar spectrum and writes a dense 3-D output
from which the cloud is read. The generator is trained here with a supervised loss alone (weighted
binary cross-entropy against the LiDAR truth's occupancy, the experiment's task), not
adversarially; the exact layer sizes of the original are not used (they are not in the seed).

Read top-down:

1. the input is RaLD's radar intensity cube ``(B, R, A, E)`` (128 x 64 x 32: range, azimuth,
   elevation bins; RaLD's normalisation, dB clipped to 0..45 and divided by 45,
   :func:`radarpc.data.coloradar.rald_intensity`), exactly what the diffusion model's radar
   encoder takes, as one input channel;
2. :class:`Encoder3d`: a 3 x 3 x 3 conv stem at full resolution, then one level per
   ``ch_mult`` entry after the first, each a stride-2 convolution that halves every axis followed
   by ``blocks`` residual blocks (GroupNorm, SiLU, 3^3 convs); it keeps every level's output for
   the skips;
3. :class:`Decoder3d`: from the coarsest level back up to the output resolution, each step a
   trilinear x2 upsampling, the encoder's features of that resolution concatenated (a U-Net skip)
   and a residual block;
4. a 1 x 1 x 1 convolution to one channel: occupancy logits ``(B, R/s, A/s, E/s)`` over a coarse
   frustum grid in range x azimuth x elevation, ``s = out_stride`` (a power of two; 2 by default:
   64 x 32 x 16 cells for RaLD's cube). The grid the logits stand for (its cells in metres and
   degrees) is the experiment's (:mod:`radarpc.experiments.rpdnet.config`); the network only
   fixes its shape (:attr:`RPDNetConfig.out_shape`).

``input_kind = "radar"``: it reads the same cube as RaLD's diffusion model.

Size variants are plain factory functions (listed in :data:`radarpc.models.MODELS`):
:func:`rpdnet` (a large, GPU size), :func:`rpdnet_s` (trains on 2 CPU cores) and
:func:`rpdnet_tiny` (tests).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["RPDNetConfig", "RPDNet", "Encoder3d", "Decoder3d", "ResBlock3d", "rpdnet", "rpdnet_s", "rpdnet_tiny"]


# ----------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RPDNetConfig:
    """A radar-to-occupancy encoder-decoder, whole.

    The encoder has ``len(ch_mult)`` levels; level ``i`` has ``channels * ch_mult[i]`` channels at
    ``1 / 2^i`` of the input's resolution. The decoder climbs back to level ``log2(out_stride)``,
    whose resolution is the output's.
    """

    radar_shape: tuple[int, int, int] = (128, 64, 32)   # the intensity cube: range, azimuth, elevation bins
    channels: int = 16                                  # the stem's width (level 0)
    ch_mult: tuple[int, ...] = (1, 2, 4, 8)             # width multiplier per encoder level
    blocks: int = 1                                     # residual blocks per encoder level
    out_stride: int = 2                                 # output cells per axis = radar_shape / out_stride
    groups: int = 8                                     # GroupNorm groups (divide every width)

    def __post_init__(self) -> None:
        for k in ("radar_shape", "ch_mult"):
            object.__setattr__(self, k, tuple(int(v) for v in getattr(self, k)))
        if len(self.radar_shape) != 3 or min(self.radar_shape) < 1:
            raise ValueError(f"RPDNetConfig.radar_shape must be three bin counts (range, azimuth, elevation), "
                             f"got {self.radar_shape}")
        for k in ("channels", "blocks", "out_stride", "groups"):
            v = getattr(self, k)
            if isinstance(v, bool) or int(v) != v or v < (0 if k == "blocks" else 1):
                raise ValueError(f"RPDNetConfig.{k} must be an integer >= {0 if k == 'blocks' else 1}, got {v!r}")
        if not self.ch_mult or min(self.ch_mult) < 1:
            raise ValueError(f"RPDNetConfig.ch_mult must be one multiplier >= 1 per level, got {self.ch_mult}")
        if self.out_stride & (self.out_stride - 1):
            raise ValueError(f"RPDNetConfig.out_stride must be a power of two, got {self.out_stride}")
        if self.out_level >= len(self.ch_mult):
            raise ValueError(f"RPDNetConfig: out_stride {self.out_stride} is level {self.out_level}, but the "
                             f"encoder has only {len(self.ch_mult)} levels (ch_mult {self.ch_mult})")
        step = 2 ** (len(self.ch_mult) - 1)
        if any(n % step for n in self.radar_shape):
            raise ValueError(f"RPDNetConfig: radar_shape {self.radar_shape} is not divisible by {step}, the "
                             f"encoder's total stride over {len(self.ch_mult)} levels")
        bad = [c for c in self.widths if c % self.groups]
        if bad:
            raise ValueError(f"RPDNetConfig: groups {self.groups} does not divide the widths {bad}")

    @property
    def widths(self) -> tuple[int, ...]:
        """Channels per encoder level."""
        return tuple(self.channels * m for m in self.ch_mult)

    @property
    def out_level(self) -> int:
        """The encoder level whose resolution the output has: ``log2(out_stride)``."""
        return int(round(math.log2(self.out_stride)))

    @property
    def out_shape(self) -> tuple[int, int, int]:
        """Occupancy cells per axis ``(n_r, n_az, n_el)``: ``radar_shape / out_stride``
        (64 x 32 x 16 for RaLD's cube at stride 2)."""
        return tuple(n // self.out_stride for n in self.radar_shape)


# ----------------------------------------------------------------------------------------------
# Blocks
# ----------------------------------------------------------------------------------------------

class ResBlock3d(nn.Module):
    """``x -> skip(x) + conv(SiLU(GN(conv(SiLU(GN(x))))))``, 3^3 convolutions; ``skip`` is a 1^3
    convolution when the width changes, else the identity."""

    def __init__(self, c_in: int, c_out: int, groups: int):
        super().__init__()
        self.norm1 = nn.GroupNorm(groups, c_in)
        self.conv1 = nn.Conv3d(c_in, c_out, 3, padding=1)
        self.norm2 = nn.GroupNorm(groups, c_out)
        self.conv2 = nn.Conv3d(c_out, c_out, 3, padding=1)
        self.skip = nn.Conv3d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:                # (B, c_in, r, a, e)
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h                                        # (B, c_out, r, a, e)


class _Down(nn.Module):
    """One encoder level below the stem: a stride-2 3^3 conv (every axis halved), GroupNorm, SiLU,
    then the residual blocks."""

    def __init__(self, c_in: int, c_out: int, cfg: RPDNetConfig):
        super().__init__()
        self.conv = nn.Conv3d(c_in, c_out, 3, stride=2, padding=1)
        self.norm = nn.GroupNorm(cfg.groups, c_out)
        self.blocks = nn.Sequential(*(ResBlock3d(c_out, c_out, cfg.groups) for _ in range(cfg.blocks)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:                # (B, c_in, r, a, e)
        return self.blocks(F.silu(self.norm(self.conv(x))))            # (B, c_out, r/2, a/2, e/2)


class Encoder3d(nn.Module):
    """``(B, 1, R, A, E)`` -> the features of every level, finest first: level ``i`` is
    ``(B, widths[i], R/2^i, A/2^i, E/2^i)``."""

    def __init__(self, cfg: RPDNetConfig):
        super().__init__()
        w = cfg.widths
        self.stem = nn.Conv3d(1, w[0], 3, padding=1)
        self.stem_norm = nn.GroupNorm(cfg.groups, w[0])
        self.down = nn.ModuleList(_Down(w[i - 1], w[i], cfg) for i in range(1, len(w)))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        h = F.silu(self.stem_norm(self.stem(x)))                       # (B, w0, R, A, E)
        levels = [h]
        for down in self.down:
            h = down(h)                                                # (B, w_i, R/2^i, A/2^i, E/2^i)
            levels.append(h)
        return levels


class _Up(nn.Module):
    """One decoder step: trilinear x2 upsampling of the coarser features, the encoder's features of
    the finer level concatenated, a residual block to the finer level's width."""

    def __init__(self, c_coarse: int, c_skip: int, groups: int):
        super().__init__()
        self.block = ResBlock3d(c_coarse + c_skip, c_skip, groups)

    def forward(self, h: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:   # (B, c, r, a, e), (B, s, 2r, 2a, 2e)
        h = F.interpolate(h, size=skip.shape[2:], mode="trilinear", align_corners=False)
        return self.block(torch.cat((h, skip), dim=1))                 # (B, s, 2r, 2a, 2e)


class Decoder3d(nn.Module):
    """The encoder's levels -> features ``(B, widths[out_level], *out_shape)``: from the coarsest
    level up to ``out_level``, one :class:`_Up` per level."""

    def __init__(self, cfg: RPDNetConfig):
        super().__init__()
        w = cfg.widths
        self.out_level = cfg.out_level
        # up[j] climbs from level L-1-j to level L-2-j
        self.up = nn.ModuleList(_Up(w[i + 1], w[i], cfg.groups) for i in reversed(range(cfg.out_level, len(w) - 1)))

    def forward(self, levels: list[torch.Tensor]) -> torch.Tensor:
        h = levels[-1]                                                 # the coarsest
        for j, up in enumerate(self.up):
            h = up(h, levels[len(levels) - 2 - j])
        return h                                                       # (B, w_out, *out_shape)


# ----------------------------------------------------------------------------------------------
# The network
# ----------------------------------------------------------------------------------------------

class RPDNet(nn.Module):
    """Radar intensity cube ``(B, R, A, E)`` -> occupancy logits ``(B, *cfg.out_shape)``."""

    input_kind = "radar"

    def __init__(self, cfg: RPDNetConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder3d(cfg)
        self.decoder = Decoder3d(cfg)
        self.norm_out = nn.GroupNorm(cfg.groups, cfg.widths[cfg.out_level])
        self.head = nn.Conv3d(cfg.widths[cfg.out_level], 1, 1)

    def forward(self, cube: torch.Tensor) -> torch.Tensor:
        """Occupancy logits of the cells of the output grid.

        Raises
        ------
        ValueError
            ``cube`` is not ``(B, *cfg.radar_shape)``.
        """
        if cube.ndim != 4 or tuple(cube.shape[1:]) != self.cfg.radar_shape:
            raise ValueError(f"RPDNet: expected intensity cubes (B, {', '.join(map(str, self.cfg.radar_shape))}), "
                             f"got {tuple(cube.shape)}")
        levels = self.encoder(cube[:, None])                           # [(B, w_i, R/2^i, A/2^i, E/2^i)]
        h = self.decoder(levels)                                       # (B, w_out, R/s, A/s, E/s)
        return self.head(F.silu(self.norm_out(h)))[:, 0]               # (B, R/s, A/s, E/s)


# ----------------------------------------------------------------------------------------------
# Size variants
# ----------------------------------------------------------------------------------------------

def rpdnet(**overrides) -> RPDNet:
    """Large (for GPUs): a 32-channel stem, five levels of two residual blocks, widths up to 512."""
    return RPDNet(RPDNetConfig(**{"channels": 32, "ch_mult": (1, 2, 4, 8, 16), "blocks": 2, **overrides}))


def rpdnet_s(**overrides) -> RPDNet:
    """For CPUs: an 8-channel stem, four levels of one residual block, widths up to 64."""
    return RPDNet(RPDNetConfig(**{"channels": 8, "ch_mult": (1, 2, 4, 8), "blocks": 1, "groups": 4, **overrides}))


def rpdnet_tiny(**overrides) -> RPDNet:
    """For tests: a 4-channel stem, three levels, on a 32 x 16 x 8 cube, output at its resolution."""
    return RPDNet(RPDNetConfig(**{"radar_shape": (32, 16, 8), "channels": 4, "ch_mult": (1, 2, 4), "blocks": 1,
                                  "out_stride": 1, "groups": 2, **overrides}))
