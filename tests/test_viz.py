"""Tests of :mod:`radarpc.viz`: each figure at tiny size, and the frame figure's encoded-cell mask."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from radarpc import viz
from radarpc.data.radial import RADIal, read_labels
from radarpc.data.summary import ColoRadarView, first_rd_power_db, summarize_radial
from radarpc.dsp.ddma import replica_bins
from radarpc.dsp.sparse_rd import sparse_rd_mask
from radarpc.pipelines.pointclouds import ConvertSettings, build_point_cloud
from radarpc.sensors.coloradar import AWR1843_FOV
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_writer import write_radial_dataset


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    # 3 sequences (train, val, test) x 2 frames of the TINY sensor
    return write_radial_dataset(tmp_path_factory.mktemp("sim") / "root", TINY, 3, 2, seed=0, progress=False)


@pytest.fixture
def figures(monkeypatch):
    """The figures the viz functions save, in order."""
    saved = []
    save = viz._save

    def keep(fig, out, dpi):
        saved.append(fig)
        save(fig, out, dpi)

    monkeypatch.setattr(viz, "_save", keep)
    return saved


def _png_size(path) -> tuple[int, int]:
    with Image.open(path) as im:
        assert im.format == "PNG"
        assert np.asarray(im.convert("L")).std() > 10          # not a blank canvas
        return im.size


def test_encoded_cells_is_sparse_rd_mask(root):
    ds = RADIal(root, split="all")
    rd = ds[1][0].unsqueeze(0)
    for enrich in ((), ("rd3",)):
        spc = build_point_cloud(ds, ConvertSettings(density=0.1, enrich=enrich), None, "cpu")
        enc, cloud = spc.encode(rd), spc(rd)
        want = sparse_rd_mask(enc.kept, TINY, rd)[0]                     # d0 resolved from the cube
        got = viz.encoded_cells(cloud, TINY)
        assert torch.equal(got, want) and int(got.sum()) == TINY.n_tx * cloud.num_points
        # the replica mask show.py used to build by hand: every point's range x its n_tx replicas
        old = torch.zeros(TINY.n_range, TINY.n_doppler, dtype=torch.bool)
        bins = replica_bins(TINY, cloud.doppler_full)
        old[cloud.range_bin[:, None].expand_as(bins), bins] = True
        assert torch.equal(got, old)
        # any point order gives the same cells
        perm = torch.randperm(cloud.num_points, generator=torch.Generator().manual_seed(0))
        shuffled = type(cloud)(**{**{k: getattr(cloud, k) for k in ("offset", "tau", "density", "peak_density")},
                                  **{k: (None if getattr(cloud, k) is None else getattr(cloud, k)[perm])
                                     for k in cloud._PER_POINT}})
        assert torch.equal(viz.encoded_cells(shuffled, TINY), want)


def test_frame_view_and_figure(root, tmp_path, figures):
    settings = ConvertSettings(density=0.1, enrich=("rd3",))
    view = viz.frame_view(root, 1, settings)
    assert view.set_name == "S*(tau)" and view.frame == 1 and view.title.startswith(f"{root.name}, frame 1 (")
    assert view.rd_magnitude.shape == view.encoded.shape == (TINY.n_range, TINY.n_doppler)
    assert view.envelope.shape == view.peaks.shape == (TINY.n_range, TINY.slot_width)
    assert torch.equal(torch.from_numpy(view.encoded), viz.encoded_cells(view.cloud, TINY))
    out = tmp_path / "f.png"
    res = viz.plot_frame_view(view, out, color_by="amplitude")
    assert res.path == out and _png_size(out) == (17 * 80, int(6.5 * 80))
    assert len(figures[-1].axes) == 6                                     # 3 panels + 3 colour bars
    assert not list(tmp_path.glob(".*.tmp"))                              # atomic write left no temp file
    assert res.n_points == view.cloud.num_points and res.n_peaks == int(view.peaks.sum())
    assert res.n_vehicles == len(view.vehicles_xy)
    assert res.peak_density == pytest.approx(res.n_peaks * TINY.n_tx / (TINY.n_range * TINY.n_doppler))
    assert res.density == pytest.approx(view.encoded.sum() / (TINY.n_range * TINY.n_doppler), rel=1e-6)
    with pytest.raises(ValueError, match="color_by must be one of"):
        viz.plot_frame_view(view, out, color_by="snr")
    with pytest.raises(ValueError, match="give exactly one of settings"):
        viz.frame_view(root, 1)
    with pytest.raises(IsADirectoryError, match="is a directory"):
        viz.plot_frame(root, 1, tmp_path, settings)


def test_geometry_of_the_rd_panels():
    # the RD image rows and the peak markers agree: row r is centred on r * range_res_m
    x0, x1, y0, y1 = viz.rd_extent(TINY, TINY.n_doppler)
    r = np.arange(TINY.n_range)
    np.testing.assert_allclose(y0 + (r + 0.5) * (y1 - y0) / TINY.n_range, viz.peak_marker_range_m(TINY, r),
                               atol=1e-9)
    assert (x0, x1) == (-0.5, TINY.n_doppler - 0.5)


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


@pytest.mark.parametrize("heatmap,cube", [(True, True), (False, True), (False, False)])
def test_plot_coloradar_info(tmp_path, figures, heatmap, cube):
    out = viz.plot_coloradar_info(_colo_view(heatmap, cube), tmp_path / "c.png")
    n = 3 if heatmap else 2
    assert _png_size(out) == (int(5.5 * n * 110), 5 * 110) and len(figures[-1].axes) == n
    assert figures[-1].axes[0].get_title().startswith("lab_run0 LiDAR 2:")
    assert bool(figures[-1].axes[1].images) == cube
    assert not list(tmp_path.glob(".*.tmp"))


def test_no_pyplot_state(root, tmp_path):
    import matplotlib
    import matplotlib.pyplot as plt

    backend = matplotlib.get_backend()
    open_before = plt.get_fignums()
    viz.plot_coloradar_info(_colo_view(True, True), tmp_path / "c.png")
    assert plt.get_fignums() == open_before and matplotlib.get_backend() == backend
