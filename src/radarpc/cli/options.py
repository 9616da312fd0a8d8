"""The names the command line offers as choices, without importing torch.

``radarpc --help`` and ``radarpc COMMAND --help`` build every parser, so the parsers may only use
values that import nothing heavy. The library keeps each list beside the code that interprets it;
these copies are checked against them by ``tests/cli/test_help.py``.
"""
from __future__ import annotations

__all__ = ["RADIAL_SENSOR_NAMES", "SCENE_KINDS", "CFAR_PRESET_NAMES", "BEAMFORMING_MODES", "ENVELOPES",
           "COLOR_BY", "DEFAULT_WAIT_S", "MODEL_NAMES", "STUDY_KINDS", "RALD_STUDY_KINDS", "GUIDE_SOURCES", "POSTERIORS",
           "OFFICIAL_RALD_WEIGHTS", "plain_text"]

RADIAL_SENSOR_NAMES = ("radial", "radial-s", "tiny")       # radarpc.sensors.radial.RADIAL_SENSORS
SCENE_KINDS = ("hallway", "lab", "classroom", "large_room", "outdoor")   # radarpc.sim.indoor.SCENE_KINDS
CFAR_PRESET_NAMES = ("radial",)                            # radarpc.dsp.pointcloud.CFAR_PRESETS
BEAMFORMING_MODES = ("auto", "exact", "screened", "subspace")        # radarpc.dsp.beamform.BEAMFORMING_MODES
ENVELOPES = ("replicas", "all-slots")                      # radarpc.dsp.ddma.ENVELOPES
COLOR_BY = ("velocity", "amplitude")                       # radarpc.viz.COLOR_BY
DEFAULT_WAIT_S = 7200.0                                    # radarpc.distributed.DEFAULT_WAIT_S
MODEL_NAMES = ("fftradnet", "fftradnet-s", "fftradnet-tiny", "pointpillars", "spectralpillars",
               "pointpillars-s", "spectralpillars-s", "pillars-tiny", "rald-ae", "rald-ae-s", "rald-ae-tiny",
               "rald-dit", "rald-dit-d12", "rald-dit-d18", "rald-dit-s", "rald-dit-tiny", "rpdnet", "rpdnet-s",
               "rpdnet-tiny")   # radarpc.models.MODELS
STUDY_KINDS = ("density-sweep", "ablation", "fps")         # radarpc.experiments.study.config.STUDY_KINDS
RALD_STUDY_KINDS = ("rald-ablation",)                      # radarpc.experiments.rald.ablation
GUIDE_SOURCES = ("peaks", "os-cfar", "none")               # radarpc.rald.guide.GUIDE_SOURCES
POSTERIORS = ("sample", "mean")                            # radarpc.rald.reconstruct.POSTERIORS
OFFICIAL_RALD_WEIGHTS = ("ema", "model")                   # radarpc.experiments.rald.official.WEIGHTS


def plain_text(text: str | None) -> str | None:
    """A docstring's reStructuredText made plain for ``--help``: ````x```` -> ``x``,
    ``:mod:`x``` -> ``x``, ``Example::`` -> ``Example:`` and a lone ``::`` line dropped."""
    import re

    if text is None:
        return None
    text = re.sub(r":(?:mod|func|class|meth|data|attr|obj|exc):`~?([^`]+)`", r"\1", text)
    text = re.sub(r"``([^`]+)``", r"\1", text)
    lines = []
    for line in text.split("\n"):
        if line.strip() == "::":
            continue
        if line.rstrip().endswith("::"):
            line = line.rstrip()[:-1]
        lines.append(line)
    return "\n".join(lines)


def frame_step(text: str) -> int:
    """argparse type of ``--every K``: a positive integer, refused before any work starts."""
    import argparse

    try:
        k = int(text)
    except ValueError:
        k = 0
    if k < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer (1: every frame), got {text!r}")
    return k
