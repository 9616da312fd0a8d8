"""Mirror averaging at test time: the map mirror against the target encoding of mirrored labels,
hand-worked averages, and the averaged detector's symmetry."""
from __future__ import annotations

import pytest
import torch
from torch import nn

from radarpc.models.heads import HeadOutput
from radarpc.models.mirror import MirrorAveraged, mirror_detection_map
from radarpc.models.pillars import pillars_tiny
from radarpc.models.targets import TargetConfig, encode_batch, encode_targets
from radarpc.points import mirror_points
from testkit import make_cloud

CFG = TargetConfig()
# the azimuth channel passes through shift - n (|shift| < 1e-3, |n| < 4 on these maps): one
# float32 rounding of a value below 4, ulp 4.8e-7, per pass
TOL = 4 * 4.8e-7

# (range m, azimuth deg) pairs at least 3 cells apart, none on a cell edge (an edge's mirror is the
# next cell's edge, which floor() assigns to the other side)
LABELS = [(12.3, 0.37), (30.0, -20.1), (55.5, 41.9), (80.2, 3.3), (7.1, -75.25)]


def _mirrored(ra):
    return torch.tensor([(r, -a) for r, a in ra], dtype=torch.float32)


def test_mirrored_targets_map_back_to_the_targets():
    labels = torch.tensor(LABELS, dtype=torch.float32)
    want = encode_targets(labels, CFG)                                          # (3, 128, 224)
    got = mirror_detection_map(encode_targets(_mirrored(LABELS), CFG)[None], CFG)[0]
    assert torch.equal(got[0], want[0]) and int(want[0].sum()) == 9 * len(LABELS)
    patch = want[0] > 0
    torch.testing.assert_close(got[1:, patch], want[1:, patch], rtol=0, atol=TOL)
    # outside the patches the targets are 0 and the mirror puts its constant shift there
    shift = (CFG.azimuth_cell_deg - 2 * CFG.reg_mean[1]) / CFG.reg_std[1]
    assert torch.equal(got[2, ~patch], torch.full_like(got[2, ~patch], shift)) and torch.equal(got[1, ~patch], want[1, ~patch])


def test_mirror_of_a_map_is_its_own_inverse():
    maps = torch.randn(2, *CFG.shape, generator=torch.Generator().manual_seed(0))
    once = mirror_detection_map(maps, CFG)
    assert not torch.allclose(once, maps)
    torch.testing.assert_close(mirror_detection_map(once, CFG), maps, rtol=0, atol=TOL)


def test_mirror_of_a_map_hand_worked():
    # column j goes to 223 - j; the azimuth offset n to (0.8 - 2 mu) / sigma - n with RADIal's
    # mu = 0.39974, sigma = 0.69430: (0.8 - 0.79948) / 0.69430 = 7.5e-4
    maps = torch.zeros(1, *CFG.shape)
    maps[0, :, 5, 10] = torch.tensor([0.9, 0.25, -1.5])
    out = mirror_detection_map(maps, CFG)
    assert out[0, 0, 5, 213] == pytest.approx(0.9) and out[0, 1, 5, 213] == pytest.approx(0.25)
    assert out[0, 2, 5, 213] == pytest.approx(1.5 + 7.5e-4, abs=1e-5)
    assert out[0, 0].sum() == pytest.approx(0.9)


def test_mirror_of_a_map_refuses_other_shapes():
    with pytest.raises(ValueError, match=r"maps must be \(B, 3, 128, 224\), got shape \(1, 3, 128, 225\)"):
        mirror_detection_map(torch.zeros(1, 3, 128, 225), CFG)


class LabelPainter(nn.Module):
    """A detector whose detections are mirror-symmetric: it paints the target map of its points as
    if each were a vehicle; its freespace map is not (column 0 free, the rest occupied)."""

    def forward(self, points):
        ra = torch.stack([points.range_m, points.azimuth_deg], 1)
        detection = encode_batch(ra, points.offset, CFG)                     # (B, 3, 128, 224)
        freespace = torch.full((len(points), 1, 256, 224), -10.0)
        freespace[..., 0] = 10.0
        return HeadOutput(detection, freespace)


def test_averaging_a_symmetric_detector_keeps_its_detections_and_averages_its_freespace():
    points = make_cloud([LABELS[:3], LABELS[3:]], sector=8)
    direct = LabelPainter()(points)
    averaged = MirrorAveraged(LabelPainter(), CFG, sectors=(4, 2))(points)
    patch = direct.detection[:, 0] > 0                                        # (B, 128, 224)
    assert torch.equal(averaged.detection[:, 0], direct.detection[:, 0]) and int(patch.sum()) == 9 * len(LABELS)
    for c in (1, 2):
        torch.testing.assert_close(averaged.detection[:, c][patch], direct.detection[:, c][patch], rtol=0, atol=TOL)
    # the background's offsets (0 in the targets) average with the mirror's shift: shift / 2
    shift = (CFG.azimuth_cell_deg - 2 * CFG.reg_mean[1]) / CFG.reg_std[1]
    torch.testing.assert_close(averaged.detection[:, 2][~patch], torch.full_like(averaged.detection[:, 2][~patch],
                                                                                 shift / 2), rtol=0, atol=TOL)
    # column 0 is free in one view, occupied in the other: p = (sigmoid(10) + sigmoid(-10)) / 2 = 1/2,
    # logit 0; the other columns keep -10 except column 223, the mirror of column 0 (also 1/2)
    fs = averaged.freespace
    assert fs.shape == (2, 1, 256, 224)
    torch.testing.assert_close(fs[..., 0], torch.zeros_like(fs[..., 0]), rtol=0, atol=1e-5)
    torch.testing.assert_close(fs[..., 223], torch.zeros_like(fs[..., 223]), rtol=0, atol=1e-5)
    torch.testing.assert_close(fs[..., 1:223], torch.full_like(fs[..., 1:223], -10.0), rtol=0, atol=1e-3)


def test_averaged_pillars_are_mirror_symmetric():
    # D averaged over both views: A(m p) = (D(m p) + M D(p)) / 2 = M A(p) whenever M is an affine
    # involution and m an exact one (negation), whatever D is
    torch.manual_seed(0)
    detector = pillars_tiny(features=("r", "a", "e", "d", "Ae", "pillar_offset", "sector"), n_sector=8).eval()
    model = MirrorAveraged(detector, CFG, sectors=(4, 2))
    points = make_cloud([[(5 + 0.9 * k, -80 + 8.3 * k) for k in range(20)], [(40.0, 10.0), (41.0, -12.0)]],
                        sector=8, seed=1)
    with torch.no_grad():
        out = model(points)
        out_m = model(mirror_points(points, (4, 2)))
        plain = detector(points).detection
    torch.testing.assert_close(out_m.detection, mirror_detection_map(out.detection, CFG), rtol=0, atol=TOL)
    torch.testing.assert_close(out_m.freespace, out.freespace.flip(-1), rtol=0, atol=1e-5)
    assert (out.detection - plain).abs().max() > 1e-3            # the average is not the detector alone


def test_mirror_points_negates_azimuth_and_reverses_sectors():
    points = make_cloud([[(10.0, 20.0), (30.0, -5.0)]], sector=8)
    m = mirror_points(points, (4, 2))
    assert torch.equal(m.azimuth_deg, -points.azimuth_deg) and torch.equal(m.y, -points.y)
    assert torch.equal(m.x, points.x) and torch.equal(m.range_m, points.range_m)
    # azimuth-major 4 x 2: sector k = 2 a + e goes to 2 (3 - a) + e
    want = points.sector[:, [6, 7, 4, 5, 2, 3, 0, 1]]
    assert torch.equal(m.sector, want)
    with pytest.raises(ValueError, match="8-wide sector descriptor"):
        mirror_points(points, (3, 2))
