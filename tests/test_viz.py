"""Tests of :mod:`radarpc.viz`: each figure at tiny size, from the inputs its callers compute."""
from __future__ import annotations

import matplotlib.colors
import numpy as np
import pytest
import torch
from PIL import Image

from radarpc import viz
from radarpc.data.radial import RADIal, read_labels
from radarpc.data.summary import ColoRadarView, first_rd_power_db, summarize_radial
from radarpc.dsp.sparse_rd import encoded_cells
from radarpc.pipelines.frames import frame_view
from radarpc.pipelines.pointclouds import ConvertSettings
from radarpc.sensors.coloradar import AWR1843_FOV
from radarpc.sensors.radial import TINY


@pytest.fixture
def root(tiny_city_root):
    # the session's 3 sequences (train, val, test) x 3 frames of the TINY sensor, city scenes (vehicles in view)
    return tiny_city_root


@pytest.fixture
def figures(monkeypatch):
    """The figures the viz functions save, in order."""
    saved = []
    save = viz.save_figure

    def keep(fig, out, *args, **kwargs):
        saved.append(fig)
        return save(fig, out, *args, **kwargs)

    monkeypatch.setattr(viz, "save_figure", keep)
    return saved


def _png_size(path) -> tuple[int, int]:
    with Image.open(path) as im:
        assert im.format == "PNG"
        assert np.asarray(im.convert("L")).std() > 10          # not a blank canvas
        return im.size


def test_frame_view_and_figure(root, tmp_path, figures):
    settings = ConvertSettings(density=0.1, enrich=("rd3",))
    labels = read_labels(root / "labels.csv")
    fr = int(labels.num_sample[labels.has_vehicle][0])                    # a frame with vehicles
    view = frame_view(root, fr, settings)
    assert view.set_name == "S*(tau)" and view.frame == fr
    assert view.rd_magnitude.shape == view.encoded.shape == (TINY.n_range, TINY.n_doppler)
    assert view.envelope.shape == view.peaks.shape == (TINY.n_range, TINY.slot_width)
    assert torch.equal(torch.from_numpy(view.encoded), encoded_cells(view.cloud, TINY))
    out = tmp_path / "f.png"
    res = viz.plot_frame_view(view, out, color_by="amplitude")
    assert res.path == out and _png_size(out) == (18 * 80, 7 * 80)
    fig = figures[-1]
    assert len(fig.axes) == 6                                             # 3 panels + 3 colour bars
    assert [a.get_label() for a in fig.axes[3:]] == ["<colorbar>"] * 3
    # the suptitle names the root, the frame and its sequence; tau carries its unit
    ds = RADIal(root, split="all")
    seq = ds.sequences[ds.index_of(fr)]
    assert fig._suptitle.get_text().startswith(f"RADIal root '{root.name}': frame {fr} (numSample), sequence {seq}")
    tau = float(view.cloud.tau[0])
    assert f"(linear SNR, {10 * np.log10(tau):.2f} dB)" in fig.axes[2].get_title()
    # Doppler in m/s on the RD panels, bins on a secondary (top) axis
    assert "[m/s]" in fig.axes[0].get_xlabel() and "[m/s]" in fig.axes[1].get_xlabel()
    assert [c.get_xlabel() for a in fig.axes[:2] for c in a.child_axes] == ["Doppler bin d of the cube",
                                                                            "consolidated Doppler bin l"]
    # one RADIal box (4 m x 1.8 m, near edge centred on the label) per labelled vehicle
    polys = [pa for pa in fig.axes[2].patches]
    assert len(polys) == len(view.vehicles_ra) > 0
    want = viz.radial_box_corners(view.vehicles_ra[:, 0], view.vehicles_ra[:, 1])
    for pa, w in zip(polys, want):
        np.testing.assert_allclose(pa.get_xy()[:4], w[:, ::-1], atol=1e-9)      # drawn as (y, x)
    lo, hi = fig.axes[2].get_ylim()
    assert lo == 0.0 and hi >= float(want[..., 0].max())
    half = fig.axes[2].get_xlim()[0]                                      # left (+y) drawn on the left
    assert fig.axes[2].get_xlim()[1] == -half
    assert min(float(np.abs(want[..., 1]).max()), TINY.max_range_m) <= half <= TINY.max_range_m
    assert not list(tmp_path.glob(".*.tmp"))                              # atomic write left no temp file
    assert res.n_points == view.cloud.num_points and res.n_peaks == int(view.peaks.sum())
    assert res.n_vehicles == len(view.vehicles_ra)
    assert res.peak_density == pytest.approx(res.n_peaks * TINY.n_tx / (TINY.n_range * TINY.n_doppler))
    assert res.density == pytest.approx(view.encoded.sum() / (TINY.n_range * TINY.n_doppler), rel=1e-6)
    with pytest.raises(ValueError, match="color_by must be one of"):
        viz.plot_frame_view(view, out, color_by="snr")
    with pytest.raises(ValueError, match="give exactly one of settings"):
        frame_view(root, 1)


def test_geometry_of_the_rd_panels():
    # the RD image rows and the peak markers agree: row r is centred on r * range_res_m
    x0, x1, y0, y1 = viz.rd_extent(TINY, TINY.n_doppler)
    r = np.arange(TINY.n_range)
    np.testing.assert_allclose(y0 + (r + 0.5) * (y1 - y0) / TINY.n_range, viz.peak_marker_range_m(TINY, r),
                               atol=1e-9)
    # columns in m/s, Doppler-centred: the fftshifted column j sits on the velocity of its cube bin
    dv, n = TINY.velocity_res_mps, TINY.n_doppler
    np.testing.assert_allclose((x0, x1), ((-n / 2 - 0.5) * dv, (n / 2 - 0.5) * dv))
    d = np.arange(n)
    shifted = np.fft.fftshift(d)                                           # cube bin drawn in column j
    centres = x0 + (np.arange(n) + 0.5) * (x1 - x0) / n
    np.testing.assert_allclose(centres, TINY.velocity_of_bin(shifted), atol=1e-9)
    np.testing.assert_allclose(viz.doppler_mps_of_column(TINY, d, n), TINY.velocity_of_bin(d), atol=1e-12)
    w = TINY.slot_width
    xw0, xw1, _, _ = viz.rd_extent(TINY, w)
    cw = xw0 + (np.arange(w) + 0.5) * (xw1 - xw0) / w
    np.testing.assert_allclose(cw, viz.doppler_mps_of_column(TINY, np.fft.fftshift(np.arange(w)), w), atol=1e-9)


def test_radial_box_corners_follow_radials_metrics():
    # label R = 10 m, A = 30 deg: (X, Y) = (8.6603, 5.0); RADIal's RA_to_cartesian_box gives
    # lateral [Y - 0.9, Y + 0.9], forward [X, X + 4], corners near right, near left, far left, far right
    c = viz.radial_box_corners([10.0, 20.0], [30.0, -90.0])
    x, y = 10 * np.sqrt(3) / 2, 5.0
    np.testing.assert_allclose(c[0], [[x, y - 0.9], [x, y + 0.9], [x + 4, y + 0.9], [x + 4, y - 0.9]], atol=1e-12)
    np.testing.assert_allclose(c[1], [[0, -20.9], [0, -19.1], [4, -19.1], [4, -20.9]], atol=1e-12)
    assert viz.radial_box_corners([], []).shape == (0, 4, 2)


def test_plot_radial_info(root, tmp_path, figures):
    labels = read_labels(root / "labels.csv")
    summary = summarize_radial(root, labels)
    rd = first_rd_power_db(root, labels, TINY)
    out = viz.plot_radial_info(summary, labels, tmp_path / "a" / "info.png", rd)
    assert _png_size(out) == (11 * 90, 8 * 90) and len(figures[-1].axes) == 5     # 4 panels + colour bar
    assert figures[-1].axes[3].get_title() == f"RD envelope, frame {rd[0]}"
    viz.plot_radial_info(summary, labels, tmp_path / "b.png")                      # no readable cube
    assert len(figures[-1].axes) == 4 and not figures[-1].axes[3].axison
    assert not list(tmp_path.rglob(".*.tmp"))


def _colo_view(heatmap: bool, cube: bool) -> ColoRadarView:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-20, 20, size=(500, 3))
    keep = (np.linalg.norm(pts, axis=1) < AWR1843_FOV.max_range_m) & (pts[:, 0] > 0)
    return ColoRadarView(
        run="lab_run0", lidar_index=2, radar_index=1, fov=AWR1843_FOV, lidar_xyz=pts, inside_xyz=pts[keep],
        cube_db=rng.normal(size=(16, 4)) if cube else None, cube_range_m=np.arange(16) * 0.12 if cube else None,
        cube_azimuth_deg=np.array([-45.0, -15.0, 15.0, 45.0]) if cube else None,
        heatmap_db=rng.normal(size=(6, 16)) if heatmap else None,
        heatmap_azimuth_deg=np.linspace(-60, 60, 6) if heatmap else None,
        heatmap_max_range_m=8.0 if heatmap else None)


def _legend_matches_scatters(ax) -> None:
    """Every legend entry of a scatter has the scatter's colour."""
    from matplotlib.collections import PathCollection
    from matplotlib.colors import to_rgba

    leg = ax.get_legend()
    scatters = {c.get_label(): c for c in ax.collections if isinstance(c, PathCollection)}
    checked = 0
    for h, t in zip(leg.legend_handles, leg.get_texts()):
        if t.get_text() in scatters:
            want = scatters[t.get_text()].get_facecolor()
            assert len(want) == 1                                      # one colour per scatter
            np.testing.assert_allclose(h.get_facecolor()[0], want[0])
            checked += 1
    assert checked == len(scatters) >= 2
    assert to_rgba(viz.LIDAR_INSIDE_COLOR) != to_rgba(viz.LIDAR_OUTSIDE_COLOR)


@pytest.mark.parametrize("heatmap,cube", [(True, True), (False, True), (False, False)])
def test_plot_coloradar_info(tmp_path, figures, heatmap, cube):
    out = viz.plot_coloradar_info(_colo_view(heatmap, cube), tmp_path / "c.png")
    n = 3 if heatmap else 2
    fig = figures[-1]
    # one colour bar per dB heatmap
    assert _png_size(out) == (6 * n * 110, 5 * 110) and len(fig.axes) == n + int(heatmap) + int(cube)
    assert [a.get_label() for a in fig.axes[n:]] == ["<colorbar>"] * (int(heatmap) + int(cube))
    assert fig.axes[0].get_title().startswith("lab_run0 LiDAR 2:")
    assert bool(fig.axes[1].collections) == cube
    _legend_matches_scatters(fig.axes[0])
    assert not list(tmp_path.glob(".*.tmp"))


def test_plot_coloradar_view_with_prediction(tmp_path, figures):
    import dataclasses

    rng = np.random.default_rng(1)
    view = dataclasses.replace(_colo_view(False, True), root_name="sim", pred_xyz=rng.uniform(0, 5, (30, 3)),
                               pred_label="os-cfar (preds)")
    viz.plot_coloradar_view(view, tmp_path / "v.png")
    fig = figures[-1]
    assert _png_size(tmp_path / "v.png") == (1800, 600) and len(fig.axes) == 4     # 3 panels + colour bar
    assert fig.axes[3].get_label() == "<colorbar>"
    _legend_matches_scatters(fig.axes[1])
    _legend_matches_scatters(fig.axes[2])
    assert any("prediction (30): os-cfar (preds)" == t.get_text() for t in fig.axes[1].get_legend().get_texts())
    assert fig._suptitle.get_text().startswith("ColoRadar root 'sim', run lab_run0: radar frame 1")
    # the cube is drawn on its true azimuth bins: edges between the sin-spaced centres
    edges = viz.angle_edges_deg(np.array([-45.0, -15.0, 15.0, 45.0]))
    assert np.all(np.diff(edges) > 0) and np.allclose(edges[1:-1], np.degrees(np.arcsin(
        0.5 * (np.sin(np.radians([-45.0, -15.0, 15.0])) + np.sin(np.radians([-15.0, 15.0, 45.0]))))))
    with pytest.raises(ValueError, match="no single-chip radar frame"):
        viz.plot_coloradar_view(_colo_view(False, False), tmp_path / "w.png")


def _tuning_json(path, rows):
    import json

    cands = [{"config": {"window": list(w), "guard": [3, 1, 1], "rank": 0.75, "tau_db": t, "angle_bins": None},
              "chamfer_m": cd, "points_per_frame": n} for w, t, cd, n in rows]
    path.write_text(json.dumps({"split": "val", "frames": 4, "best": cands[0]["config"],
                                "best_chamfer_m": 0.0, "candidates": cands}))
    return path


def test_plot_oscfar_tuning(tmp_path, figures):
    from radarpc.data.summary import read_tuning
    from radarpc.io import DataFileError

    rows = [((9, 3, 3), 4.0, 1.5, 300.0), ((9, 3, 3), 8.0, 1.2, 120.0), ((9, 3, 3), 12.0, 1.4, 40.0),
            ((13, 5, 3), 4.0, 1.6, 280.0), ((13, 5, 3), 8.0, 1.1, 100.0), ((13, 5, 3), 12.0, 1.3, 30.0)]
    table = read_tuning(_tuning_json(tmp_path / "tuning.json", rows))
    assert table.best == 4 and table.setting[4] == "window 13x5x3, guard 3x1x1, rank 0.75"
    assert read_tuning(tmp_path).best == 4                                   # the folder holding it
    out = viz.plot_oscfar_tuning(table, tmp_path / "t.png")
    fig = figures[-1]
    assert _png_size(out) == (1300, 500) and len(fig.axes) == 3               # 2 panels + colour bar
    chosen = [ln for ln in fig.axes[0].lines if ln.get_label().startswith("chosen")]
    assert len(chosen) == 1
    np.testing.assert_allclose(chosen[0].get_xydata(), [[4.0, 1.6], [8.0, 1.1], [12.0, 1.3]])
    (tmp_path / "bad").mkdir()
    with pytest.raises(DataFileError, match="tuning file is missing"):
        read_tuning(tmp_path / "bad")
    (tmp_path / "bad" / "tuning.json").write_text('{"split": "val"}')
    with pytest.raises(DataFileError, match="is not an OS-CFAR tuning file"):
        read_tuning(tmp_path / "bad")


def test_no_pyplot_state(root, tmp_path):
    import matplotlib
    import matplotlib.pyplot as plt

    backend = matplotlib.get_backend()
    open_before = plt.get_fignums()
    viz.plot_coloradar_info(_colo_view(True, True), tmp_path / "c.png")
    assert plt.get_fignums() == open_before and matplotlib.get_backend() == backend


def test_plot_learning_curves_against_time_or_steps(tmp_path, figures):
    log = tmp_path / "log.csv"
    log.write_text("epoch,step,train_time_s,train_loss,val_f1,val_f1_fixed\n"
                   "0,10,60.0,5.0,0.1,0.05\n1,20,90.0,3.0,0.2,0.1\n")
    for against, x in (("time", [1.0, 2.5]), ("step", [10, 20])):          # minutes: 60 s, then 60 + 90 s
        out = viz.plot_learning_curves({"run": log}, tmp_path / f"{against}.png", against=against)
        assert out.stat().st_size > 1000
        ax_f1 = figures[-1].axes[0]
        np.testing.assert_allclose(ax_f1.lines[0].get_xdata(), x)
        np.testing.assert_allclose(ax_f1.lines[0].get_ydata(), [0.1, 0.2])
    with pytest.raises(ValueError, match="against must be 'time' or 'step'"):
        viz.plot_learning_curves({"run": log}, tmp_path / "x.png", against="epoch")


def test_plot_label_outcomes_bars_are_the_reports_shares(tmp_path, figures):
    # 10 labels over 4 frames; at the two thresholds 6 and 3 matched (fn 4, 7), of the misses 3 and 2
    # with a detection within 3 m; 8 and 2 false alarms
    metrics = {"thresholds": [0.1, 0.2], "fn": [4, 7], "fn_near": [3, 2], "fp": [8, 2], "n_labels": 10,
               "n_frames": 4}
    viz.plot_label_outcomes(metrics, tmp_path / "labels.png")
    ax, ax_fp = figures[-1].axes
    heights = [p.get_height() for p in ax.patches]           # matched, near, nothing near; 2 bars each
    np.testing.assert_allclose(heights, [0.6, 0.3, 0.3, 0.2, 0.1, 0.5])
    np.testing.assert_allclose([p.get_height() for p in ax_fp.patches], [2.0, 0.5])


def test_plot_label_outcomes_without_labels_draws_no_share(tmp_path, figures):
    # a split without labels once showed "the 0 labels" 100 % matched (n_labels clamped to 1)
    metrics = {"thresholds": [0.1, 0.2], "fn": [0, 0], "fn_near": [0, 0], "fp": [3, 1], "n_labels": 0,
               "n_frames": 2}
    viz.plot_label_outcomes(metrics, tmp_path / "labels.png")
    ax, ax_fp = figures[-1].axes
    assert len(ax.patches) == 0 and ax.get_title() == "no labels"
    assert "no labels in these frames" in ax.texts[0].get_text()
    np.testing.assert_allclose([p.get_height() for p in ax_fp.patches], [1.5, 0.5])


def test_plot_cloud_comparison_draws_the_cube_the_truth_and_each_method(tmp_path, figures):
    from radarpc.eval.comparison import comparison_view

    rng = np.random.default_rng(0)
    cube = rng.uniform(0, 30, size=(16, 8, 2))
    truth = rng.uniform(-5, 5, size=(300, 3)) + [7, 0, 0]
    clouds = {"rald": truth[:200] + 0.1, "os-cfar": truth[:20], "empty": np.zeros((0, 3))}
    view = comparison_view(cube, np.arange(16) * 1.0, np.linspace(-60, 60, 8), [-70.0, 0.0], truth, clouds,
                           run="lab_run2", scene="lab", frame=1, lidar_index=2, split="test",
                           notes={"rald": "CD 0.100 m"}, max_points=100)
    out = viz.plot_cloud_comparison(view, tmp_path / "lab.png")
    assert out == tmp_path / "lab.png" and _png_size(out) == (int(4.2 * 5 * 100), 840)
    fig = figures[-1]
    panels = [a for a in fig.axes if a.get_label() != "<colorbar>"]
    assert len(panels) == 10 and sum(a.get_label() == "<colorbar>" for a in fig.axes) == 2
    titles = [a.get_title() for a in panels[:5]]
    assert titles == ["radar cube (single chip)", "LiDAR truth (in the frustum)", "rald (CD 0.100 m)", "os-cfar", "empty"]
    texts = [t.get_text() for t in panels[2].get_legend().get_texts()]
    assert "rald: 200 points, 100 drawn" in texts and "LiDAR truth" in texts
    assert "empty: no point (empty)" in [t.get_text() for t in panels[4].get_legend().get_texts()]
    for ax in panels[2:5] + panels[7:]:                          # a method over the truth: two scatters
        _legend_matches_scatters(ax)
    # the truth panel draws the subset's bird's-eye (y, x) and range-elevation coordinates
    np.testing.assert_allclose(panels[1].collections[0].get_offsets(), view.truth.xy[:, ::-1])
    np.testing.assert_allclose(panels[6].collections[0].get_offsets(), view.truth.range_elevation)
    assert fig._suptitle.get_text().startswith("scene lab (test split): run lab_run2, radar frame 1, LiDAR scan 2")


def test_plot_cdfs_draws_a_step_curve_per_method_and_panel(tmp_path, monkeypatch):
    from radarpc.eval.comparison import CDFCurve, CDFPanel

    saved = []
    save = viz.save_figure
    monkeypatch.setattr(viz, "save_figure", lambda fig, out, dpi, metadata=None: (saved.append(fig),
                                                                                   save(fig, out, dpi, metadata)))
    full = CDFCurve("os-cfar", np.array([1.0, 2.0]), np.array([0.5, 1.0]), 2, 0)
    part = CDFCurve("rald", np.array([0.25]), np.array([0.5]), 2, 1)
    nothing = CDFCurve("rald", np.zeros(0), np.zeros(0), 1, 1)
    panels = [CDFPanel("scene lab", (part, full)), CDFPanel("all scenes", (nothing, full))]
    out = viz.plot_cdfs(panels, tmp_path / "f" / "cdf.png", title="CDF of the per-frame Chamfer distance",
                        xlabel="Chamfer distance [m]", footer="made by a test")
    assert out == tmp_path / "f" / "cdf.png" and _png_size(out) == (int(6.4 * 2 * 110), int(4.8 * 110))
    ax0, ax1 = saved[-1].axes
    assert ax0.get_title() == "scene lab" and ax0.get_xlabel() == "Chamfer distance [m]"
    assert ax0.get_ylabel().startswith("fraction of frames")
    assert [t.get_text() for t in ax0.get_legend().get_texts()] == ["rald (2 frames, 1 empty)", "os-cfar (2 frames)"]
    # the steps: from 0 up at each score, held to the panel's largest score; rald ends at its scored half
    r, o = ax0.get_lines()
    np.testing.assert_array_equal(r.get_xdata(), [0.25, 0.25, 2.0])
    np.testing.assert_array_equal(r.get_ydata(), [0.0, 0.5, 0.5])
    np.testing.assert_array_equal(o.get_xdata(), [1.0, 1.0, 2.0, 2.0])
    np.testing.assert_array_equal(o.get_ydata(), [0.0, 0.5, 1.0, 1.0])
    assert r.get_color() == ax1.get_lines()[0].get_color() != o.get_color()        # a colour per method
    np.testing.assert_array_equal(ax1.get_lines()[0].get_ydata(), [0.0, 0.0])       # nothing scored: flat at 0
    with pytest.raises(ValueError, match="no panel"):
        viz.plot_cdfs([], tmp_path / "x.png", title="t", xlabel="x")


def test_a_long_footer_is_wrapped_inside_the_figure_below_the_axes(tmp_path, monkeypatch):
    from radarpc.eval.comparison import CDFCurve, CDFPanel

    saved = []
    save = viz.save_figure
    monkeypatch.setattr(viz, "save_figure", lambda fig, out, dpi, metadata=None: (saved.append(fig),
                                                                                   save(fig, out, dpi, metadata)))
    footer = " | ".join(f"radarpc experiment ablation configs/study/arm{i}.yaml --out runs/arm{i}" for i in range(9))
    curve = CDFCurve("os-cfar", np.array([1.0, 2.0]), np.array([0.5, 1.0]), 2, 0)
    viz.plot_cdfs([CDFPanel("scene lab", (curve,))], tmp_path / "cdf.png", title="t", xlabel="x [m]", footer=footer)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = saved[-1]
    text, renderer = fig.texts[-1], FigureCanvasAgg(fig).get_renderer()     # the saved figure, measured
    assert text.get_text().replace("\n", " ") == footer and len(text.get_text().splitlines()) >= 2
    box = text.get_window_extent(renderer)
    assert 0 <= box.x0 and box.x1 <= fig.bbox.x1 and 0 <= box.y0      # every line inside the figure
    assert all(ax.get_tightbbox(renderer).y0 >= box.y1 for ax in fig.axes if ax.get_visible())


def test_density_curves_keep_one_colour_per_label_across_panels(tmp_path, figures):
    from radarpc.eval.curves import DensityCurve

    dens = (0.02, 0.057, 0.2)
    model = DensityCurve("model", dens, ((0.1,), (0.2,), (0.3,)), None)
    classical = DensityCurve("classical", dens, ((0.05,), (0.1,), (0.2,)), None)
    panels = [viz.DensityPanel("F1", "F1", (model, classical), (("dense", (0.4,)),)),
              viz.DensityPanel("mIoU", "mIoU", (model,), (("dense", (0.5,)),))]   # no classical here
    colours = viz.label_colours(panels)
    assert colours == {"model": "C0", "classical": "C1", "dense": "C2"}
    out = viz.plot_density_curves(panels, tmp_path / "d.png", title="t")
    _png_size(out)
    fig = figures[-1]
    for ax in fig.axes:                                  # the legend's colour of each label, per panel
        legend = ax.get_legend()
        drawn = {t.get_text().split(" (")[0]: h.get_color()
                 for t, h in zip(legend.get_texts(), legend.legend_handles)}
        assert all(matplotlib.colors.same_color(c, colours[label]) for label, c in drawn.items()), drawn
    assert len(fig.axes[1].get_legend().get_texts()) == 2
