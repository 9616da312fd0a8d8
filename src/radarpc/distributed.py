"""Where this process stands in a multi-process job: torchrun ranks, their devices, local workers.

* :func:`dist_env` reads ``RANK`` / ``WORLD_SIZE`` / ``LOCAL_RANK`` as ``torchrun`` sets them
  (rank 0 of 1 outside torchrun); :func:`rank_device` gives rank ``r`` its ``cuda:LOCAL_RANK``
  when CUDA is available, else the CPU.
* :func:`barrier` synchronises ranks: a process-group barrier when one is initialised, else by
  waiting for the files the other ranks write (on a shared file system), with a timeout whose
  error names the missing files and their owners.
* :func:`run_workers` spreads items over local spawned processes and relays their progress and
  errors to the parent; a worker stops by itself when its parent dies.

NCCL and CUDA are never assumed: the same code runs on CPU-only machines.
"""
from __future__ import annotations

import dataclasses
import os
import queue as _queue
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from radarpc.machine import check_device

__all__ = ["DEFAULT_WAIT_S", "DistEnv", "dist_env", "rank_device", "barrier", "wait_for_files",
           "WorkerJob", "run_workers", "parent_alive"]

DEFAULT_WAIT_S = 2 * 3600.0
"""Default time torchrun ranks wait for each other's files (without a process group)."""


@dataclass(frozen=True)
class DistEnv:
    """Position of this process in a ``torchrun`` job (``world_size == 1`` outside torchrun)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0


def dist_env() -> DistEnv:
    """Read ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` as set by ``torchrun``."""
    def get(name: str, default: int) -> int:
        v = os.environ.get(name)
        if v is None or v == "":
            return default
        try:
            return int(v)
        except ValueError:
            raise ValueError(f"environment variable {name}={v!r} is not an integer") from None
    env = DistEnv(rank=get("RANK", 0), world_size=get("WORLD_SIZE", 1), local_rank=get("LOCAL_RANK", 0))
    if env.world_size < 1 or not 0 <= env.rank < env.world_size:
        raise ValueError(f"RANK={env.rank} must be in [0, WORLD_SIZE={env.world_size})")
    return env


def rank_device(device: torch.device | str | None, env: DistEnv) -> torch.device:
    """``device`` (checked) when given, else ``cuda:LOCAL_RANK`` when CUDA is available, else CPU."""
    if device is not None:
        return check_device(device)
    if torch.cuda.is_available():
        return torch.device(f"cuda:{env.local_rank}")
    return torch.device("cpu")


def wait_for_files(files: Sequence[Path], owners: Sequence[str], timeout_s: float, poll_s: float = 1.0,
                   ready: Callable[[Path], bool] | None = None) -> None:
    """Wait until every file exists (and ``ready(file)`` holds, when given); on timeout a
    ``TimeoutError`` names the missing ones and who writes them."""
    t0 = time.monotonic()
    while True:
        missing = [(f, o) for f, o in zip(files, owners) if not f.is_file() or (ready is not None and not ready(f))]
        if not missing:
            return
        if time.monotonic() - t0 > timeout_s:
            shown = "; ".join(f"{f} (from {o})" for f, o in missing[:8])
            more = f"; ... {len(missing) - 8} more" if len(missing) > 8 else ""
            raise TimeoutError(f"gave up after {timeout_s:.0f} s waiting for {len(missing)} of {len(files)} "
                               f"file(s): {shown}{more}. Is that rank still running (or did it fail)? "
                               f"Raise wait_timeout_s (CLI --wait-timeout) for slow ranks")
        time.sleep(poll_s)


def barrier(env: DistEnv, files: Sequence[Path], owners: Sequence[str], timeout_s: float,
            ready: Callable[[Path], bool] | None = None) -> None:
    """Synchronise torchrun ranks: a process-group barrier if one is initialised, else wait for
    ``files`` (written by ``owners``) to exist and be ``ready``. Nothing to wait for outside torchrun."""
    if env.world_size == 1:
        return
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.barrier()
        return
    if files:
        wait_for_files(files, owners, timeout_s, ready=ready)


# ---- local workers ------------------------------------------------------------------------------
@dataclass(frozen=True)
class WorkerJob:
    """What a spawned worker runs: ``run(payload, items, report)`` (a picklable top-level function),
    with ``report(item, n)`` called after each finished item."""

    run: Callable[[Any, tuple, Callable[[Any, int], None]], None]
    payload: Any
    items: tuple = ()
    threads: int | None = None           # torch threads of the worker (None: leave as is)
    parent_pid: int | None = None        # the worker stops if this process is gone


def parent_alive(job: WorkerJob) -> bool:
    """False when ``job`` runs in a worker whose parent has died (it should stop: the unfinished
    item is dropped, and a re-run redoes it)."""
    return job.parent_pid is None or os.getppid() == job.parent_pid


def _worker_main(job: WorkerJob, q) -> None:  # pragma: no cover - runs in a spawned process
    try:
        if job.threads is not None:
            torch.set_num_threads(job.threads)
        job.run(job, job.items, lambda item, n: q.put(("done", item, n)))
    except KeyboardInterrupt:        # Ctrl-C reaches the whole process group: the parent reports it
        raise SystemExit(130)
    except SystemExit:               # orphaned: nobody to report to
        raise
    except BaseException as e:  # noqa: BLE001 - report any failure to the parent, then exit non-zero
        q.put(("error", _picklable(e), traceback.format_exc()))
        raise SystemExit(1)


def _picklable(e: BaseException) -> BaseException | None:
    """``e`` when it survives pickling (to be raised again in the parent), else None."""
    import pickle

    try:
        pickle.loads(pickle.dumps(e))
    except Exception:  # noqa: BLE001 - any failure means: send the traceback text only
        return None
    return e


def run_workers(job: WorkerJob, workers: int, on_done: Callable[[Any, int], None], what: str = "worker") -> int:
    """Spread ``job.items`` over ``workers`` spawned processes (the i-th item goes to worker
    ``i % workers``, each with ``torch`` threads = this process's threads / ``workers``); relay
    their progress to ``on_done(item, n)``. On an error or an interrupt the other workers are
    stopped (finished items stay). A worker's exception is raised again here as it was (bad input
    then reads the same as in one process; the worker's traceback is attached as a note), or as a
    ``RuntimeError`` holding the traceback when it cannot cross processes. Returns the number of
    items finished."""
    import torch.multiprocessing as mp

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    threads = max(1, torch.get_num_threads() // workers)
    procs = []
    for w in range(workers):
        mine = tuple(k for i, k in enumerate(job.items) if i % workers == w)
        if mine:
            p = ctx.Process(target=_worker_main,
                            args=(dataclasses.replace(job, items=mine, threads=threads, parent_pid=os.getpid()), q),
                            daemon=False)
            p.start()
            procs.append(p)
    done, errors, finished = 0, [], False
    try:
        while True:
            try:
                kind, k, payload = q.get(timeout=0.5)
            except _queue.Empty:
                if not any(p.is_alive() for p in procs):
                    # drain what arrived between the last get and the exit
                    try:
                        kind, k, payload = q.get(timeout=0.5)
                    except _queue.Empty:
                        break
                else:
                    continue
            if kind == "done":
                done += 1
                on_done(k, payload)
            else:
                errors.append((k, payload))
                break                    # stop the others now (finally), not when they are done
        finished = True
    finally:
        for p in procs:
            if p.is_alive() and (errors or not finished):
                p.terminate()
            p.join()
    bad = [p.exitcode for p in procs if p.exitcode != 0]
    for exc, tb in errors:
        if isinstance(exc, Exception):
            if hasattr(exc, "add_note"):                     # Python >= 3.11
                exc.add_note(f"in a {what}:\n{tb}")
            raise exc
    if errors or bad:
        raise RuntimeError(f"{what} failed:\n" + ("\n".join(tb for _, tb in errors) or f"exit codes {bad}"))
    return done
