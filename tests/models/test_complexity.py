"""Convolution MACs counted on a hand-worked network."""
import pytest
import torch

from radarpc.models.complexity import conv_gmac


class _Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(4, 6, 3, padding=1, groups=2)          # 4 x 6 outputs of 6 channels
        self.up = torch.nn.ConvTranspose2d(6, 5, 3, stride=(2, 1), padding=1, output_padding=(1, 0))
        self.act = torch.nn.ReLU()
        self.head = torch.nn.Conv2d(5, 1, 1)

    def forward_channels(self, x):
        return self.up(self.act(self.conv(x)))

    def forward(self, x):
        return self.head(self.forward_channels(x))


def test_conv_gmac_counts_convolutions_and_transposed_convolutions():
    net, x = _Net(), torch.randn(1, 4, 4, 6)
    # conv: 6 x 4 x 6 outputs, each 3 x 3 x (4 / 2) MACs = 144 x 18; transposed: each of its
    # 6 x 4 x 6 inputs feeds 3 x 3 x 5 outputs = 144 x 45
    body = (144 * 18 + 144 * 45) / 1e9
    assert conv_gmac(net, x, forward=net.forward_channels) == pytest.approx(body, rel=1e-12)
    # the whole forward adds the 1 x 1 head: its 8 x 6 outputs take 5 MACs each
    assert conv_gmac(net, x) == pytest.approx(body + 8 * 6 * 5 / 1e9, rel=1e-12)
    # a batch of two costs twice as much, and the hooks are gone afterwards
    assert conv_gmac(net, torch.randn(2, 4, 4, 6)) == pytest.approx(2 * (body + 240 / 1e9), rel=1e-12)
    assert not any(m._forward_hooks for m in net.modules())
