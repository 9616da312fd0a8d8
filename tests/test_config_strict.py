"""Strict config loading: each bad value ends in one line naming the file and the field."""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import pytest

from radarpc.config import MAX_CONFIG_NODES, from_dict, load_yaml, load_yaml_mapping


@dataclass(frozen=True)
class Inner:
    n: int = 1


@dataclass(frozen=True)
class Cfg:
    count: int = 1
    rate: float = 0.5
    flag: bool = False
    name: str = "x"
    sizes: tuple[int, int] = (1, 2)
    widths: tuple[float, ...] = (1.0,)
    maybe: int | None = None
    far: float = float("inf")              # a default that is not finite allows non-finite values
    inner: Inner = field(default_factory=Inner)


@pytest.mark.parametrize("key, value, message", [
    ("count", "1", "count: expected an integer, got '1' (a string)"),
    ("count", True, "count: expected an integer, got true"),
    ("count", 1.7, "count: expected an integer, got 1.7"),
    ("count", 2**70, "count: 1180591620717411303424 is out of range (a 64-bit integer)"),
    ("count", None, "count: expected an integer, got null"),
    ("rate", "0.01", "rate: expected a number, got '0.01' (a string)"),
    ("rate", float("inf"), "rate: expected finite numbers, got inf"),
    ("rate", float("nan"), "rate: expected finite numbers, got nan"),
    ("flag", 1, "flag: expected true or false, got 1"),
    ("name", 3, "name: expected a string, got 3"),
    ("sizes", [1, 2, 3], "sizes: expected a list of 2 values, got 3"),
    ("sizes", 4, "sizes: expected a list, got 4"),
    ("widths", [1.0, "a"], "widths[1]: expected a number, got 'a' (a string)"),
    ("widths", [1.0, float("-inf")], "widths: expected finite numbers"),
    ("maybe", "3", "maybe: expected an integer, got '3'"),
    ("inner", "resnet50", "inner: expected a mapping of Inner fields, got 'resnet50'"),
    ("inner", None, "inner: expected a mapping of Inner fields, got null"),
])
def test_wrong_types_are_refused_with_the_field_named(key, value, message):
    with pytest.raises(ValueError, match="^" + re.escape(f"cfg.yaml: {message}")):
        from_dict(Cfg, {key: value}, where="cfg.yaml")


def test_right_types_pass_and_integers_become_floats():
    cfg = from_dict(Cfg, {"count": 3, "rate": 1, "flag": True, "sizes": [3, 4], "widths": [2], "maybe": None,
                          "far": float("inf"), "inner": {"n": 2}})
    assert cfg == Cfg(3, 1.0, True, "x", (3, 4), (2.0,), None, float("inf"), Inner(2))
    assert type(cfg.rate) is float and type(cfg.widths[0]) is float


def test_duplicate_keys_binary_files_and_non_mappings_are_refused(tmp_path):
    (tmp_path / "dup.yaml").write_text("count: 1\nrate: 0.1\ncount: 3\n")
    with pytest.raises(ValueError, match=r"dup.yaml: not valid YAML: found the key 'count' twice at line 3, column 1$"):
        load_yaml(Cfg, tmp_path / "dup.yaml")
    (tmp_path / "bin.yaml").write_bytes(bytes(range(128, 256)))
    with pytest.raises(ValueError, match=r"bin.yaml: not a text file \(not UTF-8 at byte 0\)"):
        load_yaml(Cfg, tmp_path / "bin.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ValueError, match=r"list.yaml: expected a mapping of config fields, got \[1, 2\]"):
        load_yaml(Cfg, tmp_path / "list.yaml")
    with pytest.raises(FileNotFoundError, match="config file .*missing.yaml does not exist"):
        load_yaml(Cfg, tmp_path / "missing.yaml")
    with pytest.raises(IsADirectoryError, match="is a folder"):
        load_yaml(Cfg, tmp_path)


def test_alias_bombs_are_refused_before_they_are_expanded(tmp_path):
    # 1.6 KB of nested anchors stands for 10^8 values: the count stops at the bound, nothing is built
    lines = ["a0: &a0 [" + ", ".join(["1"] * 10) + "]"]
    for k in range(1, 8):
        lines.append(f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 10) + "]")
    (tmp_path / "bomb.yaml").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=f"bomb.yaml: with its aliases expanded the YAML holds more than "
                                         f"{MAX_CONFIG_NODES:,} values"):
        load_yaml_mapping(tmp_path / "bomb.yaml")
    # a few aliases that stay small are ordinary YAML
    (tmp_path / "ok.yaml").write_text("a: &w [1, 2]\nb: *w\n")
    assert load_yaml_mapping(tmp_path / "ok.yaml") == {"a": [1, 2], "b": [1, 2]}
