"""How much a trained point model relies on the scenes' left-right asymmetry.

A frame mirrored about the boresight (:func:`radarpc.data.augment.mirror_frame`: points, labels
and freespace) is a valid radar frame of a mirrored world. Where the world is symmetric a model
scores the mirrored split as the split itself; where it is not (traffic keeps to the right, in
RADIal and in the simulator's road scenes) the gap measures what the model learned from the
asymmetry, and so what mirror augmentation or mirror averaging (``radarpc evaluate
--mirror-average``) would cost it. Prints one JSON object: RADIal's F1, F1 at confidence 0.2,
true and false detections at 0.2 and freespace mIoU of the run's best weights on the split as it
is, on every frame mirrored, and averaged over both views (:class:`radarpc.models.mirror.MirrorAveraged`).
Usage::

    python docs/notebook/scripts/mirror_symmetry.py runs/pp --split test [--data ROOT --points STORE]
"""
from __future__ import annotations

import argparse
import functools
import json

import torch
from torch.utils.data import DataLoader

from radarpc.data.augment import MirroredFrames
from radarpc.eval.detection import FIXED_THRESHOLD
from radarpc.experiments.radial_detection.evaluation import load_trained, mirror_sectors_of
from radarpc.models.mirror import MirrorAveraged
from radarpc.experiments.radial_detection.task import ConcatFrames, collate_detection, detection_dataset, evaluate_model, point_datasets


def scores(model, frames, cfg, batch_size: int = 4) -> dict:
    """RADIal's metrics of ``model`` on ``frames`` (fp32, CPU), as ``radarpc evaluate`` scores them."""
    loader = DataLoader(frames, batch_size=batch_size, shuffle=False,
                        collate_fn=functools.partial(collate_detection, cfg=cfg))
    with torch.inference_mode():
        report, miou = evaluate_model(model, loader, torch.device("cpu"), cfg.targets, max_candidates=None)
    m = report.to_dict()
    k = m["thresholds"].index(FIXED_THRESHOLD)
    return {"f1": m["f1"], "f1_fixed": m["f1_fixed"], "tp_fixed": m["tp"][k], "fp_fixed": m["fp"][k],
            "n_labels": m["n_labels"], "freespace_miou": miou}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a training run folder of a point model (radarpc train --out)")
    p.add_argument("--split", default="test", choices=("train", "val", "test", "all"))
    p.add_argument("--data", nargs="+", default=None, metavar="ROOT", help="roots (default: the run's)")
    p.add_argument("--points", nargs="+", default=None, metavar="FILE", help="their point stores (default: the run's)")
    args = p.parse_args(argv)
    cfg, model, key = load_trained(args.run, "cpu")
    if cfg.input_kind != "points":
        raise SystemExit(f"{args.run}: {cfg.name!r} takes RD cubes; mirroring applies to point models")
    ds = detection_dataset(cfg, args.data or key["data"], args.points or key.get("points"), args.split)
    mirrored = ConcatFrames([MirroredFrames(part, 1.0, seed=0) for part in point_datasets(ds)])
    res = {"run": str(args.run), "split": args.split, "frames": len(ds),
           "as_is": scores(model, ds, cfg),
           "mirrored": scores(model, mirrored, cfg),
           "mirror_averaged": scores(MirrorAveraged(model, cfg.targets, mirror_sectors_of(ds)), ds, cfg)}
    print(json.dumps(res))


if __name__ == "__main__":
    main()
