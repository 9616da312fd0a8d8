"""Procedural road scenes: determinism, kinematic consistency over time, occlusion."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from radarpc.sim.road import RoadScene, RoadSceneConfig

CFG = RoadSceneConfig()
MAX_R = 103.0


def fields(sc):
    return torch.stack([sc.range_m, sc.azimuth_deg, sc.elevation_deg, sc.velocity_mps, sc.rcs_m2])


def test_same_seed_same_frames_and_different_seeds_differ():
    a = RoadScene(CFG, 3, 1, 20, MAX_R).frame(0.7)
    b = RoadScene(CFG, 3, 1, 20, MAX_R).frame(0.7)
    assert torch.equal(fields(a.scatterers), fields(b.scatterers))
    assert torch.equal(a.owner, b.owner)
    np.testing.assert_array_equal(a.vehicles.center_xyz, b.vehicles.center_xyz)
    for other in (RoadScene(CFG, 3, 2, 20, MAX_R).frame(0.7), RoadScene(CFG, 4, 1, 20, MAX_R).frame(0.7)):
        sa, so = fields(a.scatterers), fields(other.scatterers)
        assert sa.shape != so.shape or not torch.equal(sa, so)
    # frames of one sequence differ in time, and a frame does not depend on which came before
    scene = RoadScene(CFG, 3, 1, 20, MAX_R)
    later = scene.frame(1.5)
    assert not torch.equal(fields(scene.frame(0.7).scatterers)[:, :5], fields(later.scatterers)[:, :5])
    assert torch.equal(fields(scene.frame(1.5).scatterers), fields(later.scatterers))


@pytest.mark.parametrize("seq", [0, 1, 2])
def test_vehicle_velocities_are_the_time_derivative_of_positions(seq):
    straight = dataclasses.replace(CFG, straight_prob=1.0)
    scene = RoadScene(straight, 0, seq, 30, MAX_R)
    t, h = 1.2, 0.05
    f0, f1, fm = scene.frame(t - h), scene.frame(t + h), scene.frame(t)
    # straight road: the radar frame only translates; central differences are exact for the
    # quadratic ego motion and the linear vehicle motion
    rate = (f1.vehicles.center_xyz[:, :2] - f0.vehicles.center_xyz[:, :2]) / (2 * h)
    np.testing.assert_allclose(rate, fm.vehicles.rel_velocity_xy, atol=1e-9)
    ego = (scene.ego_state(t + h)[0] - scene.ego_state(t - h)[0]) / (2 * h)
    assert ego[0] == pytest.approx(fm.ego_speed_mps, abs=1e-9)


def test_curved_road_world_motion_is_consistent():
    bend = dataclasses.replace(CFG, straight_prob=0.0, curvature_1pm=(1 / 120, 1 / 120))
    scene = RoadScene(bend, 2, 0, 30, MAX_R)
    t, h = 1.5, 1e-4
    # ego: world velocity = derivative of world position, heading = direction of travel
    p0, p1 = scene.ego_state(t - h)[0], scene.ego_state(t + h)[0]
    _, heading, vel, speed = scene.ego_state(t)
    np.testing.assert_allclose((p1[:2] - p0[:2]) / (2 * h), vel, atol=1e-6)
    if speed > 0.5:
        assert math.atan2(vel[1], vel[0]) == pytest.approx(heading, abs=1e-9)
    # vehicles and people: world velocities are derivatives of world positions, headings follow them
    q0, q1 = scene._body_poses(t - h)[0], scene._body_poses(t + h)[0]
    _, yaw_m, v_m = scene._body_poses(t)
    np.testing.assert_allclose((q1 - q0) / (2 * h), v_m, atol=1e-5)
    sp = np.hypot(v_m[:, 0], v_m[:, 1])
    moving = sp > 0.5
    np.testing.assert_allclose(np.cos(yaw_m[moving]), v_m[moving, 0] / sp[moving], atol=1e-9)
    np.testing.assert_allclose(np.sin(yaw_m[moving]), v_m[moving, 1] / sp[moving], atol=1e-9)
    fr = scene.frame(t)
    ahead = np.abs(fr.vehicles.yaw_rad) < 1.0
    assert np.ptp(fr.vehicles.yaw_rad[ahead]) > 0.05                 # headings vary along the bend


def test_static_clutter_has_minus_ego_speed_times_cosines():
    cfg = dataclasses.replace(CFG, pedestrians=(0, 0), cyclists=(0, 0), ego_speed_mps=(8.0, 15.0))
    fr = RoadScene(cfg, 5, 0, 10, MAX_R).frame(0.4)
    static = fr.owner == -1
    sc = fr.scatterers.select(static)
    assert len(sc) > 50
    want = -fr.ego_speed_mps * torch.cos(torch.deg2rad(sc.azimuth_deg)) * torch.cos(torch.deg2rad(sc.elevation_deg))
    torch.testing.assert_close(sc.velocity_mps, want, rtol=0, atol=1e-9)


def test_label_range_rate_matches_radial_velocity_of_vehicle_points():
    scene = RoadScene(CFG, 1, 0, 30, MAX_R)
    t, h = 1.0, 1e-3
    f0, f1, fm = scene.frame(t - h), scene.frame(t + h), scene.frame(t)
    r0 = np.linalg.norm(f0.vehicles.center_xyz, axis=1)
    r1 = np.linalg.norm(f1.vehicles.center_xyz, axis=1)
    c = fm.vehicles.center_xyz
    vr = (c[:, :2] * fm.vehicles.rel_velocity_xy).sum(1) / np.linalg.norm(c, axis=1)
    np.testing.assert_allclose((r1 - r0) / (2 * h), vr, atol=1e-4)


def test_scene_content_extended_vehicles_and_wheel_micro_doppler():
    scene = RoadScene(CFG, 0, 1, 30, MAX_R)
    fr = scene.frame(1.0)
    sc, owner = fr.scatterers, fr.owner.numpy()
    assert 100 < len(sc) < 2000
    assert float(sc.range_m.max()) < MAX_R and float(sc.range_m.min()) >= CFG.min_range_m
    assert bool((sc.azimuth_deg.abs() < 90).all())
    spreads = []
    for v in np.unique(owner[owner >= 0]):
        vel = sc.velocity_mps.numpy()[owner == v]
        assert vel.size >= 5                                  # extended: many scatterers per vehicle
        speed = float(np.hypot(*fr.vehicles.velocity_xy[v]))
        if speed > 3:
            spreads.append((vel.max() - vel.min()) / speed)
    # rotating wheel rims spread over 0 .. 2 v in the road direction: a Doppler spread ~ v
    assert spreads and max(spreads) > 0.8


def test_occluded_scatterers_are_attenuated():
    hidden = RoadScene._hidden(
        p=np.array([[30.0, 0.0], [30.0, 10.0], [10.0, 0.0], [22.0, 0.0]]),
        owner=np.array([-1, -1, -1, 0]),
        centres=np.array([[20.0, 0.0]]), yaw=np.array([0.3]), size=np.array([[4.0, 2.0, 1.5]]))
    # behind the car; beside it; in front of it; on the car itself (its own scatterer)
    np.testing.assert_array_equal(hidden, [True, False, False, False])


def test_bad_scene_parameters_are_rejected():
    with pytest.raises(ValueError, match="frame_period_s"):
        RoadSceneConfig(frame_period_s=0.0)
    with pytest.raises(ValueError, match="lanes_same"):
        RoadSceneConfig(lanes_same=(0, 2))
    with pytest.raises(ValueError, match="truck_fraction"):
        RoadSceneConfig(truck_fraction=1.5)
    with pytest.raises(ValueError, match="n_frames"):
        RoadScene(CFG, 0, 0, 0, MAX_R)
    with pytest.raises(ValueError, match="seed and sequence"):
        RoadScene(CFG, -1, 0, 5, MAX_R)
    with pytest.raises(ValueError, match="finite"):
        RoadScene(CFG, 0, 0, 5, MAX_R).frame(math.nan)


def test_bodies_stack_by_field_with_their_owner():
    from radarpc.sim.road import _Body

    a = _Body.of_one([(1.0, 0.0, 0.5), (2.0, 0.0, 0.5)], [(1.0, 0.0), (0.0, 0.0)], [1.0, 2.0], [0, 1],
                     [0.0, 0.3], [0.0, 9.0], [0.0, 1.5])
    b = _Body.of_one([(0.0, 0.0, 1.2)], [(0.0, 0.0)], [0.4], [2], [0.2], [6.0], [3.0])
    s = _Body.stack([a, b])
    np.testing.assert_array_equal(s.owner, [0, 0, 1])
    np.testing.assert_array_equal(s.local[:, 0], [1.0, 2.0, 0.0])
    np.testing.assert_array_equal(s.rcs, [1.0, 2.0, 0.4])
    np.testing.assert_array_equal(s.kind, [0, 1, 2])
    np.testing.assert_array_equal(s.omega, [0.0, 9.0, 6.0])
    assert s.normal.shape == (3, 2) and s.phase0.tolist() == [0.0, 1.5, 3.0]
    empty = _Body.stack([])
    assert empty.local.shape == (0, 3) and empty.owner.dtype == np.int64
    # a scene's vehicle bodies own exactly their vehicles' scatterers
    sc = RoadScene(CFG, 3, 0, 5, MAX_R)
    assert set(np.unique(sc._body.owner).tolist()) == set(range(sc.n_vehicles + len(sc.ppl_s0)))
