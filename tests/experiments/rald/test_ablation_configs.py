"""The shipped ablation configs (configs/rald/ablations/): each loads strictly and differs from the
base it names in exactly the fields its header documents."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from radarpc.config import to_dict
from radarpc.experiments.rald.config import load_experiment

CONFIGS = Path(__file__).parents[3] / "configs"
ABLATIONS = sorted((CONFIGS / "rald" / "ablations").glob("*.yaml"))
GENERALIZATION = sorted((CONFIGS / "rald" / "generalization").glob("*.yaml"))
CONDITIONING = sorted((CONFIGS / "rald" / "conditioning").glob("*.yaml"))
BUDGET = sorted((CONFIGS / "rald" / "budget").glob("*.yaml"))
DIFFERS = re.compile(r"^# Differs from (configs/\S+\.yaml) in: (.+?)\.?$", re.M)


def _flat(d, prefix: str = "") -> dict[str, object]:
    """Dotted paths to the leaves of nested mappings (an empty mapping has none: ``overrides: {}``
    and ``overrides: {depth: 2}`` differ in ``overrides.depth`` alone)."""
    out: dict[str, object] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _documented(path: Path) -> tuple[Path, set[str]]:
    """The base config and the changed fields a header names (``a.b (old -> new)`` reads ``a.b``)."""
    found = DIFFERS.findall(path.read_text())
    assert len(found) == 1, f"{path.name}: one '# Differs from configs/... in: ...' line expected"
    base, fields = found[0]
    return CONFIGS.parent / base, {re.sub(r"\s*\(.*\)$", "", f.strip()) for f in re.split(r",\s*(?![^()]*\))", fields)}


def test_every_table_has_its_configs():
    assert [p.name for p in ABLATIONS] == [
        "rald-ae-s-fps.yaml", "rald-ae-s-static.yaml", "rald-ae-s-voxel.yaml",
        "rald-s-ae-fps.yaml", "rald-s-ae-static.yaml", "rald-s-ae-voxel.yaml",
        "rald-s-d2.yaml", "rald-s-d3.yaml", "rald-s-no-encoder.yaml"]


@pytest.mark.parametrize("path", ABLATIONS, ids=lambda p: p.stem)
def test_ablation_differs_from_its_base_in_the_documented_fields(path):
    cfg = load_experiment(path)                            # strict: unknown fields refused
    base_path, documented = _documented(path)
    base = load_experiment(base_path)
    assert cfg.stage == base.stage and cfg.name == path.stem
    a, b = _flat(to_dict(cfg)), _flat(to_dict(base))
    changed = {k for k in a.keys() | b.keys() if a.get(k, "<absent>") != b.get(k, "<absent>")}
    assert changed == documented
    text = path.read_text()
    assert f"configs/rald/ablations/{path.name}" in text     # the header's command names this file
    assert re.search(r"^# Ablation, the seed's Table", text, re.M)


@pytest.mark.parametrize("path", GENERALIZATION + CONDITIONING + BUDGET, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_derived_configs_differ_from_their_base_in_the_documented_fields(path):
    """configs/rald/generalization, conditioning and budget: each names its base and its changes."""
    cfg = load_experiment(path)
    base_path, documented = _documented(path)
    a, b = _flat(to_dict(cfg)), _flat(to_dict(load_experiment(base_path)))
    assert {k for k in a.keys() | b.keys() if a.get(k, "<absent>") != b.get(k, "<absent>")} == documented
    assert cfg.name == path.stem and f"configs/rald/{path.parent.name}/{path.name}" in path.read_text()
    if path.parent.name == "generalization":
        assert cfg.scenes is not None


def test_the_ablations_change_what_the_tables_compare():
    load = lambda name: load_experiment(CONFIGS / "rald" / "ablations" / f"{name}.yaml")
    assert load("rald-ae-s-static").model.config.query_type == "static"
    assert load("rald-ae-s-fps").model.config.query_type == "fps"
    voxel = load("rald-ae-s-voxel")
    assert voxel.data.partition == "cartesian" and voxel.model.config.query_type == "hybrid"
    no_enc = load("rald-s-no-encoder").model.config
    assert no_enc.radar_condition == "patches" and no_enc.n_radar_tokens == 64      # as many tokens as the encoder's
    # Table 9 in proportion: 12 / 18 / 24 of 24 blocks -> 2 / 3 / 4 of rald-s's 4
    full = load_experiment(CONFIGS / "rald-s.yaml").model.config.depth
    assert full == 4
    assert [load(f"rald-s-d{d}").model.config.depth * 24 // full for d in (2, 3)] == [12, 18]
    # every diffusion ablation generates rald-ae-s's latents (so any of the autoencoders can feed it)
    ae = load_experiment(CONFIGS / "rald-ae-s.yaml").model.config
    for p in ABLATIONS:
        c = load_experiment(p)
        if c.stage == "diffusion":
            assert (c.model.config.n_latents, c.model.config.latent_dim) == (ae.n_latents, ae.latent_dim)


@pytest.mark.parametrize("path", sorted((CONFIGS / "rald").glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_generation_configs_load_strictly(path):
    """configs/rald/*.yaml are `radarpc generate --config` files: strict loading, a command naming the file."""
    from radarpc.config import load_yaml
    from radarpc.experiments.rald.generation import GenerateConfig

    cfg = load_yaml(GenerateConfig, path)
    assert cfg.generation.random_queries + cfg.generation.guided_queries > 0
    assert f"configs/rald/{path.name}" in path.read_text()
