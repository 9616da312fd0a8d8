"""Comparing a training mode's gradients with the reference's, on hand-worked tensors."""
import pytest
import torch

from radarpc.training.gradients import compare_gradients


def test_compares_weight_tensors_only():
    ref = {"conv.weight": torch.tensor([[3.0, 4.0]]), "conv.bias": torch.tensor([1.0]),
           "other.weight": torch.tensor([[1.0, 0.0]]), "frozen.weight": torch.zeros(1, 2),
           "absent.weight": torch.ones(2, 2)}
    g = {"conv.weight": torch.tensor([[6.0, 8.0]]),      # twice the reference: cosine 1, error 1
         "conv.bias": torch.tensor([-5.0]),             # 1-D: left out
         "other.weight": torch.tensor([[0.0, 1.0]]),    # orthogonal: cosine 0, error sqrt(2)
         "frozen.weight": torch.ones(1, 2)}             # zero reference: left out; absent: left out
    out = compare_gradients(g, ref)
    assert out["weights_compared"] == 2
    assert out["median_relative_error"] == pytest.approx((1 + 2 ** 0.5) / 2)
    assert out["median_cosine"] == pytest.approx(0.5)
    assert [r["parameter"] for r in out["lowest_cosines"]] == ["other.weight", "conv.weight"]
    low, high = out["lowest_cosines"]
    assert low["cosine"] == pytest.approx(0.0, abs=1e-7) and low["relative_error"] == pytest.approx(2 ** 0.5)
    assert low["norm_ratio"] == pytest.approx(1.0)
    assert high["cosine"] == pytest.approx(1.0) and high["norm_ratio"] == pytest.approx(2.0)
    assert high["relative_error"] == pytest.approx(1.0)
    assert [r["parameter"] for r in compare_gradients(g, ref, lowest=1)["lowest_cosines"]] == ["other.weight"]


def test_refuses_what_it_cannot_compare():
    with pytest.raises(ValueError, match="no weight tensor"):
        compare_gradients({"b": torch.ones(2)}, {"b": torch.ones(2)})
    with pytest.raises(ValueError, match="'w'.*shape"):
        compare_gradients({"w": torch.ones(2, 3)}, {"w": torch.ones(3, 2)})
    with pytest.raises(ValueError, match="lowest"):
        compare_gradients({}, {}, lowest=0)
