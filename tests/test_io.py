"""Atomic writes and validated array loading."""
import os
import stat

import numpy as np
import pytest

from radarpc.io import DataFileError, atomic_write, load_array, save_npy_atomic


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_write(target, "w") as f:
            f.write("half")
            raise RuntimeError("killed")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []
    with atomic_write(target, "w") as f:
        f.write("whole")
    assert target.read_text() == "whole"


def test_atomic_write_respects_umask(tmp_path):
    old = os.umask(0o022)
    try:
        with atomic_write(tmp_path / "a.bin") as f:
            f.write(b"x")
        plain = tmp_path / "plain.bin"
        plain.write_bytes(b"x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.bin").stat().st_mode) == stat.S_IMODE(plain.stat().st_mode) == 0o644


def test_load_array_validates(tmp_path):
    good = tmp_path / "a.npy"
    save_npy_atomic(good, np.ones((4, 3, 2), np.complex64))
    assert load_array(good, (4, 3, 2), complex_=True).dtype == np.complex64
    assert load_array(good, (None, 3, None)).shape == (4, 3, 2)
    with pytest.raises(DataFileError, match=r"a.npy: expected shape 4x3x5, found 4x3x2"):
        load_array(good, (4, 3, 5))
    with pytest.raises(DataFileError, match="expected a real array"):
        load_array(good, complex_=False)
    real = tmp_path / "r.npy"
    np.save(real, np.ones(3))
    with pytest.raises(DataFileError, match="r.npy: expected a complex array"):
        load_array(real, complex_=True)
    nan = tmp_path / "n.npy"
    np.save(nan, np.array([1.0, np.nan]))
    with pytest.raises(DataFileError, match="n.npy: contains NaN"):
        load_array(nan)
    trunc = tmp_path / "t.npy"
    trunc.write_bytes(good.read_bytes()[:100])
    with pytest.raises(DataFileError, match="t.npy: is truncated"):
        load_array(trunc)
    with pytest.raises(DataFileError, match="missing.npy: file is missing"):
        load_array(tmp_path / "missing.npy")
    obj = tmp_path / "o.npy"
    np.save(obj, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DataFileError, match="o.npy: holds Python objects and cannot be read without pickle"):
        load_array(obj)


def test_load_array_npz(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, cube=np.zeros((2, 2), np.complex64))
    assert load_array(p, (2, 2)).shape == (2, 2)
    with pytest.raises(DataFileError, match="named 'other'"):
        load_array(p, key="other")
