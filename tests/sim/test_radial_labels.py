"""RADIal label rows and freespace masks from hand-made scene geometry."""
import math

import numpy as np
import pytest
import torch

from radarpc.data.radial_format import FREESPACE_SHAPE, LABEL_COLUMNS, freespace_azimuth_deg
from radarpc.sensors.radial import RADIAL
from radarpc.sim.radial_labels import (
    LIDAR_OFFSET_M,
    frame_label_rows,
    freespace_mask,
    reference_points,
)
from radarpc.sim.rd import Scatterers
from radarpc.sim.road import RoadFrame, RoadGeometry, VehicleTruth

H_RADAR = 0.8


def vehicles(centres_xy, yaws, rel_vel, visible=None, size=(4.5, 1.8, 1.5)):
    n = len(centres_xy)
    c = np.concatenate([np.asarray(centres_xy, float), np.full((n, 1), -H_RADAR)], 1)
    rel = np.asarray(rel_vel, float)
    return VehicleTruth(ids=np.arange(n), kind=np.zeros(n, np.int64), center_xyz=c,
                        size_lwh=np.tile(size, (n, 1)).astype(float), yaw_rad=np.asarray(yaws, float),
                        velocity_xy=rel + [[10.0, 0.0]], rel_velocity_xy=rel,
                        visible_fraction=np.ones(n) if visible is None else np.asarray(visible, float))


def frame_of(veh, xyz, owner, rcs, road=(-5.0, 5.0)):
    xyz = torch.tensor(xyz, dtype=torch.float64).reshape(-1, 3)
    sc = Scatterers.from_xyz(xyz, torch.zeros_like(xyz), torch.tensor(rcs, dtype=torch.float64))
    geo = RoadGeometry(curvature_1pm=0.0, radar_xy=(0.0, 0.0), radar_heading_rad=0.0, bounds_m=road)
    return RoadFrame(time_s=0.0, scatterers=sc, owner=torch.tensor(owner, dtype=torch.int64), vehicles=veh,
                     road=geo, ego_speed_mps=10.0, radar_height_m=H_RADAR)


def test_reference_point_is_the_middle_of_the_visible_back_or_front_face():
    veh = vehicles([(20.0, 2.0), (30.0, -3.0), (0.5, 4.0)], [0.0, math.pi, 0.0], np.zeros((3, 2)))
    ref = reference_points(veh)
    z = -H_RADAR + 1.5 / 2
    # ahead, same direction: its back face; oncoming: its front face (both face the radar)
    np.testing.assert_allclose(ref[0], [20.0 - 2.25, 2.0, z])
    np.testing.assert_allclose(ref[1], [30.0 - 2.25, -3.0, z])
    # alongside, centre just ahead of the radar: the back face, nearer the radar
    np.testing.assert_allclose(ref[2], [0.5 - 2.25, 4.0, z])


def test_label_row_values_from_a_hand_made_vehicle():
    veh = vehicles([(20.0, 2.0), (60.0, -150.0)], [0.0, 0.0], [(3.0, 0.0), (0.0, 0.0)], visible=[0.4, 1.0])
    # two scatterers on vehicle 0, one static, one on vehicle 1 (which is outside the field of view)
    xyz = [(17.75, 2.0, -0.3), (17.75, 1.0, -0.3), (40.0, 6.0, 0.0), (57.0, -150.0, 0.0)]
    fr = frame_of(veh, xyz, [0, 0, -1, 1], [2.0, 1.0, 5.0, 1.0])
    rows = frame_label_rows(RADIAL, fr, seed=7, sequence=2, index=3, frames_per_sequence=10)
    assert len(rows) == 1
    row = dict(zip(LABEL_COLUMNS, rows[0]))
    x, y = 17.75, 2.0
    r = math.hypot(x, y)
    assert row["numSample"] == 23 and row["dataset"] == "SIM@s7_q002" and row["dataset_index"] == 3
    # the camera box of the vehicle (checked against an independent projection in test_radial_camera)
    from radarpc.sim.radial_camera import vehicle_image_boxes
    box = (row["x1_pix"], row["y1_pix"], row["x2_pix"], row["y2_pix"])
    assert box == tuple(vehicle_image_boxes(veh, H_RADAR)[0]) and 0 <= box[0] < box[2] <= 1919 and 0 <= box[1] < box[3] <= 1079
    assert row["radar_X_m"] == x and row["radar_Y_m"] == y
    assert row["radar_R_m"] == pytest.approx(r, abs=1e-4)
    assert row["radar_A_deg"] == pytest.approx(math.degrees(math.atan2(y, x)), abs=1e-4)
    assert row["radar_D"] == pytest.approx(3.0 * x / r, abs=1e-4)          # receding: positive
    z = -H_RADAR + 0.75
    assert (row["laser_X_m"], row["laser_Y_m"], row["laser_Z_m"]) == pytest.approx(
        (x - LIDAR_OFFSET_M[0], y - LIDAR_OFFSET_M[1], z - LIDAR_OFFSET_M[2]), abs=1e-4)
    # power: sum of the peak SNR per RD cell of its two scatterers (radar equation x FFT gain x window loss)
    loss = 0.54 ** 2 / (0.54 ** 2 + 0.46 ** 2 / 2)
    ranges = [math.dist((0, 0, 0), p) for p in xyz[:2]]
    snr = sum(float(RADIAL.snr_per_sample(rr, s)) for rr, s in zip(ranges, [2.0, 1.0]))
    want_db = 10 * math.log10(snr * RADIAL.n_range * RADIAL.n_doppler * loss ** 2)
    assert row["radar_P_db"] == pytest.approx(want_db, abs=0.01)
    assert row["Difficult"] == 1                                           # 60 % occluded


def test_frame_without_vehicles_gets_one_minus_one_row():
    veh = vehicles(np.zeros((0, 2)), [], np.zeros((0, 2)))
    fr = frame_of(veh, [(30.0, 0.0, 0.0)], [-1], [1.0])
    rows = frame_label_rows(RADIAL, fr, seed=0, sequence=1, index=4, frames_per_sequence=5)
    assert len(rows) == 1
    row = dict(zip(LABEL_COLUMNS, rows[0]))
    assert (row["numSample"], row["dataset"], row["dataset_index"]) == (9, "SIM@s0_q001", 4)
    others = [v for c, v in row.items() if c not in ("numSample", "dataset", "dataset_index")]
    assert others == [-1] * (len(LABEL_COLUMNS) - 3)
    with pytest.raises(ValueError, match="frame index"):
        frame_label_rows(RADIAL, fr, seed=0, sequence=1, index=5, frames_per_sequence=5)


def test_freespace_polar_raster_against_the_geometry():
    veh = vehicles([(20.0, 0.0)], [0.0], np.zeros((1, 2)))
    fs = freespace_mask(RADIAL, frame_of(veh, [(30.0, 0.0, 0.0)], [-1], [1.0], road=(-5.0, 5.0)))
    assert fs.shape == FREESPACE_SHAPE and fs.dtype == np.uint8
    assert set(np.unique(fs).tolist()) <= {0, 255}
    pitch = RADIAL.max_range_m / FREESPACE_SHAPE[0]
    az = freespace_azimuth_deg(np.arange(FREESPACE_SHAPE[1]))
    col0 = int(np.argmin(np.abs(az)))                                        # straight ahead
    row = lambda r: int(round(r / pitch))                                    # noqa: E731
    assert fs[row(10.0), col0] == 255                                        # road ahead of the car: free
    assert fs[row(20.0), col0] == 0                                          # inside the car
    assert fs[row(40.0), col0] == 0                                          # behind the car: occluded
    col45 = int(np.argmin(np.abs(az - 45.0)))
    assert fs[row(5.0), col45] == 255                                        # y = 3.5: on the road
    assert fs[row(10.0), col45] == 0                                         # y = 7.1: off the road
    # brute force over every pixel of a few columns
    for col in (col0, col45, 100, 600):
        a = math.radians(az[col])
        for i in range(0, FREESPACE_SHAPE[0], 7):
            r = i * pitch
            x, y = r * math.cos(a), r * math.sin(a)
            on_road = -5.0 <= y <= 5.0
            # first footprint hit along this ray (car box [17.75, 22.25] x [-0.9, 0.9])
            blocked = False
            for k in range(0, 400):
                s = r * k / 399
                if 17.75 <= s * math.cos(a) <= 22.25 and abs(s * math.sin(a)) <= 0.9:
                    blocked = True
                    break
            assert (fs[i, col] == 255) == (on_road and not blocked), (i, col)


def test_curved_road_lateral_offset_and_freespace():
    # left-hand bend of radius 50 m; the radar sits 2 m right of the centre line at arc length 10 m
    k, s0, l0 = 1 / 50, 10.0, -2.0

    def world(s, l):
        t = k * s
        return np.array([math.sin(t) / k - l * math.sin(t), (1 - math.cos(t)) / k + l * math.cos(t)])

    th = k * s0
    pos = world(s0, l0)
    geo = RoadGeometry(curvature_1pm=k, radar_xy=tuple(pos), radar_heading_rad=th, bounds_m=(-4.0, 4.0))
    # points of the radar's lane further along the bend, in the radar frame
    for ds in (5.0, 20.0, 40.0):
        rel = world(s0 + ds, l0) - pos
        xy = np.array([math.cos(th) * rel[0] + math.sin(th) * rel[1], -math.sin(th) * rel[0] + math.cos(th) * rel[1]])
        assert float(geo.lateral_m(xy)) == pytest.approx(l0, abs=1e-9)
        assert bool(geo.on_road(xy))
    assert float(geo.lateral_m(np.array([0.0, 3.0]))) == pytest.approx(l0 + 3.0, abs=1e-9)
    veh = vehicles(np.zeros((0, 2)), [], np.zeros((0, 2)))
    base = frame_of(veh, [(30.0, 0.0, 0.0)], [-1], [1.0])
    fr = RoadFrame(time_s=0.0, scatterers=base.scatterers, owner=base.owner, vehicles=veh, road=geo,
                   ego_speed_mps=10.0, radar_height_m=H_RADAR)
    fs = freespace_mask(RADIAL, fr)
    pitch = RADIAL.max_range_m / FREESPACE_SHAPE[0]
    az = freespace_azimuth_deg(np.arange(FREESPACE_SHAPE[1]))
    # straight ahead the road bends away to the left: free near, off the road far away
    col0 = int(np.argmin(np.abs(az)))
    assert fs[int(10 / pitch), col0] == 255 and fs[int(60 / pitch), col0] == 0
    # along the bend: the lane point 40 m further on is free
    rel = world(s0 + 40.0, l0) - pos
    x, y = math.cos(th) * rel[0] + math.sin(th) * rel[1], -math.sin(th) * rel[0] + math.cos(th) * rel[1]
    col = int(np.argmin(np.abs(az - math.degrees(math.atan2(y, x)))))
    assert fs[int(round(math.hypot(x, y) / pitch)), col] == 255


def _in_footprint(xy, veh, grow=0.0):
    """(..., V) bool: ground points xy (..., 2) inside each vehicle's footprint grown by ``grow`` m."""
    d = xy[..., None, :] - veh.center_xyz[:, :2]                             # (..., V, 2)
    c, s = np.cos(veh.yaw_rad), np.sin(veh.yaw_rad)
    along = d[..., 0] * c + d[..., 1] * s                                    # body x
    across = -d[..., 0] * s + d[..., 1] * c                                  # body y
    return (np.abs(along) <= veh.size_lwh[:, 0] / 2 + grow) & (np.abs(across) <= veh.size_lwh[:, 1] / 2 + grow)


def test_freespace_of_real_road_scene_frames():
    # frames of the procedural scene (not hand-made geometry), checked by brute force: pixels in
    # a vehicle's footprint are 0; road pixels ahead with no footprint (grown by 0.15 m) on the
    # segment from the radar are 255; pixels behind a footprint (shrunk by 0.15 m) are 0.
    from radarpc.sim.road import RoadScene, RoadSceneConfig

    cfg = RADIAL
    n_r, n_a = FREESPACE_SHAPE
    pitch = cfg.max_range_m / n_r
    cols = np.arange(0, n_a, 3)
    az = np.deg2rad(freespace_azimuth_deg(cols))                             # (C,)
    rows = np.arange(n_r)
    pix = (rows * pitch)[:, None, None] * np.stack([np.cos(az), np.sin(az)], -1)[None]  # (R, C, 2)
    steps = np.arange(0.0, cfg.max_range_m, 0.05)                            # ray samples, m
    ray = steps[:, None, None] * np.stack([np.cos(az), np.sin(az)], -1)[None]           # (K, C, 2)
    counts = np.zeros(3, int)
    for seq, t in ((0, 0.0), (1, 0.3), (2, 0.6)):
        fr = RoadScene(RoadSceneConfig(), 7, seq, 10, cfg.max_range_m).frame(t)
        veh = fr.vehicles
        assert len(veh) > 0
        fs = freespace_mask(cfg, fr)[:, cols]                                # (R, C)

        def first_entry(grow):
            hit = _in_footprint(ray, veh, grow).any(-1)                      # (K, C)
            return np.where(hit.any(0), steps[np.argmax(hit, 0)], np.inf)    # (C,)

        inside = _in_footprint(pix, veh).any(-1)                             # (R, C)
        r = (rows * pitch)[:, None]
        clear = (r < first_entry(0.15)[None] - 0.05) & fr.road.on_road(pix) & (pix[..., 0] > 0)
        shadow = r > first_entry(-0.15)[None] + 0.05
        assert np.all(fs[inside] == 0)
        assert np.all(fs[clear] == 255)
        assert np.all(fs[shadow] == 0)
        counts += [inside.sum(), clear.sum(), shadow.sum()]
    assert counts[0] > 50 and counts[1] > 5000 and counts[2] > 500, counts
