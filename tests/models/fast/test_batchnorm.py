"""BatchNorm folding against the unfolded pair, on hand-sized layers."""
import pytest
import torch
from torch import nn

from radarpc.models.fast.batchnorm import fold_batchnorm, randomise_batchnorm_


@pytest.mark.parametrize("conv", [nn.Conv2d(3, 5, 3, padding=1), nn.Conv2d(3, 5, 1, bias=False),
                                  nn.ConvTranspose2d(3, 5, 2, stride=2), nn.ConvTranspose2d(3, 5, 3, bias=False)])
def test_folded_conv_equals_conv_then_bn(conv):
    torch.manual_seed(0)
    bn = randomise_batchnorm_(nn.BatchNorm2d(5), torch.Generator().manual_seed(1)).eval()
    x = torch.randn(2, 3, 6, 7, dtype=torch.float64)
    conv, bn = conv.double(), bn.double()
    with torch.no_grad():
        want = bn(conv(x))
        fold_batchnorm(conv, bn)
        got = conv(x)
    # float64: a reassociated affine map, rounding ~1e-16 relative
    assert torch.allclose(got, want, rtol=1e-12, atol=1e-12 * want.abs().max().item())


def test_fold_without_affine_and_refusals():
    conv, bn = nn.Conv2d(2, 3, 1).double(), nn.BatchNorm2d(3, affine=False).double()
    randomise_batchnorm_(bn, torch.Generator().manual_seed(0)).eval()
    x = torch.randn(1, 2, 4, 4, dtype=torch.float64)
    with torch.no_grad():
        want = bn(conv(x))
        fold_batchnorm(conv, bn)
        assert torch.allclose(conv(x), want, rtol=1e-12, atol=1e-12 * want.abs().max().item())
    with pytest.raises(ValueError, match="groups=2"):
        fold_batchnorm(nn.ConvTranspose2d(4, 4, 2, groups=2), nn.BatchNorm2d(4))
    with pytest.raises(ValueError, match="running statistics"):
        fold_batchnorm(nn.Conv2d(2, 3, 1), nn.BatchNorm2d(3, track_running_stats=False))


def test_randomise_makes_bn_non_trivial_and_keeps_non_affine():
    g = torch.Generator().manual_seed(0)
    model = nn.Sequential(nn.BatchNorm2d(4), nn.BatchNorm1d(3, affine=False))
    randomise_batchnorm_(model, g)
    bn2, bn1 = model
    assert not torch.equal(bn2.running_mean, torch.zeros(4)) and not torch.equal(bn2.running_var, torch.ones(4))
    assert ((bn2.running_var >= 0.5) & (bn2.running_var <= 1.5)).all()
    assert ((bn2.weight >= 0.5) & (bn2.weight <= 1.5)).all()
    assert not torch.equal(bn1.running_mean, torch.zeros(3)) and bn1.weight is None
