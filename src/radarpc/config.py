"""Typed configs: frozen dataclasses, validated once, passed whole, stored with every run.

A radarpc config is a frozen dataclass that validates (and normalises) its fields in
``__post_init__``: that is the one place where a value is checked. Functions take the config
whole rather than its fields one by one, and every job stores the resolved config as a plain dict
(in a run folder's manifest, in a Parquet store's metadata) so that a result can be traced to
what made it. This module converts configs to and from plain dicts and YAML files:

* :func:`to_dict` — JSON/YAML-able dict (tuples become lists, nested configs dicts);
* :func:`from_dict` — the inverse, guided by the field types; unknown or missing keys are an
  error naming where the dict came from;
* :func:`save_yaml` / :func:`load_yaml` — atomic write, ``yaml.safe_load`` (never arbitrary
  objects).

Examples
--------
>>> from radarpc.pipelines.pointclouds import ConvertSettings        # doctest: +SKIP
>>> save_yaml(ConvertSettings(density=0.057, enrich=("rd3",)), "pc.yaml")  # doctest: +SKIP
>>> load_yaml(ConvertSettings, "pc.yaml")                              # doctest: +SKIP
"""
from __future__ import annotations

import dataclasses
import math
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

__all__ = ["to_dict", "from_dict", "save_yaml", "load_yaml", "load_yaml_mapping", "MAX_CONFIG_BYTES", "MAX_CONFIG_NODES"]

C = TypeVar("C")


def to_dict(cfg: Any) -> dict:
    """The config ``cfg`` (a dataclass instance) as a plain dict of JSON types, fields in order."""
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        raise TypeError(f"expected a dataclass config, got {type(cfg).__name__}")
    return {f.name: _plain(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}


def _plain(v: Any) -> Any:
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        to = getattr(v, "to_dict", None)
        return to() if callable(to) else to_dict(v)
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, Path):
        return str(v)
    return v


def from_dict(cls: type[C], d: Any, *, where: str = "config") -> C:
    """Build the config ``cls`` from a plain dict, converting lists to the tuples (and dicts to the
    nested configs) its field types name; ``cls.__post_init__`` then validates the values.

    Raises
    ------
    ValueError
        ``d`` is not a mapping, has keys that are not fields of ``cls``, or lacks required ones;
        the message starts with ``where`` (e.g. a file name) and lists them.
    """
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a mapping of {cls.__name__} fields, got {type(d).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(d) - set(fields))
    missing = sorted(n for n, f in fields.items() if n not in d and f.default is dataclasses.MISSING
                     and f.default_factory is dataclasses.MISSING)
    if unknown or missing:
        raise ValueError(f"{where}: {cls.__name__} " + "; ".join(
            ([f"unknown keys {unknown} (known: {sorted(fields)})"] if unknown else [])
            + ([f"missing keys {missing}"] if missing else [])))
    hints = typing.get_type_hints(cls)
    kw = {}
    for k, v in d.items():
        value = _typed(v, hints.get(k, Any), f"{where}: {k}")
        default = fields[k].default
        if not _finite(value) and (default is dataclasses.MISSING or _finite(default)):
            raise ValueError(f"{where}: {k}: expected finite numbers, got {_shown(v)}")
        kw[k] = value
    try:
        return cls(**kw)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: {e}") from e


_INT64 = 2**63


def _shown(v: Any) -> str:
    """A value as a message shows it: its YAML spelling and, where that hides it, its type."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f"{v!r} (a string)"
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _type_name(tp: Any) -> str:
    if tp is bool:
        return "true or false"
    if tp is int:
        return "an integer"
    if tp is float:
        return "a number"
    if tp is str:
        return "a string"
    if dataclasses.is_dataclass(tp):
        return f"a mapping of {tp.__name__} fields"
    return getattr(tp, "__name__", None) or str(tp)


def _finite(v: Any) -> bool:
    if isinstance(v, float):
        return math.isfinite(v)
    if isinstance(v, (tuple, list)):
        return all(_finite(x) for x in v)
    return True


def _typed(v: Any, tp: Any, where: str) -> Any:
    """``v`` checked against the field type ``tp`` and converted where YAML and JSON cannot say
    it (lists to tuples, mappings to nested configs, integers to floats). No other conversion:
    a string is not a number, a bool not an integer, a float not an integer."""
    if tp is Any:
        return v
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if v is None:
            if type(None) in args:
                return None
            raise ValueError(f"{where}: expected {' or '.join(_type_name(a) for a in args)}, got null")
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:
            return _typed(v, rest[0], where)
        for a in rest:
            try:
                return _typed(v, a, where)
            except ValueError:
                continue
        raise ValueError(f"{where}: expected {' or '.join(_type_name(a) for a in rest)}, got {_shown(v)}")
    if v is None:
        raise ValueError(f"{where}: expected {_type_name(tp)}, got null")
    if origin is tuple:
        if not isinstance(v, (list, tuple)):
            raise ValueError(f"{where}: expected a list, got {_shown(v)}")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_typed(x, args[0], f"{where}[{i}]") for i, x in enumerate(v))
        if args:
            if len(args) != len(v):
                raise ValueError(f"{where}: expected a list of {len(args)} values, got {len(v)}: {_shown(v)}")
            return tuple(_typed(x, a, f"{where}[{i}]") for i, (x, a) in enumerate(zip(v, args)))
        return tuple(v)
    if tp is dict or origin is dict:
        if not isinstance(v, dict):
            raise ValueError(f"{where}: expected a mapping, got {_shown(v)}")
        return v
    if dataclasses.is_dataclass(tp):
        if not isinstance(v, dict):
            raise ValueError(f"{where}: expected {_type_name(tp)}, got {_shown(v)}")
        fd = getattr(tp, "from_dict", None)
        return fd(v) if callable(fd) else from_dict(tp, v, where=where)
    if tp is bool:
        if not isinstance(v, bool):
            raise ValueError(f"{where}: expected true or false, got {_shown(v)}")
        return v
    if tp is int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise ValueError(f"{where}: expected an integer, got {_shown(v)}")
        if not -_INT64 <= v < _INT64:
            raise ValueError(f"{where}: {v} is out of range (a 64-bit integer)")
        return v
    if tp is float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"{where}: expected a number, got {_shown(v)}")
        if isinstance(v, int) and not -_INT64 <= v < _INT64:
            raise ValueError(f"{where}: {v} is out of range")
        return float(v)
    if tp is str:
        if not isinstance(v, str):
            raise ValueError(f"{where}: expected a string, got {_shown(v)}")
        return v
    return v


def save_yaml(cfg: Any, path: str | os.PathLike) -> Path:
    """Write ``to_dict(cfg)`` as YAML, atomically; returns the path."""
    import yaml

    from radarpc.io import atomic_write

    path = Path(path)
    with atomic_write(path, "w") as f:
        yaml.safe_dump(to_dict(cfg), f, sort_keys=False)
    return path


MAX_CONFIG_BYTES = 1 << 20
"""A config file larger than this is refused unread (configs are a few hundred bytes)."""
MAX_CONFIG_NODES = 100_000
"""A config whose values, with every YAML alias expanded, number more than this is refused: a few
nested anchors can stand for 10^8 values, which validation would then walk."""


def _yaml_loader():
    import yaml

    class StrictSafeLoader(yaml.SafeLoader):
        """``yaml.SafeLoader`` that refuses a key given twice in one mapping (where plain YAML
        loading keeps the last value without a word)."""

        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                except TypeError:             # an unhashable key: construct_mapping says so
                    break
                if duplicate:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping", node.start_mark, f"found the key {key!r} twice",
                        key_node.start_mark)
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    return StrictSafeLoader


def _expanded_nodes(root) -> int:
    """How many nodes the YAML node graph ``root`` stands for with every alias expanded."""
    import yaml

    sizes: dict[int, int] = {}
    order, stack = [], [root]
    while stack:                                   # depth-first, children before parents below
        node = stack.pop()
        if id(node) in sizes:
            continue
        sizes[id(node)] = 0
        order.append(node)
        if isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
        elif isinstance(node, yaml.MappingNode):
            stack.extend(x for pair in node.value for x in pair)
    for node in reversed(order):
        if isinstance(node, yaml.SequenceNode):
            children = node.value
        elif isinstance(node, yaml.MappingNode):
            children = [x for pair in node.value for x in pair]
        else:
            children = []
        sizes[id(node)] = min(1 + sum(sizes[id(c)] for c in children), MAX_CONFIG_NODES + 1)
    return sizes[id(root)]


def load_yaml_mapping(path: str | os.PathLike) -> dict:
    """The mapping a YAML config file holds (safe loading; an empty file is ``{}``).

    Refused, with the file named: a file over :data:`MAX_CONFIG_BYTES`, text that is not UTF-8,
    invalid YAML, a key given twice in one mapping, more than :data:`MAX_CONFIG_NODES` values once
    aliases are expanded, a top level that is not a mapping.

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        As above; the message names the file.
    """
    import yaml

    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"config file {path} is a folder")
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise FileNotFoundError(f"config file {path} does not exist") from None
    if size > MAX_CONFIG_BYTES:
        raise ValueError(f"{path}: {size:,} bytes, more than a config may hold ({MAX_CONFIG_BYTES:,})")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text file (not UTF-8 at byte {e.start})") from None
    loader = _yaml_loader()(text)
    try:
        node = loader.get_single_node()
        if node is not None and _expanded_nodes(node) > MAX_CONFIG_NODES:
            raise ValueError(f"{path}: with its aliases expanded the YAML holds more than {MAX_CONFIG_NODES:,} "
                             f"values; a config is a few hundred")
        d = loader.construct_document(node) if node is not None else None
    except yaml.YAMLError as e:
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        mark = getattr(e, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ValueError(f"{path}: not valid YAML: {problem}{at}") from None
    finally:
        loader.dispose()
    if d is None:
        return {}
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected a mapping of config fields, got {_shown(d)}")
    return d


def load_yaml(cls: type[C], path: str | os.PathLike) -> C:
    """Read a config of type ``cls`` from a YAML file (safe loading; errors name the file)."""
    return from_dict(cls, load_yaml_mapping(path), where=str(path))
