"""``benchmarks/rald_generation.py`` at tiny size against a local clone of RoyAPTX4869/RaLD: it runs,
times every stage of both, and finds the same outputs (runs only with ``RADARPC_RALD_REPO`` set)."""
from __future__ import annotations

import importlib.util
import json
import os
import sys
from pathlib import Path

import pytest
import torch

BENCHMARK = Path(__file__).parents[2] / "benchmarks" / "rald_generation.py"
REPO_ENV = "RADARPC_RALD_REPO"
OFFICIAL_MODULES = ("model", "timm", "torch_cluster", "_timm_drop", "torchvision")


@pytest.fixture
def benchmark(monkeypatch):
    repo = os.environ.get(REPO_ENV)
    if not repo:
        pytest.skip(f"needs a local clone of RoyAPTX4869/RaLD: set {REPO_ENV} to its working tree")
    if importlib.util.find_spec("einops") is None or importlib.util.find_spec("timm") is None:
        pytest.skip("needs einops and timm, imported by the official model files")
    spec = importlib.util.spec_from_file_location("rald_generation_benchmark", BENCHMARK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr(sys, "path", list(sys.path))        # the official clone goes on the path
    before, threads = set(sys.modules), torch.get_num_threads()
    yield repo, module
    torch.set_num_threads(threads)
    for name in set(sys.modules) - before:                  # the official files and their stand-ins
        if name.split(".")[0] in OFFICIAL_MODULES:
            del sys.modules[name]


def test_tiny_benchmark_times_both_and_finds_the_same_outputs(benchmark, capsys):
    repo, module = benchmark
    report = module.main(["--rald-repo", repo, "--size", "tiny", "--steps", "3", "--threads", "1", "--float64",
                          "--plain-decode"])
    assert json.loads(capsys.readouterr().out) == json.loads(json.dumps(report))      # the printed JSON is the report
    stages = ("condition", "sampler", "decoding", "refinement")
    for side in ("official", "radarpc"):
        s = report["seconds"][side]
        assert all(s[k] > 0 for k in stages) and s["total"] == pytest.approx(sum(s[k] for k in stages))
    assert report["speedup"]["total"] == pytest.approx(report["seconds"]["official"]["total"]
                                                       / report["seconds"]["radarpc"]["total"])
    assert report["config"]["network_calls"] == 5
    agree = report["agreement"]
    lat = agree["latents"]
    # the two codes' latents differ by float32 rounding: at most a few times radarpc's own float32 error
    assert 0 < lat["radarpc_float32_error"] and lat["max_abs_diff"] <= 8 * lat["radarpc_float32_error"]
    assert lat["max_abs"] > 0.5                                                # latents of order one
    # the clouds: the same queries occupied, the same points; a few hundred of them
    assert agree["outputs_agree"]
    assert agree["decoding"]["queries"] == 7000 and agree["decoding"]["differ"] == 0
    cloud = agree["cloud"]
    assert cloud["same_count"] and cloud["fraction_differ"] == 0 and cloud["max_point_distance_m"] == 0.0
    assert 100 < cloud["radarpc_points"] < 3000
    occ = agree["occupied_first_stage"]
    assert occ["official"] == occ["radarpc"] > 0
    plain = report["plain_decode"]["cloud"]
    assert plain["same_count"] and plain["fraction_differ"] == 0
