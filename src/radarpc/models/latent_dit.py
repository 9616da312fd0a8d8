"""RaLD's radar-conditioned latent diffusion model: a 3-D conv radar encoder and a latent
transformer (DiT-style blocks) inside EDM's preconditioning.

The diffusion stage of RaLD (the seed's "Diffusion Conditioned on Radar Spectrum"), as the public
RoyAPTX4869/RaLD code builds it (``model/models_radar_encoder.py`` ``Encoder`` and
``model/models_radar_generation.py`` ``EDMPrecond``, config ``kl_d512_m512_l32_d24_edm``). Read
top-down:

1. :class:`RadarEncoder`: the radar intensity cube ``(B, 128, 64, 32)`` (range, azimuth,
   elevation; RaLD's normalisation, dB clipped to 0..45 and divided by 45) as one input channel,
   a conv stem, five levels of two residual blocks (GroupNorm, SiLU, 3 x 3 x 3 convs) with a
   stride-2 convolution between levels, self-attention in the lowest level, a middle block and a
   conv to ``z = 16`` channels on the ``8 x 4 x 2`` grid;
2. :class:`RadarTokens`: each of the 64 cells projected to the transformer width, plus learned
   range, azimuth and elevation embeddings, flattened range-major: the condition ``(B, 64, W)``;
3. :class:`LatentTransformer`: the raw network ``F``: the latents ``(B, M, D)`` projected to width
   ``W``, ``depth`` blocks of [AdaLayerNorm on the noise embedding -> self-attention, AdaLayerNorm
   -> cross-attention to the radar tokens, AdaLayerNorm -> GEGLU feed-forward], each residual, a
   final LayerNorm and a zero-initialised projection back to ``D``;
4. :class:`LatentDiT`: the three, with EDM's preconditioning (:mod:`radarpc.models.edm`) around
   ``F``. ``encode_radar(cube)`` gives the condition, once per frame; ``forward(x, sigma,
   condition)`` is the denoiser ``D``; :meth:`LatentDiT.sample` runs the Heun sampler with one
   condition for all 35 network calls (the official code re-encodes the radar cube in each).

The seed's Table 3(a) "w/o radar encoder" is the config choice ``radar_condition = "patches"``
(:data:`RADAR_CONDITIONS`): no encoder; :class:`RadarPatches` cuts the normalised cube into
non-overlapping patches of the encoder's total stride (``16^3`` cells at paper size), and each
patch's intensities, flattened, are one cell of :class:`RadarTokens` (the same projection and axis
embeddings). The patch grid is the encoder's output grid, so the condition keeps its 64 tokens and
their range-major layout and only the 3-D conv encoder is gone (paper size: 166,319,616 parameters,
the encoder's 19.5M replaced by a 4,096 -> 512 projection). The public code's no-encoder path
projects each cube cell to a token (its configs' ``input_radar_*_dim``: 128 x 8 x 2, 2,048 tokens);
on the 128 x 64 x 32 cube read here that would be 262,144 tokens, hence patches.

``input_kind = "radar"``: the model reads RaLD's radar intensity cube (no other radarpc model
does; the detection models read ``"rd"`` cubes or ``"points"``).

Official state dicts map onto these modules key by key (same tensors, same shapes); the renames
are :data:`OFFICIAL_KEY_RENAMES` and :func:`official_key`.

Size variants are plain factory functions (listed in :data:`radarpc.models.MODELS`):
:func:`rald_dit` (paper size, depth 24, 183,766,160 parameters), :func:`rald_dit_d12`,
:func:`rald_dit_d18`, :func:`rald_dit_s` (trains on CPUs) and :func:`rald_dit_tiny` (tests).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models.edm import SeededNoise, edm_precondition, edm_sampler

__all__ = [
    "RADAR_CONDITIONS",
    "LatentDiTConfig",
    "LatentDiT",
    "RadarEncoder",
    "RadarPatches",
    "RadarTokens",
    "LatentTransformer",
    "OFFICIAL_KEY_RENAMES",
    "official_key",
    "rald_dit",
    "rald_dit_d12",
    "rald_dit_d18",
    "rald_dit_s",
    "rald_dit_tiny",
]


# ----------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------

RADAR_CONDITIONS: tuple[str, ...] = ("encoder", "patches")
"""How the radar cube becomes condition cells: the 3-D conv :class:`RadarEncoder` (RaLD) or the raw
cube cut into patches (:class:`RadarPatches`, the seed's Table 3(a) "w/o radar encoder")."""


@dataclass(frozen=True)
class LatentDiTConfig:
    """A radar-conditioned latent diffusion model, whole.

    The radar encoder halves every axis of ``radar_shape`` between its ``len(enc_ch_mult)``
    levels, so the condition has ``prod(radar_shape) / 8^(levels - 1)`` tokens (64 at paper size:
    ``8 x 4 x 2``) of ``width`` channels.
    """

    n_latents: int = 512                           # M: latent vectors per frame (the autoencoder's)
    latent_dim: int = 32                           # D: channels of a latent vector
    width: int = 512                               # transformer width (= heads x head dim = radar token channels)
    heads: int = 8                                 # attention heads (head dim = width / heads)
    depth: int = 24                                # transformer blocks
    noise_channels: int = 256                      # Fourier features of c_noise before the noise MLP
    ff_mult: int = 4                               # GEGLU hidden width = ff_mult x width
    sigma_data: float = 1.0                        # standard deviation of the latents (EDM preconditioning)
    radar_shape: tuple[int, int, int] = (128, 64, 32)   # the intensity cube: range, azimuth, elevation bins
    enc_channels: int = 64                         # radar encoder base width
    enc_ch_mult: tuple[int, ...] = (1, 1, 2, 2, 4)  # its width multiplier per level
    enc_res_blocks: int = 2                        # residual blocks per level
    enc_z_channels: int = 16                       # its output channels per cell
    enc_groups: int = 32                           # GroupNorm groups throughout the encoder
    enc_attention: bool = True                     # self-attention after each residual block of the last level
    radar_condition: str = "encoder"               # "encoder" (RaLD) or "patches" (raw cube patches, no encoder;
                                                   # patch edge = the encoder's total stride): RADAR_CONDITIONS

    def __post_init__(self) -> None:
        for k in ("radar_shape", "enc_ch_mult"):
            object.__setattr__(self, k, tuple(int(v) for v in getattr(self, k)))
        for k in ("n_latents", "latent_dim", "width", "heads", "depth", "noise_channels", "ff_mult",
                  "enc_channels", "enc_res_blocks", "enc_z_channels", "enc_groups"):
            v = getattr(self, k)
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise ValueError(f"LatentDiTConfig.{k} must be an integer >= 1, got {v!r}")
        if not isinstance(self.enc_attention, bool):
            raise ValueError(f"LatentDiTConfig.enc_attention must be true or false, got {self.enc_attention!r}")
        if self.radar_condition not in RADAR_CONDITIONS:
            raise ValueError(f"LatentDiTConfig.radar_condition must be one of {list(RADAR_CONDITIONS)}, "
                             f"got {self.radar_condition!r}")
        if self.width % self.heads:
            raise ValueError(f"LatentDiTConfig: width {self.width} is not divisible by heads {self.heads}")
        if self.noise_channels % 2:
            raise ValueError(f"LatentDiTConfig.noise_channels must be even (cosines and sines), "
                             f"got {self.noise_channels}")
        if not (math.isfinite(self.sigma_data) and self.sigma_data > 0):
            raise ValueError(f"LatentDiTConfig.sigma_data must be > 0, got {self.sigma_data}")
        if len(self.radar_shape) != 3 or min(self.radar_shape) < 1:
            raise ValueError(f"LatentDiTConfig.radar_shape must be three bin counts (range, azimuth, elevation), "
                             f"got {self.radar_shape}")
        if not self.enc_ch_mult or min(self.enc_ch_mult) < 1:
            raise ValueError(f"LatentDiTConfig.enc_ch_mult must be one multiplier >= 1 per level, "
                             f"got {self.enc_ch_mult}")
        step = 2 ** (len(self.enc_ch_mult) - 1)
        if any(n % step for n in self.radar_shape):
            raise ValueError(f"LatentDiTConfig: radar_shape {self.radar_shape} is not divisible by {step}, the "
                             f"encoder's total stride over {len(self.enc_ch_mult)} levels")
        widths = sorted({self.enc_channels * m for m in (1, *self.enc_ch_mult)})
        if any(c % self.enc_groups for c in widths):
            raise ValueError(f"LatentDiTConfig: enc_groups {self.enc_groups} does not divide the encoder's "
                             f"channel counts {widths}")

    @property
    def radar_grid(self) -> tuple[int, int, int]:
        """The encoder's output grid (range, azimuth, elevation cells): ``(8, 4, 2)`` at paper size."""
        step = 2 ** (len(self.enc_ch_mult) - 1)
        return tuple(n // step for n in self.radar_shape)

    @property
    def radar_stride(self) -> int:
        """Cube cells per condition cell along each axis: the encoder's total stride
        ``2^(levels - 1)``, also the patch edge of ``radar_condition = "patches"`` (16 at paper size)."""
        return 2 ** (len(self.enc_ch_mult) - 1)

    @property
    def radar_cell_channels(self) -> int:
        """Channels of a condition cell before the token projection: the encoder's ``enc_z_channels``,
        or a patch's ``radar_stride^3`` intensities."""
        return self.enc_z_channels if self.radar_condition == "encoder" else self.radar_stride ** 3

    @property
    def n_radar_tokens(self) -> int:
        """Condition tokens per frame: the cells of :attr:`radar_grid`."""
        r, a, e = self.radar_grid
        return r * a * e


# ----------------------------------------------------------------------------------------------
# Radar encoder
# ----------------------------------------------------------------------------------------------

def _group_norm(channels: int, groups: int) -> nn.GroupNorm:
    return nn.GroupNorm(groups, channels, eps=1e-6)


class ResBlock3d(nn.Module):
    """GroupNorm -> SiLU -> conv 3^3 -> GroupNorm -> SiLU -> conv 3^3, plus the input (through a
    1^3 conv where the width changes)."""

    def __init__(self, c_in: int, c_out: int, groups: int):
        super().__init__()
        self.norm1 = _group_norm(c_in, groups)
        self.conv1 = nn.Conv3d(c_in, c_out, 3, padding=1)
        self.norm2 = _group_norm(c_out, groups)
        self.conv2 = nn.Conv3d(c_out, c_out, 3, padding=1)
        self.nin_shortcut = nn.Conv3d(c_in, c_out, 1) if c_in != c_out else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:               # (B, C, R, A, E)
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        skip = x if self.nin_shortcut is None else self.nin_shortcut(x)
        return skip + h


class SelfAttention3d(nn.Module):
    """Single-head self-attention over the cells of a 3-D grid (1^3 convs for q, k, v, output)."""

    def __init__(self, channels: int, groups: int):
        super().__init__()
        self.norm = _group_norm(channels, groups)
        self.q = nn.Conv3d(channels, channels, 1)
        self.k = nn.Conv3d(channels, channels, 1)
        self.v = nn.Conv3d(channels, channels, 1)
        self.proj_out = nn.Conv3d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:               # (B, C, R, A, E)
        b, c = x.shape[:2]
        h = self.norm(x)
        q, k, v = (m(h).flatten(2).transpose(1, 2) for m in (self.q, self.k, self.v))   # (B, RAE, C)
        h = F.scaled_dot_product_attention(q, k, v)                    # softmax(q k^T / sqrt(C)) v
        h = h.transpose(1, 2).reshape(x.shape)
        return x + self.proj_out(h)


class Downsample3d(nn.Module):
    """Halves every axis: zero padding of one cell at the far end, then a stride-2 conv 3^3."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv3d(channels, channels, 3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.pad(x, (0, 1, 0, 1, 0, 1)))


class _Level(nn.Module):
    """One resolution of the encoder: residual blocks (each followed by attention in the last
    level) and the downsampling to the next."""

    def __init__(self, c_in: int, c_out: int, cfg: LatentDiTConfig, last: bool):
        super().__init__()
        self.block = nn.ModuleList(ResBlock3d(c_in if i == 0 else c_out, c_out, cfg.enc_groups)
                                   for i in range(cfg.enc_res_blocks))
        self.attn = nn.ModuleList(SelfAttention3d(c_out, cfg.enc_groups)
                                  for _ in range(cfg.enc_res_blocks if (last and cfg.enc_attention) else 0))
        self.downsample = None if last else Downsample3d(c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for i, block in enumerate(self.block):
            x = block(x)
            if len(self.attn):
                x = self.attn[i](x)
        return x if self.downsample is None else self.downsample(x)


class _Middle(nn.Module):
    def __init__(self, channels: int, groups: int):
        super().__init__()
        self.block_1 = ResBlock3d(channels, channels, groups)
        self.attn_1 = SelfAttention3d(channels, groups)
        self.block_2 = ResBlock3d(channels, channels, groups)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.block_2(self.attn_1(self.block_1(x)))


class RadarEncoder(nn.Module):
    """The 3-D conv encoder: ``(B, 1, R, A, E)`` intensity -> ``(B, z, R/s, A/s, E/s)`` features,
    ``s = 2^(levels - 1)`` (16 at paper size: ``(B, 16, 8, 4, 2)``)."""

    def __init__(self, cfg: LatentDiTConfig):
        super().__init__()
        ch = cfg.enc_channels
        widths = [ch * m for m in (1, *cfg.enc_ch_mult)]              # level i: widths[i] -> widths[i + 1]
        n = len(cfg.enc_ch_mult)
        self.conv_in = nn.Conv3d(1, ch, 3, padding=1)
        self.down = nn.ModuleList(_Level(widths[i], widths[i + 1], cfg, last=i == n - 1) for i in range(n))
        self.mid = _Middle(widths[-1], cfg.enc_groups)
        self.norm_out = _group_norm(widths[-1], cfg.enc_groups)
        self.conv_out = nn.Conv3d(widths[-1], cfg.enc_z_channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv_in(x)
        for level in self.down:
            h = level(h)
        h = self.mid(h)
        return self.conv_out(F.silu(self.norm_out(h)))


class RadarPatches(nn.Module):
    """The raw cube as condition cells, no weights: ``(B, 1, R, A, E)`` -> ``(B, s^3, R/s, A/s, E/s)``,
    channel ``(i s + j) s + k`` of cell ``(r, a, e)`` the intensity at ``(r s + i, a s + j, e s + k)``,
    ``s`` = :attr:`LatentDiTConfig.radar_stride` (the encoder's output layout, so
    :class:`RadarTokens` reads either)."""

    def __init__(self, cfg: LatentDiTConfig):
        super().__init__()
        self.s = cfg.radar_stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:               # (B, 1, R, A, E)
        s = self.s
        B, _, R, A, E = x.shape
        x = x.reshape(B, R // s, s, A // s, s, E // s, s)             # (B, r, i, a, j, e, k)
        x = x.permute(0, 2, 4, 6, 1, 3, 5)                             # (B, i, j, k, r, a, e)
        return x.reshape(B, s ** 3, R // s, A // s, E // s)           # (B, s^3, r, a, e)


class RadarTokens(nn.Module):
    """Condition cells -> condition tokens: a linear projection to ``width`` plus learned range,
    azimuth and elevation embeddings, flattened range-major (token ``(r A + a) E + e``)."""

    def __init__(self, cfg: LatentDiTConfig):
        super().__init__()
        r, a, e = cfg.radar_grid
        self.proj = nn.Linear(cfg.radar_cell_channels, cfg.width)
        self.pos_range = nn.Embedding(r, cfg.width)
        self.pos_azimuth = nn.Embedding(a, cfg.width)
        self.pos_elevation = nn.Embedding(e, cfg.width)

    def forward(self, z: torch.Tensor) -> torch.Tensor:               # (B, z or s^3, r, a, e)
        t = self.proj(z.permute(0, 2, 3, 4, 1))                       # (B, r, a, e, W)
        t = (t + self.pos_range.weight[:, None, None] + self.pos_azimuth.weight[None, :, None]
             + self.pos_elevation.weight[None, None, :])
        return t.flatten(1, 3)                                         # (B, r a e, W)


# ----------------------------------------------------------------------------------------------
# Latent transformer
# ----------------------------------------------------------------------------------------------

class NoiseEmbedding(nn.Module):
    """``c_noise (B,)`` -> ``(B, 1, W)``: cosines and sines of ``c_noise f_k``,
    ``f_k = 10000^(-k / (C/2))``, ``k = 0 .. C/2 - 1``, then two linear layers, each followed by SiLU."""

    def __init__(self, channels: int, width: int):
        super().__init__()
        self.channels = channels
        self.fc1 = nn.Linear(channels, width)
        self.fc2 = nn.Linear(width, width)

    def forward(self, c_noise: torch.Tensor) -> torch.Tensor:
        half = self.channels // 2
        freqs = (1 / 10000) ** (torch.arange(half, dtype=torch.float32, device=c_noise.device) / half)
        x = c_noise[:, None] * freqs.to(c_noise.dtype)                # (B, C/2)
        x = torch.cat([x.cos(), x.sin()], dim=1)                       # (B, C)
        return F.silu(self.fc2(F.silu(self.fc1(x))))[:, None]         # (B, 1, W)


class AdaLayerNorm(nn.Module):
    """``LayerNorm(x) (1 + scale) + shift`` with ``(scale, shift)`` a linear function of the noise
    embedding (the LayerNorm without affine parameters)."""

    def __init__(self, width: int):
        super().__init__()
        self.linear = nn.Linear(width, 2 * width)
        self.width = width

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:   # (B, M, W), (B, 1, W)
        scale, shift = self.linear(emb).chunk(2, dim=-1)
        return F.layer_norm(x, (self.width,)) * (1 + scale) + shift


class Attention(nn.Module):
    """Multi-head attention of ``x`` to ``context`` (to itself without one); q, k, v without bias."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.to_q = nn.Linear(width, width, bias=False)
        self.to_k = nn.Linear(width, width, bias=False)
        self.to_v = nn.Linear(width, width, bias=False)
        self.to_out = nn.Linear(width, width)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        context = x if context is None else context
        B, M, W = x.shape
        q = self.to_q(x).view(B, M, self.heads, -1).transpose(1, 2)                   # (B, h, M, W/h)
        k = self.to_k(context).view(B, context.shape[1], self.heads, -1).transpose(1, 2)   # (B, h, T, W/h)
        v = self.to_v(context).view(B, context.shape[1], self.heads, -1).transpose(1, 2)
        h = F.scaled_dot_product_attention(q, k, v)                    # softmax(q k^T / sqrt(W/h)) v
        return self.to_out(h.transpose(1, 2).reshape(B, M, W))


class GEGLU(nn.Module):
    """Feed-forward ``out(a * GELU(g))`` with ``(a, g) = proj(x)`` of ``2 ff_mult W`` channels."""

    def __init__(self, width: int, mult: int):
        super().__init__()
        self.proj = nn.Linear(width, 2 * mult * width)
        self.out = nn.Linear(mult * width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, gate = self.proj(x).chunk(2, dim=-1)
        return self.out(a * F.gelu(gate))


class DiTBlock(nn.Module):
    """Self-attention, cross-attention to the condition, GEGLU; each after an AdaLayerNorm on the
    noise embedding, each residual."""

    def __init__(self, width: int, heads: int, ff_mult: int):
        super().__init__()
        self.norm1 = AdaLayerNorm(width)
        self.self_attn = Attention(width, heads)
        self.norm2 = AdaLayerNorm(width)
        self.cross_attn = Attention(width, heads)
        self.norm3 = AdaLayerNorm(width)
        self.ff = GEGLU(width, ff_mult)

    def forward(self, x: torch.Tensor, emb: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        x = self.self_attn(self.norm1(x, emb)) + x
        x = self.cross_attn(self.norm2(x, emb), condition) + x
        return self.ff(self.norm3(x, emb)) + x


class LatentTransformer(nn.Module):
    """The raw network ``F(x_in (B, M, D), c_noise (B,), condition (B, T, W)) -> (B, M, D)``."""

    def __init__(self, cfg: LatentDiTConfig):
        super().__init__()
        self.noise_embed = NoiseEmbedding(cfg.noise_channels, cfg.width)
        self.proj_in = nn.Linear(cfg.latent_dim, cfg.width, bias=False)
        self.blocks = nn.ModuleList(DiTBlock(cfg.width, cfg.heads, cfg.ff_mult) for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(cfg.width)
        self.proj_out = nn.Linear(cfg.width, cfg.latent_dim, bias=False)
        nn.init.zeros_(self.proj_out.weight)                           # F = 0 at initialisation: D = c_skip x

    def forward(self, x: torch.Tensor, c_noise: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        emb = self.noise_embed(c_noise)                                # (B or 1, 1, W)
        h = self.proj_in(x)                                            # (B, M, W)
        for block in self.blocks:
            h = block(h, emb, condition)
        return self.proj_out(self.norm(h))                             # (B, M, D)


# ----------------------------------------------------------------------------------------------
# Model
# ----------------------------------------------------------------------------------------------

class LatentDiT(nn.Module):
    """RaLD's diffusion model: radar encoder (or, with ``radar_condition = "patches"``, the cube's
    patches), radar tokens and the EDM-preconditioned latent transformer.

    ``encode_radar(cube (B, R, A, E)) -> condition (B, T, W)``, once per frame;
    ``forward(x_noisy (B, M, D), sigma (B,), condition) -> denoised (B, M, D)``, the EDM denoiser
    ``D(x; sigma) = c_skip x + c_out F(c_in x; c_noise, condition)``.

    ``radar_encoder`` is the :class:`RadarEncoder`, or with ``radar_condition = "patches"`` the
    weightless :class:`RadarPatches` in its place (same input, same output layout).
    """

    input_kind = "radar"                    # reads RaLD's radar intensity cube (B, range, azimuth, elevation)

    def __init__(self, cfg: LatentDiTConfig):
        super().__init__()
        self.cfg = cfg
        self.radar_encoder = RadarEncoder(cfg) if cfg.radar_condition == "encoder" else RadarPatches(cfg)
        self.radar_tokens = RadarTokens(cfg)
        self.denoiser = LatentTransformer(cfg)

    def encode_radar(self, cube: torch.Tensor) -> torch.Tensor:
        """The condition tokens ``(B, T, W)`` of normalised intensity cubes ``(B, R, A, E)``.

        Raises
        ------
        ValueError
            ``cube`` is not ``(B, *cfg.radar_shape)``.
        """
        if cube.ndim != 4 or tuple(cube.shape[1:]) != self.cfg.radar_shape:
            raise ValueError(f"LatentDiT.encode_radar: expected intensity cubes (B, {', '.join(map(str, self.cfg.radar_shape))})"
                             f", got {tuple(cube.shape)}")
        return self.radar_tokens(self.radar_encoder(cube[:, None]))

    def forward(self, x: torch.Tensor, sigma: torch.Tensor | float, condition: torch.Tensor) -> torch.Tensor:
        return edm_precondition(self.denoiser, x, sigma, condition, self.cfg.sigma_data)

    @torch.no_grad()
    def sample(self, cube: torch.Tensor, seeds: list[int] | tuple[int, ...], **sampler: float) -> torch.Tensor:
        """Latents ``(B, M, D)`` for radar cubes ``(B, R, A, E)``, one seed per frame.

        The condition is encoded once; the initial noise is :class:`~radarpc.models.edm.SeededNoise`
        of the seeds (the official sampler's), and ``sampler`` overrides the keyword settings of
        :func:`~radarpc.models.edm.edm_sampler` (default: 18 Heun steps, 35 network calls).
        """
        if len(seeds) != cube.shape[0]:
            raise ValueError(f"LatentDiT.sample: {len(seeds)} seeds for {cube.shape[0]} radar cubes")
        condition = self.encode_radar(cube)
        rnd = SeededNoise(seeds, cube.device)
        noise = rnd.randn((cube.shape[0], self.cfg.n_latents, self.cfg.latent_dim))
        return edm_sampler(self, noise, condition, randn_like=rnd.randn_like, **sampler)


# ----------------------------------------------------------------------------------------------
# Official state dict keys
# ----------------------------------------------------------------------------------------------

OFFICIAL_KEY_RENAMES: tuple[tuple[str, str], ...] = (
    (r"^radar_enc\.", "radar_encoder."),                   # the encoder keeps its inner names
    (r"^radar_token_project\.", "radar_tokens.proj."),
    (r"^radar_r_emb\.", "radar_tokens.pos_range."),
    (r"^radar_a_emb\.", "radar_tokens.pos_azimuth."),
    (r"^radar_e_emb\.", "radar_tokens.pos_elevation."),
    (r"^model\.map_layer0\.", "denoiser.noise_embed.fc1."),
    (r"^model\.map_layer1\.", "denoiser.noise_embed.fc2."),
    (r"^model\.transformer_blocks\.", "denoiser.blocks."),
    (r"^model\.", "denoiser."),                            # proj_in, norm, proj_out
    (r"\.attn1\.", ".self_attn."),
    (r"\.attn2\.", ".cross_attn."),
    (r"\.to_out\.0\.", ".to_out."),
    (r"\.ff\.net\.0\.proj\.", ".ff.proj."),
    (r"\.ff\.net\.2\.", ".ff.out."),
)
"""Official ``EDMPrecond`` state dict key -> :class:`LatentDiT` key: regular-expression
substitutions applied in order (every tensor keeps its shape)."""


def official_key(key: str) -> str:
    """The :class:`LatentDiT` state dict key of an official ``EDMPrecond`` key."""
    for pattern, repl in OFFICIAL_KEY_RENAMES:
        key = re.sub(pattern, repl, key)
    return key


# ----------------------------------------------------------------------------------------------
# Size variants
# ----------------------------------------------------------------------------------------------

def rald_dit(**overrides) -> LatentDiT:
    """Paper size (183,766,160 parameters, 19,535,504 in the radar encoder): 24 blocks of width
    512 on 512 latents of 32 dims, the official ``kl_d512_m512_l32_d24_edm``."""
    return LatentDiT(LatentDiTConfig(**overrides))


def rald_dit_d12(**overrides) -> LatentDiT:
    """The seed's 12-block ablation (101,872,784 parameters)."""
    return LatentDiT(LatentDiTConfig(**{"depth": 12, **overrides}))


def rald_dit_d18(**overrides) -> LatentDiT:
    """The seed's 18-block ablation (142,819,472 parameters)."""
    return LatentDiT(LatentDiTConfig(**{"depth": 18, **overrides}))


# The radar encoder's first level convolves all 128 x 64 x 32 cells: its width, not the
# transformer's, sets a CPU's time per frame, hence 8 channels there.
_SMALL = dict(n_latents=128, latent_dim=32, width=128, heads=4, depth=4, noise_channels=128,
              enc_channels=8, enc_groups=4)


def rald_dit_s(**overrides) -> LatentDiT:
    """For CPUs: 4 blocks of width 128 on 128 latents of 32 dims, an 8-channel radar encoder."""
    return LatentDiT(LatentDiTConfig(**{**_SMALL, **overrides}))


def rald_dit_tiny(**overrides) -> LatentDiT:
    """For tests: 2 blocks of width 32 on 16 latents of 4 dims, a 4-channel radar encoder."""
    return LatentDiT(LatentDiTConfig(**{**_SMALL, "n_latents": 16, "latent_dim": 4, "width": 32, "heads": 2,
                                        "depth": 2, "noise_channels": 32, "enc_channels": 4, "enc_groups": 2,
                                        **overrides}))
