"""RaLD's latent diffusion model: paper parameter counts, shapes and values of the tiny model,
one radar encoding per sampled frame, and a tiny denoiser that learns a two-mode distribution."""
import pytest
import torch

from radarpc.models import MODELS, ModelSpec, build_model
from radarpc.models.edm import edm_loss, edm_sampler
from radarpc.models.latent_dit import LatentDiTConfig, official_key


def _count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


@pytest.mark.parametrize("name, total", [
    ("rald-dit", 183_766_160),          # the official kl_d512_m512_l32_d24_edm with its radar encoder
    ("rald-dit-d18", 142_819_472),      # ... _d18_ and _d12_: the seed's 142.82M and 101.87M
    ("rald-dit-d12", 101_872_784),
])
def test_paper_parameter_counts_on_the_meta_device(name, total):
    model = build_model(name, device="meta")
    assert _count(model) == total
    assert _count(model.radar_encoder) == 19_535_504
    assert model.cfg.n_radar_tokens == 64 and model.cfg.radar_grid == (8, 4, 2)


def test_block_parameters_by_hand():
    """A block of width W = 512: two attentions (q, k, v without bias, output with) 2 (4 W^2 + W),
    GEGLU W 8W + 8W + 4W W + W, three AdaLayerNorms 3 (2 W^2 + 2W): 6,824,448; six of them are the
    difference between depths 24 and 18."""
    W = 512
    block = 2 * (4 * W * W + W) + (8 * W * W + 8 * W + 4 * W * W + W) + 3 * (2 * W * W + 2 * W)
    model = build_model("rald-dit", device="meta")
    assert _count(model.denoiser.blocks[0]) == block == 6_824_448
    assert 183_766_160 - 142_819_472 == 6 * block


def test_official_keys_map_one_to_one():
    """Representative official ``EDMPrecond`` keys (of the public code's state dict) land on
    radarpc tensors of the same shapes."""
    sd = build_model("rald-dit", device="meta").state_dict()
    W = 512
    official = {
        "model.proj_in.weight": (W, 32),
        "model.map_layer0.weight": (W, 256),
        "model.map_layer1.bias": (W,),
        "model.transformer_blocks.23.attn1.to_q.weight": (W, W),
        "model.transformer_blocks.0.attn2.to_out.0.bias": (W,),
        "model.transformer_blocks.5.ff.net.0.proj.weight": (8 * W, W),
        "model.transformer_blocks.5.ff.net.2.weight": (W, 4 * W),
        "model.transformer_blocks.7.norm3.linear.weight": (2 * W, W),
        "model.norm.weight": (W,),
        "model.proj_out.weight": (32, W),
        "radar_enc.conv_in.weight": (64, 1, 3, 3, 3),
        "radar_enc.down.2.block.0.nin_shortcut.weight": (128, 64, 1, 1, 1),
        "radar_enc.down.3.downsample.conv.weight": (128, 128, 3, 3, 3),
        "radar_enc.down.4.attn.1.proj_out.weight": (256, 256, 1, 1, 1),
        "radar_enc.mid.attn_1.q.bias": (256,),
        "radar_enc.conv_out.weight": (16, 256, 3, 3, 3),
        "radar_r_emb.weight": (8, W),
        "radar_a_emb.weight": (4, W),
        "radar_e_emb.weight": (2, W),
        "radar_token_project.weight": (W, 16),
    }
    for key, shape in official.items():
        assert tuple(sd[official_key(key)].shape) == shape, key
    assert "radar_encoder.down.4.downsample.conv.weight" not in sd          # the last level keeps its size
    assert len(sd) == 637                                                    # the official state dict's length


def test_registry_and_input_kind():
    for name in ("rald-dit", "rald-dit-d12", "rald-dit-d18", "rald-dit-s", "rald-dit-tiny"):
        assert name in MODELS and ModelSpec(name).input_kind == "radar"
    assert ModelSpec("rald-dit-s").config.width == 128
    with pytest.raises(ValueError, match="not divisible by heads"):
        ModelSpec("rald-dit-tiny", {"heads": 3})
    with pytest.raises(ValueError, match="enc_groups 32 does not divide"):
        LatentDiTConfig(enc_channels=8)
    with pytest.raises(ValueError, match="not divisible by 16"):
        LatentDiTConfig(radar_shape=(128, 64, 24))


def test_shapes_and_values_of_the_tiny_model():
    torch.manual_seed(0)
    model = MODELS["rald-dit-tiny"]().eval()
    cfg = model.cfg
    cube = torch.rand(2, 128, 64, 32)
    with torch.no_grad():
        cond = model.encode_radar(cube)
        assert cond.shape == (2, 64, cfg.width)
        x = torch.randn(2, cfg.n_latents, cfg.latent_dim)
        sigma = torch.tensor([0.5, 3.0])
        # zero-initialised output projection: F = 0, so D = c_skip x = x / (1 + sigma^2)
        torch.testing.assert_close(model(x, sigma, cond), x / (1 + sigma[:, None, None] ** 2))
        torch.nn.init.normal_(model.denoiser.proj_out.weight)
        out = model(x, sigma, cond)
        assert out.shape == (2, cfg.n_latents, cfg.latent_dim)
        assert not torch.allclose(out, model(x, sigma, cond + 1))            # the condition is read
    with pytest.raises(ValueError, match=r"expected intensity cubes \(B, 128, 64, 32\), got \(2, 128, 64\)"):
        model.encode_radar(cube[..., 0])


def test_radar_tokens_are_range_major_with_axis_embeddings():
    """With the projection zeroed, token ``(r A + a) E + e`` is the sum of the range, azimuth and
    elevation embeddings."""
    model = MODELS["rald-dit-tiny"]()
    tok = model.radar_tokens
    with torch.no_grad():
        tok.proj.weight.zero_()
        tok.proj.bias.zero_()
        out = tok(torch.randn(1, model.cfg.enc_z_channels, 8, 4, 2))
    for r, a, e in ((0, 0, 1), (3, 2, 0), (7, 3, 1)):
        want = tok.pos_range.weight[r] + tok.pos_azimuth.weight[a] + tok.pos_elevation.weight[e]
        torch.testing.assert_close(out[0, (r * 4 + a) * 2 + e], want)


def test_sample_encodes_the_radar_once_and_is_deterministic():
    torch.manual_seed(0)
    model = MODELS["rald-dit-tiny"]().eval()
    torch.nn.init.normal_(model.denoiser.proj_out.weight, std=0.1)
    calls = {"encoder": 0, "denoiser": 0}
    model.radar_encoder.register_forward_hook(lambda *a: calls.__setitem__("encoder", calls["encoder"] + 1))
    model.denoiser.register_forward_hook(lambda *a: calls.__setitem__("denoiser", calls["denoiser"] + 1))
    cube = torch.rand(2, 128, 64, 32)
    first = model.sample(cube, [11, 12])
    assert calls == {"encoder": 1, "denoiser": 35}        # one encoding for both frames and 35 calls
    again = model.sample(cube, [11, 12])
    assert torch.equal(first, again)                       # bit-identical for the same seeds
    assert first.shape == (2, model.cfg.n_latents, model.cfg.latent_dim)
    # a frame's latents depend on its own seed and cube only (to float32 rounding: a batch of one
    # may take other kernels)
    torch.testing.assert_close(model.sample(cube[1:], [12])[0], first[1])
    assert not torch.equal(model.sample(cube, [11, 13])[1], first[1])
    with pytest.raises(ValueError, match="1 seeds for 2 radar cubes"):
        model.sample(cube, [1])


@pytest.fixture
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)           # a tiny model on shared cores: threads only contend
    yield
    torch.set_num_threads(n)


def _sample_near_modes(model, n: int, generator: torch.Generator
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per sample, the distance of its mean to the nearest mode; per value, its distance to that
    mode; per sample, the mode (+-1)."""
    cfg = model.cfg
    with torch.no_grad():
        x = edm_sampler(model, torch.randn(n, cfg.n_latents, cfg.latent_dim, generator=generator),
                        torch.zeros(n, 1, cfg.width))
    mean = x.mean(dim=(1, 2))
    return (mean - mean.sign()).abs(), (x - mean.sign()[:, None, None]).abs(), mean.sign()


def test_tiny_denoiser_learns_two_modes(one_thread):
    """Latents all +1 or all -1 (a frame's 4 x 2 values move together), equally likely, trained
    400 steps with the EDM loss; then 256 samples of the Heun sampler.

    How near: at least 85 % of the samples have their mean within 0.1 of a mode (a tenth of the
    distance to the midpoint between the modes), and half of all values lie within 0.05 of their
    sample's mode; both modes are drawn (each 30..70 % of the samples; binomial spread 3 %). The
    sampler itself is exact on the modes (the exact-denoiser test of test_edm.py), so these
    tolerances measure the tiny network's remaining error after 400 steps, with a margin: over
    five training seeds, 92-96 % of the sample means were within 0.1 and the median value error
    was 0.004-0.006. The untrained model (D = c_skip x, the exact denoiser of N(0, 1) data) has at
    most 3 % of its sample means within 0.1 (the control asserts under 30 %).
    """
    torch.manual_seed(0)
    model = MODELS["rald-dit-tiny"](n_latents=4, latent_dim=2)
    cfg, g = model.cfg, torch.Generator().manual_seed(1)

    mean_err, _, _ = _sample_near_modes(model, 256, g)
    assert (mean_err < 0.1).float().mean().item() < 0.3                     # the control: noise-like samples

    opt = torch.optim.Adam(model.denoiser.parameters(), lr=3e-3)
    steps, B = 400, 128
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    cond = torch.zeros(B, 1, cfg.width)
    for _ in range(steps):
        y = (torch.randint(0, 2, (B, 1, 1), generator=g) * 2.0 - 1).expand(B, cfg.n_latents, cfg.latent_dim)
        loss = edm_loss(model, y, cond, generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()

    mean_err, value_err, mode = _sample_near_modes(model, 256, g)
    assert (mean_err < 0.1).float().mean().item() >= 0.85
    assert value_err.median().item() < 0.05
    assert 0.3 <= (mode > 0).float().mean().item() <= 0.7


# ----------------------------------------------------------------------------------------------
# Table 3(a): the raw spectrum in patches instead of the radar encoder
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["rald-dit", "rald-dit-s"])
def test_patch_condition_parameter_count(name):
    """Without the encoder: its parameters and its z -> W projection go, a (s^3 -> W) projection of
    a 16^3 patch comes (s = 16, the encoder's stride, so 64 tokens as before); the transformer and
    the axis embeddings stay. Paper size: 183,766,160 - 19,535,504 - (16 + 1) 512 + (4096 + 1) 512."""
    base = build_model(name, device="meta")
    model = build_model(name, {"radar_condition": "patches"}, device="meta")
    W, z, s = base.cfg.width, base.cfg.enc_z_channels, 16
    want = _count(base) - _count(base.radar_encoder) - (z + 1) * W + (s ** 3 + 1) * W
    assert _count(model) == want
    assert _count(model.radar_encoder) == 0
    assert model.cfg.radar_stride == s and model.cfg.n_radar_tokens == 64
    if name == "rald-dit":
        assert want == 166_319_616


def test_patch_condition_tokens_are_the_cube_patches():
    """With a projection that picks patch channel ``(i s + j) s + k`` and zero embeddings, token
    ``(r A + a) E + e`` is the cube's value at ``(r s + i, a s + j, e s + k)``; a second output channel
    sums the whole patch."""
    torch.manual_seed(0)
    model = MODELS["rald-dit-tiny"](radar_condition="patches")
    cfg, s = model.cfg, model.cfg.radar_stride
    tok = model.radar_tokens
    (i, j, k) = (3, 14, 9)
    with torch.no_grad():
        tok.proj.weight.zero_()
        tok.proj.bias.zero_()
        tok.proj.weight[0, (i * s + j) * s + k] = 1.0
        tok.proj.weight[1] = 1.0
        for emb in (tok.pos_range, tok.pos_azimuth, tok.pos_elevation):
            emb.weight.zero_()
        cube = torch.rand(2, *cfg.radar_shape)
        out = model.encode_radar(cube)
    assert out.shape == (2, 64, cfg.width)
    for b, r, a, e in ((0, 0, 0, 0), (1, 7, 3, 1), (0, 5, 1, 0)):
        t = out[b, (r * 4 + a) * 2 + e]
        assert t[0] == cube[b, r * s + i, a * s + j, e * s + k]
        patch = cube[b, r * s:(r + 1) * s, a * s:(a + 1) * s, e * s:(e + 1) * s]
        torch.testing.assert_close(t[1], patch.sum(), rtol=1e-5, atol=0)   # float32 sums of 4096 values in [0, 1)
        assert torch.all(t[2:] == 0)


def test_patch_condition_samples_with_one_condition_per_frame():
    torch.manual_seed(0)
    model = MODELS["rald-dit-tiny"](radar_condition="patches").eval()
    torch.nn.init.normal_(model.denoiser.proj_out.weight, std=0.1)
    calls = {"patches": 0, "denoiser": 0}
    model.radar_encoder.register_forward_hook(lambda *a: calls.__setitem__("patches", calls["patches"] + 1))
    model.denoiser.register_forward_hook(lambda *a: calls.__setitem__("denoiser", calls["denoiser"] + 1))
    cube = torch.rand(2, 128, 64, 32)
    x = model.sample(cube, [1, 2])
    assert calls == {"patches": 1, "denoiser": 35}
    assert x.shape == (2, model.cfg.n_latents, model.cfg.latent_dim) and torch.isfinite(x).all()
    with torch.no_grad():                         # the condition reaches the output
        assert not torch.equal(model(x, torch.full((2,), 1.0), model.encode_radar(cube)),
                               model(x, torch.full((2,), 1.0), model.encode_radar(cube.flip(1))))


def test_radar_condition_is_checked():
    with pytest.raises(ValueError, match="radar_condition must be one of"):
        LatentDiTConfig(radar_condition="raw")
