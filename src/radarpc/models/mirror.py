"""Mirror averaging at test time: a pillar detector run on a frame and on its mirror image.

The frame mirrored about the radar's boresight (azimuth ``a -> -a``,
:func:`radarpc.points.mirror_points`) is a frame of the mirrored world. :class:`MirrorAveraged`
runs the detector on both, maps the second output back through the mirror and averages the two
(the polar form of the flip test-time augmentation of image detectors): a detection that one view
alone sees weakly loses half its probability, one both views see keeps it. It costs a second
forward pass, so frames/s halve. It helps only where the world is left-right symmetric: road
traffic keeps to one side, and a model that has learned where roads and oncoming cars lie scores
mirrored frames worse (``docs/notebook/scripts/mirror_symmetry.py`` measures how much; on the simulator's
right-hand traffic the average lowered F1, ``docs/notebook/2026-12-04-detection.md``).

Mirroring an output map back (:func:`mirror_detection_map`): column ``j`` of the 224 azimuth
columns starts at ``(j - 112) c_a`` (:mod:`radarpc.models.targets`), so a vehicle at azimuth
``A`` in column ``j`` with in-cell offset ``o = A - (j - 112) c_a`` appears at ``-A`` in column
``223 - j`` with offset ``o' = c_a - o``. In the normalised offsets ``n = (o - mu) / sigma``

    n = (c_a - 2 mu) / sigma - n'

and range offsets do not change. The freespace map's 224 columns sample RADIal's 900-column mask at
odd columns, so its mirror image sits a quarter of a column (0.2 deg) off
(:mod:`radarpc.data.augment`); the two freespace probabilities are averaged as they are.
"""
from __future__ import annotations

import torch
from torch import nn

from radarpc.models.heads import HeadOutput
from radarpc.models.targets import TargetConfig
from radarpc.points import PointCloudBatch, mirror_points

__all__ = ["mirror_detection_map", "MirrorAveraged"]


def mirror_detection_map(maps: torch.Tensor, cfg: TargetConfig = TargetConfig()) -> torch.Tensor:
    """Detection maps of mirrored frames mapped back to the frames' own (module docstring).

    Parameters
    ----------
    maps : float ``(B, 3, n_range, n_azimuth)``
        Probability, normalised range offset, normalised azimuth offset.
    cfg : TargetConfig

    Returns
    -------
    Tensor of ``maps``' shape: columns reversed, the azimuth offset reflected. Applied twice it
    gives ``maps`` back.
    """
    if maps.ndim != 4 or tuple(maps.shape[1:]) != cfg.shape:
        raise ValueError(f"maps must be (B, {', '.join(map(str, cfg.shape))}), got shape {tuple(maps.shape)}")
    out = maps.flip(-1)                                                            # (B, 3, H, W)
    shift = (cfg.azimuth_cell_deg - 2.0 * cfg.reg_mean[1]) / cfg.reg_std[1]
    return torch.cat([out[:, :2], shift - out[:, 2:3]], dim=1)


class MirrorAveraged(nn.Module):
    """A pillar detector averaged over the frame and its mirror image (module docstring).

    Parameters
    ----------
    detector : nn.Module
        Takes a :class:`~radarpc.points.PointCloudBatch`, returns a
        :class:`~radarpc.models.heads.HeadOutput` (probability and offsets; freespace logits or None).
    targets : TargetConfig
        The detection map's geometry.
    sectors : (int, int), optional
        ``(n_az_sec, n_el_sec)`` of the points' sector descriptor
        (:func:`radarpc.data.augment.mirror_sectors` checks the root allows the mirror).
    """

    def __init__(self, detector: nn.Module, targets: TargetConfig = TargetConfig(),
                 sectors: tuple[int, int] | None = None) -> None:
        super().__init__()
        self.detector = detector
        self.targets = targets
        self.sectors = sectors

    def forward(self, points: PointCloudBatch) -> HeadOutput:
        direct = self.detector(points)
        mirrored = self.detector(mirror_points(points, self.sectors))
        detection = 0.5 * (direct.detection + mirror_detection_map(mirrored.detection, self.targets))  # (B, 3, 128, 224)
        freespace = None
        if direct.freespace is not None:
            p = 0.5 * (torch.sigmoid(direct.freespace) + torch.sigmoid(mirrored.freespace.flip(-1)))   # (B, 1, 256, 224)
            freespace = torch.logit(p)        # logits, as every head returns: sigmoid(logit(p)) = p
        return HeadOutput(detection, freespace)
