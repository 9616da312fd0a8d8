"""Polar PointPillars / SpectralPillars: pillarisation against hand-worked cases, shapes, sizes, gradients."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F

from radarpc.config import from_dict, to_dict
from radarpc.models.fast.batchnorm import randomise_batchnorm_
from radarpc.models.heads import HeadOutput
from radarpc.models import MODELS, build_model
from radarpc.models.fast.batchnorm import fuse_for_inference
from radarpc.models.pillars import (POINT_FEATURES, PillarsConfig, PillarVFE, PointPillarScatter, PointPillars,
                                    pillar_coords, pillars_tiny, point_features)

PILLARS_VARIANTS = sorted(n for n in MODELS if isinstance(build_model(n, device="meta"), PointPillars))
from testkit import make_cloud


def random_frame(n: int, seed: int) -> list[tuple[float, float]]:
    g = torch.Generator().manual_seed(seed)
    r, a = torch.rand(n, generator=g) * 100, torch.rand(n, generator=g) * 170 - 85
    return [(float(x), float(y)) for x, y in zip(r, a)]


# Hand-worked pillars on the full 256 x 448 grid: dr = 103 / 256 = 0.40234375 m, da = 0.4 deg.
#   (10.0, 0.1):   i_r = floor(10 / 0.40234375) = floor(24.85) = 24, i_a = floor(89.7 / 0.4) = floor(224.25) = 224,
#                  centre (24.5 dr, 224.5 da - 89.6) = (9.857421875, 0.2) -> offsets (0.142578125, -0.1)
#   (10.05, 0.3):  the same pillar (10.05 < 25 dr = 10.0586, 89.9 / 0.4 = 224.75) -> offsets (0.192578125, 0.1)
#   (50.0, -45.0): i_r = floor(124.27) = 124, i_a = floor(44.6 / 0.4) = floor(111.5) = 111,
#                  centre (50.091796875, -45.0) -> offsets (-0.091796875, 0.0)
#   (103.5, 0.0) beyond 103 m and (20.0, -89.7) beyond -89.6 deg: in no pillar
# frame 1 repeats (10.0, 0.1): the same cell in another frame is another pillar; frame 2 is empty.
HAND = [[(10.0, 0.1), (50.0, -45.0), (103.5, 0.0), (10.05, 0.3), (20.0, -89.7)], [(10.0, 0.1)], []]
HAND_KEEP = [True, True, False, True, False, True]
HAND_COORDS = [(0, 24, 224), (0, 124, 111), (0, 24, 224), (1, 24, 224)]
HAND_OFFSETS = [(0.142578125, -0.1), (-0.091796875, 0.0), (0.192578125, 0.1), (0.142578125, -0.1)]
HAND_PILLARS = [(0, 24, 224), (0, 124, 111), (1, 24, 224)]        # sorted by (frame, i_r, i_a)


def test_pillar_indices_and_centre_offsets_by_hand():
    cfg = PillarsConfig(features=("r", "a", "pillar_offset"))
    assert cfg.cell == (0.40234375, pytest.approx(0.4))
    cloud = make_cloud(HAND)
    keep, coords = pillar_coords(cloud, cfg)
    assert keep.tolist() == HAND_KEEP
    assert coords.tolist() == [list(c) for c in HAND_COORDS]
    feats = point_features(cloud, keep, coords, cfg)                           # (4, 4): r, a, dr, da
    kept = [p for f in HAND for p in f]
    kept = [p for p, k in zip(kept, HAND_KEEP) if k]
    want = torch.tensor([[r, a, dr, da] for (r, a), (dr, da) in zip(kept, HAND_OFFSETS)], dtype=torch.float64)
    # float32 inputs (ulp(100) = 7.6e-6) and one float32 product and difference per offset
    torch.testing.assert_close(feats.double(), want, rtol=0, atol=2e-5)


def gelu64(x: float) -> float:
    return 0.5 * x * (1 + math.erf(x / math.sqrt(2)))


def test_pillar_features_are_the_max_over_each_pillars_points():
    cfg = PillarsConfig(features=("r", "a", "pillar_offset"), pfn_channels=3)
    vfe = PillarVFE(cfg).eval()                           # BN with running mean 0, var 1: x / sqrt(1 + eps)
    W = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]]   # r, r offset, -a
    with torch.no_grad():
        vfe.linear.weight.copy_(torch.tensor(W))
    feats, coords = vfe(make_cloud(HAND))
    assert coords.tolist() == [list(c) for c in HAND_PILLARS]
    # independent: per point, gelu(s * W (s * f)), then the channel-wise max over the pillar's points
    s = 1 / math.sqrt(1 + vfe.norm.eps)
    kept = [p for p, k in zip([p for f in HAND for p in f], HAND_KEEP) if k]
    per_point = [[gelu64(s * sum(w * s * x for w, x in zip(row, (r, a, dr, da)))) for row in W]
                 for (r, a), (dr, da) in zip(kept, HAND_OFFSETS)]
    want = [[max(per_point[i][c] for i, pc in enumerate(HAND_COORDS) if pc == pil) for c in range(3)]
            for pil in HAND_PILLARS]
    # the max takes different points per channel in pillar 0: r and its offset from (10.05, 0.3), -a from (10.0, 0.1)
    assert want[0][0] > per_point[0][0] and want[0][2] > per_point[2][2]
    torch.testing.assert_close(feats.double(), torch.tensor(want, dtype=torch.float64), rtol=0, atol=2e-5)


def test_scatter_places_pillars_on_the_pseudo_image():
    cfg = PillarsConfig(pfn_channels=2)
    feats = torch.tensor([[1.0, 2.0], [3.0, -4.0], [5.0, 6.0]])
    coords = torch.tensor(HAND_PILLARS)
    canvas = PointPillarScatter(cfg)(feats, coords, 3)
    assert canvas.shape == (3, 2, 256, 448)
    want = torch.zeros(3, 2, 256, 448)
    for f, (b, i, j) in zip(feats, HAND_PILLARS):
        want[b, :, i, j] = f
    assert torch.equal(canvas, want)


def test_unknown_feature_and_missing_or_mismatched_enrichment():
    with pytest.raises(ValueError, match=r"unknown feature\(s\) \['doppler'\]; known: \['r', 'a'"):
        PillarsConfig(features=("r", "doppler"))
    with pytest.raises(ValueError, match="each feature may be given once"):
        PillarsConfig(features=("r", "r"))
    with pytest.raises(ValueError, match="cfg.yaml: features: unknown|cfg.yaml: PillarsConfig.features: unknown"):
        from_dict(PillarsConfig, {"features": ["r", "Ae", "amp"]}, where="cfg.yaml")
    with pytest.raises(ValueError, match=r"grid \(256, 448\) with first stride 1 .* use grid \(128, 224\)"):
        PillarsConfig(layer_strides=(1, 2, 2))
    with pytest.raises(ValueError, match=r"grid \(256, 448\) is not divisible by the blocks' total stride 12"):
        PillarsConfig(layer_strides=(2, 2, 3), upsample_strides=(1, 2, 6))
    cfg = PillarsConfig(features=("r", "sector"), n_sector=8, grid=(128, 224), layer_strides=(1, 2, 2))
    cloud = make_cloud([[(10.0, 0.1)]])
    keep, coords = pillar_coords(cloud, cfg)
    with pytest.raises(ValueError, match="takes the point feature 'sector' but the point cloud has none"):
        point_features(cloud, keep, coords, cfg)
    cloud = make_cloud([[(10.0, 0.1)]], sector=32)
    with pytest.raises(ValueError, match=r"'sector' has width 32 but the model was built for 8 "
                                         r"\(PillarsConfig.n_sector\)"):
        point_features(cloud, keep, coords, cfg)


def test_config_round_trip_and_feature_widths():
    cfg = PillarsConfig(features=POINT_FEATURES, n_sector=16, n_patch=25)
    assert cfg.in_channels == 6 + 2 + 16 + 25 + 1
    back = from_dict(PillarsConfig, to_dict(cfg))
    assert back == cfg and isinstance(back.features, tuple)
    # every feature reaches the encoder: log(1 + x) of the amplitude columns, raw values otherwise
    cloud = make_cloud([random_frame(6, 1)], sector=16, patch=25)
    keep, coords = pillar_coords(cloud, cfg)
    x = point_features(cloud, keep, coords, cfg)
    assert x.shape == (int(keep.sum()), cfg.in_channels)
    assert POINT_FEATURES[:6] == ("r", "a", "e", "d", "v", "Ae")
    assert torch.equal(x[:, 3], cloud.doppler_bin[keep].float())
    assert torch.equal(x[:, 4], cloud.velocity_mps[keep])          # the resolved velocity, m/s, as it is
    torch.testing.assert_close(x[:, 5], torch.log1p(cloud.amplitude[keep]))
    torch.testing.assert_close(x[:, 8:24], torch.log1p(cloud.sector[keep]))
    assert torch.equal(x[:, -1], cloud.is_neighbour[keep].float())


def test_runs_stored_before_the_freespace_flag_keep_the_official_order():
    # a run.json written before freespace_upsample_logits existed lacks the key: its weights were
    # trained with the official head's order, which the dataclass default keeps; the size variants
    # (and the shipped configs) choose the resized logits
    stored = {k: v for k, v in to_dict(PillarsConfig()).items() if k != "freespace_upsample_logits"}
    assert from_dict(PillarsConfig, stored).freespace_upsample_logits is False
    with torch.device("meta"):
        assert all(MODELS[name]().cfg.freespace_upsample_logits for name in PILLARS_VARIANTS)


@pytest.mark.parametrize("field, value", [("freespace", 1), ("freespace_upsample_logits", "yes")])
def test_config_flags_must_be_booleans(field, value):
    with pytest.raises(ValueError, match=f"PillarsConfig.{field} must be true or false"):
        PillarsConfig(**{field: value})


@pytest.mark.parametrize("name", PILLARS_VARIANTS)
def test_output_shapes_of_every_variant(name):
    with torch.device("meta"):                          # full sizes without allocating or computing
        model = MODELS[name]()
        cfg = model.cfg
        x = model.backbone(torch.empty(2, cfg.pfn_channels, *cfg.grid))
        assert x.shape == (2, cfg.out_channels, 128, 224)
        assert model.detection_head(x).shape == (2, 3, 128, 224)
        assert model.freespace_head(x).shape == (2, 1, 256, 224)


@pytest.mark.parametrize("name, seed_params", [("pointpillars", 2.4e6), ("spectralpillars", 2.4e6)])
def test_full_size_parameter_counts_match_the_seed(name, seed_params):
    # the seed's Table 3: PointPillars and SpectralPillars both 2.4M (with the detection and freespace heads)
    with torch.device("meta"):
        model = MODELS[name]()
    n = sum(p.numel() for p in model.parameters())
    assert abs(n - seed_params) <= 0.05 * seed_params, n


def test_empty_frames_in_a_batch():
    model = pillars_tiny().eval()
    frames = [random_frame(7, 2), [], random_frame(4, 3)]
    cloud = make_cloud(frames)
    with torch.no_grad():
        out = model(cloud)
        assert isinstance(out, HeadOutput)
        assert out.detection.shape == (3, 3, 128, 224) and out.freespace.shape == (3, 1, 256, 224)
        assert torch.isfinite(out.detection).all() and torch.isfinite(out.freespace).all()
        # every frame's BEV map is that of the frame alone (the heads are per-frame convolutions)
        bev = model.bev(cloud)
        for b in range(3):
            torch.testing.assert_close(bev[b], model.bev(cloud.frame(b))[0], rtol=1e-4, atol=1e-5)
        empty = model.bev(make_cloud([[]]))[0]
        torch.testing.assert_close(bev[1], empty)
        assert not torch.allclose(bev[0], empty)
    # training batches without points, or with one point, still run (batch statistics need two)
    model = pillars_tiny(freespace=False).train()
    for frames in ([[], []], [[(10.0, 0.1)], []]):
        out = model(make_cloud(frames))
        assert out.detection.shape == (2, 3, 128, 224) and torch.isfinite(out.detection).all()
        assert out.freespace is None


def test_gradients_flow_and_loss_falls_on_one_batch():
    torch.manual_seed(0)
    model = pillars_tiny(features=("r", "a", "e", "d", "Ae", "pillar_offset", "sector"), n_sector=4,
                         freespace=False)
    cloud = make_cloud([random_frame(40, 4)], sector=4)
    target = torch.zeros(1, 128, 224)
    target[0, 30:33, 100:103] = 1
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    losses = []
    for step in range(5):
        det = model(cloud).detection
        loss = F.binary_cross_entropy(det[:, 0], target) + F.smooth_l1_loss(det[:, 1:], torch.zeros_like(det[:, 1:]))
        opt.zero_grad()
        loss.backward()
        if step == 0:                                  # through the max-pool and the scatter to the point encoder
            for name, p in model.named_parameters():
                assert p.grad is not None and torch.isfinite(p.grad).all(), name
            assert model.vfe.linear.weight.grad.abs().sum() > 0
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.9 * losses[0], losses


@pytest.mark.parametrize("upsample_logits", [False, True])
def test_fused_model_gives_the_same_outputs(upsample_logits):
    torch.manual_seed(1)
    model = pillars_tiny(features=("r", "a", "d", "Ae", "pillar_offset"), freespace_upsample_logits=upsample_logits)
    randomise_batchnorm_(model, torch.Generator().manual_seed(2))
    model.eval()
    fused = fuse_for_inference(model)
    assert not any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in fused.modules())
    cloud = make_cloud([random_frame(20, 6), []])
    with torch.no_grad():
        a, b = model(cloud), fused(cloud)
    # fp32 rounding of a reassociated affine map through a handful of layers
    for x, y in ((a.detection, b.detection), (a.freespace, b.freespace)):
        assert (x - y).abs().max() <= 1e-4 * x.abs().max()


def test_velocity_feature_reaches_the_output_and_doppler_index_does_not():
    # the + v arm's model reads velocity_mps, not doppler_bin
    torch.manual_seed(0)
    model = pillars_tiny(features=("r", "a", "e", "v", "pillar_offset")).eval()
    randomise_batchnorm_(model, torch.Generator().manual_seed(0))
    cloud = make_cloud([random_frame(40, 5)])
    with torch.no_grad():
        out = model(cloud).detection
        other_d = dataclasses.replace(cloud, doppler_bin=(cloud.doppler_bin + 5) % 16)
        assert torch.equal(model(other_d).detection, out)
        other_v = dataclasses.replace(cloud, velocity_mps=-cloud.velocity_mps)
        assert not torch.allclose(model(other_v).detection, out)
