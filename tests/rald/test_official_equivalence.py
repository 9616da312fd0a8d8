"""Official RaLD checkpoints in radarpc: the reader (no clone needed), and, against a local clone of
RoyAPTX4869/RaLD, the same numbers as the official code for the autoencoder's logits, the EDM
denoiser and the whole Heun sampler.

The equivalence tests run only with ``RADARPC_RALD_REPO`` set to a working tree of the official
repository (``git clone https://github.com/RoyAPTX4869/RaLD``) and its model files' dependency
``einops`` (and ``timm``) importable; they build the official classes at tiny sizes with random
weights, save them as the official ``save_model`` does, and load them through
:func:`radarpc.experiments.rald.official.read_official_rald`.
"""
from __future__ import annotations

import argparse
import copy
import importlib
import importlib.util
import math
import os
import sys
import types
import warnings
from pathlib import Path

import pytest
import torch

from radarpc.experiments.rald.official import (OFFICIAL_GROUPS, convert_official_diffusion, read_official_checkpoint,
                                               read_official_rald)
from radarpc.io import DataFileError
from radarpc.models import build_model
from radarpc.models.edm import SeededNoise, edm_precondition, edm_sampler
from raldkit import SYSTEM_ARGS, EasyDict, ae_official_state, dit_official_state, save_official

REPO_ENV = "RADARPC_RALD_REPO"


# ---- the reader, without the official code ----------------------------------------------------

HEADS = 2


@pytest.fixture(scope="module")
def pair():
    """A radarpc autoencoder and diffusion model of matching latents, the diffusion model's radar
    encoder with the official GroupNorm (32 groups, so 32 base channels) and two levels only."""
    torch.manual_seed(0)
    ae = build_model("rald-ae-tiny", {"n_latents": 16, "latent_dim": 4}).eval()
    dit = build_model("rald-dit-tiny", {"enc_channels": 32, "enc_groups": OFFICIAL_GROUPS, "enc_ch_mult": (1, 1),
                                        "radar_shape": (4, 4, 2)}).eval()
    with torch.no_grad():                      # proj_out starts at zero: give it values, to see them land
        dit.denoiser.proj_out.weight.normal_()
    return ae, dit


def test_official_checkpoints_load_with_their_args_and_ema(tmp_path, pair):
    ae, dit = pair
    ae_off, dit_off = ae_official_state(ae), dit_official_state(dit)
    ema = {k: v if k == "point_embed.basis" else 0.5 * v for k, v in ae_off.items()}    # the basis is a buffer
    save_official(tmp_path / "ae.pth", ae_off, ema=ema)
    save_official(tmp_path / "gen.pth", dit_off, args=argparse.Namespace(model="kl_d512_m16_l4_d2_edm", lr=1e-4))

    got = read_official_rald(tmp_path / "ae.pth", tmp_path / "gen.pth", ae_heads=HEADS, dit_heads=HEADS)
    for field in ("width", "depth", "heads", "head_dim", "n_latents", "latent_dim", "fourier_freqs", "ff_mult",
                  "query_type"):
        assert getattr(got.ae_spec.config, field) == getattr(ae.cfg, field), field
    assert got.dit_spec.config == dit.cfg                       # every field of the diffusion model, from shapes
    assert got.ae_state.keys() == ae.state_dict().keys() and got.dit_state.keys() == dit.state_dict().keys()
    for k, v in ae.state_dict().items():                        # the EMA weights, where the file has them
        assert torch.equal(got.ae_state[k], 0.5 * v), k
    for k, v in dit.state_dict().items():                       # the model's, where it has none
        assert torch.equal(got.dit_state[k], v), k
    info = got.info
    assert info["autoencoder"]["weights"] == "model_ema" and info["diffusion"]["weights"] == "model"
    assert info["autoencoder"]["args"] == SYSTEM_ARGS and info["autoencoder"]["epoch"] == 99
    assert info["diffusion"]["args"] == {"model": "kl_d512_m16_l4_d2_edm", "lr": 1e-4}
    assert info["diffusion"]["parameters"] == sum(p.numel() for p in dit.parameters())
    assert len(info["autoencoder"]["sha256"]) == 64

    built_ae, built_dit = got.build()
    assert not built_ae.training and not built_dit.training
    assert torch.equal(built_dit.denoiser.proj_out.weight, dit.denoiser.proj_out.weight)
    only_model = read_official_rald(tmp_path / "ae.pth", tmp_path / "gen.pth", weights="model",
                                    ae_heads=HEADS, dit_heads=HEADS)
    assert only_model.info["autoencoder"]["weights"] == "model"
    assert all(torch.equal(only_model.ae_state[k], v) for k, v in ae.state_dict().items())


def test_bare_state_dicts_load(tmp_path, pair):
    ae, dit = pair
    torch.save(ae_official_state(ae), tmp_path / "ae.pth")
    torch.save({"module." + k: v for k, v in dit_official_state(dit).items()}, tmp_path / "gen.pth")   # DDP's prefix
    got = read_official_rald(tmp_path / "ae.pth", tmp_path / "gen.pth", ae_heads=HEADS, dit_heads=HEADS)
    assert got.info["autoencoder"]["weights"] == got.info["diffusion"]["weights"] == "state dict"
    assert got.info["diffusion"]["epoch"] is None and got.info["diffusion"]["args"] is None
    assert all(torch.equal(got.dit_state[k], v) for k, v in dit.state_dict().items())


def _plant(path: str) -> dict:
    """What unpickling the planted object runs: it writes a file."""
    Path(path).write_text("unpickling ran code of the file's choosing")
    return {}


class Planted:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (_plant, (str(self.marker),))


def test_a_pickled_object_is_refused_and_its_code_not_run(tmp_path, pair):
    ae, _ = pair
    marker = tmp_path / "ran.txt"
    path = tmp_path / "ck.pth"
    torch.save({"model": ae_official_state(ae), "args": Planted(marker)}, path)
    with pytest.raises(DataFileError, match=r"ck\.pth.*refusing.*_plant") as e:
        read_official_checkpoint(path)
    assert "EasyDict or a Namespace" in str(e.value)
    assert not marker.exists()
    with pytest.raises(DataFileError, match=r"ck\.pth.*refusing"):
        read_official_rald(path, path)
    assert not marker.exists()
    # the file does run code under full unpickling (what radarpc refuses to do): the test is not vacuous
    torch.load(path, weights_only=False)
    assert marker.exists()


def test_other_networks_and_damaged_weights_are_refused(tmp_path, pair):
    ae, dit = pair
    ae_off, dit_off = ae_official_state(ae), dit_official_state(dit)
    save_official(tmp_path / "ae.pth", ae_off)
    save_official(tmp_path / "gen.pth", dit_off)
    kw = {"ae_heads": HEADS, "dit_heads": HEADS}
    with pytest.raises(DataFileError, match=r"gen\.pth.*no 'point_embed\.mlp\.weight'.*swapped"):
        read_official_rald(tmp_path / "gen.pth", tmp_path / "ae.pth", **kw)

    def refused(name: str, state: dict, match: str, args=None) -> None:
        """``state`` saved as ``name``, read as its stage (the other file the good one): refused."""
        save_official(tmp_path / name, state, args=args)
        files = ((tmp_path / "ae.pth", tmp_path / name) if name.startswith("gen")
                 else (tmp_path / name, tmp_path / "gen.pth"))
        with pytest.raises(DataFileError, match=match):
            read_official_rald(*files, **kw)

    missing = {k: v for k, v in dit_off.items() if k != "model.transformer_blocks.1.attn2.to_k.weight"}
    refused("gen_missing.pth", missing, r"gen_missing\.pth.*1 missing.*blocks\.1\.cross_attn\.to_k\.weight")
    extra = dict(ae_off, **{"decoder_ff.fn.net.0.weight": torch.zeros(3, 3)})    # the official decoder_ff, on
    refused("ae_extra.pth", extra, r"ae_extra\.pth.*1 unexpected.*decoder_ff")
    shape = dict(dit_off, **{"model.transformer_blocks.0.norm2.linear.bias": torch.zeros(7)})
    refused("gen_shape.pth", shape, r"gen_shape\.pth.*norm2\.linear\.bias \(7,\) \(expected \(64,\)\)")
    nan = dict(ae_off, **{"layers.1.0.fn.to_q.weight": ae_off["layers.1.0.fn.to_q.weight"] * math.nan})
    refused("ae_nan.pth", nan, r"ae_nan\.pth.*non-finite.*layers\.1\.0\.fn\.to_q\.weight")
    basis = dict(ae_off, **{"point_embed.basis": ae_off["point_embed.basis"] * 2})
    refused("ae_basis.pth", basis, r"ae_basis\.pth.*point_embed\.basis")
    frozen_encoder = {k: v for k, v in dit_off.items() if not k.startswith("radar_enc.")}
    refused("gen_frozen.pth", frozen_encoder, r"gen_frozen\.pth.*without its radar encoder inside")
    two_channels = dict(dit_off, **{"radar_enc.conv_in.weight": torch.zeros(32, 2, 3, 3, 3)})
    refused("gen_dopp.pth", two_channels, r"gen_dopp\.pth.*reads 2 channels")
    refused("gen_named.pth", dit_off, r"gen_named\.pth.*kl_d512_m512_l32_d24_edm.*depth 24 \(the weights: 2\)",
            args=EasyDict({"ar_model": {"name": "kl_d512_m512_l32_d24_edm"}}))
    wrong_dims = dict(dit_off, **{"model.proj_in.weight": torch.zeros(32, 8),
                                  "model.proj_out.weight": torch.zeros(8, 32)})
    refused("gen_dims.pth", wrong_dims, r"gen_dims\.pth.*latents have 8 dimensions.*ae\.pth.*4: not a pair")

    (tmp_path / "not.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(DataFileError, match=r"not\.pth.*not a readable torch checkpoint"):
        read_official_checkpoint(tmp_path / "not.pth")
    torch.save({"weights": [1, 2]}, tmp_path / "list.pth")
    with pytest.raises(DataFileError, match=r"list\.pth.*expected an official RaLD checkpoint"):
        read_official_checkpoint(tmp_path / "list.pth")
    with pytest.raises(DataFileError, match=r"absent\.pth.*no such file"):
        read_official_checkpoint(tmp_path / "absent.pth")
    with pytest.raises(ValueError, match="weights must be one of"):
        read_official_checkpoint(tmp_path / "ae.pth", weights="best")
    with pytest.raises(DataFileError, match=r"does not split into heads=3"):
        convert_official_diffusion(dit_off, "gen.pth", heads=3)


# ---- against the official code ----------------------------------------------------------------

N_POINTS, N_QUERIES, SEEDS = 256, 500, (3, 11)
CUBE = (32, 16, 16)          # radar cube of the tiny diffusion model: 5 encoder levels -> a (2, 1, 1) token grid


class _Configs(dict):
    """The official ``configs`` object: an EasyDict's item and attribute access."""

    def __getattr__(self, key):
        try:
            return self[key]
        except KeyError:
            raise AttributeError(key) from None


def _timm_layers() -> types.ModuleType:
    """``timm.models.layers`` as the official files use it: ``DropPath``, the identity in evaluation.

    timm's own code either way: the package if it imports; else, when timm is installed but its
    package import fails (timm imports torchvision, which may be absent or built for another torch),
    timm's ``layers/drop.py`` alone, which imports nothing but torch."""
    before = set(sys.modules)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)          # timm's notice that the module moved
            return importlib.import_module("timm.models.layers")
    except (ImportError, RuntimeError, OSError):                    # e.g. a torchvision of another torch build
        for name in set(sys.modules) - before:                     # what the failed import left behind
            del sys.modules[name]
    spec = importlib.util.find_spec("timm")
    if spec is None or spec.origin is None:
        pytest.skip("needs timm, imported by the official model files (pip install timm)")
    drop = importlib.util.spec_from_file_location("_timm_drop", Path(spec.origin).parent / "layers" / "drop.py")
    module = importlib.util.module_from_spec(drop)
    drop.loader.exec_module(module)
    return types.SimpleNamespace(DropPath=module.DropPath)


@pytest.fixture(scope="module")
def official():
    """The official model files of the clone, imported as the official scripts import them."""
    repo = os.environ.get(REPO_ENV)
    if not repo:
        pytest.skip(f"needs a local clone of RoyAPTX4869/RaLD: set {REPO_ENV} to its working tree")
    repo = Path(repo)
    if not (repo / "model" / "models_ae.py").is_file():
        pytest.fail(f"{REPO_ENV}={repo} is not a working tree of RoyAPTX4869/RaLD (no model/models_ae.py)")
    if importlib.util.find_spec("einops") is None:
        pytest.skip("needs einops, imported by the official model files (pip install einops)")
    layers = _timm_layers()
    mp = pytest.MonkeyPatch()
    mp.syspath_prepend(str(repo))
    if "timm.models.layers" not in sys.modules:          # timm's drop.py alone: where the official files look
        mp.setitem(sys.modules, "timm", types.ModuleType("timm"))
        mp.setitem(sys.modules, "timm.models", types.ModuleType("timm.models"))
        mp.setitem(sys.modules, "timm.models.layers", layers)
    if importlib.util.find_spec("torch_cluster") is None:
        # models_ae.py imports torch_cluster's fps at module level, but only the "point" query type
        # calls it; the compared autoencoder is the official "mix" (hybrid) type. This stand-in
        # fails if anything calls it.
        def fps(*args, **kwargs):
            raise RuntimeError("torch_cluster.fps is not installed (the tests use the 'mix' query type)")
        mp.setitem(sys.modules, "torch_cluster", types.SimpleNamespace(fps=fps))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)        # 2 cores shared by many processes: one thread is the fastest here
    try:
        ae_mod = importlib.import_module("model.models_ae")
        gen_mod = importlib.import_module("model.models_radar_generation")
        yield types.SimpleNamespace(models_ae=ae_mod, models_radar_generation=gen_mod)
    finally:
        torch.set_num_threads(threads)
        for name in [n for n in sys.modules if n == "model" or n.startswith("model.")]:
            del sys.modules[name]
        mp.undo()


def _randomise(module: torch.nn.Module, seed: int) -> None:
    """Every parameter random (the official zero-initialised output projection too): matrices
    N(0, 1 / fan_in), so that activations stay of order one; norm weights near 1, biases near 0."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            noise = torch.randn(p.shape, generator=g)
            p.copy_(noise / p[0].numel() ** 0.5 if p.ndim >= 2 else
                    1 + 0.1 * noise if name.endswith("weight") else 0.1 * noise)


@pytest.fixture(scope="module")
def models(official, tmp_path_factory):
    """The tiny official networks with random weights, saved as ``save_model`` saves them and
    loaded through radarpc's reader: ``(official_ae, official_net, radarpc_ae, radarpc_dit)``."""
    torch.manual_seed(0)
    ae = official.models_ae.KLAutoEncoder(depth=2, dim=64, queries_dim=64, output_dim=1, num_inputs=N_POINTS,
                                          num_latents=16, latent_dim=4, heads=HEADS, dim_head=32,
                                          query_type="mix").eval()
    configs = _Configs(cond_type="radar", unfreeze_radar_enc=True, use_radar_enc=True, radar_token_channel=32,
                       enc_hidden_ch=32, enc_radar_ch=8, enc_radar_r_dim=CUBE[0] // 16,
                       enc_radar_a_dim=CUBE[1] // 16, enc_radar_e_dim=CUBE[2] // 16)
    net = official.models_radar_generation.EDMPrecond(n_latents=16, channels=4, n_heads=HEADS, d_head=16, depth=2,
                                                      configs=configs).eval()
    _randomise(ae, 1)
    _randomise(net, 2)
    folder = tmp_path_factory.mktemp("official")
    save_official(folder / "checkpoint-0.pth", ae.state_dict())
    save_official(folder / "checkpoint-1.pth", net.state_dict())
    got = read_official_rald(folder / "checkpoint-0.pth", folder / "checkpoint-1.pth",
                             ae_heads=HEADS, dit_heads=HEADS)
    assert got.info["autoencoder"]["parameters"] == sum(p.numel() for p in ae.parameters())
    assert got.info["diffusion"]["parameters"] == sum(p.numel() for p in net.parameters())
    return (ae, net, *got.build())


def assert_float32_equal(ours: torch.Tensor, ours64: torch.Tensor, theirs: torch.Tensor) -> None:
    """radarpc's float32 result equals the official one to float32 rounding.

    The two codes evaluate the same expression in float32 in different operation orders (fused
    scaled-dot-product attention against einsum / bmm and softmax; F.silu against x sigmoid(x);
    matrix products of other shapes; the official radar encoding in every denoiser call), so each
    result carries its own rounding error and they differ by at most the sum of the two. radarpc's
    error on this very computation is measured, e = max |ours - ours64| (float64's own rounding is
    2^29 times smaller); the official code's is of the same order, as it does the same float32
    operations on the same inner-product lengths and depth (the a-priori bound c sqrt(n) L u |y| of
    both: u = 2^-24, n the longest sum, L the layers). Both are maxima over a few hundred
    elements, so their ratio scatters (d / e is 0.1 to 6 in these cases); allowed: 32 e, about
    1e-5 of |y| here. A real difference in the maths (a head split, an epsilon, a coefficient)
    shows at 1e-3 of |y| and above, a hundred times more.
    """
    e = (ours.double() - ours64).abs().max().item()
    assert e > 0                                      # float32 and float64 differ: e measures rounding
    d = (ours - theirs).abs().max().item()
    assert d <= 32 * e, f"max |radarpc - official| = {d:.3g} exceeds 32 x radarpc's float32 error {e:.3g}"


def test_autoencoder_logits_equal_the_official(models):
    ae, _, rae, _ = models
    g = torch.Generator().manual_seed(5)
    points = torch.rand(2, N_POINTS, 3, generator=g) * 2 - 1
    queries = torch.rand(2, N_QUERIES, 3, generator=g) * 2 - 1
    with torch.no_grad(), torch.random.fork_rng():
        torch.manual_seed(7)                          # the official posterior draws torch.randn(mean.shape)
        theirs = ae(points, queries)
        torch.manual_seed(7)
        eps = torch.randn(2, 16, 4)
        logits, kl = rae(points, queries, noise=eps)
        logits64, kl64 = copy.deepcopy(rae).double()(points.double(), queries.double(), noise=eps.double())
        # the maths, in float64: the official code with its frequency buffer pi 2^k in float64 too
        # (it stores them in float32, radarpc computes them)
        ae64 = copy.deepcopy(ae).double()
        k = 2.0 ** torch.arange(8, dtype=torch.float64) * math.pi
        ae64.point_embed.basis.copy_(torch.block_diag(k[None], k[None], k[None]))
        torch.manual_seed(7)
        theirs64 = ae64(points.double(), queries.double())
    assert logits.shape == theirs["logits"].shape == (2, N_QUERIES)
    assert_float32_equal(logits, logits64, theirs["logits"])
    assert_float32_equal(kl, kl64, theirs["kl"])
    assert (logits64 - theirs64["logits"]).abs().max() <= 1e-12 * theirs64["logits"].abs().max()
    assert (logits.amax(1) - logits.amin(1)).min() > 0.1      # logits that vary with the query, not a constant


def _cubes(batch: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """radarpc's intensity cube ``(B, R, A, E)`` and the official input ``(B, R, A, E, 2)`` whose
    channel 0 is that intensity (channel 1, Doppler, is read by neither model)."""
    g = torch.Generator().manual_seed(seed)
    cube = torch.rand(batch, *CUBE, generator=g)
    return cube, torch.stack([cube, torch.randn(batch, *CUBE, generator=g)], dim=-1)


def _float64_denoiser(dit64):
    """radarpc's float64 denoiser: edm_precondition computes the EDM coefficients from sigma in
    float32 (the official arithmetic), so the float64 network is handed a float32 c_noise."""
    return lambda x, sigma, cond: edm_precondition(lambda a, c, k: dit64.denoiser(a, c.double(), k),
                                                   x, sigma, cond, dit64.cfg.sigma_data)


def test_denoiser_equals_the_official(models):
    _, net, _, dit = models
    cube, cube5 = _cubes(2, 8)
    g = torch.Generator().manual_seed(9)
    x = torch.randn(2, 16, 4, generator=g) * 3
    dit64 = copy.deepcopy(dit).double()
    net64 = copy.deepcopy(net).double()
    with torch.no_grad():
        cond, cond64 = dit.encode_radar(cube), dit64.encode_radar(cube.double())
    for sigma in (torch.tensor([0.05, 3.0]), torch.tensor([80.0, 0.5])):
        with torch.no_grad():
            theirs = net(x, sigma, cube5, "radar")
            ours = dit(x, sigma, cond)
            ours64 = _float64_denoiser(dit64)(x.double(), sigma, cond64)
        assert_float32_equal(ours, ours64, theirs)
        # the raw network's output F = (D - c_skip x) / c_out is of order one: F is compared, not c_skip x alone
        c_skip, c_out = 1 / (sigma ** 2 + 1), sigma / (sigma ** 2 + 1).sqrt()
        assert ((theirs - c_skip[:, None, None] * x) / c_out[:, None, None]).abs().amax(dim=(1, 2)).min() > 0.1
    with torch.no_grad():                             # the raw network and the condition, in float64
        x_in, c_noise = x.double() / 3, torch.tensor([0.3, -0.7], dtype=torch.float64)
        theirs64 = net64.model(x_in, c_noise, cond=net64.process_radar_cond(cube5.double()))
        ours64 = dit64.denoiser(x_in, c_noise, cond64)
    assert (ours64 - theirs64).abs().max() <= 1e-12 * theirs64.abs().max()


def test_sampler_latents_equal_the_official(models):
    _, net, _, dit = models
    cube, cube5 = _cubes(2, 10)
    dit64 = copy.deepcopy(dit).double()
    with torch.no_grad():
        theirs = net.sample(cond=cube5, batch_seeds=torch.tensor(SEEDS), cond_type="radar")   # 18 Heun steps
        ours = dit.sample(cube, SEEDS)
        noise = SeededNoise(SEEDS).randn((2, 16, 4))
        ours64 = edm_sampler(_float64_denoiser(dit64), noise.double(), dit64.encode_radar(cube.double()))
    assert ours.shape == theirs.shape == (2, 16, 4)
    assert_float32_equal(ours, ours64, theirs)
    assert (theirs[0] - theirs[1]).abs().max() > 0.1           # two seeds, two samples
