"""``radarpc models``: the registry as a user sees it."""
from __future__ import annotations

from radarpc.cli import main
from radarpc.models import MODELS, ModelSpec


def test_models_lists_every_variant_with_its_parameter_count(capsys):
    assert main(["models"]) == 0
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in capsys.readouterr().out.splitlines()[2:]}
    assert list(rows) == list(MODELS)
    for name in ("fftradnet-tiny", "pillars-tiny"):               # counted here on real weights
        n = sum(p.numel() for p in MODELS[name]().parameters())
        assert rows[name][2] == f"{n:,}"
        assert rows[name][1] == ModelSpec(name).input_kind
    assert rows["fftradnet"][2] == "3,789,940"                      # the official FFTRadNet's count
    assert "``" not in "".join(" ".join(r) for r in rows.values())  # plain text


def test_train_model_choice_is_a_registry_name(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["train", "cfg.yaml", "--data", "x", "--out", "y", "--model", "resnet50"])
    assert "invalid choice: 'resnet50'" in capsys.readouterr().err


def test_a_closed_pipe_ends_quietly():
    """``radarpc models | head -1``: no BrokenPipeError traceback, the conventional exit 141."""
    import subprocess
    import sys

    # unbuffered: the header line arrives at once, the rows only after the models are built
    with subprocess.Popen([sys.executable, "-u", "-m", "radarpc", "models"], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, bufsize=0) as p:
        p.stdout.read(10)
        p.stdout.close()                             # the reader goes away before the table is written
        err = p.stderr.read().decode()
        code = p.wait(timeout=120)
    assert code == 141
    assert "Traceback" not in err and "BrokenPipeError" not in err


def test_a_full_disk_is_one_line(monkeypatch, capsys):
    """What the machine refuses (here a full disk while writing a checkpoint) ends in one line
    naming the file, with exit 1, not a traceback."""
    import errno

    from radarpc.cli import models

    def full(args):
        raise OSError(errno.ENOSPC, "No space left on device", "runs/x/checkpoints/last.safetensors")

    monkeypatch.setattr(models, "run", full)
    assert main(["models"]) == 1
    err = capsys.readouterr().err
    assert err == "radarpc models: error: No space left on device (runs/x/checkpoints/last.safetensors)\n"
