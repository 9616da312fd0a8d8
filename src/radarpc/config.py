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
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

__all__ = ["to_dict", "from_dict", "save_yaml", "load_yaml", "load_yaml_mapping"]

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
    kw = {k: _typed(v, hints.get(k, Any), f"{where}: {k}") for k, v in d.items()}
    try:
        return cls(**kw)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: {e}") from e


def _typed(v: Any, tp: Any, where: str) -> Any:
    if v is None:
        return None
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _typed(v, args[0], where) if len(args) == 1 else v
    if origin is tuple and isinstance(v, (list, tuple)):
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_typed(x, args[0], where) for x in v)
        if args and len(args) == len(v):
            return tuple(_typed(x, a, where) for x, a in zip(v, args))
        return tuple(v)
    if dataclasses.is_dataclass(tp) and isinstance(v, dict):
        fd = getattr(tp, "from_dict", None)
        return fd(v) if callable(fd) else from_dict(tp, v, where=where)
    return v


def save_yaml(cfg: Any, path: str | os.PathLike) -> Path:
    """Write ``to_dict(cfg)`` as YAML, atomically; returns the path."""
    import yaml

    from radarpc.io import atomic_write

    path = Path(path)
    with atomic_write(path, "w") as f:
        yaml.safe_dump(to_dict(cfg), f, sort_keys=False)
    return path


def load_yaml_mapping(path: str | os.PathLike) -> dict:
    """The mapping a YAML config file holds (safe loading; an empty file is ``{}``).

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Not valid YAML, or not a mapping at its top; the message names the file.
    """
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"config file {path} does not exist") from None
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not valid YAML ({e})") from None
    if d is None:
        return {}
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected a mapping of config fields, got {type(d).__name__}")
    return d


def load_yaml(cls: type[C], path: str | os.PathLike) -> C:
    """Read a config of type ``cls`` from a YAML file (safe loading; errors name the file)."""
    return from_dict(cls, load_yaml_mapping(path), where=str(path))
