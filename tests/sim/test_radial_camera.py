"""The simulated RADIal camera: calibration facts, vehicle boxes against an independent pinhole
projection, the rendered image against those boxes, bad input."""
import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from radarpc.sensors.radial import TINY
from radarpc.sim import radial_camera as rc
from radarpc.sim.scenes import scene_mix
from radarpc.sim.radial_writer import RadialSimulator
from radarpc.sim.road import VehicleTruth

# RADIal camera_calib.npy, written out independently of the module's constants
K = np.array([[1845.41929, 0.0, 855.802458], [0.0, 1788.69210, 607.342667], [0.0, 0.0, 1.0]])
RVEC = np.array([1.61803058, 0.03365624, -0.04003127])
TVEC = np.array([0.09138029, 1.38369885, 1.43674736])


def vehicles(centres, size=(4.5, 1.8, 1.5), yaw=0.0, radar_height=0.8) -> VehicleTruth:
    """Hand-made vehicles (radar frame footprint centres ``(V, 2)``) with the fields VehicleTruth has."""
    c = np.asarray(centres, float).reshape(-1, 2)
    n = len(c)
    base = dict(ids=np.arange(n), kind=np.zeros(n, np.int64),
                center_xyz=np.concatenate([c, np.full((n, 1), -radar_height)], 1),
                size_lwh=np.tile(np.asarray(size, float), (n, 1)), yaw_rad=np.full(n, float(yaw)),
                velocity_xy=np.zeros((n, 2)), rel_velocity_xy=np.zeros((n, 2)), visible_fraction=np.ones(n))
    kw = {}
    for f in dataclasses.fields(VehicleTruth):
        if f.name in base:
            kw[f.name] = base[f.name]
        else:                               # fields added to the truth later: zeros of one per vehicle
            kw[f.name] = np.zeros(n, np.int64)
    return VehicleTruth(**kw)


def reference_boxes(centres, size, yaw, radar_height) -> np.ndarray:
    """Pinhole boxes of boxes wholly in front of the camera, computed from scratch (float64)."""
    r = Rotation.from_rotvec(RVEC).as_matrix()
    out = []
    for cx, cy in np.asarray(centres, float).reshape(-1, 2):
        l, w, h = size
        pts = []
        for sx in (-0.5, 0.5):
            for sy in (-0.5, 0.5):
                for z in (0.0, h):
                    x = cx + np.cos(yaw) * sx * l - np.sin(yaw) * sy * w
                    y = cy + np.sin(yaw) * sx * l + np.cos(yaw) * sy * w
                    pts.append([-y, x, z])          # calibration frame: right, forward, up (ground = 0)
        cam = np.asarray(pts) @ r.T + TVEC
        assert (cam[:, 2] > 0.5).all()
        uv = (cam @ K.T)[:, :2] / cam[:, 2:3]
        lo, hi = uv.min(0), uv.max(0)
        out.append([max(lo[0], 0), max(lo[1], 0), min(hi[0], 1919), min(hi[1], 1079)])
    return np.asarray(out)


def test_rotation_and_mount_match_the_calibration():
    np.testing.assert_allclose(rc.rotation_matrix(RVEC), Rotation.from_rotvec(RVEC).as_matrix(), atol=1e-14)
    m, c = rc.radar_to_camera(0.8)
    # the camera centre in the radar frame: p with M p + c = 0
    centre = -np.linalg.solve(m, c)
    assert abs(centre[2] + 0.8 - 1.45) < 0.01              # RADIal's sensor table: camera 145 cm high
    assert -1.45 < centre[0] < -1.3 and abs(centre[1]) < 0.05   # behind the grille, on the axis
    np.testing.assert_allclose(rc.CAMERA_MATRIX, K)
    assert rc.IMAGE_SIZE == (960, 540) and rc.FULL_SIZE == (1920, 1080)


@pytest.mark.parametrize("yaw", [0.0, 0.4, np.pi])
def test_boxes_match_an_independent_projection(yaw):
    centres = [(12.0, 0.0), (25.0, -3.5), (40.0, 4.0), (8.0, 2.5)]
    size = (4.5, 1.8, 1.5)
    got = rc.vehicle_image_boxes(vehicles(centres, size, yaw), 0.8)
    want = reference_boxes(centres, size, yaw, 0.8)
    # the same real numbers; rint may go either way on a float rounding at .5
    assert np.abs(got - want).max() <= 0.5 + 1e-6
    assert got.dtype == np.int64


def test_boxes_outside_the_image_are_minus_one():
    # behind the radar, far to the side, and above the field of view
    v = vehicles([(-10.0, 0.0), (5.0, 40.0), (10.0, 0.0)])
    v.center_xyz[2, 2] = 30.0
    got = rc.vehicle_image_boxes(v, 0.8)
    np.testing.assert_array_equal(got, -1)
    assert rc.vehicle_image_boxes(vehicles(np.zeros((0, 2))), 0.8).shape == (0, 4)


def test_box_crossing_the_near_plane_is_clipped_not_lost():
    # a car alongside, its front ahead of the camera, its rear behind it: seen at the image's edge
    got = rc.vehicle_image_boxes(vehicles([(0.5, 3.0)], size=(6.0, 1.8, 1.5)), 0.8)[0]
    assert (got >= 0).all() and got[0] == 0 and got[2] > 0           # touches the left border
    assert got[2] < 1920 and got[3] <= 1079


@pytest.fixture(scope="module")
def framed():
    sim = RadialSimulator(TINY, 6, 3, 5, scenes=scene_mix("city"))     # city: the densest traffic
    for q in range(6):
        for i in range(3):
            fr = sim.scene_frame(q, i)
            boxes = rc.vehicle_image_boxes(fr.vehicles, fr.radar_height_m)
            if (boxes[:, 0] >= 0).sum() >= 2:
                return sim, q, fr, boxes
    raise AssertionError("no frame with two vehicles in view")


def without_vehicles(v: VehicleTruth) -> VehicleTruth:
    return VehicleTruth(**{f.name: getattr(v, f.name)[:0] for f in dataclasses.fields(VehicleTruth)})


def test_rendered_vehicles_lie_inside_their_boxes(framed):
    sim, q, fr, boxes = framed
    img = rc.render_camera(fr, lane_width_m=sim.preset(q).lane_width_m)
    assert img.shape == (540, 960, 3) and img.dtype == np.uint8
    bare = rc.render_camera(dataclasses.replace(fr, vehicles=without_vehicles(fr.vehicles)),
                            lane_width_m=sim.preset(q).lane_width_m)
    changed = np.any(img != bare, axis=2)
    assert changed.any()
    inside = np.zeros_like(changed)
    for x1, y1, x2, y2 in boxes[boxes[:, 0] >= 0]:
        # full-resolution box -> half-resolution pixels, one pixel of polygon rasterisation slack
        inside[max(int(y1 // 2) - 1, 0):int(y2 // 2) + 2, max(int(x1 // 2) - 1, 0):int(x2 // 2) + 2] = True
    assert not (changed & ~inside).any()
    # every vehicle whose box is at least 4 x 4 half-resolution pixels changed something in it
    for x1, y1, x2, y2 in boxes[boxes[:, 0] >= 0]:
        if x2 - x1 >= 8 and y2 - y1 >= 8:
            assert changed[int(y1 // 2):int(y2 // 2) + 1, int(x1 // 2):int(x2 // 2) + 1].any()


def test_empty_frame_renders(framed):
    import torch

    from radarpc.sim.rd import Scatterers

    _, _, fr, _ = framed
    z = torch.zeros(0, dtype=torch.float64)
    empty = dataclasses.replace(fr, vehicles=without_vehicles(fr.vehicles), owner=torch.zeros(0, dtype=torch.int64),
                                scatterers=Scatterers(z, z, z, z, z))
    img = rc.render_camera(empty)
    assert img.shape == (540, 960, 3)
    # sky above the horizon, ground or road below it
    assert img[0, 480, 2] > img[0, 480, 0] and not (img[-1] == img[0]).all()


def test_render_is_deterministic_and_jpeg_decodes(framed):
    from io import BytesIO

    from PIL import Image

    sim, q, fr, _ = framed
    a = rc.render_camera(fr)
    np.testing.assert_array_equal(a, rc.render_camera(fr))
    im = Image.open(BytesIO(rc.jpeg_bytes(a)))
    assert im.format == "JPEG" and im.size == rc.IMAGE_SIZE and im.mode == "RGB"
    # JPEG at quality 90: the decoded image stays close to the render
    assert np.abs(np.asarray(im, float) - a).mean() < 4.0


def test_bad_input(framed):
    sim, q, fr, _ = framed
    with pytest.raises(ValueError, match="lane_width_m must be > 0"):
        rc.render_camera(fr, lane_width_m=0.0)
    with pytest.raises(ValueError, match=r"image must be uint8 \(H, W, 3\)"):
        rc.jpeg_bytes(np.zeros((4, 4), np.uint8))
