"""The simulated RADIal laser scanner: against the general 3-D ray caster, the file layout, the
ground in closed form, bad configs."""
import numpy as np
import pytest
import torch

from radarpc.data.radial_format import LASER_PCL_COLUMNS
from radarpc.sensors.radial import TINY
from radarpc.sim.indoor import MATERIALS, Geometry, ray_cast
from radarpc.sim.radial_labels import LIDAR_OFFSET_M
from radarpc.sim.radial_lidar import POST_RADIUS_M, RADIAL_LASER, LaserConfig, _prisms, laser_directions, laser_scan
from radarpc.sim.scenes import scene_mix
from radarpc.sim.radial_writer import RadialSimulator

# a coarse scanner keeps the reference caster fast; same code paths as RADIAL_LASER
COARSE = LaserConfig(azimuth_step_deg=1.0)


@pytest.fixture(scope="module")
def frame():
    sim = RadialSimulator(TINY, 3, 2, 5, scenes=scene_mix("city"))     # facades and parked cars fill the layers
    for q in range(3):
        fr = sim.scene_frame(q, 1)
        if len(fr.vehicles):
            return fr
    raise AssertionError("no frame with vehicles")


def reference_scan(fr, cfg):
    """The same scene through radarpc.sim.indoor.ray_cast (3-D slab and cylinder tests) and a
    ground box, float64."""
    box_xy, box_yaw, box_lw, box_z, post_xy, post_z = _prisms(fr, cfg.max_range_m)
    ground = -fr.radar_height_m - LIDAR_OFFSET_M[2]
    n_b, n_c = len(box_xy), len(post_xy)
    big = 1e4
    f = lambda a: torch.as_tensor(np.asarray(a, float), dtype=torch.float64)  # noqa: E731
    centre = np.concatenate([np.concatenate([box_xy, box_z.mean(1, keepdims=True)], 1), [[0.0, 0.0, ground - 1.0]]])
    half = np.concatenate([np.concatenate([box_lw / 2, (box_z[:, 1:] - box_z[:, :1]) / 2], 1), [[big, big, 1.0]]])
    mat = {m.name: i for i, m in enumerate(MATERIALS)}
    g = Geometry(f(centre), f(half), f(np.concatenate([box_yaw, [0.0]])),
                 torch.tensor([mat["metal"]] * n_b + [mat["ground"]]),
                 f(post_xy.reshape(-1, 2)), f(np.full(n_c, POST_RADIUS_M)), f(post_z.reshape(-1, 2)),
                 torch.full((n_c,), mat["concrete"]), torch.zeros((n_c, 3), dtype=torch.float64))
    d, el, az = laser_directions(cfg)
    hits = ray_cast(g, torch.zeros(3, dtype=torch.float64), f(d), max_range=cfg.max_range_m, eps=1e-9)
    return hits, d


def on_post_caps(fr, pts, cfg):
    """Points on the flat top of a post (the reference caster's cylinders have no caps)."""
    *_, post_xy, post_z = _prisms(fr, cfg.max_range_m)
    near = np.linalg.norm(pts[:, None, :2] - post_xy[None], axis=2) <= POST_RADIUS_M + 1e-4
    return (near & (np.abs(pts[:, None, 2] - post_z[None, :, 1]) < 1e-4)).any(1)


def test_points_match_the_3d_ray_caster(frame):
    pts = laser_scan(frame, COARSE).astype(np.float64)
    hits, d = reference_scan(frame, COARSE)
    hit = hits.hit.numpy()
    assert pts.shape == (int(hit.sum()), 8)
    want = hits.point.numpy()[hit]
    caps = on_post_caps(frame, pts, COARSE)
    assert caps.mean() < 0.01
    # a ray that lands on a cap would, without it, hit the post's side further on (or the ground)
    assert (hits.t.numpy()[hit][caps] > pts[caps, 4]).all()
    # float32 storage of coordinates up to max_range: half an ulp of 150 m is 7.6e-6 m
    tol = 2 * np.finfo(np.float32).eps * COARSE.max_range_m
    np.testing.assert_allclose(pts[~caps, :3], want[~caps], atol=tol, rtol=0)
    np.testing.assert_allclose(pts[~caps, 4], hits.t.numpy()[hit][~caps], atol=tol, rtol=0)
    # intensity = reflectivity x |cos incidence| with the caster's normals and materials
    refl = np.array([m.lidar_reflectivity for m in MATERIALS])[hits.material.numpy()[hit]]
    cos = np.abs((hits.normal.numpy()[hit] * d[hit]).sum(1))
    np.testing.assert_allclose(pts[~caps, 3], (refl * cos)[~caps], atol=1e-6)


def test_laser_files_are_float32(frame):
    assert laser_scan(frame, COARSE).dtype == np.float32


def test_layout_matches_radials_columns(frame):
    pts = laser_scan(frame)
    assert LASER_PCL_COLUMNS == ("x", "y", "z", "intensity", "radialDistance", "polAngle", "aziAngle", "layer_index")
    x, y, z, inten, r, el, az, layer = pts.T.astype(np.float64)
    np.testing.assert_allclose(np.sqrt(x * x + y * y + z * z), r, rtol=1e-5)
    np.testing.assert_allclose(np.arctan2(y, x), az, atol=1e-5)
    np.testing.assert_allclose(np.arcsin(z / r), el, atol=1e-5)
    assert set(np.unique(layer)) <= set(range(RADIAL_LASER.n_layers))
    assert (np.diff(layer) >= 0).all()                                  # layer-major
    assert ((inten >= 0) & (inten <= 1)).all() and (r <= RADIAL_LASER.max_range_m).all()
    assert np.abs(np.degrees(az)).max() <= RADIAL_LASER.azimuth_fov_deg / 2 + 1e-6
    # layer k looks 0.6 deg above layer k - 1: elevation is affine in the layer index
    el_deg = np.degrees(el)
    np.testing.assert_allclose(el_deg - layer * RADIAL_LASER.layer_pitch_deg,
                               el_deg[0] - layer[0] * RADIAL_LASER.layer_pitch_deg, atol=1e-4)


def test_ground_hits_in_closed_form(frame):
    # a downward ray that meets nothing first hits the ground at h / sin(-e)
    pts = laser_scan(frame).astype(np.float64)
    h = frame.radar_height_m + LIDAR_OFFSET_M[2]
    ground = np.abs(pts[:, 2] + h) < 1e-4
    assert ground.any()
    np.testing.assert_allclose(pts[ground, 4], h / np.sin(-pts[ground, 5]), rtol=1e-5)


def test_bad_config():
    with pytest.raises(ValueError, match="n_layers must be >= 1"):
        LaserConfig(n_layers=0)
    with pytest.raises(ValueError, match="azimuth_step_deg must be > 0"):
        LaserConfig(azimuth_step_deg=0.0)
    with pytest.raises(ValueError, match=r"azimuth_fov_deg must be in \(0, 360\)"):
        LaserConfig(azimuth_fov_deg=400.0)


def test_empty_scene_is_ground_only(frame):
    import dataclasses

    from radarpc.sim.rd import Scatterers
    from radarpc.sim.road import VehicleTruth

    z = torch.zeros(0, dtype=torch.float64)
    empty = dataclasses.replace(
        frame, scatterers=Scatterers(z, z, z, z, z), owner=torch.zeros(0, dtype=torch.int64),
        vehicles=VehicleTruth(**{f.name: getattr(frame.vehicles, f.name)[:0] for f in dataclasses.fields(VehicleTruth)}))
    pts = laser_scan(empty, COARSE).astype(np.float64)
    d, el, az = laser_directions(COARSE)
    h = frame.radar_height_m + LIDAR_OFFSET_M[2]
    # exactly the downward rays whose ground point lies within range
    assert len(pts) == int(((el < 0) & (h / np.sin(np.maximum(-el, 1e-12)) <= COARSE.max_range_m)).sum())
    np.testing.assert_allclose(pts[:, 2], -h, atol=1e-5)
