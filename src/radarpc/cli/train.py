"""``radarpc train CONFIG``: train a detector (FFTRadNet, polar PointPillars, SpectralPillars) on a
RADIal-layout root, with validation every epoch and resume.

::

    radarpc train configs/spectralpillars-s.yaml --data data/sim_radial_s --points data/sim_radial_s_pc057.parquet --out runs/sp057
    radarpc train configs/fftradnet-s.yaml --data data/sim_radial_s --out runs/fft
    torchrun --nproc-per-node 2 -m radarpc train configs/fftradnet.yaml --data data/radial --out runs/fft
    radarpc train configs/spectralpillars-s.yaml --data sim_a sim_b --points pc_a.parquet pc_b.parquet --out runs/sp_ab

Several roots (``--data A B``, with one point store each for the pillar models) train as one
dataset: the training frames of every root, validated on the validation frames of every root.
A root's RD cubes may be deleted once converted to its point store: the point models read only
the stores and each root's labels and freespace.

The run folder ``--out`` holds ``config.yaml`` (the resolved config), ``run.json`` (the key: the
config and the data paths), ``checkpoints/last.safetensors`` (the whole training state, written
atomically every ``train.checkpoint_every`` steps and each epoch), ``best.safetensors`` (the
weights of the best validation F1), ``log.csv`` and TensorBoard events in ``tb/`` (when the
``tensorboard`` package is installed). Run the same command again after an interruption: it
resumes from the last checkpoint and ends with the same weights as an uninterrupted run. Another
config in the same folder is refused unless ``--overwrite``, which deletes that run's files and the
evaluations of its weights (``eval_*``, ``figures/``). ``--runs N`` trains N seeds into
``OUT/run0 .. OUT/run{N-1}`` and writes ``OUT/summary.md`` with the mean and standard deviation.
Under ``torchrun`` the run uses DistributedDataParallel (NCCL on GPUs, gloo on CPUs); ``train.batch_size``
is the global batch. The loop is :mod:`radarpc.training.loop`.
"""
from __future__ import annotations

import argparse

from radarpc.cli.options import MODEL_NAMES

__all__ = ["add_parser", "run"]


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import sys

    from radarpc.distributed import dist_env
    from radarpc.experiments.radial_detection.config import load_experiment, with_train
    from radarpc.experiments.radial_detection.train import train_runs

    cfg = load_experiment(args.config, notice=lambda s: print(s, file=sys.stderr))
    if args.model is not None and args.model != cfg.model.variant:
        from radarpc.models import ModelSpec

        # the config's overrides belong to its own variant; another variant starts from its own sizes
        cfg = dataclasses.replace(cfg, model=ModelSpec(args.model))
    changes = {k: v for k, v in (("epochs", args.epochs), ("batch_size", args.batch_size),
                                 ("num_workers", args.num_workers), ("seed", args.seed)) if v is not None}
    if changes:
        cfg = with_train(cfg, **changes)
    rank0 = dist_env().rank == 0
    results = train_runs(cfg, args.data, args.out, points=args.points, runs=args.runs, device=args.device,
                         overwrite=args.overwrite, progress=not args.no_progress,
                         log=print if rank0 else (lambda s: None))
    if rank0:
        for r in results:
            print(f"{r.out}: best validation {cfg.train.select_metric} {r.best_score:.4f} at epoch {r.best_epoch}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("train", help="train a detector from a config (resumable, DDP under torchrun)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("config", help="experiment YAML (see configs/)")
    p.add_argument("--data", required=True, nargs="+", metavar="ROOT",
                   help="RADIal-layout root (or a sparse-RD root for FFTRadNet); several train together")
    p.add_argument("--points", default=None, nargs="+", metavar="FILE",
                   help="point store made from each --data root, in the same order (pillar models)")
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--model", default=None, choices=MODEL_NAMES,
                   help="train this variant of the model registry instead of the config's model.variant "
                        "(without its overrides; see `radarpc models`)")
    p.add_argument("--runs", type=int, default=1, help="train this many seeds (train.seed, +1, ...) and summarise")
    p.add_argument("--device", default=None, help="torch device (default: this rank's GPU, else the CPU)")
    p.add_argument("--epochs", type=int, default=None, help="override train.epochs")
    p.add_argument("--batch-size", type=int, default=None, help="override train.batch_size (global)")
    p.add_argument("--num-workers", type=int, default=None, help="override train.num_workers")
    p.add_argument("--seed", type=int, default=None, help="override train.seed")
    p.add_argument("--overwrite", action="store_true", help="start over in a folder that holds another run")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
