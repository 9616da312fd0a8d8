"""The official RaLD networks at the paper's size against radarpc's, with the same random weights.

Runs, unchanged, the model files of a local clone of RoyAPTX4869/RaLD given by ``--rald-repo``:
``model/models_ae.py`` ``kl_d512_m512_l32_mix`` (10,000 input points) and
``model/models_radar_generation.py`` ``kl_d512_m512_l32_d24_edm`` with the radar encoder inside, as
the published generation config builds it (``unfreeze_radar_enc: true``, ``enc_hidden_ch: 64``,
``enc_radar_ch: 16``, ``radar_token_channel: 512``, an 8 x 4 x 2 token grid from the 128 x 64 x 32
cube). Every parameter gets a random value (fp32; the zero-initialised output projection too), both
networks are saved as ``utils/misc.py`` ``save_model`` saves them (``model``, ``model_ema``,
``epoch``, ``args`` an EasyDict; no optimizer state), read back through
:func:`radarpc.experiments.rald.official.read_official_rald`, and compared:

* ``parameters``: the official networks' and radarpc's counts, and the paper's 108,002,881
  (autoencoder) and 183,766,160 (diffusion model with its radar encoder);
* ``autoencoder``: the occupancy logits of ``--queries`` random queries given ``--points`` random
  points, with the same posterior noise, and the KL term;
* ``denoiser``: ``EDMPrecond.forward`` against ``LatentDiT.forward`` at four noise levels;
* ``sampler``: the Heun sampler's latents for the same seeds over ``--steps`` steps (the paper's 18
  are ``2 x 18 - 1 = 35`` network calls; the official code re-encodes the radar cube in each, so a
  paper-size run takes long on a CPU: ``--steps 2`` makes 3 calls).

Each comparison prints ``max_abs_diff`` (radarpc against official), ``max_abs_official`` and
``radarpc_float32_error``: radarpc's float32 result against its float64 result, the size of float32
rounding in that very computation (``--no-float64`` skips it). Equal to float32 rounding means a
difference of the order of that error.

The official model files import ``einops`` (needed), ``timm`` (for ``DropPath``, the identity in
evaluation; where timm's package import fails, as without a torchvision built for this torch, its
own ``layers/drop.py`` is loaded alone) and ``torch_cluster`` (only the autoencoder's ``point``
query type calls it; a stand-in that fails if called replaces it when absent).

Usage::

    python checks/rald_official.py --rald-repo path/to/RaLD [--steps 2] [--points 10000] [--queries 20000]
"""
from __future__ import annotations

import argparse
import copy
import gc
import importlib
import importlib.util
import json
import math
import subprocess
import sys
import tempfile
import types
import warnings
from pathlib import Path

import torch

from radarpc.experiments.rald.official import read_official_rald
from radarpc.models.edm import SeededNoise, edm_precondition, edm_sampler

PAPER_AE_PARAMETERS = 108_002_881
PAPER_GENERATION_PARAMETERS = 183_766_160
SEEDS = (0, 1)
SIGMAS = (0.002, 0.5, 3.0, 80.0)

# The published generation config's ar_model.configs (ge_indoor_cfg_aniso_mix_view_cone_unfreeze_enc_ints_only.yml)
GENERATION_CONFIGS = {"cond_type": "radar", "use_radar_cond": True, "use_radar_enc": True, "unfreeze_radar_enc": True,
                      "enc_radar_r_dim": 8, "enc_radar_a_dim": 4, "enc_radar_e_dim": 2, "enc_radar_ch": 16,
                      "enc_hidden_ch": 64, "radar_token_channel": 512}
SYSTEM_ARGS = {"device": "cuda:0", "seed": 1024, "expname": "check", "log_dir": "./result/ckpt",
               "output_dir": "./result/ckpt", "distributed": False, "dist_eval": False, "mode": "train"}


class EasyDict(dict):
    """Pickles byte for byte as ``easydict.EasyDict`` (the official ``args``), without easydict."""

    __module__ = "easydict"

    def __init__(self, d):
        super().__init__(d)
        self.__dict__.update(d)

    def __getattr__(self, key):                     # the official configs object's attribute access
        try:
            return self[key]
        except KeyError:
            raise AttributeError(key) from None


def import_official(repo: Path) -> types.SimpleNamespace:
    """``model.models_ae`` and ``model.models_radar_generation`` of the clone, as its scripts import them."""
    if not (repo / "model" / "models_ae.py").is_file():
        sys.exit(f"--rald-repo {repo}: not a working tree of RoyAPTX4869/RaLD (no model/models_ae.py)")
    if importlib.util.find_spec("einops") is None:
        sys.exit("the official model files import einops: pip install einops")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)          # timm's notice that the module moved
            importlib.import_module("timm.models.layers")
    except (ImportError, RuntimeError, OSError):
        for name in [n for n in sys.modules if n.split(".")[0] in ("timm", "torchvision")]:
            del sys.modules[name]
        spec = importlib.util.find_spec("timm")
        if spec is None or spec.origin is None:
            sys.exit("the official model files import timm: pip install timm")
        drop = importlib.util.spec_from_file_location("_timm_drop", Path(spec.origin).parent / "layers" / "drop.py")
        module = importlib.util.module_from_spec(drop)
        drop.loader.exec_module(module)
        sys.modules.update({"timm": types.ModuleType("timm"), "timm.models": types.ModuleType("timm.models"),
                            "timm.models.layers": types.SimpleNamespace(DropPath=module.DropPath)})
    if importlib.util.find_spec("torch_cluster") is None:
        def fps(*args, **kwargs):
            raise RuntimeError("torch_cluster.fps is not installed (this check uses the 'mix' query type)")
        sys.modules["torch_cluster"] = types.SimpleNamespace(fps=fps)
    sys.path.insert(0, str(repo))
    return types.SimpleNamespace(models_ae=importlib.import_module("model.models_ae"),
                                 models_radar_generation=importlib.import_module("model.models_radar_generation"))


def randomise(module: torch.nn.Module, seed: int) -> None:
    """Matrices N(0, 1 / fan_in), norm weights near 1, biases near 0: every parameter random."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            noise = torch.randn(p.shape, generator=g)
            p.copy_(noise / p[0].numel() ** 0.5 if p.ndim >= 2 else
                    1 + 0.1 * noise if name.endswith("weight") else 0.1 * noise)


def save_official(path: Path, state: dict) -> None:
    sys.modules["easydict"] = types.SimpleNamespace(EasyDict=EasyDict)   # where pickle looks the class up
    try:
        torch.save({"model": state, "model_ema": None, "epoch": 0, "args": EasyDict(SYSTEM_ARGS)}, path)
    finally:
        del sys.modules["easydict"]


def compare(ours: torch.Tensor, theirs: torch.Tensor, ours64: torch.Tensor | None) -> dict:
    out = {"max_abs_diff": (ours - theirs).abs().max().item(), "max_abs_official": theirs.abs().max().item()}
    if ours64 is not None:
        out["radarpc_float32_error"] = (ours.double() - ours64).abs().max().item()
    return out


def count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rald-repo", type=Path, required=True, help="working tree of RoyAPTX4869/RaLD")
    ap.add_argument("--steps", type=int, default=18, help="Heun steps of the sampler comparison (paper: 18)")
    ap.add_argument("--points", type=int, default=10_000, help="LiDAR points per frame (official: 10,000)")
    ap.add_argument("--queries", type=int, default=20_000, help="occupancy queries per frame")
    ap.add_argument("--batch", type=int, default=1, help="frames per comparison")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-float64", action="store_true", help="skip radarpc's float64 runs (the rounding scale)")
    args = ap.parse_args()
    if args.steps < 2:
        ap.error("--steps must be at least 2")
    official = import_official(args.rald_repo.resolve())
    report: dict = {"official_repo": str(args.rald_repo)}
    try:
        report["official_commit"] = subprocess.run(["git", "-C", str(args.rald_repo), "rev-parse", "HEAD"],
                                                   capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        report["official_commit"] = None
    torch.manual_seed(args.seed)

    # ---- the official networks, random, saved and read back ---------------------------------------
    ae = official.models_ae.kl_d512_m512_l32_mix(N=args.points).eval()
    net = official.models_radar_generation.kl_d512_m512_l32_d24_edm(configs=EasyDict(GENERATION_CONFIGS)).eval()
    randomise(ae, args.seed + 1)
    randomise(net, args.seed + 2)
    with tempfile.TemporaryDirectory() as tmp:
        save_official(Path(tmp) / "ae.pth", ae.state_dict())
        save_official(Path(tmp) / "gen.pth", net.state_dict())
        got = read_official_rald(Path(tmp) / "ae.pth", Path(tmp) / "gen.pth")
    rae, rdit = got.build()
    report["radarpc_models"] = {"autoencoder": {"variant": got.ae_spec.variant, "overrides": got.ae_spec.overrides},
                                "diffusion": {"variant": got.dit_spec.variant, "overrides": got.dit_spec.overrides}}
    del got
    gc.collect()
    report["parameters"] = {
        "autoencoder": {"official": count(ae), "radarpc": count(rae), "paper": PAPER_AE_PARAMETERS},
        "generation": {"official": count(net), "radarpc": count(rdit), "paper": PAPER_GENERATION_PARAMETERS,
                       "radar_encoder_official": count(net.radar_enc),
                       "radar_encoder_radarpc": count(rdit.radar_encoder)},
    }
    for v in report["parameters"].values():
        v["equal"] = v["official"] == v["radarpc"] == v["paper"]

    # ---- autoencoder -----------------------------------------------------------------------------
    g = torch.Generator().manual_seed(args.seed + 3)
    points = torch.rand(args.batch, args.points, 3, generator=g) * 2 - 1
    queries = torch.rand(args.batch, args.queries, 3, generator=g) * 2 - 1
    with torch.no_grad(), torch.random.fork_rng():
        torch.manual_seed(args.seed + 4)             # the official posterior draws torch.randn(mean.shape)
        theirs = ae(points, queries)
        torch.manual_seed(args.seed + 4)
        eps = torch.randn(args.batch, rae.cfg.n_latents, rae.cfg.latent_dim)
        logits, kl = rae(points, queries, noise=eps)
        logits64 = kl64 = None
        if not args.no_float64:
            logits64, kl64 = copy.deepcopy(rae).double()(points.double(), queries.double(), noise=eps.double())
    report["autoencoder"] = {"logits": compare(logits, theirs["logits"], logits64),
                             "kl": compare(kl, theirs["kl"], kl64),
                             "occupied_fraction_official": (theirs["logits"] > 0).float().mean().item(),
                             "occupied_fraction_radarpc": (logits > 0).float().mean().item()}
    del ae, rae, theirs, logits, logits64
    gc.collect()

    # ---- denoiser --------------------------------------------------------------------------------
    g = torch.Generator().manual_seed(args.seed + 5)
    cube = torch.rand(args.batch, *rdit.cfg.radar_shape, generator=g)
    cube5 = torch.stack([cube, torch.randn(cube.shape, generator=g)], dim=-1)   # channel 0: intensity
    x = torch.randn(args.batch, rdit.cfg.n_latents, rdit.cfg.latent_dim, generator=g)
    dit64 = None if args.no_float64 else copy.deepcopy(rdit).double()
    # radarpc's float64 denoiser: edm_precondition computes the coefficients from sigma in float32
    # (the official arithmetic), so the float64 network is handed a float32 c_noise
    den64 = None if dit64 is None else (lambda xx, s, c: edm_precondition(
        lambda a, n, k: dit64.denoiser(a, n.double(), k), xx, s, c, dit64.cfg.sigma_data))
    with torch.no_grad():
        cond = rdit.encode_radar(cube)
        cond64 = None if dit64 is None else dit64.encode_radar(cube.double())
        report["denoiser"] = {}
        for s in SIGMAS:
            sigma = torch.full((args.batch,), s)
            xs = x * math.sqrt(1 + s * s)                # noisy latents of the size the sampler gives them
            theirs = net(xs, sigma, cube5, "radar")
            ours = rdit(xs, sigma, cond)
            ours64 = None if den64 is None else den64(xs.double(), sigma, cond64)
            report["denoiser"][f"sigma={s}"] = compare(ours, theirs, ours64)

    # ---- sampler ---------------------------------------------------------------------------------
    seeds = [args.seed + i for i in range(args.batch)]
    gen = official.models_radar_generation
    with torch.no_grad():
        if args.steps == 18:
            theirs = net.sample(cond=cube5, batch_seeds=torch.tensor(seeds), cond_type="radar")
        else:                                            # what EDMPrecond.sample does, with num_steps
            rnd = gen.StackedRandomGenerator(cube5.device, torch.tensor(seeds))
            latents = rnd.randn([args.batch, net.n_latents, net.channels], device=cube5.device)
            theirs = gen.edm_sampler(net, latents, cube5, "radar", randn_like=rnd.randn_like, num_steps=args.steps)
        ours = rdit.sample(cube, seeds, num_steps=args.steps)
        ours64 = None
        if den64 is not None:
            noise = SeededNoise(seeds).randn((args.batch, rdit.cfg.n_latents, rdit.cfg.latent_dim))
            ours64 = edm_sampler(den64, noise.double(), cond64, num_steps=args.steps)
    report["sampler"] = {"steps": args.steps, "network_calls": 2 * args.steps - 1,
                         "latents": compare(ours, theirs, ours64)}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
