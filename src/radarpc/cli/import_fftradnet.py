"""``radarpc import-fftradnet CHECKPOINT``: official FFTRadNet weights as a run folder that
``radarpc evaluate`` scores.

::

    radarpc import-fftradnet FFTRadNet_RA_192_56_epoch78_loss_172.8239_AP_0.9813.pth \\
        --official-config RADIal/FFTRadNet/config/config_FFTRadNet_192_56.json --data data/RADIal --out runs/fft_official
    radarpc evaluate runs/fft_official --split test --show 5

The checkpoint (a state dict, or the official training script's ``{"net_state_dict": ...}``) is
read with ``torch.load(weights_only=True)``: a file that needs full unpickling is refused. The
official JSON config gives the network sizes (``model``) and the input normalisation and
regression statistics (``dataset.statistics``) the weights were trained with. The run folder
holds ``run.json`` (the config, ``--data`` and both files' SHA-256), ``config.yaml`` and
``best.safetensors``, as a run of ``radarpc train`` does; ``--data`` is what ``radarpc evaluate``
scores unless given its own ``--data``. ``--geometry`` takes a radarpc experiment YAML whose
``fftradnet`` section gives the cube sizes and the sizes the official config does not set
(default: the official model on RADIal's 512 x 256 x 16 cubes).
"""
from __future__ import annotations

import argparse

__all__ = ["add_parser", "run"]


def run(args: argparse.Namespace) -> int:
    from radarpc.experiments.radial_detection.config import load_experiment
    from radarpc.experiments.radial_detection.official import import_official_fftradnet
    from radarpc.io import DataFileError
    from radarpc.models.fftradnet import FFTRadNetConfig

    base = FFTRadNetConfig()
    if args.geometry is not None:
        like = load_experiment(args.geometry)
        if not isinstance(like.model.config, FFTRadNetConfig):
            raise DataFileError(args.geometry, f"expected an FFTRadNet experiment config, got model "
                                               f"{like.model.variant!r}")
        base = like.model.config
    out = import_official_fftradnet(args.checkpoint, args.official_config, args.data, args.out, base=base,
                                    overwrite=args.overwrite)
    print(f"{out}: official FFTRadNet weights of {args.checkpoint}; score them with `radarpc evaluate {out} --split test`")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("import-fftradnet", help="official FFTRadNet weights as a run folder for `radarpc evaluate`",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", help="official FFTRadNet checkpoint (.pth)")
    p.add_argument("--official-config", required=True, metavar="JSON",
                   help="the official JSON config the weights were trained with (valeoai/RADIal FFTRadNet/config/)")
    p.add_argument("--data", required=True, nargs="+", metavar="ROOT", help="RADIal root(s) to score by default")
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--geometry", default=None, metavar="YAML",
                   help="radarpc FFTRadNet experiment config giving the cube sizes (default: RADIal's)")
    p.add_argument("--overwrite", action="store_true", help="replace a folder that holds another run")
    p.set_defaults(func=run)
