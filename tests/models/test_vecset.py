"""RaLD's vector-set occupancy autoencoder: sizes against the official code, losses against hand-worked
cases, order invariance, and an overfit on one synthetic frame's frustum occupancy."""
from __future__ import annotations

import copy
import math

import pytest
import torch
import torch.nn.functional as F

from radarpc.models import MODELS, ModelSpec, build_model
from radarpc.models.vecset import (FourierEmbedding, VecSetAEConfig, VecSetAutoencoder, farthest_point_sample,
                                   kl_divergence, occupancy_loss, official_key)
from radarpc.rald.frustum import FrustumGrid, cartesian_to_polar, in_frustum, normalize, sample_queries, voxelize


@pytest.fixture
def one_thread():
    # 2 cores shared by many processes: one intra-op thread is several times faster than oversubscribing
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def tiny(query_type: str = "hybrid", dtype: torch.dtype = torch.float32, seed: int = 0) -> VecSetAutoencoder:
    torch.manual_seed(seed)
    return build_model("rald-ae-tiny", {"query_type": query_type}).to(dtype).eval()


def cloud(b: int, n: int, seed: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(b, n, 3, generator=g, dtype=torch.float64) * 2 - 1).to(dtype)


# ---- sizes and layout ------------------------------------------------------------------------

def test_paper_size_parameter_count_is_the_official_one():
    n = lambda v, o=None: sum(p.numel() for p in build_model(v, o, device="meta").parameters())   # noqa: E731
    assert n("rald-ae") == 108_002_881                   # official kl_d512_m512_l32_mix
    # the official "learnable" and "point" query types lack the hybrid's dynamic queries (512 x 512),
    # their attention (2 x 512 LayerNorm + 512 x 512 + 512 x 1024 + 512 x 512 + 512) and the
    # projection (512 x 512 + 512): 262,144 + 1,050,112 + 262,656 = 1,574,912; "point" also the
    # static queries (262,144)
    assert n("rald-ae", {"query_type": "static"}) == 108_002_881 - 1_574_912
    assert n("rald-ae", {"query_type": "fps"}) == 108_002_881 - 1_574_912 - 262_144
    assert ModelSpec("rald-ae-s").input_kind == "lidar"
    assert {"rald-ae", "rald-ae-s", "rald-ae-tiny"} <= set(MODELS)


def official_mix_layout(depth: int = 24, c: int = 512, d: int = 32, m: int = 512, inner: int = 512,
                        ff: int = 4) -> dict[str, tuple[int, ...]]:
    """The official KLAutoEncoder(query_type='mix') state dict, key -> shape, transcribed from
    RoyAPTX4869/RaLD model/models_ae.py (PreNorm wraps `fn` with `norm` and, for a context_dim,
    `norm_context`; Attention has to_q, to_kv without bias, to_out; FeedForward is net.0 / GEGLU / net.2)."""
    out: dict[str, tuple[int, ...]] = {"point_embed.basis": (3, 24), "point_embed.mlp.weight": (c, 51),
                                       "point_embed.mlp.bias": (c,)}

    def prenorm(prefix, context):
        out.update({f"{prefix}.norm.weight": (c,), f"{prefix}.norm.bias": (c,)})
        if context:
            out.update({f"{prefix}.norm_context.weight": (c,), f"{prefix}.norm_context.bias": (c,)})

    def attn(prefix, inner_dim, context):
        prenorm(prefix, context)
        out.update({f"{prefix}.fn.to_q.weight": (inner_dim, c), f"{prefix}.fn.to_kv.weight": (2 * inner_dim, c),
                    f"{prefix}.fn.to_out.weight": (c, inner_dim), f"{prefix}.fn.to_out.bias": (c,)})

    def feed_forward(prefix):
        prenorm(prefix, False)
        out.update({f"{prefix}.fn.net.0.weight": (2 * ff * c, c), f"{prefix}.fn.net.0.bias": (2 * ff * c,),
                    f"{prefix}.fn.net.2.weight": (c, ff * c), f"{prefix}.fn.net.2.bias": (c,)})

    attn("cross_attend_blocks.0", c, True)
    feed_forward("cross_attend_blocks.1")
    out.update({"s_latents.weight": (m, c), "d_latents.weight": (m, c), "query_proj.weight": (c, c),
                "query_proj.bias": (c,)})
    attn("mix_attn_layer", inner, False)
    for i in range(depth):
        attn(f"layers.{i}.0", inner, False)
        feed_forward(f"layers.{i}.1")
    attn("decoder_cross_attn", c, True)
    out.update({"to_outputs.weight": (1, c), "to_outputs.bias": (1,), "proj.weight": (c, d), "proj.bias": (c,),
                "mean_fc.weight": (d, c), "mean_fc.bias": (d,), "logvar_fc.weight": (d, c), "logvar_fc.bias": (d,)})
    return out


def test_official_state_dict_maps_key_by_key_onto_the_paper_model():
    official = official_mix_layout()
    assert sum(math.prod(s) for k, s in official.items() if k != "point_embed.basis") == 108_002_881
    ours = {k: tuple(v.shape) for k, v in build_model("rald-ae", device="meta").state_dict().items()}
    mapped = {official_key(k): s for k, s in official.items() if official_key(k) is not None}
    assert len(mapped) == len(official) - 1                  # one-to-one (only the basis buffer is dropped)
    assert mapped == ours
    assert official_key("layers.3.1.fn.net.0.weight") == "blocks.3.ff.fc1.weight"
    assert official_key("latents.weight") == "static_queries"           # query type "learnable"


def test_config_refuses_bad_values_by_name():
    for bad, field in [({"query_type": "mix"}, "query_type"), ({"width": 0}, "width"), ({"heads": 2.5}, "heads"),
                       ({"drop_path": 1.0}, "drop_path"), ({"kl_weight": -1.0}, "kl_weight"),
                       ({"empty_weight": float("nan")}, "empty_weight")]:
        with pytest.raises(ValueError, match=field):
            VecSetAEConfig(**bad)
    with pytest.raises(ValueError, match="rald-ae-tiny"):
        build_model("rald-ae-tiny", {"n_latent": 3})
    model = tiny()
    with pytest.raises(ValueError, match=r"points must be a \(B, N, 3\)"):
        model(torch.zeros(2, 5), torch.zeros(2, 4, 3))
    with pytest.raises(ValueError, match="fps"):
        tiny("fps")(cloud(1, 8, 0), cloud(1, 4, 1))          # fewer points than latents


# ---- layers against hand-worked values -------------------------------------------------------

def test_fourier_features_are_sines_cosines_and_the_point():
    emb = FourierEmbedding(2, 15).double()
    with torch.no_grad():
        emb.proj.weight.copy_(torch.eye(15, dtype=torch.float64))
        emb.proj.bias.zero_()
    x, y, z = 0.3, -0.7, 0.125
    want = ([math.sin(math.pi * f * a) for a in (x, y, z) for f in (1, 2)]
            + [math.cos(math.pi * f * a) for a in (x, y, z) for f in (1, 2)] + [x, y, z])
    got = emb(torch.tensor([[[x, y, z]]], dtype=torch.float64))[0, 0]
    torch.testing.assert_close(got, torch.tensor(want, dtype=torch.float64), rtol=0, atol=1e-15)


def test_farthest_point_sampling_by_hand():
    # points on a line at 0, 1, 2, 3, 10; from 0: 10 is farthest; then 3 (min distance 3 to {0, 10})
    # beats 2 (2) and 1 (1); then 1 and 2 tie at distance 1 to {0, 3, 10}: the first index, 1
    p = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [10, 0, 0]]])
    assert farthest_point_sample(p, 4, torch.tensor([0])).tolist() == [[0, 4, 3, 1]]
    assert farthest_point_sample(p, 2, torch.tensor([4])).tolist() == [[4, 0]]


def test_occupancy_loss_against_a_hand_computed_case():
    logits = torch.tensor([[0.0, 2.0, -1.0, math.log(3.0)], [3.0, -2.0, 0.5, 1.0]], dtype=torch.float64)
    occupied = torch.tensor([[True, False, True, False], [False, False, False, True]])
    # -log sigmoid(l) = log(1 + e^-l) for the occupied, -log(1 - sigmoid(l)) = log(1 + e^l) for the empty;
    # each set averaged over its own queries of the whole batch (3 occupied, 5 empty)
    occ = [math.log(2.0), math.log(1 + math.e), math.log(1 + math.exp(-1.0))]
    emp = [math.log(1 + math.e ** 2), math.log(4.0), math.log(1 + math.exp(3.0)), math.log(1 + math.exp(-2.0)),
           math.log(1 + math.exp(0.5))]
    want = 0.1 * sum(occ) / 3 + 1.0 * sum(emp) / 5
    assert occupancy_loss(logits, occupied).item() == pytest.approx(want, rel=1e-14)
    assert occupancy_loss(logits, occupied.double(), 2.0, 0.5).item() == pytest.approx(
        2.0 * sum(occ) / 3 + 0.5 * sum(emp) / 5, rel=1e-14)
    # no occupied query: the occupied term adds nothing (not NaN)
    assert occupancy_loss(logits, torch.zeros_like(occupied)).item() == pytest.approx(
        float(F.softplus(logits).mean()), rel=1e-14)
    with pytest.raises(ValueError, match="shape"):
        occupancy_loss(logits, occupied[:, :3])


def test_kl_term_against_its_closed_form():
    mean = torch.tensor([[[1.0, 0.0], [0.0, 2.0]]], dtype=torch.float64)
    logvar = torch.tensor([[[0.0, math.log(4.0)], [-math.log(2.0), 0.0]]], dtype=torch.float64)
    # 1/2 (mu^2 + sigma^2 - 1 - log sigma^2) per entry: 1/2, (3 - ln 4)/2, (ln 2 - 1/2)/2, 2; their mean
    entries = [0.5, (3 - math.log(4.0)) / 2, (math.log(2.0) - 0.5) / 2, 2.0]
    assert kl_divergence(mean, logvar).tolist() == pytest.approx([sum(entries) / 4], rel=1e-14)
    # the same as torch's KL of normals, averaged over the entries
    g = torch.Generator().manual_seed(3)
    mu, lv = torch.randn(3, 5, 4, generator=g, dtype=torch.float64), torch.randn(3, 5, 4, generator=g,
                                                                                  dtype=torch.float64)
    ref = torch.distributions.kl_divergence(torch.distributions.Normal(mu, (0.5 * lv).exp()),
                                            torch.distributions.Normal(0.0, 1.0)).mean(dim=(1, 2))
    torch.testing.assert_close(kl_divergence(mu, lv), ref, rtol=1e-12, atol=0)


# ---- the model's behaviour -------------------------------------------------------------------

@pytest.mark.parametrize("query_type", ["hybrid", "static", "fps"])
def test_shapes_and_the_pieces_add_up(query_type):
    model = tiny(query_type)
    cfg = model.cfg
    points, queries = cloud(2, 40, 1), cloud(2, 7, 2)
    with torch.no_grad():
        logits, kl = model(points, queries)
        mean, logvar = model.encode(points)
        assert logits.shape == (2, 7) and kl.shape == (2,)
        assert mean.shape == logvar.shape == (2, cfg.n_latents, cfg.latent_dim)
        # evaluation decodes the posterior mean; chunks of queries against tokens computed once
        torch.testing.assert_close(logits, model.decode(mean, queries), rtol=0, atol=0)
        tokens = model.latent_tokens(mean)
        chunks = torch.cat([model.occupancy_logits(tokens, queries[:, :3]),
                            model.occupancy_logits(tokens, queries[:, 3:])], dim=1)
        torch.testing.assert_close(chunks, logits, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(kl, kl_divergence(mean, logvar), rtol=0, atol=0)
        # given noise: z = mu + sigma * eps
        eps = torch.randn(mean.shape, generator=torch.Generator().manual_seed(4))
        got, _ = model(points, queries, noise=eps)
        torch.testing.assert_close(got, model.decode(mean + (0.5 * logvar).exp() * eps, queries))


# Permuting the input points changes only the order of the N-term sums inside the attention over
# the points (softmax normaliser and weighted value sum). In float64 a sum of N terms in any order
# is within gamma_N = N u / (1 - N u) (u = 2^-53) of the exact sum, relative to the sum of the
# magnitudes (here <= the largest |value| since the weights are a convex combination): two orders
# differ by <= 2 gamma_N ~ 1.4e-14 for N = 64. The layers after it (a few linear maps, LayerNorms,
# GELUs of this random tiny model) amplify that by far less than 1e3, so 1e-10 on outputs of order
# 1 holds with a wide margin, while an order-dependent encoder differs by order 0.1 (the fps check).
PERM_ATOL = 2 * 64 * 2.0 ** -53 * 1e3 * 1e2          # 1.4e-9: the bound above with a 100x cushion

@pytest.mark.parametrize("query_type", ["hybrid", "static"])
def test_encoder_is_invariant_to_the_order_of_the_points(query_type):
    model = tiny(query_type, torch.float64)
    points = cloud(2, 64, 5, torch.float64)
    perm = torch.randperm(64, generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        mean, logvar = model.encode(points)
        mean_p, logvar_p = model.encode(points[:, perm])
    assert mean.abs().max() > 0.1                       # outputs of order 1, not vanishing
    torch.testing.assert_close(mean_p, mean, rtol=0, atol=PERM_ATOL)
    torch.testing.assert_close(logvar_p, logvar, rtol=0, atol=PERM_ATOL)


def test_point_sampled_queries_depend_on_the_order():
    # the negative control: farthest point sampling starts at the first point
    model = tiny("fps", torch.float64)
    points = cloud(1, 64, 5, torch.float64)
    perm = torch.randperm(64, generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        diff = (model.encode(points)[0] - model.encode(points[:, perm])[0]).abs().max()
    assert diff > 1e-3


def test_each_logit_is_its_own_querys():
    model = tiny("hybrid", torch.float64)
    latents = torch.randn(2, model.cfg.n_latents, model.cfg.latent_dim, dtype=torch.float64,
                          generator=torch.Generator().manual_seed(7))
    queries = cloud(2, 50, 8, torch.float64)
    perm = torch.randperm(50, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        logits = model.decode(latents, queries)
        permuted = model.decode(latents, queries[:, perm])
        alone = torch.cat([model.decode(latents, queries[:, i:i + 1]) for i in (0, 17, 49)], dim=1)
    # each query's attention reduces over the same M latents in the same order whatever the other
    # queries are: only the batching of the matrix products can differ, within float64 rounding
    torch.testing.assert_close(permuted, logits[:, perm], rtol=0, atol=1e-12)
    torch.testing.assert_close(alone, logits[:, [0, 17, 49]], rtol=0, atol=1e-12)
    assert logits.std() > 1e-3                          # the queries get different logits


def _randomised(model: VecSetAutoencoder, seed: int) -> VecSetAutoencoder:
    """Every parameter moved off its initial value (LayerNorm gains and biases too), so that every
    folded term (gamma, beta, the embedding's mean, the output bias) is exercised."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.2 * torch.randn(p.shape, generator=g, dtype=torch.float64).to(p.dtype))
    return model


def test_folded_decoder_is_the_decoder_multiplied_out():
    """In float64 the folded decoder is the same function as the layer-by-layer one (to float64
    rounding); in float32 both are within float32 error of the exact logits of the same float32
    inputs, the folded one no further than the unfolded one's own error (measured on the same
    queries) allows."""
    m32 = _randomised(tiny("hybrid", seed=3), 4)
    m64 = copy.deepcopy(m32).double()
    latents = torch.randn(2, m32.cfg.n_latents, m32.cfg.latent_dim, generator=torch.Generator().manual_seed(5))
    queries = cloud(2, 3000, 6)
    with torch.no_grad():
        t32 = m32.latent_tokens(latents)                       # the same tokens for all: the decoders compared
        t64, q64 = t32.double(), queries.double()
        exact = m64.occupancy_logits(t64, q64)
        torch.testing.assert_close(m64.folded_decoder(t64)(q64), exact, rtol=0, atol=1e-12 * exact.abs().max().item())
        assert exact.std() > 0.1 and (exact > 0).any() and (exact < 0).any()   # logits of both signs, varied
        plain32 = m32.occupancy_logits(t32, queries)
        folded32 = m32.folded_decoder(t32)(queries)
    err_plain = (plain32.double() - exact).abs().max().item()
    err_folded = (folded32.double() - exact).abs().max().item()
    # float32 rounding, a few hundred u = 2^-24 of |l| here (the softmax amplifies the scores' rounding);
    # an error in the maths would be of the order of the logits themselves
    assert 0 < err_plain < 1e-3 * exact.abs().max().item()
    assert err_folded <= 4 * err_plain                        # the same order as the unfolded float32 error
    # a query changes sides only where its logit lies within that rounding of 0
    flip = (plain32 > 0) != (folded32 > 0)
    assert bool((exact[flip].abs() <= err_plain + err_folded).all())
    with pytest.raises(ValueError, match=r"queries hold 1 frames but the latents 2"):
        m32.folded_decoder(t32)(queries[:1])


def synthetic_frame() -> tuple[FrustumGrid, torch.Tensor]:
    """A coarse frustum (16 x 16 x 8 cells) and a LiDAR cloud on three planes: a front wall, a
    side wall and the floor (points outside the frustum dropped)."""
    g = torch.Generator().manual_seed(0)
    grid = FrustumGrid(range_m=(0.0, 8.0), azimuth_deg=(-60.0, 60.0), elevation_deg=(-20.0, 20.0),
                       cell=(0.5, 7.5, 5.0))

    def plane(n, origin, u, v):
        a = torch.rand(n, 2, generator=g, dtype=torch.float64)
        return torch.tensor(origin) + a[:, :1] * torch.tensor(u) + a[:, 1:] * torch.tensor(v)

    pts = torch.cat([plane(400, (5.0, -3.0, -1.0), (0.0, 6.0, 0.0), (0.0, 0.0, 2.5)),
                     plane(300, (1.0, 2.5, -1.0), (4.0, 0.0, 0.0), (0.0, 0.0, 2.5)),
                     plane(300, (2.0, -3.0, -1.0), (3.0, 0.0, 0.0), (0.0, 6.0, 0.0))])
    return grid, pts[in_frustum(grid, pts)]


def test_tiny_autoencoder_overfits_one_frames_occupancy(one_thread):
    grid, pts = synthetic_frame()
    occ = voxelize(grid, pts)
    assert 100 < occ.n_occupied < 400                    # a few walls' worth of the 2,048 cells
    g = torch.Generator().manual_seed(1)
    x = normalize(grid, cartesian_to_polar(pts)).float()[None]            # (1, N, 3) in [-1, 1]
    x = x[:, torch.randperm(x.shape[1], generator=g)[:256]]               # (1, 256, 3)
    # every cell's centre, normalised, and its label
    ijk = torch.stack(torch.meshgrid(*[torch.arange(n) for n in grid.shape], indexing="ij"), -1).reshape(-1, 3)
    centres = normalize(grid, torch.tensor(grid.lo, dtype=torch.float64)
                        + (ijk + 0.5) * torch.tensor(grid.cell, dtype=torch.float64)).float()[None]   # (1, 2048, 3)
    truth = occ.dense().reshape(1, -1)                                                          # (1, 2048)

    torch.manual_seed(0)
    model = build_model("rald-ae-tiny")

    def scores() -> tuple[float, float]:
        model.eval()
        with torch.no_grad():
            logits, _ = model(x, centres)
        model.train()
        pred = logits > 0
        return (float(F.binary_cross_entropy_with_logits(logits, truth.float())),
                float((pred & truth).sum() / (pred | truth).sum()))

    bce0, _ = scores()
    steps = 1000
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3, weight_decay=0.0)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=3e-3, total_steps=steps, pct_start=0.1)
    model.train()
    for _ in range(steps):
        # fresh queries each step, RaLD's 6.25 % in occupied cells
        q, labels = sample_queries(occ, 1024, 0.0625, generator=g)
        logits, kl = model(x, q[None])
        loss = model.loss(logits, labels[None], kl)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    bce, iou = scores()
    assert bce < bce0 / 15, (bce0, bce)                 # ~0.68 -> ~0.03 over every cell centre
    assert iou > 0.75, iou                              # the decoded occupied cells are the frame's
