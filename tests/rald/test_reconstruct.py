"""The autoencoder's reconstruction of a frame (radarpc.rald.reconstruct): the latents of the posterior
(its mean, or a sample seeded by the frame), decoded by generation's own decoding."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from radarpc.models import build_model
from radarpc.rald.frustum import RALD_GRID, cartesian_to_polar
from radarpc.rald.generate import GenerationConfig, decode_cloud
from radarpc.rald.reconstruct import (RECONSTRUCTION_STAGES, ReconstructionConfig, encode_latents, points_generator,
                                      reconstruct_cloud)

SMALL = GenerationConfig(random_queries=1500, guided_queries=1000, refine_queries=3000, chunk=512)
CFAR = np.array([[4.0, 1.0, 0.2], [7.5, -2.0, 0.0], [2.0, 0.5, -0.3]], np.float32)


def _points(seed: int, n: int = 200) -> torch.Tensor:
    return 2 * torch.rand((n, 3), generator=torch.Generator().manual_seed(seed)) - 1       # model coordinates


class Shell(torch.nn.Module):
    """A stand-in autoencoder with a posterior and an occupancy worked by hand: the posterior of
    points ``P`` has mean ``mu = mean_n P[n, 0]`` (the mean normalised range) in every entry and
    standard deviation ``SIGMA``; a query ``u`` is occupied on the shell ``|u_range - mean(z)| < W``."""

    SIGMA, W, M, D = 0.02, 0.01, 8, 4

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.eval()

    def encode(self, points):
        mean = points[..., 0].mean(-1)[:, None, None].expand(-1, self.M, self.D).clone()      # (1, M, D)
        return mean, torch.full_like(mean, 2 * math.log(self.SIGMA))

    sample = staticmethod(lambda mean, logvar, noise: mean + torch.exp(0.5 * logvar) * noise)

    def latent_tokens(self, z):
        return z

    def occupancy_logits(self, tokens, q):
        return self.W - (q[..., 0] - tokens.mean()).abs() + 0 * self.w


def test_the_posterior_mean_or_a_sample_seeded_by_the_frame():
    ae = Shell()
    p, q = _points(0), _points(1)
    mu = float(p[:, 0].mean())
    mean = encode_latents(ae, p, seed=7, posterior="mean")
    assert mean.shape == (1, Shell.M, Shell.D) and torch.equal(mean, torch.full_like(mean, mu))
    z = encode_latents(ae, p, seed=7)                                                  # the default: a sample
    eps = (z - mean) / Shell.SIGMA
    # eps is the frame's seed's alone: the same for other points, another for another seed, N(0, 1)-like
    eps_q = (encode_latents(ae, q, seed=7) - encode_latents(ae, q, seed=7, posterior="mean")) / Shell.SIGMA
    torch.testing.assert_close(eps, eps_q, rtol=0, atol=1e-4)
    assert torch.equal(z, encode_latents(ae, p, seed=7))
    assert not torch.allclose(z, encode_latents(ae, p, seed=8))
    assert abs(float(eps.mean())) < 4 / math.sqrt(eps.numel()) and 0.5 < float(eps.std()) < 1.5   # 32 draws
    with pytest.raises(ValueError, match="posterior must be one of sample, mean, got 'mode'"):
        encode_latents(ae, p, 7, "mode")
    with pytest.raises(ValueError, match="ReconstructionConfig.posterior must be one of sample, mean"):
        ReconstructionConfig(posterior="mode")


@pytest.mark.parametrize("posterior", ["mean", "sample"])
def test_the_cloud_is_the_decoding_of_the_encoded_latents(posterior):
    ae = Shell()
    p = _points(2)
    res = reconstruct_cloud(ae, p, CFAR, SMALL, 11, posterior=posterior)
    # every point on the shell of the decoded latents: |u_range - mean(z)| < W, u_range = 2 r / r_max - 1
    z = encode_latents(ae, p, 11, posterior)
    lo, hi = RALD_GRID.range_m
    r = cartesian_to_polar(torch.from_numpy(res.points).double())[:, 0]
    u = 2 * (r - lo) / (hi - lo) - 1
    assert len(res.points) > 100 and float((u - float(z.mean())).abs().max()) < Shell.W + 1e-5
    # generation's decoding of those latents, the frame's seed drawing the same queries
    same = decode_cloud(ae, z, CFAR, SMALL, 11)
    np.testing.assert_array_equal(res.points, same.points)
    assert res.n_queries == same.n_queries and res.n_cfar_points == 3
    # its record: the reconstruction's stages, no sampler
    assert res.stages == RECONSTRUCTION_STAGES and set(res.seconds) == set(RECONSTRUCTION_STAGES)
    rec = res.record()
    assert [k for k in rec if k.startswith("seconds_")] == [f"seconds_{s}" for s in RECONSTRUCTION_STAGES]
    assert rec["seed"] == 11 and rec["n_points"] == len(res.points)


def test_a_tiny_autoencoders_reconstruction_is_deterministic_per_seed():
    torch.manual_seed(0)
    ae = build_model("rald-ae-tiny").eval()
    p = _points(3, 256)
    one = reconstruct_cloud(ae, p, CFAR, SMALL, 5)
    assert np.array_equal(one.points, reconstruct_cloud(ae, p, CFAR, SMALL, 5).points)
    assert not np.array_equal(one.points, reconstruct_cloud(ae, p, CFAR, SMALL, 6).points)
    # the encoder's points of a frame: a stream of the frame's seed of their own
    a, b = points_generator(5), points_generator(5)
    assert torch.equal(torch.rand(4, generator=a), torch.rand(4, generator=b))
    ae.train()
    with pytest.raises(ValueError, match="training mode"):
        reconstruct_cloud(ae, p, CFAR, SMALL, 5)
