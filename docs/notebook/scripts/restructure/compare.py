#!/usr/bin/env python
"""Compare two output folders of run_commands.sh (e.g. the old tree's and the new tree's).

    compare.py A B [--ignore-key software --ignore-key seconds ...] [--ignore-file 'logs/*.err' ...]

* file lists: files only in A, only in B;
* Parquet: the Arrow schema, the rows (every column, exactly) and the file's key-value metadata
  (JSON values parsed and normalised as JSON files; ARROW:schema is the schema, compared as such);
* JSON: by content, with every key named by --ignore-key dropped at any depth;
* CSV: by rows, with the columns named by --ignore-column dropped (header row names them);
* safetensors: every tensor exactly (dtype, shape, bits) and the header metadata (JSON values
  parsed, normalised as JSON files);
* npz: every array exactly (name, dtype, shape, bytes; the zip members' timestamps are ignored);
* everything else byte for byte.

In every text (JSON strings, metadata, any file that decodes as UTF-8) the folder's own absolute
path (as given and resolved) is replaced by <OUT> before comparing, since stores and logs record
their source root; each --mask REGEX is replaced by <MASKED> there too (e.g. a timing).
A byte-identical pair is always equal. Prints each differing file with the reason (for JSON, the differing key paths)
and exits 1 if anything differs, else 0.
"""
from __future__ import annotations

import argparse
import csv
import fnmatch
import io
import json
import os
import struct
import sys
import zipfile
from pathlib import Path

import numpy as np


def _roots(folder: Path) -> list[str]:
    """The spellings of ``folder``'s absolute path, longest first."""
    out = {str(folder.absolute()), str(folder.resolve()), os.path.realpath(folder)}
    return sorted(out, key=len, reverse=True)


MASKS: list = []          # compiled --mask patterns


def _norm_text(text: str, roots: list[str]) -> str:
    for r in roots:
        text = text.replace(r, "<OUT>")
    for m in MASKS:
        text = m.sub("<MASKED>", text)
    return text


def _norm_json(obj, roots: list[str], ignore: set[str]):
    """``obj`` with ignored keys dropped (any depth) and the folder path replaced in strings."""
    if isinstance(obj, dict):
        return {k: _norm_json(v, roots, ignore) for k, v in obj.items() if k not in ignore}
    if isinstance(obj, list):
        return [_norm_json(v, roots, ignore) for v in obj]
    if isinstance(obj, str):
        return _norm_text(obj, roots)
    return obj


def _json_diff(a, b, path: str = "") -> list[str]:
    """Key paths where two normalised JSON values differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b), key=str):
            p = f"{path}.{k}" if path else str(k)
            if k not in a or k not in b:
                out.append(f"{p} (only in {'B' if k not in a else 'A'})")
            else:
                out += _json_diff(a[k], b[k], p)
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path} (length {len(a)} vs {len(b)})"]
        out = []
        for i, (u, v) in enumerate(zip(a, b)):
            out += _json_diff(u, v, f"{path}[{i}]")
        return out
    if a != b and not (isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b)):
        return [f"{path} ({_short(a)} vs {_short(b)})"]
    return []


def _short(v, n: int = 60) -> str:
    s = json.dumps(v) if not isinstance(v, str) else repr(v)
    return s if len(s) <= n else s[: n - 3] + "..."


def _maybe_json(text: str):
    try:
        return json.loads(text)
    except (ValueError, TypeError):
        return text


def _kv_diff(ma: dict, mb: dict, ra, rb, ignore) -> list[str]:
    """Differences of two string -> string metadata maps (JSON values parsed)."""
    na = {k: _norm_json(_maybe_json(v), ra, ignore) for k, v in ma.items() if k not in ignore}
    nb = {k: _norm_json(_maybe_json(v), rb, ignore) for k, v in mb.items() if k not in ignore}
    return _json_diff(na, nb)


def cmp_json(a: Path, b: Path, ra, rb, ignore) -> list[str]:
    ja = _norm_json(json.loads(a.read_text()), ra, ignore)
    jb = _norm_json(json.loads(b.read_text()), rb, ignore)
    return _json_diff(ja, jb)


def cmp_parquet(a: Path, b: Path, ra, rb, ignore) -> list[str]:
    import pyarrow.parquet as pq

    fa, fb = pq.ParquetFile(a), pq.ParquetFile(b)
    out = []
    ta, tb = fa.read(), fb.read()
    if not ta.schema.remove_metadata().equals(tb.schema.remove_metadata()):
        out.append("schema differs")
    elif ta.num_rows != tb.num_rows:
        out.append(f"rows {ta.num_rows} vs {tb.num_rows}")
    else:
        cols = [c for c in ta.column_names if not ta.column(c).equals(tb.column(c))]
        if cols:
            out.append(f"rows differ in columns {cols}")
    kv = lambda f: {k.decode(): v.decode("utf-8", "replace") for k, v in (f.metadata.metadata or {}).items()
                    if k != b"ARROW:schema"}
    out += [f"metadata {d}" for d in _kv_diff(kv(fa), kv(fb), ra, rb, ignore)]
    return out


def _safetensors(path: Path):
    """``(metadata, {name: (dtype, shape, bytes)})`` read from the file itself (any dtype)."""
    raw = path.read_bytes()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8:8 + n])
    meta = header.pop("__metadata__", {}) or {}
    body = raw[8 + n:]
    tensors = {k: (v["dtype"], tuple(v["shape"]), body[v["data_offsets"][0]:v["data_offsets"][1]])
               for k, v in header.items()}
    return meta, tensors


def cmp_safetensors(a: Path, b: Path, ra, rb, ignore) -> list[str]:
    ma, ta = _safetensors(a)
    mb, tb = _safetensors(b)
    out = []
    if set(ta) != set(tb):
        out.append(f"tensor names differ: only in A {sorted(set(ta) - set(tb))[:5]}, "
                   f"only in B {sorted(set(tb) - set(ta))[:5]}")
    diff = [k for k in sorted(set(ta) & set(tb)) if ta[k] != tb[k]]
    if diff:
        out.append(f"{len(diff)} tensors differ, e.g. {diff[:5]}")
    out += [f"metadata {d}" for d in _kv_diff(ma, mb, ra, rb, ignore)]
    return out


def _npz(path: Path) -> dict:
    out = {}
    with zipfile.ZipFile(path) as z:
        for name in z.namelist():
            arr = np.load(io.BytesIO(z.read(name)), allow_pickle=False)
            out[name] = (arr.dtype.str, arr.shape, arr.tobytes())
    return out


def cmp_npz(a: Path, b: Path, ra, rb, ignore) -> list[str]:
    na, nb = _npz(a), _npz(b)
    if set(na) != set(nb):
        return [f"array names differ: {sorted(na)} vs {sorted(nb)}"]
    diff = [k for k in sorted(na) if na[k] != nb[k]]
    return [f"arrays differ: {diff[:5]}"] if diff else []


def cmp_bytes(a: Path, b: Path, ra, rb, ignore) -> list[str]:
    da, db = a.read_bytes(), b.read_bytes()
    if da == db:
        return []
    try:
        ta, tb = da.decode("utf-8"), db.decode("utf-8")
    except UnicodeDecodeError:
        return [f"bytes differ ({len(da)} vs {len(db)} bytes)"]
    ta, tb = _norm_text(ta, ra), _norm_text(tb, rb)
    if ta == tb:
        return []
    la, lb = ta.splitlines(), tb.splitlines()
    first = next((i for i, (u, v) in enumerate(zip(la, lb)) if u != v), min(len(la), len(lb)))
    show = lambda ls: _short(ls[first] if first < len(ls) else "<end>", 100)
    return [f"text differs from line {first + 1}: {show(la)} vs {show(lb)}"]


IGNORED_COLUMNS: set[str] = set()   # --ignore-column names


def cmp_csv(a: Path, b: Path, ra, rb, ignore) -> list[str]:
    if a.read_bytes() == b.read_bytes():
        return []

    def rows(path, roots):
        with open(path, newline="", encoding="utf-8") as f:
            table = list(csv.reader(f))
        keep = [i for i, h in enumerate(table[0] if table else []) if h not in IGNORED_COLUMNS]
        return [[_norm_text(r[i], roots) if i < len(r) else None for i in keep] for r in table]

    xa, xb = rows(a, ra), rows(b, rb)
    if xa == xb:
        return []
    if len(xa) != len(xb):
        return [f"rows {len(xa)} vs {len(xb)}"]
    first = next(i for i, (u, v) in enumerate(zip(xa, xb)) if u != v)
    cols = [xa[0][j] for j in range(len(xa[first])) if xa[first][j] != xb[first][j]] if first else ["header"]
    return [f"rows differ from row {first + 1}, columns {cols[:8]}"]


COMPARERS = {".parquet": cmp_parquet, ".json": cmp_json, ".safetensors": cmp_safetensors, ".npz": cmp_npz,
             ".csv": cmp_csv}


def compare(a: Path, b: Path, ignore_keys: set[str], ignore_files: list[str]) -> dict[str, list[str]]:
    """``{relative path: [reasons]}`` of every file that differs (or exists on one side only)."""
    ra, rb = _roots(a), _roots(b)
    files = lambda root: {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}
    fa, fb = files(a), files(b)
    skip = lambda rel: any(fnmatch.fnmatch(rel, g) for g in ignore_files)
    out: dict[str, list[str]] = {}
    for rel in sorted(fa | fb):
        if skip(rel):
            continue
        if rel not in fb:
            out[rel] = ["only in A"]
        elif rel not in fa:
            out[rel] = ["only in B"]
        else:
            cmp = COMPARERS.get(Path(rel).suffix.lower(), cmp_bytes)
            try:
                why = cmp(a / rel, b / rel, ra, rb, ignore_keys)
            except Exception as e:                      # an unreadable file is a difference, not a crash
                why = [f"cannot compare: {type(e).__name__}: {e}"]
            if why:
                out[rel] = why
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("--ignore-key", action="append", default=[], metavar="KEY",
                   help="JSON / metadata key to ignore at any depth (repeatable), e.g. software, seconds")
    p.add_argument("--ignore-file", action="append", default=[], metavar="GLOB",
                   help="relative paths to leave out (fnmatch, repeatable), e.g. 'logs/*.err'")
    p.add_argument("--ignore-column", action="append", default=[], metavar="NAME",
                   help="CSV column to ignore (repeatable), e.g. train_time_s")
    p.add_argument("--mask", action="append", default=[], metavar="REGEX",
                   help="replace matches by <MASKED> in every text before comparing (repeatable), "
                        "e.g. '[0-9.]+ frames/s'")
    p.add_argument("--max-reasons", type=int, default=8, help="reasons printed per file (default 8)")
    args = p.parse_args(argv)
    import re

    MASKS[:] = [re.compile(m) for m in args.mask]
    IGNORED_COLUMNS.update(args.ignore_column)
    diff = compare(args.a, args.b, set(args.ignore_key), args.ignore_file)
    n_a = sum(1 for q in args.a.rglob("*") if q.is_file())
    n_b = sum(1 for q in args.b.rglob("*") if q.is_file())
    for rel, why in diff.items():
        print(f"DIFF {rel}")
        for w in why[: args.max_reasons]:
            print(f"    {w}")
        if len(why) > args.max_reasons:
            print(f"    ... {len(why) - args.max_reasons} more")
    print(f"{len(diff)} differing files ({n_a} files in {args.a}, {n_b} in {args.b})")
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
