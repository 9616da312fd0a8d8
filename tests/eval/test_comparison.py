"""Methods side by side (radarpc.eval.comparison): the per-scene table and the figure's projections."""
from __future__ import annotations

import numpy as np
import pytest

from radarpc.eval.comparison import (angle_edges_deg, cdf_panels, cloud_view, common_scored_frames, comparison_dict,
                                     comparison_markdown, comparison_view, empirical_cdf, range_edges)
from radarpc.eval.pointsets import FrameMetrics, PointSetReport, summarize_frames


def _report(cds: dict[str, list[float | None]]) -> PointSetReport:
    """Frames of run ``{scene}_run0``; a None score is an empty prediction; EMD = 2 CD, EMD_equal = 3 CD."""
    frames = [FrameMetrics(f"{s}_run0", k, s, cd, None if cd is None else 2 * cd, 0 if cd is None else 10, 20,
                           0 if cd is None else 10, 20, emd_equal=None if cd is None else 3 * cd)
              for s, v in cds.items() for k, cd in enumerate(v)]
    scenes, overall = summarize_frames(frames)
    return PointSetReport(frames, scenes, overall, emd_points=64)


def test_table_has_a_row_per_scene_and_method():
    a = _report({"lab": [0.1, 0.3], "hall": [0.5]})
    b = _report({"lab": [1.0, 2.0], "hall": [4.0]})
    md = comparison_markdown({"rald": a, "os-cfar": b})
    lines = md.splitlines()
    assert lines[0] == ("| scene | method | frames | empty | CD mean | CD median | EMD mean | EMD median | "
                        "EMD_equal mean | EMD_equal median |")
    assert lines[2] == "| hall | rald | 1 | 0 | 0.500 | 0.500 | 1.000 | 1.000 | 1.500 | 1.500 |"
    assert lines[3] == "| hall | os-cfar | 1 | 0 | 4.000 | 4.000 | 8.000 | 8.000 | 12.000 | 12.000 |"
    assert lines[4] == "| lab | rald | 2 | 0 | 0.200 | 0.200 | 0.400 | 0.400 | 0.600 | 0.600 |"
    assert lines[7] == "| **all** | os-cfar | 3 | 0 | 2.333 | 2.000 | 4.667 | 4.000 | 7.000 | 6.000 |"
    assert "min(64, |gt|)" in md and "EMD_equal" in md and "differ in which frames" not in md
    # a scene one method lacks shows 0 frames and dashes
    c = _report({"lab": [1.0, 2.0]})
    row = [ln for ln in comparison_markdown({"rald": a, "x": c}).splitlines() if ln.startswith("| hall | x")][0]
    assert row == "| hall | x | 0 | - | - | - | - | - | - | - |"
    d = comparison_dict({"rald": a}, {"rald": "preds/rald"})
    assert d["methods"][0]["folder"] == "preds/rald" and d["methods"][0]["overall"]["chamfer_mean"] == pytest.approx(0.3)
    assert d["common_scored"] is None


def test_empty_predictions_are_counted_and_compared_over_the_frames_all_scored():
    # rald fails (empty) on the hard lab frame 1, where os-cfar scores 3.0
    a = _report({"lab": [0.1, None, 0.3]})
    b = _report({"lab": [1.0, 3.0, 2.0]})
    assert common_scored_frames({"rald": a, "os-cfar": b}) == {("lab_run0", 0), ("lab_run0", 2)}
    assert common_scored_frames({"rald": a, "again": a}) is None
    md = comparison_markdown({"rald": a, "os-cfar": b})
    lines = md.splitlines()
    assert "| lab | rald | 3 | 1 | 0.200 | 0.200 |" in lines[2]
    assert "| lab | os-cfar | 3 | 0 | 2.000 | 2.000 |" in lines[3]
    k = lines.index("The methods differ in which frames they scored (an empty prediction is counted, not scored). "
                    "Over the 2 frames every method scored:")
    assert lines[k + 2] == ("| scene | method | frames | CD mean | CD median | EMD mean | EMD median | EMD_equal mean | "
                            "EMD_equal median |")
    assert lines[k + 4] == "| lab | rald | 2 | 0.200 | 0.200 | 0.400 | 0.400 | 0.600 | 0.600 |"
    assert lines[k + 5] == "| lab | os-cfar | 2 | 1.500 | 1.500 | 3.000 | 3.000 | 4.500 | 4.500 |"
    d = comparison_dict({"rald": a, "os-cfar": b})
    assert d["methods"][0]["overall"]["empty"] == 1 and d["common_scored"]["n_frames"] == 2
    assert d["common_scored"]["methods"][1]["overall"]["chamfer_mean"] == pytest.approx(1.5)
    # no frame scored by all
    none = comparison_markdown({"a": _report({"lab": [None, 1.0]}), "b": _report({"lab": [1.0, None]})})
    assert "Over the 0 frames every method scored" in none and "(no frame was scored by every method)" in none


def test_empirical_cdf_by_hand():
    x, p = empirical_cdf([0.3, 0.1, 0.3, 0.7])
    np.testing.assert_array_equal(x, [0.1, 0.3, 0.7])
    np.testing.assert_array_equal(p, [0.25, 0.75, 1.0])
    # an unscored frame (NaN) counts in the denominator and is never reached
    x, p = empirical_cdf([0.2, float("nan"), 0.4, float("inf"), 0.2])
    np.testing.assert_array_equal(x, [0.2, 0.4])
    np.testing.assert_array_equal(p, [0.4, 0.6])
    x, p = empirical_cdf([float("nan")])
    assert x.size == 0 and p.size == 0
    with pytest.raises(ValueError, match="at least one"):
        empirical_cdf([])


def test_cdf_panels_per_scene_and_all():
    a = _report({"lab": [0.1, None], "hall": [0.5]})
    b = _report({"lab": [1.0, 2.0], "hall": [4.0]})
    panels = cdf_panels({"rald": a, "os-cfar": b}, "chamfer")
    assert [p.title for p in panels] == ["scene hall", "scene lab", "all scenes"]
    lab = panels[1]
    assert [c.label for c in lab.curves] == ["rald", "os-cfar"]
    np.testing.assert_array_equal(lab.curves[0].x, [0.1])
    np.testing.assert_array_equal(lab.curves[0].p, [0.5])            # the empty frame is never reached
    assert (lab.curves[0].n_frames, lab.curves[0].n_empty) == (2, 1)
    everything = panels[2].curves[1]
    np.testing.assert_allclose(everything.x, [1.0, 2.0, 4.0])
    np.testing.assert_allclose(everything.p, [1 / 3, 2 / 3, 1.0])
    np.testing.assert_allclose(cdf_panels({"b": b}, "emd_equal")[1].curves[0].x, [3.0, 6.0])
    assert [p.title for p in cdf_panels({"a": _report({"lab": [1.0]})}, "emd")] == ["scene lab"]   # one scene: no "all"
    with pytest.raises(ValueError, match="metric must be"):
        cdf_panels({"a": a}, "cd")


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
