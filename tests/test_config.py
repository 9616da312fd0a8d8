"""Typed configs: dict and YAML round trips, validation in one place, errors that name the file."""
from __future__ import annotations

import dataclasses

import pytest

from radarpc.config import from_dict, load_yaml, save_yaml, to_dict
from radarpc.dsp.pointcloud import SpectralPointCloudConfig
from radarpc.pipelines.pointclouds import ConvertSettings


@dataclasses.dataclass(frozen=True)
class Inner:
    sizes: tuple[int, int] = (1, 2)


@dataclasses.dataclass(frozen=True)
class Outer:
    name: str
    inner: Inner = Inner()
    tags: tuple[str, ...] = ()
    limit: float | None = None


def test_round_trip_of_nested_typed_configs(tmp_path):
    cfg = Outer("a", Inner((3, 4)), ("x", "y"), 0.5)
    d = to_dict(cfg)
    assert d == {"name": "a", "inner": {"sizes": [3, 4]}, "tags": ["x", "y"], "limit": 0.5}
    assert from_dict(Outer, d) == cfg
    assert load_yaml(Outer, save_yaml(cfg, tmp_path / "c.yaml")) == cfg


def test_convert_settings_dict_and_yaml(tmp_path):
    s = ConvertSettings(density=0.05, density_mode="per-dataset", enrich=("rd3", "sector8"), window=(19, 19),
                        guard=(7, 7), envelope="all-slots", split="train")
    d = s.to_dict()
    assert d["window"] == [19, 19] and d["enrich"] == ["rd3", "sector8"]
    assert ConvertSettings.from_dict(d) == s
    assert load_yaml(ConvertSettings, save_yaml(s, tmp_path / "pc.yaml")) == s
    pc = SpectralPointCloudConfig(density=0.1, enrich="rd3,patch5")
    assert SpectralPointCloudConfig.from_dict(pc.to_dict()) == pc


def test_values_are_validated_by_the_config_itself(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("density: 1.5\n")
    with pytest.raises(ValueError, match=r"bad\.yaml: density must be in \(0, 1\]"):
        load_yaml(ConvertSettings, p)
    p.write_text("tau: 2.0\nwindow: [4, 9]\n")
    with pytest.raises(ValueError, match=r"bad\.yaml: .*odd"):
        load_yaml(ConvertSettings, p)


def test_unknown_and_missing_keys_are_named():
    with pytest.raises(ValueError, match=r"run\.yaml: ConvertSettings unknown keys \['desnity'\]"):
        from_dict(ConvertSettings, {"desnity": 0.1}, where="run.yaml")
    with pytest.raises(ValueError, match=r"cfg: Outer missing keys \['name'\]"):
        from_dict(Outer, {}, where="cfg")
    with pytest.raises(ValueError, match="expected a mapping"):
        from_dict(Outer, [1, 2])


def test_yaml_is_loaded_safely(tmp_path):
    p = tmp_path / "evil.yaml"
    p.write_text("name: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(ValueError, match=r"evil\.yaml: not valid YAML"):
        load_yaml(Outer, p)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_yaml(Outer, tmp_path / "missing.yaml")
