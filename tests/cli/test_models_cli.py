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
