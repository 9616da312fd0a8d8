"""Train the learned baseline in a run folder (:mod:`.runs` for the format and the key), resumable,
through the one training loop (:func:`radarpc.training.loop.fit`)."""
from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Callable, Sequence

from radarpc.config import save_yaml
from radarpc.distributed import dist_env
from radarpc.experiments.rald.train import CONFIG_YAML
from radarpc.experiments.rpdnet.config import OccupancyExperiment, canonical_key
from radarpc.experiments.rpdnet.runs import run_key
from radarpc.experiments.rpdnet.task import OccupancyTask
from radarpc.training.loop import FitResult, fit

__all__ = ["train_occupancy"]


def train_occupancy(cfg: OccupancyExperiment, data: str | os.PathLike | Sequence[str | os.PathLike],
                    out: str | os.PathLike, *, device: str | None = None, overwrite: bool = False,
                    progress: bool = True, log: Callable[[str], None] = print,
                    on_step: Callable[[int], None] | None = None) -> FitResult:
    """Train ``cfg`` on the one ColoRadar root ``data`` (its train and val splits) into the run
    folder ``out``; the same call again resumes (``on_step`` is called with the global step after
    each optimizer step).

    Raises
    ------
    ValueError
        Not one root; a split without paired frames.
    RunMismatchError
        ``out`` holds another run (another config or root) and ``overwrite`` is False.
    """
    roots = [data] if isinstance(data, (str, os.PathLike)) else list(data)
    if len(roots) != 1:
        raise ValueError(f"the occupancy baseline reads one ColoRadar root (its runs give the splits), got "
                         f"{len(roots)}: {', '.join(map(str, roots)) or 'none'}")
    root = Path(roots[0])
    out = Path(out)
    res = fit(OccupancyTask(cfg, root), cfg.train, out, run_key(cfg, root), device=device, overwrite=overwrite,
              progress=progress, log=log, extra_outputs=(CONFIG_YAML,), on_step=on_step,
              canonical_key=functools.partial(canonical_key, num_workers=cfg.train.num_workers))
    if dist_env().rank == 0 and not (out / CONFIG_YAML).is_file():      # under torchrun, rank 0 alone writes
        save_yaml(cfg, out / CONFIG_YAML)
    return res
