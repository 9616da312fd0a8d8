"""Methods side by side (radarpc.eval.comparison): the per-scene table and the figure's projections."""
from __future__ import annotations

import numpy as np
import pytest

from radarpc.eval.comparison import (angle_edges_deg, cloud_view, comparison_dict, comparison_markdown,
                                     comparison_view, range_edges)
from radarpc.eval.pointsets import FrameMetrics, PointSetReport, SceneSummary


def _report(cds: dict[str, list[float]]) -> PointSetReport:
    frames = [FrameMetrics(f"{s}_run0", k, s, cd, 2 * cd, 10, 20, 10, 20) for s, v in cds.items()
              for k, cd in enumerate(v)]
    scenes = [SceneSummary.of(s, [f for f in frames if f.scene == s]) for s in sorted(cds)]
    return PointSetReport(frames, scenes, SceneSummary.of("all", frames), emd_points=64)


def test_table_has_one_column_group_per_method():
    a = _report({"lab": [0.1, 0.3], "hall": [0.5]})
    b = _report({"lab": [1.0, 2.0], "hall": [4.0]})
    md = comparison_markdown({"rald": a, "os-cfar": b})
    lines = md.splitlines()
    assert lines[0] == ("| scene | frames | rald: CD mean | rald: CD median | rald: EMD mean | rald: EMD median | "
                        "os-cfar: CD mean | os-cfar: CD median | os-cfar: EMD mean | os-cfar: EMD median |")
    assert lines[2] == "| hall | 1 | 0.500 | 0.500 | 1.000 | 1.000 | 4.000 | 4.000 | 8.000 | 8.000 |"
    assert lines[3] == "| lab | 2 | 0.200 | 0.200 | 0.400 | 0.400 | 1.500 | 1.500 | 3.000 | 3.000 |"
    assert lines[4] == "| **all** | 3 | 0.300 | 0.300 | 0.600 | 0.600 | 2.333 | 2.000 | 4.667 | 4.000 |"
    assert "min(64, |cloud|)" in md
    # a scene one method lacks shows dashes, and the frame counts of both
    c = _report({"lab": [1.0, 2.0]})
    row = [ln for ln in comparison_markdown({"rald": a, "x": c}).splitlines() if ln.startswith("| hall")][0]
    assert row == "| hall | 1/0 | 0.500 | 0.500 | 1.000 | 1.000 | - | - | - | - |"
    d = comparison_dict({"rald": a}, {"rald": "preds/rald"})
    assert d["methods"][0]["folder"] == "preds/rald" and d["methods"][0]["overall"]["chamfer_mean"] == pytest.approx(0.3)


def test_bin_edges():
    # sine-spaced bins: edges at the midpoints in sine, the outer ones half a step beyond (clipped)
    e = angle_edges_deg([-30.0, 0.0, 30.0])
    np.testing.assert_allclose(np.sin(np.radians(e)), [-0.75, -0.25, 0.25, 0.75])
    np.testing.assert_allclose(angle_edges_deg([-80.0, 0.0]), [-90.0, np.degrees(np.arcsin(-np.sin(np.radians(80)) / 2)),
                                                               np.degrees(np.arcsin(np.sin(np.radians(80)) / 2))])
    np.testing.assert_allclose(range_edges([0.0, 0.5, 1.0]), [-0.25, 0.25, 0.75, 1.25])


def test_cloud_projections_by_hand():
    c = cloud_view("m", [[3.0, 4.0, 0.0], [0.0, 0.0, 2.0], [1.0, 0.0, -1.0]])
    np.testing.assert_allclose(c.xy, [[3, 4], [0, 0], [1, 0]])
    np.testing.assert_allclose(c.range_elevation, [[5, 0], [2, 90], [np.sqrt(2), -45]])
    assert (c.n_points, c.n_drawn) == (3, 3)
    empty = cloud_view("e", np.zeros((0, 3)))
    assert empty.n_points == 0 and empty.xy.shape == (0, 2)
    pts = np.arange(30, dtype=np.float64).reshape(10, 3) + 1
    sub = cloud_view("s", pts, max_points=4, seed=1)
    assert (sub.n_points, sub.n_drawn) == (10, 4)
    assert all(any(np.allclose(row, p[:2]) for p in pts) for row in sub.xy)          # a subset of the points


def test_comparison_view_projects_the_cube():
    x = np.zeros((2, 3, 2))
    x[0, 2, 1] = 5.0          # range 0, azimuth bin 2, elevation bin 1
    x[1, 0, 0] = 7.0
    az = np.array([30.0, 0.0, -30.0])                                   # descending: drawn ascending
    v = comparison_view(x, [1.0, 2.0], az, [-10.0, 10.0], np.ones((4, 3)), {"a": np.ones((2, 3)), "b": np.zeros((0, 3))},
                        run="r_run0", scene="r", frame=3, lidar_index=4, notes={"a": "CD 1 m"})
    # max over elevation, azimuth ascending: bin 2 (-30 deg) first
    np.testing.assert_array_equal(v.bev_db, [[5.0, 0.0, 0.0], [0.0, 0.0, 7.0]])
    np.testing.assert_array_equal(v.re_db, [[0.0, 5.0], [7.0, 0.0]])                 # max over azimuth
    np.testing.assert_allclose(v.re_range, [0.5, 1.5, 2.5])
    edges = np.radians(angle_edges_deg([-30.0, 0.0, 30.0]))
    np.testing.assert_allclose(v.bev_x, np.outer([0.5, 1.5, 2.5], np.cos(edges)))
    np.testing.assert_allclose(v.bev_y, np.outer([0.5, 1.5, 2.5], np.sin(edges)))
    assert [m.name for m in v.methods] == ["a", "b"] and v.methods[0].note == "CD 1 m" and v.methods[1].n_points == 0
    assert v.truth.name == "LiDAR truth" and v.truth.n_points == 4
    with pytest.raises(ValueError, match="must be"):
        comparison_view(x[:, :2], [1.0, 2.0], az, [-10.0, 10.0], np.ones((4, 3)), {"a": np.ones((2, 3))},
                        run="r", scene="r", frame=0, lidar_index=0)
