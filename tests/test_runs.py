"""The shared run-folder mechanism: lock, key check, resume, overwrite, leftovers."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from radarpc.io import atomic_write
from radarpc.runs import (OutputBusyError, OutputLock, RunFolder, RunMismatchError, check_writable,
                          remove_temp_files)


def _hold_lock_in_child(output, seconds: float) -> subprocess.Popen:
    """A second real process that takes the lock on ``output`` and holds it."""
    code = textwrap.dedent(f"""
        import sys, time
        from radarpc.runs import OutputLock
        with OutputLock({str(output)!r}):
            print("locked", flush=True)
            time.sleep({seconds})
    """)
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "locked"
    return child


def test_second_process_is_refused_while_the_first_holds_the_output(tmp_path):
    out = tmp_path / "store.parquet"
    child = _hold_lock_in_child(out, 30)
    try:
        with pytest.raises(OutputBusyError, match=rf"pid {child.pid}.*store\.parquet"):
            OutputLock(out, "point store").acquire()
        run = RunFolder(tmp_path / "parts", {"run.json": {"a": 1}}, lock_output=out)
        with pytest.raises(OutputBusyError):
            run.start()
        assert not (tmp_path / "parts").exists()          # refused before anything was written
    finally:
        child.kill()
        child.wait()
        child.stdout.close()
    # a killed holder releases the lock (flock dies with the process)
    with OutputLock(out) as lock:
        assert lock.held
    assert not lock.path.exists()                           # removed on release


def test_lock_is_reacquirable_and_exclusive_within_a_process(tmp_path):
    a = OutputLock(tmp_path / "x")
    a.acquire()
    with pytest.raises(OutputBusyError):
        OutputLock(tmp_path / "x").acquire()              # flock is per open file description
    a.release()
    with OutputLock(tmp_path / "x"):
        pass


def test_resume_keeps_parts_and_mismatch_is_refused(tmp_path):
    d = tmp_path / "run"
    with RunFolder(d, {"run.json": {"seed": 0, "version": "1"}}, ignore_keys=("version",)) as run:
        assert not run.resumed
        with atomic_write(d / "part-0.bin") as f:
            f.write(b"abc")
    assert json.loads((d / "run.json").read_text()) == {"seed": 0, "version": "1"}
    # same key, another version string: resumes and keeps the part
    with RunFolder(d, {"run.json": {"seed": 0, "version": "2"}}, ignore_keys=("version",)) as run:
        assert run.resumed
        assert run.done(d / "part-0.bin")
        assert not run.done(d / "part-1.bin")
        assert not run.done(d / "part-0.bin", check=lambda p: p.read_bytes() == b"xyz")
    # another key: refused, naming the difference; nothing deleted
    with pytest.raises(RunMismatchError, match=r"run\.json:seed.*--overwrite"):
        RunFolder(d, {"run.json": {"seed": 1}}).start()
    assert (d / "part-0.bin").read_bytes() == b"abc"
    # overwrite starts over
    with RunFolder(d, {"run.json": {"seed": 1}}).start(overwrite=True) as run:
        assert not run.resumed and not run.done(d / "part-0.bin")
    assert sorted(p.name for p in d.iterdir()) == ["run.json"]


def test_overwrite_deletes_only_owned_entries(tmp_path):
    d = tmp_path / "root"
    (d / "radar_FFT").mkdir(parents=True)
    (d / "radar_FFT" / "a.npy").write_bytes(b"1")
    (d / "notes.txt").write_text("user file")
    run = RunFolder(d, {"sensor.json": {"n": 2}}, owned=("radar_FFT",))
    with pytest.raises(RunMismatchError):
        run.start()
    run.start(overwrite=True)
    run.close()
    assert (d / "notes.txt").read_text() == "user file"
    assert not (d / "radar_FFT").exists()


def test_overwrite_deletes_owned_patterns(tmp_path):
    # a run's evaluations (eval_*) are stale once its weights are replaced; other files stay
    d = tmp_path / "run"
    d.mkdir()
    for name in ("best.safetensors", "eval_test.json", "eval_test_on_b.md", "evaluation_notes.txt"):
        (d / name).write_text("x")
    (d / "tb").symlink_to(tmp_path / "gone")              # an owned name is deleted even as a broken link
    run = RunFolder(d, {"run.json": {"k": 2}}, owned=("best.safetensors", "tb", "eval_*"))
    run.start(overwrite=True)
    run.close()
    assert sorted(p.name for p in d.iterdir()) == ["evaluation_notes.txt", "run.json"]


def test_not_resume_clears_a_matching_run(tmp_path):
    d = tmp_path / "run"
    with RunFolder(d, {"run.json": {"k": 1}}):
        (d / "part").write_text("x")
    with RunFolder(d, {"run.json": {"k": 1}}).start(resume=False) as run:
        assert not run.resumed
    assert not (d / "part").exists()


def test_leftover_temp_files_are_removed_on_resume(tmp_path):
    d = tmp_path / "run"
    with RunFolder(d, {"run.json": {"k": 1}}):
        pass
    (d / "sub").mkdir()
    for name in (".part-3.parquet.abc123.tmp", "sub/.frame_1.bin.x.tmp"):
        (d / name).write_bytes(b"half")
    keep = d / "keep.tmp"                                   # not an atomic-write temp name
    keep.write_text("x")
    with RunFolder(d, {"run.json": {"k": 1}}) as run:
        assert run.resumed
    assert not list(d.rglob(".*.tmp"))
    assert keep.exists()
    assert remove_temp_files(tmp_path / "missing") == 0


def test_a_file_in_place_of_the_folder(tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(NotADirectoryError, match="not a folder"):
        RunFolder(f, {"run.json": {}}).start()


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="permissions are not enforced for root")
def test_read_only_output_fails_before_work(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(PermissionError, match=r"cannot write the dataset root .*ro"):
            RunFolder(ro / "sim", {"run.json": {}}, what="dataset root").start()
        with pytest.raises(PermissionError):
            check_writable(ro / "x.parquet")
    finally:
        ro.chmod(0o755)


def test_check_writable_accepts_new_nested_paths(tmp_path):
    check_writable(tmp_path / "a" / "b" / "c.parquet")
    check_writable(tmp_path / "new_folder")


def test_a_run_killed_while_writing_its_manifests_resumes(tmp_path):
    d = tmp_path / "root"
    d.mkdir()
    (d / ".sensor.json.x1.tmp").write_text("{")              # killed during the first manifest write
    manifests = {"sensor.json": {"seed": 0}, "scene.json": {"n": 1}}
    with RunFolder(d, manifests) as run:
        assert not run.resumed                                  # nothing of the run was there
    (d / "scene.json").unlink()                                 # killed between the two writes
    (d / "frame_0.npy").write_bytes(b"x")
    with RunFolder(d, manifests) as run:
        assert run.resumed and run.done(d / "frame_0.npy")
    assert json.loads((d / "scene.json").read_text()) == {"n": 1}   # the resumed run completed it
    (d / "sensor.json").unlink()                                # no manifest at all: not this run's
    (d / "scene.json").unlink()
    with pytest.raises(RunMismatchError, match="missing or unreadable"):
        RunFolder(d, manifests).start()
    (d / "sensor.json").write_text('{"seed": 1}')               # one present and different
    with pytest.raises(RunMismatchError, match=r"sensor\.json:seed"):
        RunFolder(d, manifests).start()


def test_the_current_folder_is_locked_beside_it(tmp_path, monkeypatch):
    # "." names the folder itself: its lock goes in the parent, not inside the output
    d = tmp_path / "here"
    d.mkdir()
    monkeypatch.chdir(d)
    with RunFolder(".", {"run.json": {"k": 1}}).start(overwrite=True) as run:
        assert run.lock.path == tmp_path / ".here.lock" and run.lock.path.exists()
        with pytest.raises(OutputBusyError):
            OutputLock(d).acquire()                             # the same output, named otherwise
    assert sorted(p.name for p in d.iterdir()) == ["run.json"]


def test_clear_removes_the_manifests_last(tmp_path, monkeypatch):
    # a kill while an overwrite clears the folder leaves a folder that still says whose it is
    import shutil as _shutil

    d = tmp_path / "run"
    with RunFolder(d, {"run.json": {"k": 1}}, owned=("a", "b")):
        for name in ("a", "b"):
            (d / name).mkdir()
            (d / name / "x").write_text("x")
    calls = []
    real = _shutil.rmtree

    def dying_rmtree(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt("simulated kill")
        return real(path, *args, **kwargs)

    monkeypatch.setattr("radarpc.runs.shutil.rmtree", dying_rmtree)
    with pytest.raises(KeyboardInterrupt):
        RunFolder(d, {"run.json": {"k": 2}}, owned=("a", "b")).start(overwrite=True)
    monkeypatch.undo()
    assert (d / "run.json").is_file()                           # still a run folder, of the old key
    with pytest.raises(RunMismatchError, match=r"run\.json:k"):
        RunFolder(d, {"run.json": {"k": 2}}, owned=("a", "b")).start()
    with RunFolder(d, {"run.json": {"k": 2}}, owned=("a", "b")).start(overwrite=True):
        pass
    assert sorted(p.name for p in d.iterdir()) == ["run.json"]


def test_only_atomic_write_temp_names_are_removed(tmp_path):
    from radarpc.runs import is_temp_name

    assert is_temp_name(".part-3.parquet.abc123_x.tmp") and is_temp_name(".frame_1.bin.1234.tmp")
    assert not is_temp_name("notes.tmp") and not is_temp_name(".tmp") and not is_temp_name(".x.tmp")


def test_changed_keys_names_the_top_level_keys_that_differ(tmp_path):
    d = tmp_path / "run"
    with RunFolder(d, {"a.json": {"x": 1, "s": {"w": 9}}, "b.json": {"y": 2}}):
        pass
    assert RunFolder(d, {"a.json": {"x": 1, "s": {"w": 9}}, "b.json": {"y": 2}}).changed_keys() == set()
    assert RunFolder(d, {"a.json": {"x": 1, "s": {"w": 7}}, "b.json": {"y": 3}}).changed_keys() == {"s", "y"}
    (d / "a.json").write_text("{")
    (d / "b.json").unlink()
    assert RunFolder(d, {"a.json": {"x": 1}, "b.json": {"y": 2}}).changed_keys() == {"*"}


def test_a_stored_key_is_read_through_the_canonical_function(tmp_path):
    d = tmp_path / "run"
    with RunFolder(d, {"run.json": {"a": 1, "version": "1"}}, ignore_keys=("version",)):
        pass                                                    # stored before "b" existed
    new = {"run.json": {"a": 1, "b": 5, "version": "2"}}
    with pytest.raises(RunMismatchError, match=r"run\.json:b"):
        RunFolder(d, new, ignore_keys=("version",)).start()     # raw: "b" reads as missing
    seen = []

    def with_defaults(stored: dict) -> dict:
        seen.append(dict(stored))
        if set(stored) - {"a", "b"}:
            raise ValueError(f"unknown keys {sorted(set(stored) - {'a', 'b'})}")
        return {"b": 5, **stored}

    run = RunFolder(d, new, ignore_keys=("version",), canonical={"run.json": with_defaults})
    assert run.differences() == [] and run.changed_keys() == set()
    assert seen[0] == {"a": 1}                                  # the stored key, without ignore_keys
    with run:
        assert run.resumed
    assert json.loads((d / "run.json").read_text()) == {"a": 1, "version": "1"}   # kept as found
    # a stored value that differs after reading is a difference
    assert RunFolder(d, {"run.json": {"a": 2, "b": 5}}, ignore_keys=("version",),
                     canonical={"run.json": with_defaults}).differences() == ["run.json:a"]
    # a stored key the function cannot read is another run's, named with the reason
    (d / "run.json").write_text(json.dumps({"a": 1, "z": 0}))
    other = RunFolder(d, new, ignore_keys=("version",), canonical={"run.json": with_defaults})
    assert other.changed_keys() == {"a", "b"}
    with pytest.raises(RunMismatchError, match=r"run\.json \(not readable as this run's key: unknown keys \['z'\]\)"):
        other.start()
    with pytest.raises(ValueError, match=r"canonical functions for \['x.json'\]"):
        RunFolder(d, new, canonical={"x.json": with_defaults})



def test_locators_are_not_compared_and_are_updated_on_resume(tmp_path):
    d = tmp_path / "run"
    key = {"x": 1, "ae": {"path": "/old/ae", "sha": "s1"}, "v": "1"}
    with RunFolder(d, {"run.json": key}, ignore_keys=("v",), locators=("ae.path", "init.path")) as run:
        (run.path / "part.npy").write_bytes(b"p")
    moved = {"x": 1, "ae": {"path": "/new/ae", "sha": "s1"}, "v": "2"}
    run = RunFolder(d, {"run.json": moved}, ignore_keys=("v",), locators=("ae.path", "init.path"))
    assert run.differences() == [] and run.changed_keys() == set()
    with run:
        assert run.resumed and (d / "part.npy").is_file()
    # the new place is recorded, the ignored record kept as found; the absent "init" stays absent
    assert json.loads((d / "run.json").read_text()) == {"x": 1, "ae": {"path": "/new/ae", "sha": "s1"}, "v": "1"}
    # what the locator points at is still compared through the keys beside it
    other = {"x": 1, "ae": {"path": "/new/ae", "sha": "s2"}}
    with pytest.raises(RunMismatchError, match=r"run\.json:ae\.sha\)"):
        RunFolder(d, {"run.json": other}, locators=("ae.path",)).start()
    # without the locator the path is part of the key
    with pytest.raises(RunMismatchError, match=r"run\.json:ae\.path\)"):
        RunFolder(d, {"run.json": {"x": 1, "ae": {"path": "/elsewhere", "sha": "s1"}}}, ignore_keys=("v",)).start()

def _fake_repo(root, head: str, *, loose=None, packed=None):
    git = root / ".git"
    git.mkdir(parents=True)
    (git / "HEAD").write_text(head + "\n")
    for ref, name in (loose or {}).items():
        (git / ref).parent.mkdir(parents=True, exist_ok=True)
        (git / ref).write_text(name + "\n")
    if packed:
        (git / "packed-refs").write_text("# pack-refs with: peeled fully-peeled sorted\n" + "".join(
            f"{name} {ref}\n^{'f' * 40}\n" for ref, name in packed.items()))
    return git


def test_git_commit_is_read_from_the_files(tmp_path, monkeypatch):
    import subprocess as sp

    from radarpc import runs
    from radarpc.runs import git_commit

    calls = []
    monkeypatch.setattr(runs.subprocess, "run", lambda *a, **k: calls.append((a, k)) or sp.CompletedProcess(a, 1, "", ""))
    a, b, c = "a" * 40, "b" * 40, "c" * 40
    _fake_repo(tmp_path / "loose", "ref: refs/heads/main", loose={"refs/heads/main": a})
    assert git_commit(tmp_path / "loose") == a
    _fake_repo(tmp_path / "packed", "ref: refs/heads/dev", packed={"refs/heads/main": a, "refs/heads/dev": b})
    assert git_commit(tmp_path / "packed") == b                 # the peeled "^..." line is not a ref
    _fake_repo(tmp_path / "detached", c)
    assert git_commit(tmp_path / "detached") == c
    # a linked work tree: .git is a file naming its git dir, whose commondir holds the branches
    main = _fake_repo(tmp_path / "main", "ref: refs/heads/main", loose={"refs/heads/main": a},
                      packed={"refs/heads/topic": b})
    wt_git = main / "worktrees" / "wt"
    wt_git.mkdir(parents=True)
    (wt_git / "HEAD").write_text("ref: refs/heads/topic\n")
    (wt_git / "commondir").write_text("../..\n")
    (tmp_path / "wt").mkdir()
    (tmp_path / "wt" / ".git").write_text(f"gitdir: {wt_git}\n")
    assert git_commit(tmp_path / "wt") == b
    assert calls == []                                          # all read without running git
    assert git_commit(tmp_path / "nothing") is None and calls == []
    # a HEAD the files do not resolve (an unborn branch, another ref format): git is asked, with
    # a timeout, and its failure gives None
    _fake_repo(tmp_path / "unborn", "ref: refs/heads/new")
    assert git_commit(tmp_path / "unborn") is None
    (args,), kwargs = calls[0]
    assert args[:3] == ["git", "-C", str(tmp_path / "unborn")] and kwargs["timeout"] == 5.0


def test_git_commit_never_fails_when_git_is_missing_or_hangs(tmp_path, monkeypatch):
    import subprocess as sp

    from radarpc import runs
    from radarpc.runs import git_commit

    _fake_repo(tmp_path / "r", "ref: refs/heads/new")

    def missing(*a, **k):
        raise FileNotFoundError("git")

    def hangs(*a, **k):
        raise sp.TimeoutExpired("git", k["timeout"])

    for fake in (missing, hangs):
        monkeypatch.setattr(runs.subprocess, "run", fake)
        assert git_commit(tmp_path / "r") is None
    monkeypatch.setattr(runs.subprocess, "run", lambda *a, **k: sp.CompletedProcess(a, 0, "d" * 40 + "\n", ""))
    assert git_commit(tmp_path / "r") == "d" * 40               # what git says when the files do not
    monkeypatch.setattr(runs.subprocess, "run", lambda *a, **k: sp.CompletedProcess(a, 0, "not a hash\n", ""))
    assert git_commit(tmp_path / "r") is None


def test_source_commit_is_the_checkouts_head():
    import shutil
    from pathlib import Path

    import radarpc
    from radarpc.runs import source_commit

    root = Path(radarpc.__file__).resolve().parents[2]          # ROOT/src/radarpc/__init__.py
    got = source_commit()
    if not (root / ".git").exists() or shutil.which("git") is None:
        # an installed package (no checkout), or no git to compare with: None or a commit name
        assert got is None or len(got) == 40
        return
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                          check=True, timeout=30).stdout.strip()
    assert got == head
