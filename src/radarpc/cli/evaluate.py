"""``radarpc evaluate RUN``: RADIal's metrics of a trained run's best weights on a split.

::

    radarpc evaluate runs/sp057 --split test
    radarpc evaluate runs/fft --split test --show 5
    radarpc evaluate runs/sp_ab --split test --data sim_a --points pc_a.parquet   # one root of several: eval_test_on_sim_a.*

Prints and writes ``RUN/eval_{split}.md`` and ``.json``: AP, AR and F1 at IoU 0.5 over the
confidence thresholds 0.1 .. 0.9, precision/recall/F1 at confidence 0.2, mean range (m) and
azimuth (deg) errors of matched pairs, freespace mIoU (rows 0..123, 0-50 m), the parameter count,
the batch-1 frames/s on the evaluation device and the roots (and point stores) scored. Data given
with ``--data`` / ``--points`` that is not the run's own goes to ``RUN/eval_{split}_on_{names}.*``
instead (the roots' folder names, and the stores' file names when a root of the run is scored with
another store), so the run's own scores stay. ``--show K`` draws K frames spread evenly over
the split, first and last included (``RUN/figures/eval_{split}_{item}.png``): points or nothing in
bird's-eye view with the label and predicted boxes, and the predicted probability map;
``--show-frames N ...`` draws the frames of these numSample values the same way.
``RUN/figures/learning_curve.png`` (validation F1 and training loss per epoch, from ``log.csv``;
drawn again only when the log is newer), and ``RUN/figures/eval_{split}_labels.png``: per threshold, the labels matched,
missed with a detection within 3 m (a box in the wrong place) and missed with nothing near, and
the false alarms per frame. A folder of several runs (``--runs N``) is evaluated run by run, then
summarised (mean and standard deviation). ``--precision bf16`` scores the same weights under bf16
autocast, fast on GPUs and on CPUs with native bf16 (AVX512-BF16, AMX), and writes
``eval_{split}_bf16.*`` beside the fp32 files: compare the two before trusting bf16 for a model.
``--mirror-average`` scores a point model averaged over each frame and its mirror image about the
boresight (``radarpc.models.mirror``; twice the forward passes) into ``eval_{split}_mirror.*``.
``--no-difficult`` scores RADIal's easy mode, what its ``3-Evaluation.py`` scores without ``--difficult``:
labels marked ``Difficult`` dropped, and the frames all of whose vehicles are (frames without
vehicles stay, so their false alarms count), into ``eval_{split}_easy.*``. Runs train and are
scored by default with every label (``difficult: true`` in the config, as RADIal's ``1-Train.py``);
a run trained with ``difficult: false`` is scored in easy mode unless given ``--difficult``, which
scores every label (into ``eval_{split}.*``).
"""
from __future__ import annotations

import argparse

__all__ = ["add_parser", "run"]


def run(args: argparse.Namespace) -> int:
    from radarpc.experiments.radial_detection.evaluation import evaluate_run

    if args.fps_frames < 0:
        raise ValueError(f"fps-frames must be an integer >= 0 (0: no timing), got {args.fps_frames}")
    evaluate_run(args.run, args.split, data=args.data, points=args.points, device=args.device,
                 show=args.show, show_frames=tuple(args.show_frames), fps_frames=max(args.fps_frames, 1),
                 timed=args.fps_frames > 0, precision=args.precision,
                 mirror_average=args.mirror_average, fast=args.fast,
                 easy=None if args.difficult is None else not args.difficult,
                 empty_frames=not args.drop_empty_frames)
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("evaluate", help="RADIal metrics, figures and frames/s of a trained run",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="run folder of `radarpc train`")
    p.add_argument("--split", default="test", choices=("train", "val", "test", "all"), help="split (default test)")
    p.add_argument("--data", default=None, nargs="+", metavar="ROOT",
                   help="RADIal root(s) (default: those the run was trained on)")
    p.add_argument("--points", default=None, nargs="+", metavar="FILE",
                   help="point store of each root (default: those the run was trained on)")
    p.add_argument("--device", default=None, help="torch device (default: a GPU if any, else the CPU)")
    p.add_argument("--show", type=int, default=0, metavar="K", help="draw K frames spread evenly over the split")
    p.add_argument("--show-frames", type=int, nargs="+", default=(), metavar="N",
                   help="draw these frames of the split (RADIal numSample), as --show draws its frames")
    p.add_argument("--fps-frames", type=int, default=20,
                   help="frames timed for frames/s (default 20; 0: no timing, frames/s n/a)")
    p.add_argument("--precision", default="fp32", choices=("fp32", "bf16"),
                   help="fp32 (default) or bf16 autocast; bf16 writes eval_{split}_bf16.*")
    p.add_argument("--mirror-average", action="store_true",
                   help="point models: average each frame's output with its mirror image's (two forward "
                        "passes); writes eval_{split}_mirror.*")
    p.add_argument("--fast", action="store_true",
                   help="score and time the fast inference copy (radarpc.models.fast: exact rewrites, "
                        "fp32; the first passes compile kernels); writes eval_{split}_fast.*")
    p.add_argument("--difficult", action=argparse.BooleanOptionalAction, default=None,
                   help="--no-difficult leaves out RADIal's 'Difficult' labels: its easy mode (3-Evaluation.py "
                        "without --difficult), into eval_{split}_easy.*; --difficult scores every label. Default: "
                        "as the run was trained (its config's 'difficult')")
    p.add_argument("--drop-empty-frames", action="store_true",
                   help="leave out the frames without a vehicle to score, as RADIal's loader does in its easy mode "
                        "(with --no-difficult this is what RADIal's 3-Evaluation.py scores); default: keep them, "
                        "so their false alarms count. Writes eval_{split}[_easy]_vehicle_frames.*")
    p.set_defaults(func=run)
