"""One run-folder mechanism for every long job: simulation, conversion, baselines, training.

A long job fills one output (a folder, or a file with a parts folder beside it) that it owns
from start to finish:

* **lock** — :class:`OutputLock` takes an exclusive lock on the output before anything is read or
  written; a second writer of the same output is refused at once with a message naming the
  holder (:class:`OutputBusyError`), so two jobs can never mix their results in one output;
* **key** — the settings that shape the output (a JSON-able dict) are stored in manifest files
  inside the folder (:class:`RunFolder`). A rerun with the same key resumes; a rerun with another
  key is refused (:class:`RunMismatchError`) unless the caller asks to overwrite, which removes
  the job's own outputs first;
* **atomic parts** — every file is written through :func:`radarpc.io.atomic_write` (a temp file
  beside it, then a rename), so a finished part is never half-written; :meth:`RunFolder.done`
  tells a resumed job which parts it can keep (optionally validating them);
* **leftovers** — temp files that a killed job left (``.NAME.*.tmp``) are removed when the next
  job takes the output;
* **older keys** — a key stored before a setting existed lacks it; the caller may pass a
  ``canonical`` function per manifest that reads the stored key through its config type (so the
  missing setting takes its default) before it is compared;
* **locators** — where another output the key refers to lives (a stage-1 run's folder) is
  recorded in the key but is not what identifies it (its own key and weights' digest do): dotted
  ``locators`` are left out of the comparison, and a resumed run records their current values, so
  a moved or copied folder resumes instead of being refused;
* **provenance** — :func:`source_commit` names the git commit of the radarpc source tree (read from
  ``.git`` without running git when it can), for records that are kept but not compared
  (``ignore_keys``).

Resuming is bit-identical by construction: every part is a deterministic function of the key and
the part's index, and a part either exists whole under its final name or not at all.

Examples
--------
>>> with RunFolder("out/sim", {"sim.json": {"seed": 0}}, what="simulation") as run:  # doctest: +SKIP
...     for i in range(10):
...         if not run.done(f"frame_{i}.npy"):
...             save_npy_atomic(run.path / f"frame_{i}.npy", make(i))
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

__all__ = [
    "OutputBusyError",
    "RunMismatchError",
    "OutputLock",
    "RunFolder",
    "check_writable",
    "remove_temp_files",
    "is_temp_name",
    "read_json",
    "locked_output",
    "git_commit",
    "source_commit",
]


class OutputBusyError(FileExistsError):
    """Another process is writing the same output."""


class RunMismatchError(FileExistsError):
    """The output holds a run with other settings."""


def read_json(path: str | os.PathLike) -> object | None:
    """The JSON content of ``path``, or None when it is missing or unreadable."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None


def _existing_ancestor(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_writable(path: str | os.PathLike, what: str = "output") -> None:
    """Raise a clear :class:`PermissionError` now if ``path`` cannot be created or written.

    Checks the path itself when it exists, else its nearest existing folder, so that a job fails
    before it starts work rather than with a traceback at its first write.
    """
    path = Path(path)
    target = path if path.exists() else _existing_ancestor(path.parent if path.suffix else path)
    if target.is_dir():
        ok = os.access(target, os.W_OK | os.X_OK)
    else:
        ok = os.access(target, os.W_OK) and os.access(target.parent, os.W_OK | os.X_OK)
    if not ok:
        raise PermissionError(f"cannot write the {what} {path}: {target} is not writable")


_TEMP_NAME = re.compile(r"\..+\.[A-Za-z0-9_]+\.tmp")


def is_temp_name(name: str) -> bool:
    """Whether ``name`` is that of an atomic write's temp file: ``.NAME.RANDOM.tmp``."""
    return _TEMP_NAME.fullmatch(name) is not None


def remove_temp_files(folder: str | os.PathLike, recursive: bool = True) -> int:
    """Delete the temp files of interrupted atomic writes (``.NAME.*.tmp``) under ``folder``.

    Call it only while holding the folder's :class:`OutputLock`: a live writer's temp file looks
    the same. Returns how many were removed.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    files = folder.rglob(".*.tmp") if recursive else folder.glob(".*.tmp")
    n = 0
    for p in files:
        if p.is_file() and is_temp_name(p.name):
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                n += 1
    return n


class OutputLock:
    """An exclusive, non-blocking lock on an output path, held by one writer at a time.

    The lock is a file ``.NAME.lock`` beside the output (so that it covers a file output and its
    parts folder alike, and is not part of a dataset folder's contents). It holds the holder's
    pid for the error message, is locked with ``flock`` (released by the OS if the holder dies,
    so a killed job never blocks its rerun) and is removed on release.

    Parameters
    ----------
    output : path-like
        The output to protect (a folder or a file).
    what : str
        What the output is, for messages ("point store", "dataset root", ...).

    Raises
    ------
    OutputBusyError
        On :meth:`acquire`, when another process holds the lock.
    """

    def __init__(self, output: str | os.PathLike, what: str = "output") -> None:
        self.output = Path(output)
        self.what = what
        # absolute and normalised: "." and "sub/.." name the folder itself, whose lock is beside it
        absolute = Path(os.path.abspath(self.output))
        self.path = absolute.parent / f".{absolute.name or 'root'}.lock"
        self._fd: int | None = None

    def acquire(self) -> "OutputLock":
        if self._fd is not None:
            raise RuntimeError(f"{self.path} is already held by this object")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            except PermissionError:
                raise PermissionError(f"cannot write the {self.what} {self.output}: {self.path.parent} is not "
                                      f"writable (the output's lock file goes there)") from None
            try:
                _lock_fd(fd)
            except BlockingIOError:
                holder = ""
                with contextlib.suppress(OSError, ValueError):
                    os.lseek(fd, 0, os.SEEK_SET)
                    holder = f" (pid {int(os.read(fd, 32).decode().strip())})"
                os.close(fd)
                raise OutputBusyError(
                    f"another radarpc process{holder} is writing the {self.what} {self.output}; wait for it "
                    f"to finish or choose another output") from None
            # The previous holder may have removed the file between our open and our lock: then we
            # hold a lock on an unlinked inode, which protects nothing. Retry on the current file.
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        # before unlocking: a waiter then retries on a fresh file (Windows cannot remove an open
        # file: the lock file then stays, which is harmless)
        with contextlib.suppress(FileNotFoundError, PermissionError):
            os.unlink(self.path)
        os.close(self._fd)
        self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _lock_fd(fd: int) -> None:
    try:
        import fcntl
    except ImportError:    # pragma: no cover - Windows
        import msvcrt
        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        except OSError as e:
            raise BlockingIOError(str(e)) from e
        return
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)


def _differing(want: dict, have: dict, prefix: str = "") -> list[str]:
    """Dotted paths of the keys whose values differ, descending into dicts present on both sides."""
    out = []
    for k in sorted(set(want) | set(have), key=str):
        a, b = want.get(k), have.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differing(a, b, f"{prefix}{k}.")
        elif a != b:
            out.append(f"{prefix}{k}")
    return out


def _canonical(d: object) -> object:
    return json.loads(json.dumps(d))


_MISSING = object()


def _lookup(d: object, path: tuple[str, ...]) -> object:
    for k in path:
        if not isinstance(d, dict) or k not in d:
            return _MISSING
        d = d[k]
    return d


def _assign(d: dict, path: tuple[str, ...], value: object) -> None:
    """Set ``d[path]`` where its parent dict exists (a locator of an absent reference stays absent)."""
    parent = _lookup(d, path[:-1])
    if isinstance(parent, dict):
        parent[path[-1]] = value


def _without(paths: Sequence[tuple[str, ...]], d: dict) -> dict:
    """``d`` without the dotted ``paths`` (copied where it changes, never modified)."""
    for path in paths:
        if _lookup(d, path) is _MISSING:
            continue
        d = dict(d)
        node = d
        for k in path[:-1]:
            node[k] = dict(node[k])
            node = node[k]
        del node[path[-1]]
    return d


class RunFolder:
    """A folder that one job owns, fills part by part, and resumes after an interruption.

    Parameters
    ----------
    path : path-like
        The folder (created on :meth:`start`).
    manifests : mapping of str to dict
        Files in the folder that record the run's key, ``{file name: JSON-able dict}``; written
        at start, compared on rerun. A stored manifest may hold more keys than the key (records
        the job adds as it goes, with :meth:`write_manifest`): only the key's keys are compared. Usually one (``{"run.json": config.to_dict()}``); a dataset
        layout with its own description files passes those (e.g. ``sensor.json``).
    what : str
        What the folder is, for messages.
    ignore_keys : sequence of str
        Top-level manifest keys that are recorded but do not identify the run (a version string).
    locators : sequence of str
        Dotted keys (``"ae.path"``) that say where something the run refers to lives, not what it
        is: not compared, and brought up to date in the stored manifests when a run resumes (the
        keys beside them, e.g. the referred run's key and digest, identify it).
    canonical : mapping of str to callable, optional
        ``{file name: function}``: the function reads that manifest as stored (a dict, without its
        ``ignore_keys`` and ``locators``) and returns it as this run would write it, e.g. through
        the config type (``to_dict(from_dict(Config, d))``) so that a setting added since the run
        started takes its default instead of reading as missing. It is applied before comparing; a
        ``ValueError``, ``KeyError`` or ``TypeError`` it raises makes the stored manifest a
        difference (the folder then holds another run).
    indent : int, optional
        JSON indentation of the manifests as written.
    owned : sequence of str, optional
        The entries of the folder that the job writes (files or subfolders); a name with ``*`` is
        a glob pattern (``"eval_*"``: outputs made from the job's, stale once it is replaced).
        ``overwrite`` deletes these and the manifests; None means the whole folder's content is
        the job's.
    lock_output : path-like, optional
        The output to lock, when it is not the folder itself (a store file whose parts folder
        this is). Default: the folder.
    lock : OutputLock, optional
        A lock the caller already holds (and releases) for this output, instead of ``lock_output``.

    Attributes
    ----------
    resumed : bool
        After :meth:`start`: the folder held a run with the same key, whose parts are kept.
    """

    def __init__(self, path: str | os.PathLike, manifests: Mapping[str, Mapping], *, what: str = "run folder",
                 ignore_keys: Sequence[str] = (), locators: Sequence[str] = (), indent: int | None = 1,
                 owned: Sequence[str] | None = None,
                 lock_output: str | os.PathLike | None = None, lock: OutputLock | None = None,
                 canonical: Mapping[str, Callable[[dict], dict]] | None = None) -> None:
        if not manifests:
            raise ValueError("a run folder needs at least one manifest file")
        self.path = Path(path)
        self.manifests = {str(k): _canonical(dict(v)) for k, v in manifests.items()}
        self.what = what
        self.ignore_keys = tuple(ignore_keys)
        self.locators = tuple(tuple(k.split(".")) for k in locators)
        self.canonical = dict(canonical or {})
        unknown = sorted(set(self.canonical) - set(self.manifests))
        if unknown:
            raise ValueError(f"canonical functions for {unknown}, which are not manifests of {self.path} "
                             f"({sorted(self.manifests)})")
        self.indent = indent
        self.owned = None if owned is None else tuple(owned)
        self.lock = lock if lock is not None else OutputLock(self.path if lock_output is None else lock_output, what)
        self._own_lock = lock is None
        self.resumed = False
        self._started = False

    # ---- state ----------------------------------------------------------------------------------
    def _key(self, d: object) -> object:
        if not isinstance(d, dict):
            return d
        return _without(self.locators, {k: v for k, v in d.items() if k not in self.ignore_keys})

    def stored(self) -> dict[str, object | None]:
        """The manifests as found in the folder (None for a missing or unreadable one)."""
        return {name: read_json(self.path / name) for name in self.manifests}

    def _stored_key(self, name: str, stored: object) -> object:
        """The key part of stored manifest ``name`` (a dict), read through its ``canonical``
        function; a :class:`ValueError` naming the problem when that function cannot read it."""
        have = self._key(stored)
        fn = self.canonical.get(name)
        if fn is None or not isinstance(have, dict):
            return have
        try:
            read = fn(dict(have))
        except (ValueError, KeyError, TypeError) as e:
            raise ValueError(f"{name} (not readable as this run's key: {e})") from e
        if not isinstance(read, dict):
            raise TypeError(f"the canonical function of {name} returned {type(read).__name__}, not a dict")
        return self._key(_canonical(read))

    def differences(self) -> list[str]:
        """Keys (``file:key``) whose stored value differs from this run's; empty when they match.

        A manifest missing while the others are present and match is not a difference: the run
        that wrote them was killed between two manifest writes. Without any readable manifest
        the folder is not this run's.
        """
        out, missing = [], []
        for name, stored in self.stored().items():
            want = self._key(self.manifests[name])
            if not isinstance(stored, dict):
                missing.append(f"{name} (missing or unreadable)")
                continue
            try:
                have = self._stored_key(name, stored)
            except ValueError as e:
                out.append(str(e))
                continue
            # the stored manifest may also hold records of the run (progress, calibrated values):
            # only this run's key is compared
            out += [f"{name}:{k}" for k in _differing(want, {k: have.get(k) for k in want})]
        return out + missing if out or len(missing) == len(self.manifests) else out

    def changed_keys(self) -> set[str]:
        """The top-level key names whose stored value differs from this run's (in any manifest);
        ``{"*"}`` when no manifest is readable."""
        stored = self.stored()
        if not any(isinstance(v, dict) for v in stored.values()):
            return {"*"}
        out: set[str] = set()
        for name, have in stored.items():
            if isinstance(have, dict):
                want = self._key(self.manifests[name])
                try:
                    have = self._stored_key(name, have)
                except ValueError:
                    out |= set(want)
                    continue
                out |= {k for k in want if want[k] != have.get(k)}
        return out

    def is_empty(self) -> bool:
        """No entry in the folder (temp files of interrupted writes aside)."""
        if not self.path.exists():
            return True
        return all(is_temp_name(p.name) and p.is_file() for p in self.path.iterdir())

    # ---- lifecycle ------------------------------------------------------------------------------
    def start(self, *, overwrite: bool = False, resume: bool = True, write_manifests: bool = True) -> "RunFolder":
        """Lock the output, check the folder against this run's key, and write the manifests.

        Parameters
        ----------
        overwrite : bool
            Replace a folder that holds another run (or, with ``resume=False``, this one): its
            owned entries are deleted first.
        resume : bool
            Keep the parts of an earlier run with the same key. False starts over (deleting the
            owned entries of a matching run; a non-matching one still needs ``overwrite``).
        write_manifests : bool
            Write the manifests of a new run now. False when the caller completes them first
            (e.g. with a calibrated value) and writes them with :meth:`write_manifest`. A resumed
            run keeps the manifests it finds (they match, ``ignore_keys`` and ``locators`` aside), with
            the ``locators`` updated to this run's.

        Raises
        ------
        NotADirectoryError
            ``path`` is a file.
        RunMismatchError
            The folder is not empty and does not hold a run with this key, without ``overwrite``.
        OutputBusyError
            Another process writes the same output.
        PermissionError
            The folder cannot be written.
        """
        if self.path.exists() and not self.path.is_dir():
            raise NotADirectoryError(f"the {self.what} {self.path} exists and is not a folder")
        check_writable(self.path, self.what)
        if self._own_lock:
            self.lock.acquire()
        elif not self.lock.held:
            raise RuntimeError(f"the lock of {self.lock.output} must be held before starting {self.path}")
        try:
            self._start(overwrite, resume, write_manifests)
        except BaseException:
            self.close()
            raise
        return self

    def _start(self, overwrite: bool, resume: bool, write_manifests: bool) -> None:
        self.resumed = False
        self._started = True
        remove_temp_files(self.path)            # a killed run's leftovers: ours, since we hold the lock
        if not self.is_empty():
            diff = self.differences()
            if diff and not overwrite:
                raise RunMismatchError(
                    f"{self.path} is not empty and does not hold a run with these settings (differs in "
                    f"{', '.join(diff[:6])}{' ...' if len(diff) > 6 else ''}); pass --overwrite "
                    f"(overwrite=True) to replace it, or choose another output")
            if diff or not resume:
                self.clear()
            else:
                self.resumed = True
                self._update_locators()
        self.path.mkdir(parents=True, exist_ok=True)
        if write_manifests:
            for name, content in self.manifests.items():
                # a resumed run keeps what it finds, and completes what a kill left unwritten
                if not self.resumed or not isinstance(read_json(self.path / name), dict):
                    self.write_manifest(name, content)

    def _update_locators(self) -> None:
        """Record this run's locator values in the stored manifests (the rest as stored)."""
        for name, stored in self.stored().items():
            if not isinstance(stored, dict):
                continue
            updated = _canonical(stored)
            for path in self.locators:
                have = _lookup(self.manifests[name], path)
                if have is not _MISSING:
                    _assign(updated, path, have)
            if updated != stored:
                from radarpc.io import atomic_write

                with atomic_write(self.path / name, "w") as f:
                    json.dump(updated, f, indent=self.indent)

    def write_manifest(self, name: str, content: Mapping) -> None:
        """Write manifest ``name`` atomically (its key part must be this run's)."""
        from radarpc.io import atomic_write

        if name not in self.manifests:
            raise ValueError(f"{name} is not a manifest of {self.path}")
        want = {k: v for k, v in self.manifests[name].items() if k not in self.ignore_keys}
        have = _canonical(dict(content))
        if {k: have.get(k) for k in want} != want:
            raise ValueError(f"manifest {name} of {self.path} would not match this run's key")
        with atomic_write(self.path / name, "w") as f:
            json.dump(dict(content), f, indent=self.indent)

    def clear(self) -> None:
        """Delete the job's entries of the folder (the owned ones and the manifests)."""
        if not self.path.is_dir():
            return
        if self.owned is None:
            owned = {p.name for p in self.path.iterdir()}
        else:
            owned = {name for name in self.owned if "*" not in name}
            owned |= {p.name for name in self.owned if "*" in name for p in self.path.glob(name)}
        # The manifests go last: a kill half-way leaves a folder that still says whose it is.
        names = sorted(owned - set(self.manifests)) + sorted(self.manifests)
        for name in names:
            p = self.path / name
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()
        remove_temp_files(self.path)

    def done(self, part: str | os.PathLike, check: Callable[[Path], bool] | None = None) -> bool:
        """Whether the file ``part`` (a path, e.g. ``run.path / "part-00001.parquet"``) is finished and
        can be kept.

        False when the run does not resume, the file is missing, or ``check(path)`` is False (a
        file damaged after its atomic write is then redone).
        """
        p = Path(part)
        if not self.resumed or not p.is_file():
            return False
        return True if check is None else bool(check(p))

    def close(self) -> None:
        """Release the lock if this folder took it (the folder stays)."""
        if self._own_lock:
            self.lock.release()

    def __enter__(self) -> "RunFolder":
        return self if self._started else self.start()

    def __exit__(self, *exc) -> None:
        self.close()


_HASH = re.compile(r"[0-9a-f]{40}|[0-9a-f]{64}")       # SHA-1 or SHA-256 object names


def _git_dirs(tree: Path) -> tuple[Path, Path] | None:
    """``(git dir, common dir)`` of the work tree ``tree``: ``.git`` itself, or for a linked work
    tree (``.git`` a file ``gitdir: PATH``) that folder and the main repository's (``commondir``)."""
    dot = tree / ".git"
    if dot.is_dir():
        return dot, dot
    if not dot.is_file():
        return None
    text = dot.read_text(encoding="utf-8").strip()
    if not text.startswith("gitdir:"):
        return None
    gitdir = Path(text[len("gitdir:"):].strip())
    gitdir = gitdir if gitdir.is_absolute() else tree / gitdir
    common = gitdir
    if (gitdir / "commondir").is_file():
        c = Path((gitdir / "commondir").read_text(encoding="utf-8").strip())
        common = c if c.is_absolute() else gitdir / c
    return gitdir, common


def _read_ref(gitdir: Path, common: Path, ref: str) -> str | None:
    """The object name a ref (``refs/heads/main``) holds: its loose file (in the work tree's git
    dir, then the common one) or its line of ``packed-refs``; None when neither has it."""
    for d in (gitdir, common):
        p = d / ref
        if p.is_file():
            return p.read_text(encoding="utf-8").strip()
    for d in dict.fromkeys((gitdir, common)):
        packed = d / "packed-refs"
        if packed.is_file():
            for line in packed.read_text(encoding="utf-8").splitlines():
                parts = line.split()
                if len(parts) == 2 and parts[1] == ref and not line.startswith(("#", "^")):
                    return parts[0]
    return None


def git_commit(tree: str | os.PathLike, timeout: float = 5.0) -> str | None:
    """The commit checked out (``HEAD``) in the git work tree ``tree``, or None.

    Read from the files (``.git/HEAD``, the ref it names as a loose file or in ``packed-refs``,
    linked work trees included) without running git; only when they do not give a commit (a
    repository in another ref format) ``git rev-parse --verify HEAD`` is asked, with a
    ``timeout`` in seconds. None when ``tree`` is not a git work tree, HEAD names no commit yet,
    or git is missing, slow or fails: a record of the commit never stops a job. Changes not yet
    committed are not detected.
    """
    tree = Path(tree)
    try:
        dirs = _git_dirs(tree)
        if dirs is None:
            return None
        head: str | None = (dirs[0] / "HEAD").read_text(encoding="utf-8").strip()
        for _ in range(5):                       # a symbolic ref may name another one
            if head is None or not head.startswith("ref:"):
                break
            head = _read_ref(*dirs, head[len("ref:"):].strip())
        if head is not None and _HASH.fullmatch(head):
            return head
    except (OSError, UnicodeDecodeError):
        pass
    try:
        done = subprocess.run(["git", "-C", str(tree), "rev-parse", "--verify", "--quiet", "HEAD"],
                              capture_output=True, text=True, timeout=timeout, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    name = done.stdout.strip()
    return name if done.returncode == 0 and _HASH.fullmatch(name) else None


def source_commit() -> str | None:
    """The git commit of the radarpc source tree when radarpc runs from a git checkout (the
    ``src`` layout: ``ROOT/src/radarpc`` with ``ROOT/.git``), else None (an installed package)."""
    package = Path(__file__).resolve().parent
    root = package.parent.parent if package.parent.name == "src" else package.parent
    return git_commit(root) if (root / ".git").exists() else None


@contextlib.contextmanager
def locked_output(path: str | os.PathLike, what: str = "output") -> Iterator[OutputLock]:
    """``with locked_output(p): ...``: check that ``p`` is writable, then hold its :class:`OutputLock`."""
    check_writable(path, what)
    with OutputLock(path, what) as lock:
        yield lock
