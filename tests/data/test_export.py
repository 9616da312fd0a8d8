"""Per-frame writers (radarpc.data.export): .npy, .bin and PLY read back by independent parsers."""
from __future__ import annotations

import ast

import numpy as np
import pytest
import torch

from radarpc.data.export import (
    DEFAULT_COLUMNS,
    check_columns,
    columns_text,
    frame_file_name,
    frame_points,
    ply_header,
    write_frame,
    write_ply,
)
from radarpc.data.pointstore import FLOAT_COLUMNS, PointStore, PointStoreMetadata, PointStoreWriter
from radarpc.points import PointCloudBatch
from radarpc.sensors.radial import TINY


# ---- independent readers: the header parsed by hand, the data with np.frombuffer -----------------
def read_npy(path):
    raw = path.read_bytes()
    assert raw[:6] == b"\x93NUMPY"
    major = raw[6]
    hlen_size = 2 if major == 1 else 4
    hlen = int.from_bytes(raw[8:8 + hlen_size], "little")
    start = 8 + hlen_size
    header = ast.literal_eval(raw[start:start + hlen].decode("latin1"))
    assert header["descr"] == "<f4" and header["fortran_order"] is False
    return np.frombuffer(raw[start + hlen:], dtype="<f4").reshape(header["shape"])


def read_bin(path, n_cols):
    return np.frombuffer(path.read_bytes(), dtype="<f4").reshape(-1, n_cols)


def read_ply(path):
    """``(names, (N, C) float32)`` of a binary little-endian PLY of float vertex properties."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0" and lines[-1] == "end_header"
    n, names = None, []
    for ln in lines[2:-1]:
        words = ln.split()
        if words[0] == "element":
            assert words[1] == "vertex" and n is None
            n = int(words[2])
        elif words[0] == "property":
            assert words[1] == "float"
            names.append(words[2])
        else:
            assert words[0] == "comment"
    data = raw[end:]
    assert len(data) == n * len(names) * 4
    return names, np.frombuffer(data, dtype="<f4").reshape(n, len(names))


# ---- a tiny store ---------------------------------------------------------------------------------
def make_store(path, counts=(3, 0, 5, 1), frames=(10, 11, 12, 1234567), seed=0):
    g = torch.Generator().manual_seed(seed)
    n = int(sum(counts))
    f = {name: torch.randn(n, generator=g) * 10 for name in FLOAT_COLUMNS}
    f["range_bin"] = torch.randint(0, TINY.n_range, (n,), generator=g)
    f["doppler_bin"] = torch.randint(0, TINY.slot_width, (n,), generator=g)
    f["doppler_full"] = torch.randint(0, TINY.n_doppler, (n,), generator=g)
    f["is_neighbour"] = torch.rand(n, generator=g) > 0.5
    b = len(counts)
    batch = PointCloudBatch(offset=torch.tensor(np.cumsum(counts), dtype=torch.int64), tau=torch.rand(b, generator=g) + 1,
                            density=torch.rand(b, generator=g) * 0.1, sector=None, rd_patch=None, **f)
    meta = PointStoreMetadata(sensor=TINY, density_mode="fixed-tau", tau=10.0, target_density=None,
                              achieved_density=0.0, peak_density=0.0, enrich=(), window=(9, 9), guard=(3, 3),
                              source_root="/data/root", split="test")
    with PointStoreWriter(path, meta, row_group_frames=2) as w:
        w.write(batch, frames=list(frames), sequences=["A"] * b)
    return PointStore(path)


def expected(store, i, columns):
    """The store's frame ``i`` through PointStore's own tensors, as float32 ``(N, C)``."""
    cloud = store[i]
    return np.stack([getattr(cloud, c).numpy().astype(np.float32) for c in columns], axis=1).reshape(-1, len(columns))


@pytest.fixture
def store(tmp_path):
    return make_store(tmp_path / "pc.parquet")


def test_default_columns_put_position_and_intensity_first():
    assert DEFAULT_COLUMNS[:4] == ("x", "y", "z", "amplitude")
    assert check_columns(DEFAULT_COLUMNS) == DEFAULT_COLUMNS


@pytest.mark.parametrize("fmt", ["npy", "bin", "ply"])
@pytest.mark.parametrize("columns", [DEFAULT_COLUMNS, ("x", "y", "z", "snr", "range_bin", "is_neighbour")])
def test_frame_round_trip_exact(store, tmp_path, fmt, columns):
    for i in range(len(store)):
        pts = frame_points(store, i, columns)
        want = expected(store, i, columns)
        assert pts.dtype == np.float32 and pts.shape == (int(store.frame_table.n_points[i]), len(columns))
        path = write_frame(tmp_path / fmt / frame_file_name(store.frames[i], fmt), pts, fmt, columns)
        if fmt == "npy":
            got = read_npy(path)
            np.testing.assert_array_equal(np.load(path), want)
        elif fmt == "bin":
            got = read_bin(path, len(columns))
            assert path.stat().st_size == want.size * 4
        else:
            names, got = read_ply(path)
            assert names == list(columns)
        assert got.shape == want.shape
        np.testing.assert_array_equal(got, want)        # bit-exact float32


def test_empty_frame_gives_valid_files(store, tmp_path):
    assert int(store.frame_table.n_points[1]) == 0
    pts = frame_points(store, 1)
    assert pts.shape == (0, len(DEFAULT_COLUMNS))
    npy = write_frame(tmp_path / "e.npy", pts, "npy")
    assert read_npy(npy).shape == (0, 9) and np.load(npy).shape == (0, 9)
    b = write_frame(tmp_path / "e.bin", pts, "bin")
    assert b.stat().st_size == 0 and read_bin(b, 9).shape == (0, 9)
    names, got = read_ply(write_frame(tmp_path / "e.ply", pts, "ply", DEFAULT_COLUMNS))
    assert names == list(DEFAULT_COLUMNS) and got.shape == (0, 9)


def test_write_ply_from_dict_and_header_text(tmp_path):
    x = np.array([1.5, -2.25], dtype=np.float64)          # cast to float32 (exact values)
    path = write_ply(tmp_path / "a.ply", {"x": x, "y": [0, 1], "z": np.float32([3, 4]), "snr": [7, 8]},
                     comments=["hello"])
    raw = path.read_bytes()
    assert raw.startswith(b"ply\nformat binary_little_endian 1.0\ncomment hello\nelement vertex 2\n"
                          b"property float x\nproperty float y\nproperty float z\nproperty float snr\nend_header\n")
    names, got = read_ply(path)
    assert names == ["x", "y", "z", "snr"]
    np.testing.assert_array_equal(got, [[1.5, 0, 3, 7], [-2.25, 1, 4, 8]])
    assert not list(tmp_path.glob(".*.tmp"))                 # written atomically, nothing left beside


def test_file_names_follow_openpcdet():
    assert frame_file_name(7, "npy") == "000007.npy"
    assert frame_file_name(1234567, "bin") == "1234567.bin"


def test_bad_columns_and_formats_are_named():
    with pytest.raises(ValueError, match="unknown point column.*'speed'"):
        check_columns(["x", "y", "z", "speed"])
    with pytest.raises(ValueError, match="must start with x,y,z"):
        check_columns(["amplitude", "x", "y", "z"])
    with pytest.raises(ValueError, match="x given more than once"):
        check_columns(["x", "y", "z", "x"])
    with pytest.raises(ValueError, match="no columns"):
        check_columns([])
    with pytest.raises(ValueError, match="unknown export format 'pcd'; choose one of npy, bin, ply"):
        frame_file_name(1, "pcd")
    with pytest.raises(ValueError, match="differ in length"):
        write_ply("unused.ply", {"x": [1, 2], "y": [1]})
    with pytest.raises(ValueError, match="without spaces"):
        ply_header(["x y"], 1)


def test_columns_text_states_the_order():
    text = columns_text(DEFAULT_COLUMNS, "bin", "points/*.bin")
    rows = [ln.split()[:2] for ln in text.splitlines() if not ln.startswith("#")]
    assert rows == [[str(k), c] for k, c in enumerate(DEFAULT_COLUMNS)]
    assert 'reshape(-1, 9)' in text
