"""Multipath of road scenes: ground bounce and wall ghosts against closed forms and mirrors."""
import dataclasses
import math

import numpy as np
import pytest

from radarpc.sensors.radial import RADIAL
from radarpc.sim.multipath import (
    bistatic_fields,
    ground_image,
    mirror_through_line,
    path_fields,
    reflection_amplitude,
)
from radarpc.sim.radial_labels import frame_label_rows, labelled_vehicles
from radarpc.sim.road import GHOST_OWNER, PATH_NAMES, RoadFrame, RoadScene
from radarpc.sim.scenes import CITY, HIGHWAY

H = 0.8
EPS = np.finfo(float).eps


def xyz_of(sc, mask):
    r = sc.range_m.numpy()[mask]
    az, el = np.radians(sc.azimuth_deg.numpy()[mask]), np.radians(sc.elevation_deg.numpy()[mask])
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)


@pytest.mark.parametrize("d, z_w, az_deg, v", [(10.0, 0.5, 0.0, 12.0), (37.0, 1.2, 25.0, -8.0), (4.0, 0.3, -60.0, 3.0)])
def test_ground_bounce_paths_match_the_two_ray_closed_form(d, z_w, az_deg, v):
    # a point at ground distance d and height z_w above flat ground, moving radially at v;
    # radar at height H: direct path sqrt(d^2 + (z_w - H)^2), via the ground sqrt(d^2 + (z_w + H)^2)
    a = math.radians(az_deg)
    p = np.array([[d * math.cos(a), d * math.sin(a), z_w - H]])
    vel = np.array([[v * math.cos(a), v * math.sin(a), 0.0]])
    r_d, r_b = math.hypot(d, z_w - H), math.hypot(d, z_w + H)
    img, vimg = ground_image(p, vel, H)
    r, az, el, vr = path_fields(img, vimg)
    tol = 8 * EPS * (d + z_w + H)
    assert r[0] == pytest.approx(r_b, abs=tol)
    assert el[0] == pytest.approx(-math.degrees(math.atan2(z_w + H, d)), abs=1e-12)
    assert az[0] == pytest.approx(az_deg, abs=1e-12)
    assert vr[0] == pytest.approx(v * d / r_b, abs=8 * EPS * abs(v))            # d(r_b)/dt
    # out direct, back via the ground: delay (r_d + r_b) / c, Doppler of the half path length
    r, az, el, vr = bistatic_fields(p, vel, img, vimg)
    assert r[0] == pytest.approx((r_d + r_b) / 2, abs=tol)
    assert vr[0] == pytest.approx(v * d * (1 / r_d + 1 / r_b) / 2, abs=8 * EPS * abs(v))
    assert az[0] == pytest.approx(az_deg, abs=1e-12)                           # same vertical plane
    e_d, e_b = math.atan2(z_w - H, d), -math.atan2(z_w + H, d)
    # the direction of the mean unit vector: the bisector of the two legs' elevations
    assert el[0] == pytest.approx(math.degrees((e_d + e_b) / 2), abs=1e-9)
    assert reflection_amplitude(-6.0) ** 2 == pytest.approx(10 ** -0.6, rel=1e-15)
    with pytest.raises(ValueError, match="<= 0 dB"):
        reflection_amplitude(3.0)


def test_mirror_through_a_line():
    p = np.array([[10.0, 2.0, 0.3], [5.0, -1.0, 1.0]])
    v = np.array([[3.0, 1.0, 0.5], [0.0, -2.0, 0.0]])
    # the wall y = 6 (direction along x): (x, y) -> (x, 12 - y), v_y -> -v_y
    m, mv = mirror_through_line(p, v, np.array([0.0, 6.0]), np.array([2.0, 0.0]))
    np.testing.assert_allclose(m, [[10.0, 10.0, 0.3], [5.0, 13.0, 1.0]], atol=1e-14)
    np.testing.assert_allclose(mv, [[3.0, -1.0, 0.5], [0.0, 2.0, 0.0]], atol=1e-14)
    # the diagonal y = x through the origin swaps x and y
    m, _ = mirror_through_line(p, v, np.zeros(2), np.array([1.0, 1.0]))
    np.testing.assert_allclose(m[:, :2], p[:, [1, 0]], atol=1e-13)


def _frame_with(cfg, kind, seqs=range(40), t=0.3):
    for q in seqs:
        scene = RoadScene(cfg, 0, q, 10, RADIAL.max_range_m)
        fr = scene.frame(t)
        if (fr.path.numpy() == PATH_NAMES.index(kind)).sum() >= 4:
            return scene, fr
    raise AssertionError(f"no {kind} scatterers in the seeded scenes")


def test_ground_double_paths_pair_with_direct_returns():
    scene, fr = _frame_with(HIGHWAY, "ground_double")
    sc, path, owner = fr.scatterers, fr.path.numpy(), fr.owner.numpy()
    r, az, el = sc.range_m.numpy(), sc.azimuth_deg.numpy(), sc.elevation_deg.numpy()
    direct = np.flatnonzero(path == PATH_NAMES.index("direct"))
    n = 0
    for k in np.flatnonzero(path == PATH_NAMES.index("ground_double")):
        # the partner: the direct return of the same vehicle in the same azimuth
        j = direct[(owner[direct] == owner[k]) & (az[direct] == az[k])]
        assert j.size >= 1
        j = j[0]
        z_w = r[j] * math.sin(math.radians(el[j])) + H                              # height above ground
        d = r[j] * math.cos(math.radians(el[j]))
        assert r[k] == pytest.approx(math.hypot(d, z_w + H), abs=1e-9)
        assert el[k] == pytest.approx(-math.degrees(math.atan2(z_w + H, d)), abs=1e-9)
        n += 1
    assert n >= 4 and owner[path == PATH_NAMES.index("ground_double")].min() >= -1


def test_under_body_returns_belong_to_their_vehicle_below_its_footprint():
    scene, fr = _frame_with(CITY, "underbody")
    under = fr.path.numpy() == PATH_NAMES.index("underbody")
    owner = fr.owner.numpy()[under]
    assert (owner >= 0).all()
    p = xyz_of(fr.scatterers, under)
    veh = fr.vehicles
    for q, v in zip(p, owner):
        # image through the ground of a point 0.3..0.5 m above it, inside the footprint
        z_w = -(q[2] + H) - H
        assert -1e-9 <= -z_w - 0.3 <= 0.2 + 1e-9
        c, s = math.cos(veh.yaw_rad[v]), math.sin(veh.yaw_rad[v])
        dx, dy = q[:2] - veh.center_xyz[v, :2]
        assert abs(c * dx + s * dy) <= veh.size_lwh[v, 0] / 2 and abs(-s * dx + c * dy) <= veh.size_lwh[v, 1] / 2


def _rail_lines(scene):
    # the guard rails of a highway scene: 1 m outside each edge and in the middle of the median
    return [scene.road_right - 1.0, scene.road_left + 1.0, HIGHWAY.median_m / 2]


def test_wall_ghosts_sit_at_the_mirror_of_a_vehicle_and_are_not_labelled():
    straight = dataclasses.replace(HIGHWAY, straight_prob=1.0)
    scene, fr = _frame_with(straight, "wall_double")
    assert scene.kappa == 0.0
    ego_y = scene.ego_l                                       # straight road: radar frame = world - ego
    ghost = fr.path.numpy() == PATH_NAMES.index("wall_double")
    assert (fr.owner.numpy()[ghost] == GHOST_OWNER).all()
    assert (fr.owner.numpy()[fr.path.numpy() == PATH_NAMES.index("wall_bistatic")] == GHOST_OWNER).all()
    g = xyz_of(fr.scatterers, ghost)
    veh = fr.vehicles
    vr = fr.scatterers.velocity_mps.numpy()[ghost]
    n_matched = 0
    for q, v_r in zip(g, vr):
        hits = []
        for y_w in _rail_lines(scene):
            y_wall = y_w - ego_y
            m = np.array([q[0], 2 * y_wall - q[1]])                         # mirror through the rail
            for v in range(len(veh)):
                c, s = math.cos(veh.yaw_rad[v]), math.sin(veh.yaw_rad[v])
                dx, dy = m - veh.center_xyz[v, :2]
                if abs(c * dx + s * dy) <= veh.size_lwh[v, 0] / 2 + 1e-6 and \
                        abs(-s * dx + c * dy) <= veh.size_lwh[v, 1] / 2 + 1e-6:
                    # the ghost moves with the vehicle's mirrored velocity (rigid scatterers)
                    vel = np.array([veh.velocity_xy[v, 0], -veh.velocity_xy[v, 1], 0.0])
                    rel = vel - np.array([fr.ego_speed_mps, 0.0, 0.0])
                    hits.append(abs(float(q @ rel) / np.linalg.norm(q) - v_r))
        assert hits and min(hits) < 1e-9
        n_matched += 1
        # no real vehicle is where the ghost appears
        for v in range(len(veh)):
            assert np.linalg.norm(q[:2] - veh.center_xyz[v, :2]) > veh.size_lwh[v, 1] / 2
    assert n_matched >= 4
    # ghosts change no label: the rows are the same without them
    rows = frame_label_rows(RADIAL, fr, seed=0, sequence=0, index=0, frames_per_sequence=1)
    keep = fr.owner != GHOST_OWNER
    bare = RoadFrame(time_s=fr.time_s, scatterers=fr.scatterers.select(keep), owner=fr.owner[keep],
                     vehicles=veh, road=fr.road, ego_speed_mps=fr.ego_speed_mps, radar_height_m=fr.radar_height_m)
    assert frame_label_rows(RADIAL, bare, seed=0, sequence=0, index=0, frames_per_sequence=1) == rows
    assert GHOST_OWNER not in labelled_vehicles(RADIAL, fr).tolist()
