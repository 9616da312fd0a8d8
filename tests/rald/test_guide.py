"""Guide points of RaLD's generation (radarpc.rald.guide): RaLD's intensity peaks, OS-CFAR, none."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.config import from_dict, load_yaml, save_yaml, to_dict
from radarpc.rald.frustum import cartesian_to_polar
from radarpc.rald.guide import GuideConfig, guide_points, peak_cells, peak_points, weighted_allocation
from radarpc.rald.oscfar_baseline import CubeAxes, OSCFARConfig, detect_points


def test_weighted_allocation_by_hand():
    # 10 in proportion 1 : 2 : 1 -> floor(2.5, 5, 2.5) = (2, 5, 2), the remaining 1 to the largest
    assert weighted_allocation([1.0, 2.0, 1.0], 10).tolist() == [2, 6, 2]
    # every weight 0: an even split, the first ones one more
    assert weighted_allocation([0.0, 0.0, 0.0], 10).tolist() == [4, 3, 3]
    # ties for the largest: the first
    assert weighted_allocation([3.0, 3.0], 5).tolist() == [3, 2]
    with pytest.raises(ValueError, match="finite values >= 0"):
        weighted_allocation([1.0, -1.0], 3)


def test_peak_cells_share_by_slice_intensity_and_pick_the_brightest():
    x = torch.zeros(3, 2, 2)
    x[0] = torch.tensor([[1.0, 4.0], [3.0, 0.0]])     # slice sum 8
    x[1] = torch.tensor([[0.0, 0.0], [0.0, 0.0]])     # 0
    x[2] = torch.tensor([[2.0, 2.0], [1.0, 3.0]])     # 8
    # 5 picks: floor(2.5) = 2 each, 1 more to the first largest slice (0): 3 from slice 0, 2 from slice 2
    got = peak_cells(x, 5).tolist()
    assert got == [[0, 0, 1], [0, 1, 0], [0, 0, 0],    # 4, 3, 1
                   [2, 1, 1], [2, 0, 0]]               # 3, then the first of the two 2s
    with pytest.raises(ValueError, match=r"n must be in \[1, 12\]"):
        peak_cells(x, 13)
    # a share above a slice's cells is cut to the slice
    y = torch.zeros(2, 1, 2)
    y[0] = 10.0
    y[1, 0, 0] = 0.1
    assert peak_cells(y, 3).tolist() == [[0, 0, 0], [0, 0, 1]]


def test_peak_points_sit_on_the_cube_axes():
    axes = CubeAxes((0.0, 1.0, 2.0, 3.0), (-30.0, 0.0, 30.0), (-10.0, 10.0))
    x = torch.zeros(4, 3, 2)
    x[2, 0, 1] = 40.0                               # one bright cell: 2 m, azimuth -30 deg, elevation 10 deg
    # no upsampling: the brightest cell of its slice, at its bin centre
    p = peak_points(x, axes, n=1, upsample=(4, 3, 2))
    torch.testing.assert_close(cartesian_to_polar(p.double()), torch.tensor([[2.0, -30.0, 10.0]], dtype=torch.float64),
                               atol=1e-5, rtol=0)
    # upsampled 2x (align_corners=False): output bin i sits at input position (i + 1/2) / 2 - 1/2, clamped,
    # range linear there, angles linear in their sine
    p = peak_points(x, axes, n=48, upsample=(8, 6, 4))
    rae = cartesian_to_polar(p.double())
    pos = lambda n_in, n_out: np.clip((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0, n_in - 1)
    r_bins = np.interp(pos(4, 8), np.arange(4), axes.range_m)
    s = np.interp(pos(3, 6), np.arange(3), np.sin(np.radians(axes.azimuth_deg)))
    az_bins = np.degrees(np.arcsin(s))
    assert set(np.round(rae[:, 0].numpy(), 6)) <= set(np.round(r_bins, 6))
    nz = rae[:, 0] > 0                              # at the origin the azimuth is not defined
    assert np.all(np.isclose(rae[nz, 1].numpy()[:, None], az_bins[None], atol=1e-4).any(1))
    # all 48 cells are picked (n = every cell), listed by range slice
    assert len(p) == 48


def test_guide_points_of_each_source(colo_root):
    from radarpc.data.coloradar import ColoRadar
    from radarpc.dsp.tdm import radar_cube

    ds = ColoRadar(colo_root, "test", cube_size=None)
    k, ri, _ = ds.index[0]
    adc, chip = ds.runs[k].adc(ri), ds.calib.single_chip
    assert guide_points(GuideConfig(source="none"), adc, chip).shape == (0, 3)
    cube = radar_cube(adc, chip)
    cfg = GuideConfig(source="os-cfar", oscfar=OSCFARConfig(tau_db=6.0))
    axes = CubeAxes.from_radians(cube.range_m, cube.azimuth_rad, cube.elevation_rad)
    np.testing.assert_array_equal(guide_points(cfg, adc, chip), detect_points(cube.intensity_db, axes, cfg.oscfar).numpy())
    peaks = guide_points(GuideConfig(n_points=500, upsample=(64, 32, 16)), adc, chip)
    hr = radar_cube(adc, chip, n_azimuth=32, n_elevation=16)
    hr_axes = CubeAxes.from_radians(hr.range_m, hr.azimuth_rad, hr.elevation_rad)
    np.testing.assert_array_equal(peaks, peak_points(hr.intensity_db, hr_axes, 500, (64, 32, 16)).numpy())
    assert peaks.shape == (500, 3) and peaks.dtype == np.float32


def test_guide_config_checks_and_round_trips(tmp_path):
    with pytest.raises(ValueError, match="GuideConfig.source must be one of"):
        GuideConfig(source="cfar")
    with pytest.raises(ValueError, match="GuideConfig.upsample must be 3 integers"):
        GuideConfig(upsample=(256, 256))
    cfg = GuideConfig(source="os-cfar", n_points=1000, oscfar=OSCFARConfig(tau_db=5.0, angle_bins=(32, 8)))
    assert from_dict(GuideConfig, to_dict(cfg)) == cfg
    assert load_yaml(GuideConfig, save_yaml(cfg, tmp_path / "guide.yaml")) == cfg
