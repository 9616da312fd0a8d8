"""Tests for radarpc.sim.indoor: scenes, trajectories and ray casting."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from radarpc.sensors.coloradar import quaternion_to_matrix
from radarpc.sim.coloradar_synth import LidarConfig, lidar_scan
from radarpc.sim.indoor import SCENE_KINDS, Person, Scene, Trajectory, make_scene, ray_cast


def _wall_scene(x_face: float = 5.0) -> Scene:
    # one wall: a box whose front face is the plane x = x_face, spanning y in [-20, 20], z in [-5, 5]
    boxes = np.array([[x_face + 0.1, 0.0, 0.0, 0.1, 20.0, 5.0, 0.0, 0]], dtype=np.float64)
    traj = Trajectory(((0.0, 0.0), (0.0, 1.0)), speed=1.0, height=0.0, handheld=False)
    return Scene("hallway", 0, boxes, np.zeros((0, 6)), (), traj)


def test_ray_cast_plane_wall_and_normal():
    g = _wall_scene().geometry(0.0)
    rng = np.random.default_rng(0)
    az = rng.uniform(-1.0, 1.0, 200)
    el = rng.uniform(-0.5, 0.5, 200)
    d = torch.tensor(np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1), dtype=torch.float32)
    h = ray_cast(g, torch.zeros(3), d)
    assert h.hit.all()
    np.testing.assert_allclose(h.point[:, 0].numpy(), 5.0, atol=1e-4)
    np.testing.assert_allclose(h.t.numpy(), 5.0 / (np.cos(el) * np.cos(az)), rtol=1e-5)
    np.testing.assert_allclose(h.normal.numpy(), np.tile([-1.0, 0.0, 0.0], (200, 1)), atol=1e-6)
    # rays pointing away miss
    miss = ray_cast(g, torch.zeros(3), -d)
    assert not miss.hit.any() and torch.isinf(miss.t).all()


def test_ray_cast_cylinder_and_yawed_box():
    boxes = np.array([[0.0, 6.0, 0.0, 1.0, 0.5, 1.0, math.radians(30), 2]])
    cyl = np.array([[4.0, 0.0, 0.5, -1.0, 1.0, 3]])
    s = Scene("lab", 0, boxes, cyl, (), Trajectory(((0, 0), (1, 0))))
    g = s.geometry(0.0)
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    h = ray_cast(g, torch.zeros(3), d)
    assert h.t[0].item() == pytest.approx(3.5, abs=1e-5)              # cylinder surface at x = 4 - 0.5
    np.testing.assert_allclose(h.normal[0].numpy(), [-1, 0, 0], atol=1e-5)
    # yawed box: ray along +y hits the face whose outward normal is the rotated local -y or -x axis;
    # brute force: march along the ray and test point-in-box in the box frame
    c, sn = math.cos(math.radians(30)), math.sin(math.radians(30))
    ts = np.linspace(0, 10, 200001)
    py = ts - 6.0
    lx, ly = sn * py, c * py                                          # rotate (0, py) by -30 deg
    inside = (np.abs(lx) <= 1.0) & (np.abs(ly) <= 0.5)
    assert h.t[1].item() == pytest.approx(ts[np.argmax(inside)], abs=1e-4)
    assert int(h.material[1]) == 2 and int(h.material[0]) == 3


def test_shared_origin_culling_is_exact():
    s = make_scene("outdoor", 3)
    g = s.geometry(1.0)
    pos = torch.tensor(s.trajectory.pose(1.0)[0], dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    d = torch.randn(600, 3, generator=gen)
    d = d / d.norm(dim=1, keepdim=True)
    a = ray_cast(g, pos, d, chunk=256)
    b = ray_cast(g, pos.expand(600, 3).contiguous(), d, chunk=128)
    assert torch.equal(a.hit, b.hit)
    torch.testing.assert_close(a.t[a.hit], b.t[b.hit])


def test_lidar_scan_of_wall_lies_on_wall():
    s = _wall_scene(4.0)
    from radarpc.sensors.coloradar import Transform
    pose = Transform((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    cfg = LidarConfig(beams=8, azimuth_steps=64, range_noise_m=0.0, dropout=0.0)
    cloud = lidar_scan(s, 0.0, pose, cfg=cfg).numpy()
    pts = cloud[np.any(cloud[:, :3] != 0, axis=1)]
    assert len(pts) > 8 * 64 // 4
    np.testing.assert_allclose(pts[:, 0], 4.0, atol=1e-3)
    assert (pts[:, 3] > 0).all()


def test_scenes_seeded_and_valid():
    for kind in SCENE_KINDS:
        a, b, c = make_scene(kind, 5), make_scene(kind, 5), make_scene(kind, 5, run=1)
        np.testing.assert_array_equal(a.boxes, b.boxes)
        np.testing.assert_array_equal(a.cylinders, b.cylinders)
        assert a.trajectory == b.trajectory and a.people == b.people
        # another run is another layout of the kind (held-out scenes), path and people
        assert a.boxes.shape != c.boxes.shape or not np.array_equal(a.boxes, c.boxes)
        assert not np.array_equal(a.boxes[:, :3].mean(0), c.boxes[:, :3].mean(0))
        assert a.trajectory != c.trajectory
        assert a.trajectory.duration > 5 and len(a.people) >= 1
        assert np.isfinite(a.boxes).all() and (a.boxes[:, 3:6] > 0).all()
    with pytest.raises(ValueError, match="unknown scene kind"):
        make_scene("kitchen", 0)


def test_trajectory_heading_is_base_plus_y():
    tr = Trajectory(((0.0, 0.0), (10.0, 0.0), (10.0, 10.0)), speed=1.0, height=1.2, handheld=False)
    for t in (1.0, 4.0, 18.0):
        pos, q = tr.pose(t)
        v = tr.velocity(t)
        r = quaternion_to_matrix(q)
        assert np.dot(r[:, 1], v / np.linalg.norm(v)) > 0.99
        assert pos[2] == pytest.approx(1.2)
        assert np.linalg.norm(q) == pytest.approx(1.0)


def test_person_bounces():
    p = Person((0.0, 0.0), (2.0, 0.0), speed=1.0, phase=0.0)
    np.testing.assert_allclose(p.state(1.0)[0], [1.0, 0.0])
    np.testing.assert_allclose(p.state(3.0)[0], [1.0, 0.0])
    np.testing.assert_allclose(p.state(3.0)[1], [-1.0, 0.0])
