"""FFTRadNet: sizes, the official key layout against an independent functional forward, weights
files, input statistics and the fused inference path."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from radarpc.models.fast.batchnorm import randomise_batchnorm_
from radarpc.config import from_dict, to_dict
from radarpc.experiments.radial_detection.official import (load_official_checkpoint, official_to_radarpc,
                                                           radarpc_to_official)
from radarpc.models import ModelSpec
from radarpc.models.fast.batchnorm import fuse_for_inference
from radarpc.models.fftradnet import (FFTRadNetConfig, StridedConv1x1, cube_to_channels, fftradnet, fftradnet_s,
                                      fftradnet_tiny, input_statistics)
from radarpc.training.checkpoint import load_weights, save_weights


def _cube(b: int, cfg: FFTRadNetConfig, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, cfg.n_range, cfg.n_doppler, cfg.n_rx, dtype=torch.complex64, generator=g)


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    m = fftradnet_tiny().eval()
    randomise_batchnorm_(m, torch.Generator().manual_seed(0))
    return m


# ---- sizes ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("factory", [fftradnet, fftradnet_s])
def test_output_shapes_on_meta(factory):
    with torch.device("meta"):
        m = factory()
        # the real network input: complex ops on meta tensors are slow to trace
        out = m.forward_channels(torch.empty(2, 2 * m.cfg.n_rx, m.cfg.n_range, m.cfg.n_doppler))
    assert out.detection.shape == (2, 3, 128, 224)
    assert out.freespace.shape == (2, 1, 256, 224)


def test_full_size_has_the_official_parameter_count():
    with torch.device("meta"):
        m = fftradnet()
    assert sum(p.numel() for p in m.parameters()) == 3_789_940
    assert m.cfg.blocks == (3, 6, 6, 3) and m.cfg.channels == (32, 40, 48, 56)


def test_tiny_forward_and_no_freespace(tiny):
    rd = _cube(1, tiny.cfg)
    with torch.no_grad():
        out = tiny(rd)
    assert out.detection.shape == (1, 3, 128, 224) and out.freespace.shape == (1, 1, 256, 224)
    p = out.detection[:, 0]
    assert bool(((p >= 0) & (p <= 1)).all())            # channel 0 is a probability
    m = fftradnet_tiny(freespace=False)
    assert m.freespace_head is None and m(rd).freespace is None


def test_bad_config_and_input_are_refused():
    with pytest.raises(ValueError, match="128 rows"):
        FFTRadNetConfig(n_range=256)
    with pytest.raises(ValueError, match="azimuth columns"):
        FFTRadNetConfig(channels=(32, 40, 48, 50))
    with pytest.raises(ValueError, match=r"rd must be \(B, 128, 64, 16\) complex"):
        fftradnet_tiny()(torch.zeros(1, 64, 64, 16, dtype=torch.complex64))
    with pytest.raises(ValueError, match="rd must be a complex"):
        cube_to_channels(torch.zeros(1, 4, 4, 2))


# ---- input layout and statistics ------------------------------------------------------------------
def test_channel_layout_is_real_parts_then_imaginary_parts():
    rd = torch.zeros(1, 2, 3, 2, dtype=torch.complex64)
    rd[0, 1, 2, 0] = 1 + 2j
    rd[0, 0, 1, 1] = 3 - 4j
    x = cube_to_channels(rd)
    assert x.shape == (1, 4, 2, 3)
    assert x[0, 0, 1, 2] == 1 and x[0, 2, 1, 2] == 2      # rx 0: channel 0 real, channel 2 imaginary
    assert x[0, 1, 0, 1] == 3 and x[0, 3, 0, 1] == -4
    assert int((x != 0).sum()) == 4


def test_input_statistics_hand_case():
    # one receiver, two frames of two cells: real parts (1, 3) and (5, 5), imaginary (0, 2) and (-2, 2)
    f1 = torch.tensor([[[1 + 0j]], [[3 + 2j]]], dtype=torch.complex64)    # (Nr=2, Nd=1, Nrx=1)
    f2 = torch.tensor([[[5 - 2j]], [[5 + 2j]]], dtype=torch.complex64)
    mean, std = input_statistics([f1, f2.unsqueeze(0)])
    # per-frame means (2, 5) and (1, 0); population stds (1, 0) and (1, 2); averaged over frames
    torch.testing.assert_close(mean, torch.tensor([3.5, 0.5]))
    torch.testing.assert_close(std, torch.tensor([0.5, 1.5]))
    with pytest.raises(ValueError, match="empty"):
        input_statistics([])
    with pytest.raises(ValueError, match="constant"):
        input_statistics([f2])                                            # real part constant in the frame


def test_normalised_input_uses_the_stored_statistics(tiny):
    m = fftradnet_tiny()
    mean, std = torch.arange(32.0), torch.linspace(1, 4, 32)
    m.set_input_statistics(mean, std)
    rd = _cube(1, m.cfg)
    x = m.normalised_input(rd)
    ref = (torch.cat([rd.real, rd.imag], -1) - mean) / std                 # channels last here
    torch.testing.assert_close(x, ref.permute(0, 3, 1, 2), rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"\(32,\) each"):
        m.set_input_statistics(mean[:16], std[:16])


# ---- official key layout, against a functional forward written from the official architecture -----
def _bn(x, w, p):
    return F.batch_norm(x, w[p + "running_mean"], w[p + "running_var"], w[p + "weight"], w[p + "bias"],
                        training=False, eps=1e-5)


def _conv_bn_block(x, w, p):        # official BasicBlock: conv(bias)-BN-ReLU twice
    x = F.relu(_bn(F.conv2d(x, w[p + "conv1.weight"], w[p + "conv1.bias"], padding=1), w, p + "bn1."))
    return F.relu(_bn(F.conv2d(x, w[p + "conv2.weight"], w[p + "conv2.bias"], padding=1), w, p + "bn2."))


def _bottleneck(x, w, p, stride):
    out = F.relu(_bn(F.conv2d(x, w[p + "conv1.weight"]), w, p + "bn1."))
    out = F.relu(_bn(F.conv2d(out, w[p + "conv2.weight"], stride=stride, padding=1), w, p + "bn2."))
    out = _bn(F.conv2d(out, w[p + "conv3.weight"]), w, p + "bn3.")
    if p + "downsample.0.weight" in w:
        x = _bn(F.conv2d(x, w[p + "downsample.0.weight"], stride=stride), w, p + "downsample.1.")
    return F.relu(x + out)


def _official_functional(x, w, cfg):
    """FFTRadNet from the official key names with torch.nn.functional (no radarpc module used)."""
    half = cfg.n_tx * cfg.slot_width // 2
    # pre-encoder: circular Doppler padding, dilated Doppler conv, centre crop of width Nd, BN
    xp = F.pad(x, (half, half, 0, 0), mode="circular")
    y = F.conv2d(xp, w["FPN.pre_enc.conv.weight"], dilation=(1, cfg.slot_width))
    start = (y.shape[-1] - x.shape[-1]) // 2
    y = _bn(y[..., start:start + x.shape[-1]], w, "FPN.pre_enc.bn.")
    y = F.relu(_bn(F.conv2d(y, w["FPN.conv.weight"], padding=1), w, "FPN.bn."))
    feats = []
    for k, (n, rs) in enumerate(zip(cfg.blocks, (*cfg.range_strides, 2, 2)), start=1):
        for j in range(n):
            y = _bottleneck(y, w, f"FPN.block{k}.{j}.", (rs, 2) if j == 0 else 1)
        feats.append(y)
    _, x2, x3, x4 = feats
    t4 = x4.transpose(1, 3)
    t3 = F.conv2d(x3, w["RA_decoder.L3.weight"], w["RA_decoder.L3.bias"]).transpose(1, 3)
    t2 = F.conv2d(x2, w["RA_decoder.L2.weight"], w["RA_decoder.L2.bias"]).transpose(1, 3)
    up = lambda t, p: F.conv_transpose2d(t, w[p + ".weight"], w[p + ".bias"], stride=(2, 1), padding=1,
                                         output_padding=(1, 0))
    s4 = _conv_bn_block(torch.cat([up(t4, "RA_decoder.deconv4"), t3], 1), w, "RA_decoder.conv_block4.")
    ra = _conv_bn_block(torch.cat([up(s4, "RA_decoder.deconv3"), t2], 1), w, "RA_decoder.conv_block3.")
    h = ra
    for i in range(1, 5):
        h = _bn(F.conv2d(h, w[f"detection_header.conv{i}.weight"], padding=1), w, f"detection_header.bn{i}.")
    det = torch.cat([torch.sigmoid(F.conv2d(h, w["detection_header.clshead.weight"],
                                            w["detection_header.clshead.bias"], padding=1)),
                     F.conv2d(h, w["detection_header.reghead.weight"], w["detection_header.reghead.bias"],
                              padding=1)], 1)
    f = F.interpolate(ra, (256, 224))
    f = _conv_bn_block(_conv_bn_block(f, w, "freespace.0."), w, "freespace.1.")
    return det, F.conv2d(f, w["freespace.2.weight"], w["freespace.2.bias"])


def test_official_keys_load_and_match_a_functional_forward(tiny):
    official = {k: v.clone() for k, v in radarpc_to_official(tiny.state_dict()).items()}
    assert "FPN.pre_enc.conv.weight" in official and "freespace.2.bias" in official
    assert not any(k.startswith(("backbone", "decoder", "input_")) for k in official)
    m = fftradnet_tiny().eval()
    missing, unexpected = m.load_state_dict(official_to_radarpc(official), strict=False)
    assert set(missing) == {"input_mean", "input_std"} and not unexpected
    cfg = m.cfg
    x = torch.randn(1, 2 * cfg.n_rx, cfg.n_range, cfg.n_doppler, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        out = m.forward_channels(x)
        det, fs = _official_functional(x, official, cfg)
    # the same ops in the same order: equal up to the summation order inside library kernels
    for a, b in ((out.detection, det), (out.freespace, fs)):
        scale = b.abs().max()
        assert (a - b).abs().max() <= 1e-5 * scale, float((a - b).abs().max() / scale)
    assert out.detection[:, 0].std() > 0 and fs.std() > 0                  # not a degenerate map


def test_official_checkpoint_layouts(tmp_path, tiny):
    official = radarpc_to_official(tiny.state_dict())
    # the training script's layout: metric history as NumPy scalars beside the weights
    torch.save({"net_state_dict": official, "optimizer": {"lr": 1e-4}, "epoch": 3,
                "history": {"mAP": [np.float64(0.9)], "mIoU": [np.float32(0.7)]}}, tmp_path / "a.pth")
    torch.save({"module." + k: v for k, v in official.items()}, tmp_path / "b.pth")
    for name in ("a.pth", "b.pth"):
        sd = load_official_checkpoint(tmp_path / name)
        assert sd.keys() == official_to_radarpc(official).keys()
        torch.testing.assert_close(sd["pre_encoder.conv.weight"], tiny.pre_encoder.conv.weight)
    with pytest.raises(KeyError, match="not a key of the official FFTRadNet"):
        official_to_radarpc({"encoder.weight": torch.zeros(1)})


class _Opaque:
    """An object only full unpickling can rebuild."""


def test_pickle_only_checkpoint_is_refused(tmp_path, tiny):
    path = tmp_path / "c.pth"
    torch.save({"net_state_dict": radarpc_to_official(tiny.state_dict()), "args": _Opaque()}, path)
    with pytest.raises(ValueError, match=r"c\.pth: refusing to load: .*full unpickling"):
        load_official_checkpoint(path)
    (tmp_path / "d.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"d\.pth: "):
        load_official_checkpoint(tmp_path / "d.pth")


# ---- radarpc weights ------------------------------------------------------------------------------
def test_weights_and_spec_rebuild_the_model(tmp_path, tiny):
    """radarpc's one weights format (safetensors, radarpc.training.checkpoint) with the model's
    registry spec beside it rebuilds the same network: statistics buffers included."""
    tiny.set_input_statistics(torch.full((32,), 0.5), torch.full((32,), 2.0))
    spec = ModelSpec.matching("fftradnet-tiny", tiny.cfg)
    path = save_weights(tmp_path / "w.safetensors", tiny.state_dict(), {"model": to_dict(spec)})
    state, info = load_weights(path)
    back = from_dict(ModelSpec, info["model"]).build()
    back.load_state_dict(state)
    back.eval()
    assert back.cfg == tiny.cfg
    for k, v in tiny.state_dict().items():
        assert torch.equal(back.state_dict()[k], v), k
    rd = _cube(1, tiny.cfg, seed=3)
    with torch.no_grad():
        assert torch.equal(back(rd).detection, tiny(rd).detection)
    tiny.set_input_statistics(torch.zeros(32), torch.ones(32))


# ---- fused inference path -------------------------------------------------------------------------
def test_fused_model_equals_plain_model(tiny):
    fused = fuse_for_inference(tiny)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in tiny.modules())   # the original is untouched
    plain64 = copy.deepcopy(tiny).double()
    fused64 = fuse_for_inference(plain64)                 # folded in float64
    rd = _cube(1, tiny.cfg, seed=2)
    with torch.no_grad():
        p32, f32 = tiny(rd), fused(rd)
        p64, f64 = plain64(rd.to(torch.complex128)), fused64(rd.to(torch.complex128))
    for name in ("detection", "freespace"):
        a32, b32, a64, b64 = (getattr(o, name) for o in (p32, f32, p64, f64))
        scale = a64.abs().max()
        # exact in real arithmetic: in float64 they agree to float64 rounding
        assert (a64 - b64).abs().max() <= 1e-10 * scale
        # in float32 the fused model is as close to the exact result as the plain one, within a few
        # times the plain model's own float32 error
        err = (a32.double() - a64).abs().max()
        assert (b32.double() - a64).abs().max() <= 4 * err + 1e-6 * scale


@pytest.mark.parametrize("stride", [(1, 2), (2, 2)])
def test_strided_shortcut_is_the_strided_1x1_convolution(stride):
    # StridedConv1x1 (subsample, then a 1 x 1 convolution) against torch's own strided convolution in
    # float64 (not a oneDNN path), values and gradients; odd sizes check the ceil(H / s) output
    g = torch.Generator().manual_seed(0)
    conv = StridedConv1x1(3, 5, stride=stride, bias=True).double()
    assert dict(conv.state_dict()).keys() == {"weight", "bias"} and conv.weight.shape == (5, 3, 1, 1)
    x = torch.randn(2, 3, 7, 9, dtype=torch.float64, generator=g, requires_grad=True)
    y = conv(x)
    ref = F.conv2d(x, conv.weight, conv.bias, stride=stride)
    assert y.shape == ref.shape == (2, 5, -(-7 // stride[0]), -(-9 // stride[1]))
    torch.testing.assert_close(y, ref, rtol=1e-12, atol=1e-12)
    w = torch.randn(y.shape, dtype=torch.float64, generator=g)
    gx, gw, gb = torch.autograd.grad((y * w).sum(), (x, conv.weight, conv.bias))
    rx, rw, rb = torch.autograd.grad((ref * w).sum(), (x, conv.weight, conv.bias))
    for a, b in ((gx, rx), (gw, rw), (gb, rb)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_strided_shortcut_backward_runs_where_onednn_crashed():
    # the fp32 channels-last shape whose strided-conv backward corrupted memory in oneDNN's AVX-512
    # kernels (torch 2.13): 8 -> 16 channels, stride (1, 2), a 4 x 8 x 128 x 64 input
    g = torch.Generator().manual_seed(0)
    conv = StridedConv1x1(8, 16, stride=(1, 2)).to(memory_format=torch.channels_last)
    x = torch.randn(4, 8, 128, 64, generator=g).contiguous(memory_format=torch.channels_last).requires_grad_()
    for _ in range(2):
        conv(x).square().mean().backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(conv.weight.grad).all()
