"""RaLD's generation (radarpc.rald.generate): chunked decoding, guided queries, refinement, whole frames."""
from __future__ import annotations

import math
import zlib

import numpy as np
import pytest
import torch

from radarpc.models import build_model
from radarpc.rald.frustum import RALD_GRID, cartesian_to_polar, denormalize, normalize, polar_to_cartesian
from radarpc.rald.generate import (STAGES, GenerationConfig, cfar_guided_queries, decode_occupied, frame_seed,
                                   generate_cloud, generate_clouds, random_queries, refine, spread_queries)
from radarpc.rald.voxels import CartesianGrid

CUBE = (32, 16, 16)        # the tiny diffusion model's radar grid (two encoder levels)
EPS32 = float(np.finfo(np.float32).eps)


def _models(seed: int = 0):
    torch.manual_seed(seed)
    ae = build_model("rald-ae-tiny").eval()
    dit = build_model("rald-dit-tiny", {"radar_shape": CUBE, "enc_ch_mult": (1, 2), "n_latents": 32,
                                        "latent_dim": 8}).eval()
    # the tiny denoiser's output projection starts at zero (D = c_skip x): give it weights, so that
    # the latents depend on the radar condition
    torch.nn.init.normal_(dit.denoiser.proj_out.weight, std=0.05)
    return ae, dit


SMALL = GenerationConfig(random_queries=1500, guided_queries=1000, refine_queries=3000, chunk=512, num_steps=3)
CFAR = np.array([[4.0, 1.0, 0.2], [7.5, -2.0, 0.0], [2.0, 0.5, -0.3], [40.0, 0.0, 0.0]], np.float32)   # the last: beyond the grid


class Occupancy(torch.nn.Module):
    """A stand-in autoencoder whose logit is a hand-made function of the normalised query:
    ``l(u) = 0.05 - |u_range - 0.2|`` (occupied on a shell of normalised range 0.15..0.25)."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.eval()

    def latent_tokens(self, z):
        return z

    def occupancy_logits(self, tokens, q):
        return 0.05 - (q[..., 0] - 0.2).abs() + 0 * self.w


def test_config_checks_name_the_field(tmp_path):
    from radarpc.config import load_yaml, save_yaml

    assert GenerationConfig().sampler() == dict(num_steps=18, sigma_min=0.002, sigma_max=80.0, rho=7.0)
    assert load_yaml(GenerationConfig, save_yaml(SMALL, tmp_path / "gen.yaml")) == SMALL
    with pytest.raises(ValueError, match="GenerationConfig.chunk must be >= 1"):
        GenerationConfig(chunk=0)
    with pytest.raises(ValueError, match="random_queries must be an integer"):
        GenerationConfig(random_queries=1.5)
    with pytest.raises(ValueError, match="nothing to decode"):
        GenerationConfig(random_queries=0, guided_queries=0)
    with pytest.raises(ValueError, match="sigma_min 80.0 must be below sigma_max 2.0"):
        GenerationConfig(sigma_min=80.0, sigma_max=2.0)


def test_frame_seed_is_the_crc_of_seed_run_and_frame():
    assert frame_seed(3, "lab_run2", 7) == zlib.crc32(b"3:lab_run2:7")
    assert frame_seed(3, "lab_run2", 7) != frame_seed(4, "lab_run2", 7) != frame_seed(3, "lab_run2", 8)


def test_chunked_decoding_equals_unchunked_to_float32_rounding():
    """A query's logit depends on that query and the latents only: the chunk changes which float32
    sums the matrix products group together (BLAS blocking), nothing else. Each ordering is within
    float32 evaluation error of the exact logits, estimated by the same network in float64; the two
    differ by at most twice that error (4x for margin)."""
    ae, _ = _models()
    torch.manual_seed(1)
    z = torch.randn(1, ae.cfg.n_latents, ae.cfg.latent_dim)
    q = random_queries(2000, torch.Generator().manual_seed(2))
    with torch.no_grad():
        tokens = ae.latent_tokens(z)
        full = ae.occupancy_logits(tokens, q[None])[0]                                    # one call
        ae64 = build_model("rald-ae-tiny").double().eval()
        ae64.load_state_dict(ae.state_dict())
        exact = ae64.occupancy_logits(ae64.latent_tokens(z.double()), q[None].double())[0]
    err = (full.double() - exact).abs().max().item()
    tol = 4 * max(err, EPS32 * exact.abs().max().item())
    for chunk in (17, 333, 2000, 10_000):
        kept, logits = decode_occupied(ae, z, q, chunk=chunk)
        want = full > 0
        # the kept sets agree except for logits within rounding of 0
        near = full.abs() <= tol
        got = torch.zeros(len(q), dtype=torch.bool)
        idx = torch.cdist(kept.double(), q.double()).argmin(1) if len(kept) else torch.zeros(0, dtype=torch.long)
        got[idx] = True
        assert torch.equal(got[~near], want[~near]) and len(kept) == int(got.sum())
        torch.testing.assert_close(kept, q[got], rtol=0, atol=0)                       # the queries themselves, in order
        assert (logits.double() - full[got].double()).abs().max().item() <= tol
        assert bool((logits > 0).all())


def test_decoding_keeps_exactly_the_positive_queries_in_order():
    occ = Occupancy()
    q = random_queries(5000, torch.Generator().manual_seed(0))
    kept, logits = decode_occupied(occ, torch.zeros(1, 4, 2), q, chunk=777)
    want = 0.05 - (q[:, 0] - 0.2).abs() > 0
    assert torch.equal(kept, q[want]) and torch.equal(logits, (0.05 - (q[:, 0] - 0.2).abs())[want])
    with pytest.raises(ValueError, match=r"queries must be \(Q, 3\)"):
        decode_occupied(occ, torch.zeros(1, 4, 2), q[:, :2])


def test_random_queries_are_uniform_in_the_normalised_grid():
    q = random_queries(200_000, torch.Generator().manual_seed(0))
    assert q.dtype == torch.float32 and q.shape == (200_000, 3)
    assert float(q.min()) >= -1 and float(q.max()) < 1
    # mean 0 and variance 1/3 of U(-1, 1), within 5 standard errors
    se_mean, se_var = math.sqrt(1 / 3 / 200_000), math.sqrt((1 / 5 - 1 / 9) / 200_000)
    assert torch.all(q.double().mean(0).abs() < 5 * se_mean)
    assert torch.all(((q.double() ** 2).mean(0) - 1 / 3).abs() < 5 * se_var)


@pytest.mark.parametrize("grid", [RALD_GRID, CartesianGrid((0.0, 16.0), (-16.0, 16.0), (-6.0, 6.0), (0.05, 0.05, 0.05))])
def test_cfar_guided_queries_lie_within_the_spread_and_inside_the_grid(grid):
    gen = torch.Generator().manual_seed(0)
    q = cfar_guided_queries(CFAR, 5000, grid, gen, spread=2)
    assert q.shape == (5000, 3) and q.dtype == torch.float32
    assert float(q.min()) >= -1 and float(q.max()) <= 1                                  # inside the grid
    from radarpc.rald.voxels import grid_coords

    seeds = grid_coords(grid, torch.from_numpy(CFAR[:3]).double())                       # the 3 in the grid, in order
    g = denormalize(grid, q.double())                                                    # (n, 3) grid coordinates
    cell = torch.tensor(grid.cell, dtype=torch.float64)
    # the CFAR points first (float32 rounding of their normalised coordinates), then copies
    torch.testing.assert_close(g[:3], seeds, rtol=0, atol=1e-5 * float(cell.max()))
    # every copy is within 2 cells of one CFAR point on every axis (float32 slack of 1e-6 of the span)
    steps = ((g[3:, None, :] - seeds[None]).abs() / cell).amax(-1)                       # (n - 3, 3) in cells
    span = torch.tensor(grid.hi, dtype=torch.float64) - torch.tensor(grid.lo, dtype=torch.float64)
    assert bool((steps.min(1).values <= 2 + 1e-6 * float((span / cell).max())).all())
    # both scales 1 and 2 occur: some copies move further than one cell
    assert bool((steps.min(1).values > 1.05).any())
    # fewer wanted than CFAR points: the first ones; none in the grid: no query
    torch.testing.assert_close(cfar_guided_queries(CFAR, 2, grid, gen), q[:2], rtol=0, atol=0)
    assert cfar_guided_queries(CFAR[3:], 100, grid, gen).shape == (0, 3)
    assert cfar_guided_queries(np.zeros((0, 3), np.float32), 100, grid, gen).shape == (0, 3)


def test_copies_near_the_grid_edge_are_clipped_into_it():
    lo, hi, cell = (torch.tensor(v, dtype=torch.float64) for v in (RALD_GRID.lo, RALD_GRID.hi, RALD_GRID.cell))
    edge = torch.tensor([[hi[0] - 0.01, lo[1] + 0.1, hi[2] - 0.1]], dtype=torch.float64)   # polar, at a corner
    g = spread_queries(edge, 2000, RALD_GRID, 10, torch.Generator().manual_seed(0))
    assert bool((g >= lo).all() and (g <= hi).all())
    assert bool((g[:, 0] == hi[0]).any() and (g[:, 1] == lo[1]).any())                      # some were clipped


def test_refinement_adds_the_occupied_copies_and_keeps_the_first():
    occ = Occupancy()
    z = torch.zeros(1, 4, 2)
    q = random_queries(3000, torch.Generator().manual_seed(1))
    kept, logits = decode_occupied(occ, z, q)
    k = len(kept)
    gen = torch.Generator().manual_seed(2)
    out, out_logits, n_dec = refine(occ, z, kept, logits, RALD_GRID, n=3 * k, spread=10, rounds=1, generator=gen)
    assert n_dec == 2 * k and torch.equal(out[:k], kept)                                  # the kept points stay first
    new = out[k:]
    assert bool((0.05 - (new[:, 0] - 0.2).abs() > 0).all()) and 0 < len(new) < 2 * k    # only occupied copies
    torch.testing.assert_close(out_logits, 0.05 - (out[:, 0] - 0.2).abs())
    # as many kept as wanted already: the first n, nothing decoded
    few, _, n0 = refine(occ, z, kept, logits, RALD_GRID, n=k // 2, generator=gen)
    assert n0 == 0 and torch.equal(few, kept[: k // 2])
    # no round, or nothing occupied: unchanged
    assert refine(occ, z, kept, logits, RALD_GRID, n=3 * k, rounds=0)[2] == 0
    assert refine(occ, z, kept[:0], logits[:0], RALD_GRID, n=3 * k)[0].shape == (0, 3)


def test_generation_is_deterministic_per_seed_and_independent_of_the_batch():
    ae, dit = _models()
    cubes = torch.rand((2, *CUBE), generator=torch.Generator().manual_seed(3))
    one = generate_cloud(ae, dit, cubes[0], CFAR, SMALL, 11)
    again = generate_cloud(ae, dit, cubes[0], CFAR, SMALL, 11)
    assert one.points.dtype == np.float32 and one.points.ndim == 2 and one.points.shape[1] == 3
    assert np.array_equal(one.points, again.points) and len(one.points) > 0 and not one.empty
    other = generate_cloud(ae, dit, cubes[0], CFAR, SMALL, 12)
    assert not np.array_equal(one.points, other.points)
    both = generate_clouds(ae, dit, cubes, [CFAR, CFAR[:1]], SMALL, [11, 5])
    single = generate_cloud(ae, dit, cubes[1], CFAR[:1], SMALL, 5)
    # the batch's second frame equals it alone, up to float32 rounding of the batched network calls
    assert len(both[1].points) == len(single.points)
    np.testing.assert_allclose(both[1].points, single.points, rtol=0, atol=1e-4)
    # the record: per-stage seconds, query counts, guide points in the grid (the 40 m one is not)
    assert set(one.seconds) == set(STAGES) and all(v >= 0 for v in one.seconds.values())
    assert one.n_queries["random"] == 1500 and one.n_queries["guided"] == 1000 and one.n_cfar_points == 3
    assert one.n_queries["refinement"] == max(0, 3000 - one.n_occupied)
    rec = one.record()
    assert rec["n_points"] == len(one.points) and rec["seed"] == 11 and rec["empty"] is False
    assert {f"seconds_{s}" for s in STAGES} <= set(rec)
    # points lie in the frustum grid: their polar coordinates are in its box
    rae = cartesian_to_polar(torch.from_numpy(one.points).double())
    assert bool((rae >= torch.tensor(RALD_GRID.lo) - 1e-4).all() and (rae <= torch.tensor(RALD_GRID.hi) + 1e-4).all())


def test_the_radar_is_encoded_once_and_the_sampler_is_latent_dits(monkeypatch):
    ae, dit = _models()
    cube = torch.rand(CUBE, generator=torch.Generator().manual_seed(4))
    calls, conditions, latents = [], [], []
    encode = dit.encode_radar
    monkeypatch.setattr(dit, "encode_radar", lambda x: calls.append(1) or encode(x))
    forward = dit.denoiser.forward
    monkeypatch.setattr(dit.denoiser, "forward", lambda x, c, cond: conditions.append(cond) or forward(x, c, cond))
    tokens = ae.latent_tokens
    monkeypatch.setattr(ae, "latent_tokens", lambda z: latents.append(z.clone()) or tokens(z))
    generate_cloud(ae, dit, cube, CFAR, SMALL, 9)
    assert len(calls) == 1 and len(conditions) == 2 * SMALL.num_steps - 1
    assert all(c is conditions[0] for c in conditions)
    monkeypatch.undo()
    want = dit.sample(cube[None], [9], **SMALL.sampler())
    assert torch.equal(latents[0], want)


def test_an_empty_decoding_is_reported():
    ae, dit = _models()
    with torch.no_grad():
        ae.to_logit.bias.fill_(-1e4)                                                  # every logit negative
    res = generate_cloud(ae, dit, torch.rand(CUBE), CFAR, SMALL, 0)
    assert res.empty and res.points.shape == (0, 3) and res.points.dtype == np.float32
    assert res.n_occupied == 0 and res.n_queries["refinement"] == 0
    assert res.warning.startswith("empty decoding: none of the 2,500 queries") and res.record()["empty"] is True
    with torch.no_grad():
        ae.to_logit.bias.fill_(1e4)
    assert generate_cloud(ae, dit, torch.rand(CUBE), CFAR, SMALL, 0).warning is None


def test_models_in_training_mode_and_bad_inputs_are_refused():
    ae, dit = _models()
    with pytest.raises(ValueError, match=r"autoencoder is in training mode.*call \.eval\(\) on it"):
        generate_cloud(ae.train(), dit, torch.rand(CUBE), CFAR, SMALL, 0)
    ae.eval()
    with pytest.raises(ValueError, match="cfar_points must be"):
        generate_cloud(ae, dit, torch.rand(CUBE), CFAR[:, :2], SMALL, 0)
    with pytest.raises(ValueError, match="2 cubes need as many"):
        generate_clouds(ae, dit, torch.rand((2, *CUBE)), [CFAR], SMALL, [0, 1])


def test_normalised_guided_queries_map_back_to_cartesian_within_the_spread():
    # a single CFAR point and spread 1: every query's polar coordinates are within one cell of it
    p = torch.tensor([[5.0, 2.0, 1.0]], dtype=torch.float64)
    q = cfar_guided_queries(p.numpy(), 500, RALD_GRID, torch.Generator().manual_seed(0), spread=1)
    rae = denormalize(RALD_GRID, q.double())
    d = (rae - cartesian_to_polar(p)).abs() / torch.tensor(RALD_GRID.cell, dtype=torch.float64)
    assert float(d.max()) <= 1 + 1e-4
    xyz = polar_to_cartesian(rae)
    assert float((xyz - p).norm(dim=1).max()) < 0.2                                      # a cell is ~5 cm x 2 cm x 4 cm here
    torch.testing.assert_close(normalize(RALD_GRID, cartesian_to_polar(p)).float(), q[:1])
