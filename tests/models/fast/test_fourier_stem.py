"""FourierStem (pre-encoder + stem + ReLU per Doppler frequency) against the two layers in float64."""
import copy
import math

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models.fast.batchnorm import randomise_batchnorm_
from radarpc.models.fftradnet import MIMOPreEncoder, fftradnet_tiny
from radarpc.models.fast.fourier_stem import FourierStem, doppler_shifts, fourier_stem_for_inference
from radarpc.models.fast.winograd import WinogradConv2d, winograd_for_inference
from testkit import warns_reduced_fp32_matmul

UNIT_ROUNDOFF = {torch.float32: 2.0 ** -24, torch.float64: 2.0 ** -53}


def layers(c_in, c_mid, c_out, n_tx, slot_width, seed):
    """A BN-folded pre-encoder (random weights and bias) and stem."""
    g = torch.Generator().manual_seed(seed)
    pre = MIMOPreEncoder(c_in, c_mid, n_tx, slot_width)
    with torch.no_grad():
        pre.conv.weight.copy_(torch.randn(pre.conv.weight.shape, generator=g) / math.sqrt(c_in * n_tx))
        pre.conv.bias = nn.Parameter(torch.randn(c_mid, generator=g))
    pre.bn = nn.Identity()
    stem = nn.Conv2d(c_mid, c_out, 3, padding=1)
    with torch.no_grad():
        stem.weight.copy_(torch.randn(stem.weight.shape, generator=g) / math.sqrt(9 * c_mid))
        stem.bias.copy_(torch.randn(c_out, generator=g))
    return pre.eval(), stem.eval()


def direct(pre, stem, x, weights=lambda w: w):
    """``stem(pre_encoder(x))`` before the ReLU, in float64 (``weights`` maps each weight and bias)."""
    pre, stem = copy.deepcopy(pre).double(), copy.deepcopy(stem).double()
    with torch.no_grad():
        for p in (*pre.parameters(), *stem.parameters()):
            p.copy_(weights(p))
        return stem(pre(x.double()))


def error_bound(layer: FourierStem, pre, stem, x) -> float:
    """A worst-case bound on ``||computed - exact||_F`` over the whole output, in ``x``'s precision.

    Each step's error, carried to the output (Frobenius norms; F = N / 2 + 1 frequencies):

    * the forward and inverse real FFTs: normwise relative ``e = L eta / (1 - L eta)``, ``L`` their
      radix-2 stages (log2 N, and one more for the real-to-complex packing), ``eta = u + gamma_4 (sqrt 2 + u)``
      (Higham, Accuracy and Stability, Thm 24.2); the inverse maps a spectrum error ``dY`` to at most
      ``sqrt(2 / N) ||dY||`` (Parseval for a half spectrum);
    * the spectra's error through the products: ``sqrt 3 e ||X|| max_f ||W_f||_2`` (three row taps);
    * the products themselves, the weights' rounding to ``x``'s dtype and the bias added at frequency
      0: ``gamma_{6C+2} || |A| |W| + N |bias| ||``;
    * the edge columns computed directly: ``gamma_{C T + 3 O + 2}`` times the magnitude of their terms;
    * the epilogue's subtraction: ``u`` times the output (the ReLU does not add error).
    """
    u = UNIT_ROUNDOFF[x.dtype]
    gamma = lambda n: n * u / (1 - n * u)                                      # noqa: E731
    b, c, r, n = x.shape
    stages = math.log2(n) + 1
    eta = u + gamma(4) * (math.sqrt(2) + u)
    e = stages * eta / (1 - stages * eta)
    x64 = x.double()
    spectra = torch.fft.rfft(x64, dim=3)                                       # (B, C, R, F)
    w = layer.w.double()                                                       # (F, 6C, 2K)
    norm_w = float(torch.linalg.matrix_norm(w, ord=2).max())
    padded = F.pad(torch.view_as_real(spectra).abs().permute(3, 0, 2, 4, 1), (0, 0, 0, 0, 1, 1))   # (F, B, R+2, 2, C)
    a = torch.cat([padded[:, :, i:i + r].flatten(3) for i in range(3)], dim=3).flatten(1, 2)    # |A|, (F, B R, 6C)
    terms = a @ w.abs()
    terms[0, :, 0::2] += n * (layer.bias.double().abs() + layer.bias_taps.double().abs().sum(0))
    spectrum_error = (math.sqrt(3) * e * float(spectra.abs().pow(2).sum().sqrt()) * norm_w
                      + gamma(6 * c + 2) * float(terms.pow(2).sum().sqrt()))
    exact = direct(pre, stem, x64)
    edges = direct(pre, stem, x64, weights=lambda p: p.abs())                  # |S| (|P| |x| + |b1|) + |b2|
    edge_terms = float(edges[..., [0, n - 1]].pow(2).sum().sqrt())
    return (math.sqrt(2 / n) * spectrum_error + e * float(exact.pow(2).sum().sqrt())
            + gamma(c * pre.conv.kernel_size[1] + 3 * stem.in_channels + 2) * edge_terms
            + u * float(exact.pow(2).sum().sqrt()))


CASES = [  # (B, C, O, K, n_tx, slot_width, R, N, row_block): even and odd n_tx, row blocks not dividing R
    (1, 4, 6, 5, 4, 2, 9, 16, 4),
    (2, 3, 5, 7, 3, 4, 7, 32, 64),
    (1, 8, 8, 8, 12, 4, 12, 64, 5),
]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", CASES)
def test_matches_the_two_layers_within_the_rounding_bound(case, dtype):
    bsz, c, o, k, n_tx, slot_width, r, n, row_block = case
    pre, stem = layers(c, o, k, n_tx, slot_width, seed=sum(case))
    # weights formed in float64 and rounded once to dtype (as from a model of that dtype)
    layer = FourierStem(pre.to(dtype), stem.to(dtype), n, row_block=row_block, compiled=False)
    x = torch.randn(bsz, c, r, n, generator=torch.Generator().manual_seed(1), dtype=dtype)
    with torch.inference_mode():
        y = layer(x)
    exact = direct(pre, stem, x)
    assert y.shape == (bsz, k, r, n) and y.dtype == dtype
    assert y.is_contiguous(memory_format=torch.channels_last)
    bound = error_bound(layer, pre, stem, x)
    err = float((y.double() - exact.clamp_min(0)).pow(2).sum().sqrt())
    assert err <= bound
    # the bound is far below the output, so a wrong edge, bias or shift breaks it
    assert bound < 1e-3 * float(exact.pow(2).sum().sqrt())


def test_doppler_shifts_follow_the_official_crop():
    """Every tap's offset against a direct evaluation of the circular pad, conv and centre crop."""
    for n_tx, slot_width, n in ((12, 16, 256), (4, 2, 16), (3, 4, 32), (12, 4, 64)):
        pre = MIMOPreEncoder(1, n_tx, n_tx, slot_width)
        pre.bn = nn.Identity()
        with torch.no_grad():
            pre.conv.weight.copy_(torch.eye(n_tx)[:, None, None, :])          # output t = tap t alone
        x = torch.arange(n, dtype=torch.float64).reshape(1, 1, 1, n)
        with torch.no_grad():
            y = pre.double()(x)[0, :, 0]                                     # (T, N): the input bin each reads
        d = torch.arange(n, dtype=torch.float64)
        for t, s in enumerate(doppler_shifts(pre, n)):
            assert torch.equal(y[t], (d + s) % n)


def test_wrong_edges_break_the_bound():
    pre, stem = layers(4, 6, 5, 4, 2, seed=3)
    layer = FourierStem(pre, stem, 16, compiled=False)
    layer.s_edges.zero_()                                                    # as if the circular stem were right
    x = torch.randn(1, 4, 9, 16, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        y = layer(x)
    err = float((y.double() - direct(pre, stem, x).clamp_min(0)).pow(2).sum().sqrt())
    assert err > error_bound(layer, pre, stem, x)


def test_compiled_epilogue_agrees():
    pre, stem = layers(4, 6, 5, 4, 2, seed=4)
    x = torch.randn(2, 4, 9, 16, generator=torch.Generator().manual_seed(2))
    with torch.inference_mode():
        y = FourierStem(pre, stem, 16, row_block=4, compiled=True)(x)
    layer = FourierStem(pre, stem, 16, compiled=False)
    err = float((y.double() - direct(pre, stem, x).clamp_min(0)).pow(2).sum().sqrt())
    assert err <= error_bound(layer, pre, stem, x)


def test_tiny_fftradnet_conversion():
    """The converted copy's maps agree with the model's (the stem's output is within its bound above;
    what follows is the same network), the original is untouched, and Winograd layers compose."""
    model = randomise_batchnorm_(fftradnet_tiny(), torch.Generator().manual_seed(5)).eval()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    fast = fourier_stem_for_inference(model, compiled=False)
    assert isinstance(fast.pre_encoder, FourierStem) and isinstance(fast.backbone.conv, nn.Identity)
    assert isinstance(model.pre_encoder, MIMOPreEncoder) and isinstance(model.backbone.conv, nn.Conv2d)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())
    both = winograd_for_inference(fast, min_channels=8, compiled=False)
    assert any(isinstance(m, WinogradConv2d) for m in both.modules())
    x = torch.randn(2, 32, 128, 64, generator=torch.Generator().manual_seed(6))
    with torch.inference_mode():
        ref = model.forward_channels(x)
        for m in (fast, both):
            out = m.forward_channels(x)
            assert float((out.detection - ref.detection).abs().max()) <= 1e-3 * float(ref.detection.abs().max())
            assert float((out.freespace - ref.freespace).abs().max()) <= 1e-3 * float(ref.freespace.abs().max())
    with pytest.raises(ValueError, match="already converted"):
        fourier_stem_for_inference(fast)


def test_bad_input_is_named():
    pre, stem = layers(4, 6, 5, 4, 2, seed=3)
    layer = FourierStem(pre, stem, 16, compiled=False)
    with pytest.raises(ValueError, match=r"x must be \(B, 4, R, 16\), got \(1, 4, 9, 8\)"):
        layer(torch.randn(1, 4, 9, 8))
    with pytest.raises(ValueError, match="x is torch.float64 on cpu, the weights torch.float32"):
        layer(torch.randn(1, 4, 9, 16, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="inference only"):
        layer(torch.randn(1, 4, 9, 16, requires_grad=True))
    unfolded = MIMOPreEncoder(4, 6, 4, 2)
    with pytest.raises(ValueError, match="BatchNorm folded"):
        FourierStem(unfolded, stem, 16)
    with pytest.raises(ValueError, match="3 x 3, stride-1, padding-1 Conv2d with 6 input channels"):
        FourierStem(pre, nn.Conv2d(6, 5, 3, stride=2, padding=1), 16)
    with pytest.raises(ValueError, match="3 x 3, stride-1, padding-1 Conv2d with 6 input channels"):
        FourierStem(pre, nn.Conv2d(7, 5, 3, padding=1), 16)
    with pytest.raises(ValueError, match="row_block >= 1"):
        FourierStem(pre, stem, 16, row_block=0)
    with pytest.raises(TypeError, match="expected an FFTRadNet"):
        fourier_stem_for_inference(nn.Conv2d(1, 1, 1))


def test_reduced_float32_matmul_precision_is_warned():
    pre, stem = layers(4, 6, 5, 4, 2, seed=3)
    layer = FourierStem(pre, stem, 16, compiled=False)
    with warns_reduced_fp32_matmul(), torch.inference_mode():
        layer(torch.randn(1, 4, 9, 16))


def test_built_on_the_weights_device():
    """Every composed buffer is made where the weights are (the meta device here stands in for a GPU:
    a tensor made on the CPU by mistake would meet a meta one and raise)."""
    pre, stem = layers(4, 6, 5, 4, 2, seed=3)
    layer = FourierStem(pre.to("meta"), stem.to("meta"), 16, compiled=False)
    assert all(b.device.type == "meta" for b in layer.buffers())
    with pytest.raises(ValueError, match="circular pad 16 exceeds n_doppler=8"):
        FourierStem(*layers(4, 6, 5, 8, 4, seed=3), 8)
