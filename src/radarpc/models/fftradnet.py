"""FFTRadNet: vehicle detection and freespace from a dense (or sparse) range-Doppler cube.

The network of Rebut et al., "Raw High-Definition Radar for Multi-Task Learning" (CVPR 2022), as
the public valeoai/RADIal code builds it (``FFTRadNet/model/FFTRadNet.py``); the seed's dense-RD
and sparse-RD baselines. Read top-down:

1. input: the complex cube ``(B, Nr, Nd, Nrx)`` becomes ``2 Nrx`` real channels (all real parts,
   then all imaginary parts, as the official ``np.concatenate([x.real, x.imag], axis=2)`` and
   ``permute(2, 0, 1)``), normalised per channel with the training split's statistics;
2. MIMO pre-encoder: a Doppler convolution with one tap per Tx, taps ``slot_width`` bins apart
   (the DDMA replicas of a target), on the circularly padded Doppler axis;
3. FPN backbone: a 3 x 3 stem and four stages of ResNet bottlenecks, each halving Doppler;
4. range-angle decoder: the Doppler axis of the deep features is swapped with the channel axis
   (channels become azimuth columns), then upsampled in range and fused;
5. the common heads of :mod:`radarpc.models.heads`.

Sizes are those of a :class:`FFTRadNetConfig`; the variants are plain factory functions, listed
with every other model in :data:`radarpc.models.MODELS`. Official checkpoints are converted by
:mod:`radarpc.experiments.radial_detection.official`; inference rewrites are in
:mod:`radarpc.models.fast`.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models.heads import (DETECTION_SHAPE, FREESPACE_SHAPE, ConvBlock, DetectionHead, FreespaceHead,
                                  HeadOutput, conv3x3)
from radarpc.sensors.radial import RADIAL, RADIAL_S, DDMARadarConfig

__all__ = [
    "FFTRadNetConfig", "FFTRadNet", "MIMOPreEncoder", "Bottleneck", "FPNBackbone", "RangeAngleDecoder",
    "fftradnet", "fftradnet_s", "fftradnet_tiny", "cube_to_channels", "input_statistics",
]


# ---- configuration ------------------------------------------------------------------------------
@dataclass(frozen=True)
class FFTRadNetConfig:
    """Sizes of an FFTRadNet. Defaults: the official ``config_FFTRadNet_192_56.json`` on RADIal."""

    n_range: int = 512                       # range bins of the input cube
    n_doppler: int = 256                     # Doppler bins of the input cube
    n_rx: int = 16                           # receivers: 2 * n_rx input channels (real, imaginary)
    n_tx: int = 12                           # transmitters: taps of the MIMO pre-encoder
    slot_width: int = 16                     # Doppler bins between the replicas of consecutive DDMA slots (dilation)
    mimo_channels: int = 192                 # pre-encoder output channels (official "MIMO_output")
    blocks: tuple[int, ...] = (3, 6, 6, 3)   # bottlenecks per backbone stage
    channels: tuple[int, ...] = (32, 40, 48, 56)   # bottleneck widths per stage (outputs are 4x)
    range_strides: tuple[int, int] = (2, 2)  # range stride of stages 1, 2 (3, 4: always 2, undone by the decoder)
    decoder_channels: tuple[int, int] = (128, 256)   # outputs of the decoder's two conv blocks
    detection_widths: tuple[int, int] = (144, 96)    # DetectionHead widths
    freespace_widths: tuple[int, int] = (128, 64)    # FreespaceHead widths
    n_reg: int = 2                           # regression channels of the detection head
    freespace: bool = True                   # build the freespace head

    expansion = 4                            # bottleneck output / width (official block_expansion), not a field

    def __post_init__(self) -> None:
        def bad(msg: str) -> None:
            raise ValueError(f"FFTRadNetConfig: {msg}")

        if len(self.blocks) != 4 or len(self.channels) != 4 or min(self.blocks) < 1:
            bad(f"blocks and channels need 4 stages (blocks >= 1), got {self.blocks} and {self.channels}")
        if len(self.range_strides) != 2 or any(s not in (1, 2) for s in self.range_strides):
            bad(f"range_strides must be two of 1 or 2, got {self.range_strides}")
        if self.n_doppler % 16:
            bad(f"n_doppler={self.n_doppler} must be a multiple of 16 (four stages halve it)")
        if self.out_range != DETECTION_SHAPE[0] or self.n_range % (4 * self.range_strides[0] * self.range_strides[1]):
            bad(f"n_range={self.n_range} with range_strides={self.range_strides} gives a {self.out_range}-row RA map; "
                f"the detection grid has {DETECTION_SHAPE[0]} rows")
        if self.angle_size not in (224, 448, 896):
            bad(f"4 * channels[3] = {self.angle_size} azimuth columns; the detection head takes 224, 448 or 896")
        if self.pad > self.n_doppler:
            bad(f"n_tx * slot_width / 2 = {self.pad} exceeds n_doppler={self.n_doppler}")

    @property
    def pad(self) -> int:
        """Circular Doppler padding of the pre-encoder, ``n_tx * slot_width / 2`` (official: 96)."""
        return self.n_tx * self.slot_width // 2

    @property
    def out_range(self) -> int:
        """Rows of the decoder's RA map: the range of stage 2's output."""
        return self.n_range // (self.range_strides[0] * self.range_strides[1])

    @property
    def angle_size(self) -> int:
        """Azimuth columns of the decoder's RA map: the channels of stage 4's output."""
        return self.channels[3] * self.expansion

    @classmethod
    def for_sensor(cls, sensor: DDMARadarConfig, **fields) -> "FFTRadNetConfig":
        """A config whose input sizes are those of ``sensor``'s cubes."""
        return cls(**{"n_range": sensor.n_range, "n_doppler": sensor.n_doppler, "n_rx": sensor.n_rx,
                      "n_tx": sensor.n_tx, "slot_width": sensor.slot_width, **fields})


# ---- input --------------------------------------------------------------------------------------
def cube_to_channels(rd: torch.Tensor) -> torch.Tensor:
    """Complex cubes ``(B, Nr, Nd, Nrx)`` -> real ``(B, 2 Nrx, Nr, Nd)``: channel ``k < Nrx`` is
    ``Re rd[..., k]``, channel ``Nrx + k`` is ``Im rd[..., k]`` (the official dataset's layout)."""
    if not isinstance(rd, torch.Tensor) or not rd.is_complex() or rd.ndim != 4:
        raise ValueError(f"rd must be a complex (B, Nr, Nd, Nrx) tensor, got "
                         f"{getattr(rd, 'dtype', type(rd).__name__)} {tuple(getattr(rd, 'shape', ()))}")
    return torch.cat([rd.real, rd.imag], dim=-1).permute(0, 3, 1, 2)   # (B, 2 Nrx, Nr, Nd)


def input_statistics(cubes: Iterable[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel normalisation statistics of the training split, as the official script computes them.

    For each frame ``f`` and channel ``c`` (of :func:`cube_to_channels`), ``m_fc`` is the mean and
    ``s_fc`` the population standard deviation over the ``Nr x Nd`` cells; the statistics are
    ``mean_c = mean_f m_fc`` and ``std_c = mean_f s_fc`` (a mean of per-frame deviations, as
    ``print_dataset_statistics.py``, not a pooled one). Accumulated in float64.

    Parameters
    ----------
    cubes : iterable of complex Tensor
        Frames ``(Nr, Nd, Nrx)`` or batches ``(B, Nr, Nd, Nrx)``, e.g.
        ``(ds.cube(i) for i in range(len(ds)))`` over a training split.

    Returns
    -------
    mean, std : float32 Tensor, ``(2 Nrx,)`` each
    """
    m_sum = s_sum = None
    n = 0
    for rd in cubes:
        x = cube_to_channels(rd.unsqueeze(0) if isinstance(rd, torch.Tensor) and rd.ndim == 3 else rd)
        x = x.to(torch.float64).flatten(2)                              # (B, 2 Nrx, Nr Nd)
        m, s = x.mean(-1), x.std(-1, correction=0)                      # (B, 2 Nrx)
        if m_sum is not None and m.shape[1] != m_sum.shape[0]:
            raise ValueError(f"frame {n} has {m.shape[1] // 2} receivers, the first frame {m_sum.shape[0] // 2}")
        m_sum = m.sum(0) if m_sum is None else m_sum + m.sum(0)
        s_sum = s.sum(0) if s_sum is None else s_sum + s.sum(0)
        n += m.shape[0]
    if n == 0:
        raise ValueError("input_statistics needs at least one frame, got an empty iterable")
    std = s_sum / n
    if bool((std <= 0).any()):
        raise ValueError(f"channels {torch.nonzero(std <= 0).flatten().tolist()} are constant over the frames: "
                         f"their standard deviation is 0 and cannot normalise")
    return (m_sum / n).float(), std.float()


# ---- MIMO pre-encoder ---------------------------------------------------------------------------
class MIMOPreEncoder(nn.Module):
    """Doppler convolution over the ``n_tx`` DDMA replicas of every cell, then BN.

    ``y[o, r, d] = sum_{c, t} w[o, c, t] x[c, r, (d + t * slot_width - (n_tx - 1) * slot_width / 2) mod Nd]``
    for even ``n_tx`` (the official circular pad by ``n_tx * slot_width / 2`` and centre crop).
    """

    def __init__(self, c_in: int, c_out: int, n_tx: int, slot_width: int):
        super().__init__()
        self.pad = n_tx * slot_width // 2
        self.conv = nn.Conv2d(c_in, c_out, kernel_size=(1, n_tx), dilation=(1, slot_width), bias=False)
        self.bn = nn.BatchNorm2d(c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        width = x.shape[-1]
        x = torch.cat([x[..., -self.pad:], x, x[..., :self.pad]], dim=3)   # circular in Doppler
        x = self.conv(x)                                                     # (B, C, Nr, Nd + slot_width)
        # the official crop, its float arithmetic kept so odd sizes crop identically
        x = x[..., int(x.shape[-1] / 2 - width / 2):int(x.shape[-1] / 2 + width / 2)]
        return self.bn(x)                                                    # (B, C, Nr, Nd)


# ---- FPN backbone -------------------------------------------------------------------------------
class StridedConv1x1(nn.Conv2d):
    """A strided 1 x 1 convolution computed as subsampling, then a stride-1 1 x 1 convolution.

    The same function and parameters as ``nn.Conv2d(c_in, c_out, 1, stride=stride)`` (the state
    dict is unchanged). The detour exists because oneDNN's AVX-512 backward of some strided 1 x 1
    convolutions corrupts memory in torch 2.13 (e.g. 8 -> 16 channels, stride (1, 2), on a
    (4, 8, 128, 64) input: the tiny test model's first shortcut); a stride-1 1 x 1 convolution of
    the subsampled input takes other kernels and is exact, since a 1 x 1 kernel reads one pixel.
    """

    def __init__(self, c_in: int, c_out: int, stride: tuple[int, int], bias: bool = False):
        super().__init__(c_in, c_out, kernel_size=1, stride=stride, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        sr, sc = self.stride
        return F.conv2d(x[:, :, ::sr, ::sc], self.weight, self.bias)          # (B, C_out, ceil(H/sr), ceil(W/sc))


class Bottleneck(nn.Module):
    """ResNet bottleneck: 1x1 -> 3x3 (strided) -> 1x1 (x expansion), identity or 1x1 shortcut."""

    def __init__(self, c_in: int, planes: int, stride: int | tuple[int, int] = 1,
                 downsample: nn.Module | None = None, expansion: int = 4):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, planes, kernel_size=1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, kernel_size=3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, expansion * planes, kernel_size=1, bias=False)
        self.bn3 = nn.BatchNorm2d(expansion * planes)
        self.act1, self.act2 = nn.ReLU(), nn.ReLU()     # modules, so an inference copy can fuse them
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.act1(self.bn1(self.conv1(x)))
        out = self.act2(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        shortcut = x if self.downsample is None else self.downsample(x)
        return F.relu(shortcut + out)


class FPNBackbone(nn.Module):
    """3x3 stem and four bottleneck stages; stage ``k`` has stride ``(range_stride_k, 2)``."""

    def __init__(self, cfg: FFTRadNetConfig):
        super().__init__()
        c = cfg.mimo_channels
        self.conv = conv3x3(c, c)
        self.bn = nn.BatchNorm2d(c)
        self.act = nn.ReLU()                         # a module, so an inference copy can fuse it
        strides = (*cfg.range_strides, 2, 2)
        stages = []
        for n, planes, s in zip(cfg.blocks, cfg.channels, strides):
            out = planes * cfg.expansion
            down = nn.Sequential(StridedConv1x1(c, out, stride=(s, 2)), nn.BatchNorm2d(out))
            layers = [Bottleneck(c, planes, stride=(s, 2), downsample=down, expansion=cfg.expansion)]
            layers += [Bottleneck(out, planes, expansion=cfg.expansion) for _ in range(1, n)]
            stages.append(nn.Sequential(*layers))
            c = out
        self.block1, self.block2, self.block3, self.block4 = stages

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = self.act(self.bn(self.conv(x)))          # (B, M, Nr, Nd)
        x2 = self.block2(self.block1(x))             # (B, 4 c1, Nr / (s1 s2), Nd / 4)
        x3 = self.block3(x2)                         # (B, 4 c2, R2 / 2, Nd / 8)
        x4 = self.block4(x3)                         # (B, 4 c3 = A, R2 / 4, Nd / 16)
        return x2, x3, x4


# ---- range-angle decoder ------------------------------------------------------------------------
class RangeAngleDecoder(nn.Module):
    """Doppler <-> channel swap of stages 2..4, then upsampling in range and fusion.

    Stage 4's ``A`` channels, and stages 2 and 3 mapped to ``A`` channels by 1x1 convs, become
    azimuth columns once ``transpose(1, 3)`` moves them last; their Doppler bins become channels.
    Output: ``(B, decoder_channels[1], R2, A)``.
    """

    def __init__(self, cfg: FFTRadNetConfig):
        super().__init__()
        d2, d3, d4 = cfg.n_doppler // 4, cfg.n_doppler // 8, cfg.n_doppler // 16   # Doppler bins of x2, x3, x4
        c4, c3 = cfg.decoder_channels
        a = cfg.angle_size
        self.deconv4 = nn.ConvTranspose2d(d4, d4, kernel_size=3, stride=(2, 1), padding=1, output_padding=(1, 0))
        self.conv_block4 = ConvBlock(d4 + d3, c4)
        self.deconv3 = nn.ConvTranspose2d(c4, c4, kernel_size=3, stride=(2, 1), padding=1, output_padding=(1, 0))
        self.conv_block3 = ConvBlock(c4 + d2, c3)
        self.L3 = nn.Conv2d(cfg.channels[2] * cfg.expansion, a, kernel_size=1)
        self.L2 = nn.Conv2d(cfg.channels[1] * cfg.expansion, a, kernel_size=1)

    def forward(self, x2: torch.Tensor, x3: torch.Tensor, x4: torch.Tensor) -> torch.Tensor:
        t4 = x4.transpose(1, 3)                                  # (B, d4, R4, A)
        t3 = self.L3(x3).transpose(1, 3)                         # (B, d3, R3 = 2 R4, A)
        t2 = self.L2(x2).transpose(1, 3)                         # (B, d2, R2 = 2 R3, A)
        s4 = self.conv_block4(torch.cat([self.deconv4(t4), t3], dim=1))     # (B, c4, R3, A)
        return self.conv_block3(torch.cat([self.deconv3(s4), t2], dim=1))   # (B, c3, R2, A)


# ---- the model ----------------------------------------------------------------------------------
class FFTRadNet(nn.Module):
    """FFTRadNet with its input normalisation.

    ``model(rd)`` takes complex cubes ``(B, Nr, Nd, Nrx)`` (what :func:`radarpc.data.radial.radial_collate`
    stacks) and returns :class:`~radarpc.models.heads.HeadOutput`: ``detection (B, 1 + n_reg, 128, 224)``
    (probability, then offsets) and ``freespace (B, 1, 256, 224)`` logits (None without the head).
    ``model.forward_channels(x)`` takes the normalised real input ``(B, 2 Nrx, Nr, Nd)`` of the official
    model instead. The buffers ``input_mean`` / ``input_std`` (``(2 Nrx,)``, zeros / ones until
    :meth:`set_input_statistics`) travel with the weights.
    """

    input_kind = "rd"                       # forward takes complex RD cubes (B, Nr, Nd, Nrx)

    def __init__(self, cfg: FFTRadNetConfig):
        super().__init__()
        self.cfg = cfg
        n_in = 2 * cfg.n_rx
        self.register_buffer("input_mean", torch.zeros(n_in))
        self.register_buffer("input_std", torch.ones(n_in))
        self.pre_encoder = MIMOPreEncoder(n_in, cfg.mimo_channels, cfg.n_tx, cfg.slot_width)
        self.backbone = FPNBackbone(cfg)
        self.decoder = RangeAngleDecoder(cfg)
        c = cfg.decoder_channels[1]
        self.detection_head = DetectionHead(c, angle_stride=cfg.angle_size // DETECTION_SHAPE[1], n_reg=cfg.n_reg,
                                            widths=cfg.detection_widths)
        self.freespace_head = FreespaceHead(c, FREESPACE_SHAPE, cfg.freespace_widths) if cfg.freespace else None

    def set_input_statistics(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """Store the normalisation statistics (e.g. of :func:`input_statistics`), ``(2 Nrx,)`` each."""
        n = self.input_mean.numel()
        mean, std = torch.as_tensor(mean, dtype=torch.float32), torch.as_tensor(std, dtype=torch.float32)
        if mean.shape != (n,) or std.shape != (n,):
            raise ValueError(f"input statistics must be ({n},) each (real then imaginary per receiver), "
                             f"got {tuple(mean.shape)} and {tuple(std.shape)}")
        if not bool((std > 0).all()):
            raise ValueError("input_std must be positive in every channel")
        self.input_mean.copy_(mean)
        self.input_std.copy_(std)

    def normalised_input(self, rd: torch.Tensor) -> torch.Tensor:
        """Complex cubes ``(B, Nr, Nd, Nrx)`` -> the model's real input ``(B, 2 Nrx, Nr, Nd)``,
        ``(x_c - mean_c) / std_c`` per channel (the official dataset's arithmetic, in float32)."""
        cfg = self.cfg
        if rd.ndim != 4 or tuple(rd.shape[1:]) != (cfg.n_range, cfg.n_doppler, cfg.n_rx):
            raise ValueError(f"rd must be (B, {cfg.n_range}, {cfg.n_doppler}, {cfg.n_rx}) complex for this "
                             f"FFTRadNet, got {tuple(rd.shape)}")
        x = cube_to_channels(rd).to(self.input_mean.dtype)
        return (x - self.input_mean[:, None, None]) / self.input_std[:, None, None]

    def forward(self, rd: torch.Tensor) -> HeadOutput:
        return self.forward_channels(self.normalised_input(rd))

    def forward_channels(self, x: torch.Tensor) -> HeadOutput:
        """The network on the normalised real input ``(B, 2 Nrx, Nr, Nd)``."""
        x = self.pre_encoder(x)                                 # (B, M, Nr, Nd)
        ra = self.decoder(*self.backbone(x))                    # (B, C, 128, A)
        det = self.detection_head(ra)                           # (B, 1 + n_reg, 128, 224)
        fs = self.freespace_head(ra) if self.freespace_head is not None else None   # (B, 1, 256, 224)
        return HeadOutput(det, fs)


# ---- variants -----------------------------------------------------------------------------------
def fftradnet(**fields) -> FFTRadNet:
    """The official size on full RADIal cubes (512 x 256 x 16): 3,789,940 parameters."""
    return FFTRadNet(FFTRadNetConfig.for_sensor(RADIAL, **fields))


def fftradnet_s(**fields) -> FFTRadNet:
    """``radial-s`` cubes (128 x 64 x 16, 0.8047 m range bins = one detection row): no range stride in
    stages 1 and 2, a 64-channel pre-encoder and thin decoder and heads, so it trains on 2 CPU cores."""
    # the decoder's last block and the heads run at the full 128 x 224 map and dominate a CPU step
    d = dict(mimo_channels=64, blocks=(2, 3, 3, 2), range_strides=(1, 1), decoder_channels=(16, 32),
             detection_widths=(16, 16), freespace_widths=(8, 8))
    return FFTRadNet(FFTRadNetConfig.for_sensor(RADIAL_S, **(d | fields)))


def fftradnet_tiny(**fields) -> FFTRadNet:
    """For tests: ``radial-s`` cubes, one bottleneck per stage, a few channels (output shapes as the others)."""
    d = dict(mimo_channels=8, blocks=(1, 1, 1, 1), channels=(4, 4, 4, 56), range_strides=(1, 1),
             decoder_channels=(8, 8), detection_widths=(8, 8), freespace_widths=(8, 8))
    return FFTRadNet(FFTRadNetConfig.for_sensor(RADIAL_S, **(d | fields)))


