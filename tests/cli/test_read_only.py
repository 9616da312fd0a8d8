"""Every writing command on a read-only output folder: one clear line naming the path, exit 2,
checked before any work (nothing half-written elsewhere).

Permission bits do not bind root. As root the commands run under ``setpriv`` with the
DAC-override capabilities dropped from the bounding set, so that the folder's mode is enforced
for them too; where that is not possible (root without setpriv) the test is skipped.
"""
from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys

import pytest

from radarpc.sensors.radial import TINY
from radarpc.sim.radial_writer import write_radial_dataset

_SETPRIV = shutil.which("setpriv")
_ROOT = os.name == "posix" and os.geteuid() == 0
pytestmark = pytest.mark.skipif(os.name != "posix" or (_ROOT and _SETPRIV is None),
                                reason="read-only folders cannot be enforced for root without setpriv")


def _radarpc(args: list[str], cwd) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "radarpc", *args]
    if _ROOT:
        cmd = [_SETPRIV, "--bounding-set", "-dac_override,-dac_read_search", *cmd]
    env = dict(os.environ, MPLCONFIGDIR=str(cwd / "mpl"))
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env, timeout=600)


@pytest.fixture(scope="module")
def place(tmp_path_factory):
    d = tmp_path_factory.mktemp("ro")
    write_radial_dataset(d / "root", TINY, n_sequences=3, frames_per_sequence=2, seed=0, progress=False)
    (d / "mpl").mkdir()
    ro = d / "ro"
    ro.mkdir()
    ro.chmod(stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP | stat.S_IROTH | stat.S_IXOTH)
    yield d
    ro.chmod(0o755)


@pytest.mark.parametrize("args,what", [
    (["pointcloud", "root", "--snr", "3", "--out", "ro/pc.parquet"], "point store ro/pc.parquet"),
    (["pointcloud", "root", "--snr", "3", "--out", "pc.parquet", "--sparse-rd-out", "ro/sparse"],
     "sparse-RD root ro/sparse"),
    (["simulate", "radial", "--out", "ro/sim", "--sensor", "tiny", "--sequences", "1",
      "--frames-per-sequence", "1", "--no-progress"], "dataset root ro/sim"),
    (["show", "root", "--frame", "0", "--snr", "3", "--out", "ro/f.png"], "figure ro/f.png"),
    (["info", "root", "--plot", "ro/i.png"], "figure ro/i.png"),
    (["info", "root", "--check", "--no-plot", "--write-skip", "ro/skip.txt"], "skip list ro/skip.txt"),
])
def test_read_only_output_is_one_clear_line(place, args, what):
    before = sorted(p.name for p in place.iterdir())
    r = _radarpc(args, place)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in r.stderr
    assert lines[-1] == f"radarpc {args[0]}: error: cannot write the {what}: {place / 'ro'} is not writable"
    assert sorted(p.name for p in place.iterdir()) == before          # nothing written elsewhere first
    assert list((place / "ro").iterdir()) == []
