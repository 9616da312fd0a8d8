"""The README's commands and snippets, run in order in a temporary folder at tiny sizes.

Every ```bash and ```python block of README.md is run (and every ```yaml block loaded as an experiment
config), top to bottom, in one working folder, so
that later blocks find what earlier ones wrote (``data/sim_radial``, the point stores,
``data/sim_colo``). ``radarpc`` commands run in-process through :func:`radarpc.cli.main` and must
exit 0; Python blocks are executed as written.

Size mapping (the README's sizes take minutes to hours; the commands are otherwise unchanged):

============================  ==========================================================================
``simulate radial``           ``--sensor tiny --sequences 6 --frames-per-sequence 2`` (12 frames, so
                              ``--frame 10`` exists)
``simulate coloradar``        ``--scenes hallway --runs-per-scene 3 --frames 1 --lidar-beams 4
                              --lidar-azimuth-steps 64`` (one train, val and test run)
``show ROOT --run RUN``       ``--frame 0`` (each run has one frame)
``baseline os-cfar``          ``+ --quick-tune --max-tune-frames 2``
``evaluate-points``           ``+ --emd-points 64``
``pointcloud``, ``simulate``  ``+ --quiet`` / ``--no-progress``
============================  ==========================================================================

Skipped, each for a stated reason: ``pip install`` (the suite runs in an installed environment and
must not touch the network), ``python -m pytest`` (this suite itself), ``radarpc demo`` and
``radarpc demo --tiny`` (``tests/cli/test_demo.py`` runs the second; the first takes minutes), ``radarpc train``,
``radarpc evaluate`` and ``torchrun`` (``tests/training`` runs them on tiny models), ``radarpc generate``,
``radarpc import-rald`` and the ``evaluate-points`` line that scores the generated clouds
(``tests/cli/test_rald_cli.py`` runs them on tiny runs and official-layout checkpoints), ``radarpc experiment``
and ``radarpc report`` (``tests/experiments/study`` runs tiny studies and reports them) and the Python
block that converts the real ``CalibrationTable.npy`` (it needs RADIal's download, which this
repository cannot ship). Any other command is an error here, so a new kind of README line gets a
mapping instead of going untested.
"""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"

# First word(s) -> why the line is not run.
SKIPPED = {
    "pip": "installs packages; the suite runs in an installed environment, without network",
    "python -m pytest": "the test suite itself",
    "radarpc demo": "tests/cli/test_demo.py runs `radarpc demo --tiny` end to end; the full demo takes minutes",
    "radarpc train": "tests/experiments/radial_detection/test_experiment.py, tests/experiments/rald/test_train.py and "
                     "tests/experiments/rpdnet/test_train.py train and resume tiny models through this command; the "
                     "shipped configs train for minutes to days",
    "radarpc evaluate": "tests/experiments/radial_detection/test_experiment.py evaluates a tiny run through this command",
    "radarpc generate": "generates (and reconstructs) with the RaLD runs of `radarpc train` and `radarpc import-rald`, "
                        "which this test skips; tests/cli/test_rald_cli.py generates and reconstructs with tiny runs "
                        "trained through `radarpc train` and imported through `radarpc import-rald`; "
                        "tests/experiments/rpdnet/test_train.py generates with a tiny occupancy baseline run",
    "radarpc evaluate-points preds/rald": "scores the clouds of `radarpc generate` above (skipped); "
                                          "tests/cli/test_rald_cli.py scores tiny generated and reconstructed "
                                          "clouds beside OS-CFAR's",
    "radarpc import-rald": "needs the official RaLD checkpoints, which this repository cannot ship; "
                           "tests/cli/test_rald_cli.py imports tiny checkpoints in the official layout",
    "torchrun": "starts several processes (GPUs); tests/training/test_loop.py runs a 2-process gloo job",
    "radarpc experiment": "tests/experiments/study runs tiny studies through this command (configs/study/tiny-*.yaml); "
                          "the shipped studies train for hours",
    "radarpc report": "tests/experiments/study/test_report.py reports result rows through this command; the README's "
                      "runs folders come from the studies above",
}
# A Python block holding one of these needs real data.
NEEDS_REAL_DATA = {
    "CalibrationTable.npy": "converts RADIal's real pickled calibration, which only the dataset download holds",
}

# option -> value, per command; a missing option is appended.
SET_OPTIONS = {
    ("simulate", "radial"): {"--sensor": "tiny", "--sequences": "6", "--frames-per-sequence": "2"},
    ("simulate", "coloradar"): {"--scenes": "hallway", "--runs-per-scene": "3", "--frames": "1",
                                "--lidar-beams": "4", "--lidar-azimuth-steps": "64"},
    ("baseline", "os-cfar"): {"--max-tune-frames": "2"},
    ("evaluate-points",): {"--emd-points": "64"},
}
ADD_FLAGS = {
    ("simulate", "radial"): ["--no-progress"],
    ("simulate", "coloradar"): ["--no-progress"],
    ("baseline", "os-cfar"): ["--quick-tune"],
    ("pointcloud",): ["--quiet"],
}


def readme_blocks(text: str) -> list[tuple[str, str]]:
    """``(language, body)`` of every fenced block, in order."""
    return [(m.group(1), m.group(2)) for m in re.finditer(r"^```(\w+)\n(.*?)^```", text, re.S | re.M)]


def bash_commands(body: str) -> list[list[str]]:
    """The commands of a bash block: continuation lines joined, comments dropped, ``&&`` split."""
    out: list[list[str]] = []
    for line in body.replace("\\\n", " ").splitlines():
        words = shlex.split(line, comments=True)
        cmd: list[str] = []
        for w in words + ["&&"]:
            if w == "&&":
                if cmd:
                    out.append(cmd)
                cmd = []
            else:
                cmd.append(w)
    return out


def skip_reason(cmd: list[str]) -> str | None:
    line = " ".join(cmd)
    return next((why for head, why in SKIPPED.items() if line == head or line.startswith(head + " ")), None)


def tiny_argv(cmd: list[str]) -> list[str]:
    """The ``radarpc`` argv of a README command at the sizes of the mapping above."""
    assert cmd[0] == "radarpc", f"README command {shlex.join(cmd)!r} has no mapping in tests/test_readme.py"
    argv = list(cmd[1:])
    for key in sorted(set(SET_OPTIONS) | set(ADD_FLAGS), key=len, reverse=True):
        if tuple(argv[:len(key)]) != key:
            continue
        for opt, val in SET_OPTIONS.get(key, {}).items():
            if opt in argv:
                argv[argv.index(opt) + 1] = val
            else:
                argv += [opt, val]
        argv += [f for f in ADD_FLAGS.get(key, []) if f not in argv]
        break
    if argv[0] == "show" and "--run" in argv and "--frame" in argv:    # a ColoRadar run's frame
        argv[argv.index("--frame") + 1] = "0"
    return argv


def test_bash_parsing_and_mapping():
    cmds = bash_commands("a --x 1 \\\n  --y 2   # comment\nb && c d\n")
    assert cmds == [["a", "--x", "1", "--y", "2"], ["b"], ["c", "d"]]
    assert tiny_argv(["radarpc", "simulate", "radial", "--out", "d", "--sequences", "60"]) == [
        "simulate", "radial", "--out", "d", "--sequences", "6", "--sensor", "tiny", "--frames-per-sequence", "2",
        "--no-progress"]
    assert skip_reason(["pip", "install", "-e", "."]) and skip_reason(["radarpc", "demo"])
    assert skip_reason(["radarpc", "info", "x"]) is None


def test_readme_commands_and_snippets_run(tmp_path, monkeypatch, capsys):
    from radarpc.cli import main

    monkeypatch.chdir(tmp_path)
    blocks = readme_blocks(README.read_text())
    ran = {"bash": 0, "python": 0}
    skipped: list[str] = []
    for k, (lang, body) in enumerate(blocks):
        if lang == "bash":
            for cmd in bash_commands(body):
                why = skip_reason(cmd)
                if why is not None:
                    skipped.append(f"{shlex.join(cmd)}: {why}")
                    continue
                argv = tiny_argv(cmd)
                code = main(argv)
                err = capsys.readouterr().err
                assert code == 0, f"README command failed ({code}): radarpc {shlex.join(argv)}\n{err[-2000:]}"
                ran["bash"] += 1
        elif lang == "python":
            why = next((w for key, w in NEEDS_REAL_DATA.items() if key in body), None)
            if why is not None:
                skipped.append(f"python block {k}: {why}")
                continue
            exec(compile(body, f"README.md python block {k}", "exec"), {"__name__": "readme"})
            ran["python"] += 1
        elif lang == "yaml":                  # an experiment config as the README shows one: it must load
            from radarpc.experiments.radial_detection.config import load_experiment

            (tmp_path / f"readme_block{k}.yaml").write_text(body)
            load_experiment(tmp_path / f"readme_block{k}.yaml")
        else:
            pytest.fail(f"README block {k} has language {lang!r}; this test runs bash and python blocks "
                        f"and loads yaml ones as experiment configs")
    # every part of the README ran: the radial, point-cloud and ColoRadar commands and 3 snippets
    assert ran["bash"] >= 12 and ran["python"] >= 3, (ran, skipped)
    assert sum("CalibrationTable" in s or "real" in s for s in skipped) == 1, skipped
    assert (tmp_path / "data" / "sim_radial_pc057.parquet").is_file()
    assert (tmp_path / "preds" / "oscfar" / "metrics.json").is_file()
