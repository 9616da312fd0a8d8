"""The classical reference detector: ego speed, Doppler gating, clustering."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.models.classical import ClassicalConfig, classical_detect, estimate_ego_speed, wrap_velocity
from radarpc.points import PointCloudBatch

CFG = ClassicalConfig()
V_MAX = CFG.max_velocity_mps


def _static_scene(rng, n, v_ego, noise=0.05):
    az = rng.uniform(-60, 60, n)
    el = rng.uniform(-5, 5, n)
    r = rng.uniform(5, 90, n)
    vr = -v_ego * np.cos(np.deg2rad(az)) * np.cos(np.deg2rad(el)) + rng.normal(0, noise, n)
    return r, az, el, wrap_velocity(vr, V_MAX)


@pytest.mark.parametrize("v_ego", [0.0, 7.3, 17.9, 26.0])   # 26 > v_max: static points alias
def test_ego_speed_from_a_static_scene_with_outliers(v_ego):
    rng = np.random.default_rng(1)
    _, az, el, vr = _static_scene(rng, 400, v_ego)
    n_out = 150                                                         # 27 % movers and clutter
    az = np.r_[az, rng.uniform(-60, 60, n_out)]
    el = np.r_[el, rng.uniform(-5, 5, n_out)]
    vr = np.r_[vr, rng.uniform(-V_MAX, V_MAX, n_out)]
    v, static = estimate_ego_speed(vr, az, el, CFG)
    # least squares over ~400 inliers of 0.05 m/s noise: error ~ 0.05 / sqrt(400) / 0.8; the few
    # outliers that fall inside the 0.5 m/s band add a bias bounded by tol * their share (~2 %)
    assert v == pytest.approx(v_ego, abs=0.03)
    assert static[:400].mean() > 0.99 and static[400:].mean() < 0.1
    assert np.isnan(estimate_ego_speed(np.zeros(0), np.zeros(0), np.zeros(0))[0])


def _cloud(frames):
    """A PointCloudBatch from per-frame dicts of range_m, azimuth_deg, elevation_deg, velocity_mps
    and optionally snr (20 when absent)."""
    cols = {k: np.concatenate([f[k] for f in frames]) for k in ("range_m", "azimuth_deg", "elevation_deg", "velocity_mps")}
    n = cols["range_m"].size
    a, e = np.deg2rad(cols["azimuth_deg"]), np.deg2rad(cols["elevation_deg"])
    f32 = lambda v: torch.as_tensor(np.asarray(v), dtype=torch.float32)
    z = torch.zeros(n, dtype=torch.int64)
    return PointCloudBatch(
        offset=torch.cumsum(torch.tensor([f["range_m"].size for f in frames]), 0),
        range_bin=z, doppler_bin=z, doppler_full=z,
        range_m=f32(cols["range_m"]), azimuth_deg=f32(cols["azimuth_deg"]), elevation_deg=f32(cols["elevation_deg"]),
        velocity_mps=f32(cols["velocity_mps"]), amplitude=torch.ones(n),
        snr=f32(np.concatenate([f.get("snr", np.full(f["range_m"].size, 20.0)) for f in frames])),
        x=f32(cols["range_m"] * np.cos(e) * np.cos(a)), y=f32(cols["range_m"] * np.cos(e) * np.sin(a)),
        z=f32(cols["range_m"] * np.sin(e)), is_neighbour=torch.zeros(n, dtype=torch.bool), sector=None,
        rd_patch=None, tau=torch.ones(len(frames)), density=torch.ones(len(frames)))


def test_moving_vehicle_is_detected_at_its_near_face():
    rng = np.random.default_rng(2)
    v_ego, v_car = 12.0, 18.0                                           # car ahead-left, same direction
    r, az, el, vr = _static_scene(rng, 300, v_ego)
    # 8 scatterers on the car's rear face (x = 30 m, y = 2.5 .. 4.3 m) and side
    cx = np.r_[np.full(5, 30.0), 30.5, 31.5, 32.5]
    cy = np.r_[np.linspace(2.5, 4.3, 5), 2.5, 2.5, 2.5]
    cr, ca = np.hypot(cx, cy), np.degrees(np.arctan2(cy, cx))
    # radial velocity of a car moving along +x at v_car seen from an ego at v_ego
    cv = (v_car - v_ego) * np.cos(np.deg2rad(ca))
    snr = np.r_[np.full(300, 20.0), np.full(5, 50.0), np.full(3, 10.0)]      # the rear face is strongest
    scene = dict(range_m=np.r_[r, cr], azimuth_deg=np.r_[az, ca], elevation_deg=np.r_[el, np.zeros(8)],
                 velocity_mps=np.r_[vr, cv], snr=snr)
    empty = {k: np.zeros(0) for k in scene}
    det = classical_detect(_cloud([scene, empty]), CFG)
    assert det.offset.tolist() == [1, 1]                               # one cluster, nothing in the empty frame
    ref_r, ref_a = np.hypot(30.0, 3.4), np.degrees(np.arctan2(3.4, 30.0))   # middle of the rear face
    # SNR-weighted means: the rear face (weight 250) against the side (weight 30, 0.5 .. 2.4 m
    # further and 0.9 m to the right) moves the point < 0.2 m in range and < 1 deg in azimuth
    w = snr[300:]
    assert det.range_m[0].item() == pytest.approx(np.average(cr, weights=w), abs=1e-4)
    assert det.range_m[0].item() == pytest.approx(ref_r, abs=0.2)
    assert det.azimuth_deg[0].item() == pytest.approx(ref_a, abs=1.0)
    assert det.score[0].item() == pytest.approx(8 / (8 + CFG.score_half_points))


def test_static_scene_gives_nothing_and_bad_config_is_named():
    rng = np.random.default_rng(3)
    r, az, el, vr = _static_scene(rng, 300, 9.0)
    det = classical_detect(_cloud([dict(range_m=r, azimuth_deg=az, elevation_deg=el, velocity_mps=vr)]), CFG)
    assert det.num_detections == 0 and det.offset.tolist() == [0]
    with pytest.raises(ValueError, match=r"ClassicalConfig: invalid cluster_eps_m=0\.0"):
        ClassicalConfig(cluster_eps_m=0.0)
