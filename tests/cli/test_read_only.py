"""Every writing command on a read-only output folder: one clear line naming the path, exit 2,
checked before any work (nothing half-written elsewhere).

Permission bits do not bind root. As root the commands run under ``setpriv`` with the
DAC-override capabilities dropped from the bounding set, so that the folder's mode is enforced
for them too; where that is not possible (root without setpriv) the test is skipped.

One command runs as ``python -m radarpc`` (the installed command's entry point); the others run one
after another through :func:`radarpc.cli.main` in one child process (the entry point's only work),
each recording the folder before and after it: one interpreter and torch import instead of one per
command.
"""
from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import textwrap

import pytest

_SETPRIV = shutil.which("setpriv")
_ROOT = os.name == "posix" and os.geteuid() == 0
pytestmark = pytest.mark.skipif(os.name != "posix" or (_ROOT and _SETPRIV is None),
                                reason="read-only folders cannot be enforced for root without setpriv")

CASES = [
    (["pointcloud", "root", "--snr", "3", "--out", "ro/pc.parquet"], "point store ro/pc.parquet"),
    (["pointcloud", "root", "--snr", "3", "--out", "pc.parquet", "--sparse-rd-out", "ro/sparse"],
     "sparse-RD root ro/sparse"),
    (["simulate", "radial", "--out", "ro/sim", "--sensor", "tiny", "--sequences", "1",
      "--frames-per-sequence", "1", "--no-progress"], "dataset root ro/sim"),
    (["show", "root", "--frame", "0", "--snr", "3", "--out", "ro/f.png"], "figure ro/f.png"),
    (["info", "root", "--plot", "ro/i.png"], "figure ro/i.png"),
    (["info", "root", "--check", "--no-plot", "--write-skip", "ro/skip.txt"], "skip list ro/skip.txt"),
    # checked before the run or the checkpoints are read: neither need exist here
    (["generate", "run", "--data", "root", "--out", "ro/gen"], "prediction folder ro/gen"),
    (["import-rald", "ae.pth", "gen.pth", "--out", "ro/official"], "imported RaLD run ro/official"),
]
ENTRY = 0                                   # the case that runs as `python -m radarpc`

# Runs each argv of sys.argv[1] (JSON) as `python -m radarpc` would (radarpc.cli.main; SystemExit's code;
# an uncaught exception prints its traceback and exits 1), capturing its output; prints one JSON list.
_DRIVER = textwrap.dedent("""
    import contextlib, io, json, os, sys, traceback
    from radarpc.cli import main
    results = []
    for argv in json.loads(sys.argv[1]):
        before = sorted(os.listdir("."))
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as e:
                code = e.code
            except BaseException:
                traceback.print_exc()
                code = 1
        results.append({"returncode": code, "stderr": err.getvalue(), "before": before,
                        "after": sorted(os.listdir(".")), "ro": sorted(os.listdir("ro"))})
    print(json.dumps(results))
""")


def _python(args: list[str], cwd) -> subprocess.CompletedProcess:
    cmd = [sys.executable, *args]
    if _ROOT:
        cmd = [_SETPRIV, "--bounding-set", "-dac_override,-dac_read_search", *cmd]
    env = dict(os.environ, MPLCONFIGDIR=str(cwd / "mpl"))
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env, timeout=600)


@pytest.fixture(scope="module")
def place(tiny_root, tmp_path_factory):
    d = tmp_path_factory.mktemp("ro")
    shutil.copytree(tiny_root, d / "root")            # the session's TINY root (3 x 2 frames, seed 0)
    (d / "mpl").mkdir()
    ro = d / "ro"
    ro.mkdir()
    ro.chmod(stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP | stat.S_IROTH | stat.S_IXOTH)
    yield d
    ro.chmod(0o755)


@pytest.fixture(scope="module")
def driven(place) -> dict[tuple[str, ...], dict]:
    """What every case but :data:`ENTRY` did, run in one child process, by its argv."""
    argvs = [args for k, (args, _) in enumerate(CASES) if k != ENTRY]
    r = _python(["-c", _DRIVER, json.dumps(argvs)], place)
    assert r.returncode == 0, r.stderr
    return {tuple(a): res for a, res in zip(argvs, json.loads(r.stdout.splitlines()[-1]))}


@pytest.mark.parametrize("args,what", CASES)
def test_read_only_output_is_one_clear_line(place, driven, args, what):
    if args == CASES[ENTRY][0]:
        before = sorted(p.name for p in place.iterdir())
        r = _python(["-m", "radarpc", *args], place)
        res = {"returncode": r.returncode, "stderr": r.stderr, "before": before,
               "after": sorted(p.name for p in place.iterdir()), "ro": sorted(p.name for p in (place / "ro").iterdir())}
    else:
        res = driven[tuple(args)]
    assert res["returncode"] == 2, res["stderr"]
    lines = [ln for ln in res["stderr"].splitlines() if ln.strip()]
    assert "Traceback" not in res["stderr"]
    assert lines[-1] == f"radarpc {args[0]}: error: cannot write the {what}: {place / 'ro'} is not writable"
    assert res["after"] == res["before"]                                  # nothing written elsewhere first
    assert res["ro"] == [] and list((place / "ro").iterdir()) == []
