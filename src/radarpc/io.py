"""Atomic file writes and validated array loading, shared by every stage that touches disk.

Every writer in radarpc goes through :func:`atomic_write` (temp file in the same folder, then
``os.replace``), so an interrupted job never leaves a half-written file under its final name.
Every reader that opens an array goes through :func:`load_array`, which names the file and what
was expected when the file is missing, truncated, of the wrong shape or dtype, or holds NaN.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

__all__ = [
    "DataFileError",
    "atomic_write",
    "temp_file_beside",
    "save_npy_atomic",
    "save_npz_atomic",
    "load_array",
]


class DataFileError(ValueError):
    """A file on disk is missing, unreadable or does not hold what was expected.

    The message always names the file and the expectation.
    """

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        # rebuilt from (path, problem), so that it crosses to the parent of a worker process
        return (type(self), (self.path, self.problem))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def temp_file_beside(path: str | os.PathLike) -> Path:
    """Create an empty temporary file next to ``path`` (same folder, so ``os.replace`` is atomic).

    Unlike a bare ``mkstemp`` (mode 0600), the file gets the permissions a plain ``open()`` would
    give it under the current umask, so renamed outputs are readable as users expect.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())
    return Path(tmp)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator:
    """Open a temporary file next to ``path``; rename it onto ``path`` only on success.

    Parameters
    ----------
    path : path-like
        Final file name. Its folder is created if needed.
    mode : str
        ``"wb"`` or ``"w"``.

    Examples
    --------
    >>> with atomic_write("out.txt", "w") as f:  # doctest: +SKIP
    ...     f.write("hello")
    """
    tmp = temp_file_beside(path)
    try:
        with open(tmp, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def save_npy_atomic(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write ``array`` as a ``.npy`` file atomically (never pickled)."""
    with atomic_write(path, "wb") as f:
        np.save(f, np.asarray(array), allow_pickle=False)


def save_npz_atomic(path: str | os.PathLike, **arrays: np.ndarray) -> None:
    """Write arrays to a ``.npz`` file atomically (never pickled)."""
    with atomic_write(path, "wb") as f:
        np.savez(f, **{k: np.asarray(v) for k, v in arrays.items()})


def load_array(
    path: str | os.PathLike,
    shape: Sequence[int | None] | None = None,
    *,
    complex_: bool | None = None,
    key: str | None = None,
    allow_nan: bool = False,
) -> np.ndarray:
    """Load a ``.npy`` (or one key of a ``.npz``) array and validate it.

    Parameters
    ----------
    path : path-like
        File to read. Pickled object arrays are refused.
    shape : sequence of int or None, optional
        Expected shape; ``None`` entries match any length.
    complex_ : bool, optional
        If True the array must be complex, if False it must be real.
    key : str, optional
        For ``.npz`` files, the array to read (default: the only array, or ``arr_0``).
    allow_nan : bool
        If False (default), NaN or infinite values raise.

    Returns
    -------
    numpy.ndarray

    Raises
    ------
    DataFileError
        Naming ``path`` and what was expected.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "file is missing")
    try:
        obj = np.load(path, allow_pickle=False)
        if isinstance(obj, np.lib.npyio.NpzFile):
            with obj:
                names = list(obj.files)
                if key is None:
                    key = names[0] if len(names) == 1 else "arr_0"
                if key not in names:
                    raise DataFileError(path, f"expected an array named {key!r} in the .npz, found {names}")
                arr = obj[key]
        else:
            arr = obj
    except DataFileError:
        raise
    except ValueError as e:
        if "allow_pickle" in str(e):  # object arrays would need pickle
            raise DataFileError(path, "holds Python objects and cannot be read without pickle "
                                      "(expected a plain numeric array)") from e
        raise DataFileError(path, f"is truncated or corrupt ({e})") from e
    except (OSError, EOFError) as e:
        raise DataFileError(path, f"is truncated or not a NumPy file ({e})") from e
    if shape is not None:
        ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
        if not ok:
            want = "x".join("*" if s is None else str(s) for s in shape)
            raise DataFileError(path, f"expected shape {want}, found {'x'.join(map(str, arr.shape))}")
    if complex_ is True and not np.iscomplexobj(arr):
        raise DataFileError(path, f"expected a complex array, found dtype {arr.dtype}")
    if complex_ is False and np.iscomplexobj(arr):
        raise DataFileError(path, f"expected a real array, found dtype {arr.dtype}")
    if not allow_nan and arr.dtype.kind in "fc" and not np.isfinite(arr).all():
        raise DataFileError(path, "contains NaN or infinite values")
    return arr
