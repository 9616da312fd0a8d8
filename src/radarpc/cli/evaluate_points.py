"""``radarpc evaluate-points``: Chamfer distance and EMD of predicted point clouds, per scene.

::

    radarpc evaluate-points PRED_DIR [PRED_DIR ...] --data ROOT --split test [--emd-points 2048]
                            [--emd-seed 0] [--figures] [--out DIR] [--common-frames] [--force] [--rescore]

Scores exactly the frames each ``PRED_DIR/index.json`` lists (every paired radar frame of the
split, or a subset such as every K-th frame), reading ``PRED_DIR/{run}/{frame:06d}.npy`` (float32
``(N, 3)``, radar frame; the layout ``radarpc baseline os-cfar`` and ``radarpc generate`` write)
against the reader's LiDAR cropped to the radar frustum (:mod:`radarpc.eval.pointsets`, batched;
the folder layout is :mod:`radarpc.eval.predictions`):

* CD: RaLD's non-squared Chamfer distance on the full clouds (KD-trees, exact);
* EMD: the exact Wasserstein-1 distance (POT's network simplex) between a fixed random subset of
  min(n, |gt|) LiDAR points -- the same draw for every method, keyed only by seed and frame -- and
  min(n, |pred|) predicted points, each subset carrying uniform mass (unequal sizes allowed, so a
  sparse prediction is not scored against a shrunken ground truth);
* EMD_equal: the exact Wasserstein-1 distance between both clouds resampled to exactly n points
  (without replacement from a larger cloud; every point once plus the rest drawn with replacement
  from a smaller one), the mean distance of the optimal one-to-one assignment.

An empty predicted cloud (a frame where the method found nothing: an empty RaLD decoding, an
OS-CFAR frame without detection) is counted, not scored: the tables give the number of such
frames (``empty``) and the means and medians over the other frames. A missing or malformed cloud
is an error, and so is an empty LiDAR truth.

Each ``PRED_DIR/index.json`` (written by ``radarpc baseline`` or ``radarpc generate``) must name the
same ``--data`` root and ``--split``, so that predictions are never scored against another
dataset's LiDAR; ``--force`` skips that check (e.g. for hand-made prediction folders; a folder
without an index is then scored on every paired frame of the split, and frames an index lists
outside the split are left out). Prints a per-scene Markdown
table per folder and writes ``PRED_DIR/metrics.json`` (per frame, per scene, overall) and
``metrics.md``, always over that folder's own frames. A folder is scored once: when its
``metrics.json`` holds the scores of the same clouds (by SHA-256), root, split, frames and EMD
settings, made by the same scoring, and the LiDAR and calibration files have not changed (size and
modification time), those scores are used and the command says so; ``--rescore`` scores again.

With several folders, they must list the same frames: if they do not (e.g. RaLD generated every
10th frame, OS-CFAR every frame), nothing is scored and the command says how they differ, unless
``--common-frames``, which compares them over the frames every folder lists. The methods side by
side (a row per scene and method; methods named by their index.json) are printed and written as
``DIR/comparison.md`` and ``comparison.json``; when the methods differ in which frames they
scored (empty predictions), a second table gives the means over the frames every method scored,
so that no method gains by failing. ``--figures`` draws the empirical CDFs of the per-frame CD,
EMD and EMD_equal (one panel per scene and one of all frames, one curve per method, as RaLD's
Figs. 6-7) as ``DIR/figures/cdf_chamfer.png``, ``cdf_emd.png`` and ``cdf_emd_equal.png``, and one
compared frame per scene -- the radar cube, the LiDAR truth and each method's cloud side by side,
bird's-eye view and range-elevation -- as ``DIR/figures/{scene}.png``. ``DIR`` (``--out``) defaults
to the first PRED_DIR. The driver is :mod:`radarpc.pipelines.point_eval`.
"""
from __future__ import annotations

import argparse

__all__ = ["add_parser", "run_evaluate_points"]


def run_evaluate_points(args: argparse.Namespace) -> int:
    from radarpc.pipelines.point_eval import evaluate_folders

    res = evaluate_folders(args.pred_dir, args.data, args.split, emd_points=args.emd_points, emd_seed=args.emd_seed,
                           force=args.force, figures=args.figures, out=args.out,
                           common_frames=args.common_frames, rescore=args.rescore, progress=True)
    for name, report in res.reports.items():
        folder = res.folders[name]
        if len(res.reports) > 1:
            print(f"## {name} ({folder})\n")
        print(report.to_markdown(), end="")
        if name in res.reused:
            print(f"reused {folder / 'metrics.json'}: the same clouds, truth, split and EMD settings were scored "
                  f"before (--rescore scores them again)")
        else:
            print(f"wrote {folder / 'metrics.json'} and {folder / 'metrics.md'}")
    if res.comparison is not None:
        n = len(res.compared)
        print(f"\n## side by side ({n} frame{'' if n == 1 else 's'})\n\n{res.comparison.read_text()}", end="")
        print(f"wrote {res.comparison} and {res.comparison.with_suffix('.json')}")
    for path in res.figures:
        print(f"wrote {path}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("evaluate-points", help="Chamfer distance and EMD of predicted clouds per scene, methods "
                                               "side by side",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pred_dir", nargs="+", help="prediction folders ({run}/{frame:06d}.npy), one per method")
    p.add_argument("--data", required=True, help="ColoRadar root the predictions were made on")
    p.add_argument("--split", default="test", choices=("train", "val", "test", "all"),
                   help="split the predictions were made on (default test; must match each PRED_DIR/index.json)")
    p.add_argument("--emd-points", type=int, default=2048,
                   help="EMD subset size n: min(n, |gt|) LiDAR and min(n, |pred|) predicted points; EMD_equal "
                        "resamples both clouds to exactly n points (default 2048)")
    p.add_argument("--emd-seed", type=int, default=0, help="seed of the EMD subsets and resampling (default 0)")
    p.add_argument("--figures", action="store_true",
                   help="draw the per-frame CD / EMD / EMD_equal CDFs (DIR/figures/cdf_chamfer.png, cdf_emd.png, "
                        "cdf_emd_equal.png) and one frame per scene: radar cube, LiDAR truth and each method's "
                        "cloud (DIR/figures/{scene}.png)")
    p.add_argument("--common-frames", action="store_true",
                   help="when the folders' index.json list different frames (e.g. one generated every K-th "
                        "frame), compare them over the frames all of them list instead of refusing; each "
                        "metrics.json still covers its own folder's frames")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="folder for comparison.md/.json and figures/ (default: the first PRED_DIR)")
    p.add_argument("--force", action="store_true",
                   help="score even if a PRED_DIR/index.json is missing or names another root/split")
    p.add_argument("--rescore", action="store_true",
                   help="score every folder again, even where its metrics.json holds the scores of the same "
                        "clouds, truth and settings")
    p.set_defaults(func=run_evaluate_points)
