"""``radarpc import-rald AE.pth GEN.pth``: the official RaLD weights as a run folder that
``radarpc generate`` runs.

::

    radarpc import-rald ae/checkpoint-149.pth generation/checkpoint-99.pth --out runs/rald-official
    radarpc generate runs/rald-official --data data/coloradar --split test --out preds/rald-official

AE.pth is the official autoencoder's checkpoint (``main_ae.py``), GEN.pth the generation model's
(``main_generation.py``); each a ``checkpoint-N.pth`` of the official ``save_model`` or a bare
state dict. They are read without running pickled code (``torch.load(weights_only=True)``, the
pickled args rebuilt as plain data; anything else a file asks to construct is refused, named),
and their network sizes come from the tensor shapes. --weights ema (the default) takes each
file's moving-average weights where it has them; --weights model takes ``model``, what the
official evaluation scores.

OUT gets OUT/ae, a stage-1 run folder, and OUT itself, a stage-2 run folder trained against it,
each with ``run.json``, ``config.yaml`` and ``best.safetensors``, as ``radarpc train`` writes them.
The autoencoder's config is the official one: points and queries of ``configs/ae``, range
normalised over 0..15.8 m and azimuth counted positive to the right (``mirror_azimuth: true``);
``radarpc generate`` maps its clouds to radarpc's radar frame. Both ``run.json`` record the
official files (path, SHA-256, which weights were taken, epoch, args). --data names a ColoRadar
root as the run's data: what ``radarpc generate`` reads when not given its own --data. A folder
that holds anything else is refused unless --overwrite.
"""
from __future__ import annotations

import argparse

from radarpc.cli.options import OFFICIAL_RALD_WEIGHTS

__all__ = ["add_parser", "run"]


def run(args: argparse.Namespace) -> int:
    from radarpc.experiments.rald.official import import_official_rald
    from radarpc.runs import read_json

    out = import_official_rald(args.ae, args.gen, args.out, weights=args.weights, data=args.data,
                               overwrite=args.overwrite)
    taken = read_json(out / "run.json")["imported"]
    used = ", ".join(f"{stage} {taken[stage]['weights']}" for stage in ("autoencoder", "diffusion"))
    data = "" if args.data else " --data ROOT"
    print(f"{out}: official RaLD weights ({used}); generate with "
          f"`radarpc generate {out}{data} --split test --out preds/rald-official`")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("import-rald", help="official RaLD checkpoints (both stages) as a run folder for "
                                           "`radarpc generate`",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("ae", metavar="AE.pth", help="the official autoencoder checkpoint (main_ae.py)")
    p.add_argument("gen", metavar="GEN.pth", help="the official generation checkpoint (main_generation.py)")
    p.add_argument("--out", required=True, help="run folder (the autoencoder's run goes to OUT/ae)")
    p.add_argument("--weights", default="ema", choices=OFFICIAL_RALD_WEIGHTS,
                   help="ema: each file's moving-average weights where it has them (default); model: the "
                        "weights the official evaluation scores")
    p.add_argument("--data", default=None, metavar="ROOT",
                   help="ColoRadar root recorded as the run's data, what radarpc generate reads by default "
                        "(default: none; give generate --data)")
    p.add_argument("--overwrite", action="store_true", help="replace a folder that holds anything else")
    p.set_defaults(func=run)
