"""The radar-to-occupancy network (RaLD's learned baseline): parameter counts of the factories
against a count by hand, output shapes, per-frame independence and the config's checks."""
import pytest
import torch

from radarpc.models import MODELS, ModelSpec, build_model
from radarpc.models.rpdnet import RPDNetConfig


def _count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def _by_hand(cfg: RPDNetConfig) -> int:
    """Parameters of the network the module docstring describes, counted from the layer list:
    a k^3 conv ``c_in c_out k^3 + c_out``, a GroupNorm ``2 c``, a residual block two GN + 3^3 conv
    pairs and a 1^3 skip conv when the width changes."""
    def conv(ci, co, k):
        return ci * co * k ** 3 + co

    def res(ci, co):
        return 2 * ci + conv(ci, co, 3) + 2 * co + conv(co, co, 3) + (conv(ci, co, 1) if ci != co else 0)

    w = [cfg.channels * m for m in cfg.ch_mult]
    n = conv(1, w[0], 3) + 2 * w[0]                                             # stem
    n += sum(conv(w[i - 1], w[i], 3) + 2 * w[i] + cfg.blocks * res(w[i], w[i]) for i in range(1, len(w)))
    n += sum(res(w[i + 1] + w[i], w[i]) for i in range(cfg.out_level, len(w) - 1))   # decoder
    return n + 2 * w[cfg.out_level] + conv(w[cfg.out_level], 1, 1)              # head


@pytest.mark.parametrize("name, total, out_shape", [
    ("rpdnet", 51_869_697, (64, 32, 16)),
    ("rpdnet-s", 506_785, (64, 32, 16)),
    ("rpdnet-tiny", 30_961, (32, 16, 8)),
])
def test_factories_parameter_counts_and_output_grids(name, total, out_shape):
    model = build_model(name, device="meta")
    assert _count(model) == _by_hand(model.cfg) == total
    assert model.cfg.out_shape == out_shape and type(model).input_kind == "radar"
    assert name in MODELS and ModelSpec(name).input_kind == "radar"


def test_output_shape_and_each_frame_alone():
    """Logits (B, *out_shape) for cubes (B, *radar_shape); GroupNorm normalises each frame by
    itself, so a frame's logits do not depend on the other frames of its batch."""
    torch.manual_seed(0)
    model = MODELS["rpdnet-tiny"]().eval()
    x = torch.rand(3, 32, 16, 8)
    with torch.no_grad():
        out = model(x)
        alone = torch.cat([model(x[i:i + 1]) for i in range(3)])
    assert out.shape == (3, 32, 16, 8) and out.dtype == torch.float32 and bool(torch.isfinite(out).all())
    torch.testing.assert_close(out, alone, rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        assert MODELS["rpdnet-tiny"](out_stride=2)(x).shape == (3, 16, 8, 4)


def test_bad_inputs_and_configs():
    with pytest.raises(ValueError, match=r"expected intensity cubes \(B, 32, 16, 8\), got \(2, 32, 16\)"):
        MODELS["rpdnet-tiny"]()(torch.zeros(2, 32, 16))
    with pytest.raises(ValueError, match="out_stride must be a power of two, got 3"):
        RPDNetConfig(out_stride=3)
    with pytest.raises(ValueError, match="out_stride 16 is level 4, but the encoder has only 4 levels"):
        RPDNetConfig(out_stride=16)
    with pytest.raises(ValueError, match=r"radar_shape \(128, 64, 20\) is not divisible by 8"):
        RPDNetConfig(radar_shape=(128, 64, 20))
    with pytest.raises(ValueError, match="groups 3 does not divide the widths"):
        RPDNetConfig(groups=3)
    with pytest.raises(ValueError, match="model 'rpdnet-s'"):
        ModelSpec("rpdnet-s", {"channels": 0})
