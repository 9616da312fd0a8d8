"""RADIal's front camera seen from a simulated road frame: perspective images and vehicle boxes.

Geometry (facts of the public RADIal material, written here as constants):

* the intrinsic matrix :data:`CAMERA_MATRIX` and the extrinsic rotation / translation vectors
  :data:`ROTATION_VECTOR`, :data:`TRANSLATION_M` are those of RADIal's
  ``DBReader/examples/camera_calib.npy`` (also written out in ``FFTRadNet/utils/util.py``). They
  map a point of the calibration frame -- x right, y forward, z up, origin on the ground below
  the sensor column of the front grille (radar above the LiDAR) -- to the OpenCV camera frame
  (x right, y down, z forward): ``p_cam = R(rvec) p + t``. The camera centre ``-R^T t`` is
  then 2 cm left, 1.37 m behind the grille and 1.45 m above the ground (RADIal's sensor table:
  145 cm), looking 2.7 deg down and 2.7 deg left;
* the recorded frames are :data:`FULL_SIZE` = 1920 x 1080 pixels (``FFTRadNet/utils/util.py``);
  ``labels.csv``'s ``x1_pix .. y2_pix`` are in those pixels. RADIal's ready-to-use release stores
  the images at half width and height (its ``loader/example_dataset.ipynb`` divides the boxes
  by 2), :data:`IMAGE_SIZE` = 960 x 540, which is what :func:`render_camera` draws;
* the camera is an ideal pinhole: the published distortion coefficients (k1, k2, p1, p2, k3 =
  0.25, -13.3, 0.004, -0.007, 59.6) are a polynomial fit that is not monotonic over the frame
  (radial factor 0.95 at r^2 = 0.1 but 2.8 in the corners), so they are not applied.

The radar frame (x forward, y left, z up, at ``radar_height_m`` above the ground) maps to the
calibration frame as ``(-y, x, z + radar_height_m)``.

Rendering (:func:`render_camera`): sky, ground, the road surface between its edges (and a cross
street), lane lines (dashed between lanes of one direction, solid at the centre line), every
vehicle as a shaded
3-D box with windows (painter's order, far to near, back faces culled, faces clipped at the near
plane), and every static reflector of the frame standing above the ground (poles, rails, facades,
people) as a post, so the camera sees the same world as the radar. PIL draws the polygons.
"""
from __future__ import annotations

import io
import math

import numpy as np
from PIL import Image, ImageDraw

from radarpc.sim.road import RoadFrame, VehicleTruth

__all__ = [
    "CAMERA_MATRIX",
    "ROTATION_VECTOR",
    "TRANSLATION_M",
    "FULL_SIZE",
    "IMAGE_SIZE",
    "NEAR_M",
    "rotation_matrix",
    "radar_to_camera",
    "project",
    "vehicle_corners",
    "vehicle_image_boxes",
    "scatterer_xyz",
    "render_camera",
    "jpeg_bytes",
]

CAMERA_MATRIX: tuple[tuple[float, float, float], ...] = (
    (1845.41929, 0.0, 855.802458),
    (0.0, 1788.69210, 607.342667),
    (0.0, 0.0, 1.0),
)
"""Intrinsics of the 1920 x 1080 frames (RADIal ``camera_calib.npy``, ``camera_matrix``)."""
ROTATION_VECTOR: tuple[float, float, float] = (1.61803058, 0.03365624, -0.04003127)
"""Rodrigues vector of the calibration-frame -> camera rotation (``camera_calib.npy``)."""
TRANSLATION_M: tuple[float, float, float] = (0.09138029, 1.38369885, 1.43674736)
"""Translation of the calibration-frame -> camera transform, metres (``camera_calib.npy``)."""
FULL_SIZE: tuple[int, int] = (1920, 1080)
"""Width, height of the recorded frames: the pixels of ``labels.csv``'s boxes."""
IMAGE_SIZE: tuple[int, int] = (960, 540)
"""Width, height of the written ``camera/image_*.jpg`` (half of :data:`FULL_SIZE`, as the release)."""
NEAR_M: float = 0.2
"""Near plane: geometry closer than this along the optical axis is clipped."""

_SCALE = IMAGE_SIZE[0] / FULL_SIZE[0]
_SKY_TOP, _SKY_HORIZON = np.array([92, 140, 205]), np.array([200, 218, 235])
_GROUND, _ROAD, _MARK = (96, 112, 72), (88, 88, 92), (235, 235, 225)
_POST = (120, 118, 112)
_BODY_COLOURS = ((170, 30, 35), (30, 60, 140), (200, 200, 205), (40, 40, 45), (110, 115, 120),
                 (230, 230, 232), (20, 90, 60), (190, 150, 40))
# brightness of the 6 faces (rear, front, right, left, bottom, top): light from above
_FACE_SHADE = (0.75, 0.9, 0.6, 0.6, 0.45, 1.05)
# box faces as corner indices (corners: rear-right, front-right, front-left, rear-left at the
# bottom, then the same on the top)
_FACES = ((0, 3, 7, 4), (1, 5, 6, 2), (0, 4, 5, 1), (3, 2, 6, 7), (0, 1, 2, 3), (4, 7, 6, 5))
_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))


def rotation_matrix(rvec) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of a Rodrigues vector: ``I + sin t K + (1 - cos t) K^2``."""
    r = np.asarray(rvec, dtype=np.float64)
    theta = float(np.linalg.norm(r))
    if theta == 0.0:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * kx @ kx


def radar_to_camera(radar_height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(M, c)`` with ``p_cam = M @ p_radar + c`` (OpenCV camera frame, metres)."""
    r = rotation_matrix(ROTATION_VECTOR)
    to_calib = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # (-y, x, z)
    c = np.asarray(TRANSLATION_M, dtype=np.float64) + r @ np.array([0.0, 0.0, float(radar_height_m)])
    return r @ to_calib, c


def project(p_cam: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Pixel coordinates ``(..., 2)`` of camera-frame points ``(..., 3)`` (``z > 0``).

    ``scale`` 1 gives :data:`FULL_SIZE` pixels, 0.5 :data:`IMAGE_SIZE` pixels.
    """
    k = np.asarray(CAMERA_MATRIX)
    z = p_cam[..., 2]
    u = (k[0, 0] * p_cam[..., 0] / z + k[0, 2]) * scale
    v = (k[1, 1] * p_cam[..., 1] / z + k[1, 2]) * scale
    return np.stack([u, v], -1)


def vehicle_corners(vehicles: VehicleTruth) -> np.ndarray:
    """The 8 corners ``(V, 8, 3)`` of each vehicle's box in the radar frame (bottom 4, then top 4)."""
    xy = vehicles.corners_xy()                                                  # (V, 4, 2)
    z0 = np.broadcast_to(vehicles.center_xyz[:, None, 2:3], xy.shape[:2] + (1,))
    z1 = z0 + vehicles.size_lwh[:, None, 2:3]
    return np.concatenate([np.concatenate([xy, z0], -1), np.concatenate([xy, z1], -1)], 1)


def _clipped_points(cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners in front of the near plane and the edges' crossings of it: ``(V, 20, 3)``, valid."""
    a = cam[:, [e[0] for e in _EDGES]]                                          # (V, 12, 3)
    b = cam[:, [e[1] for e in _EDGES]]
    za, zb = a[..., 2], b[..., 2]
    crosses = (za - NEAR_M) * (zb - NEAR_M) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(crosses, (NEAR_M - za) / (zb - za), 0.0)
    x = a + s[..., None] * (b - a)
    pts = np.concatenate([cam, x], 1)
    valid = np.concatenate([cam[..., 2] >= NEAR_M, crosses], 1)
    return pts, valid


def vehicle_image_boxes(vehicles: VehicleTruth, radar_height_m: float) -> np.ndarray:
    """Image boxes of the vehicles in :data:`FULL_SIZE` pixels, int64 ``(V, 4)``: x1, y1, x2, y2.

    The bounding rectangle of the projection of the vehicle's 3-D box (its part in front of the
    near plane), rounded to whole pixels and clipped to the image; ``-1`` in all four where the
    box lies behind the camera or entirely outside the image.
    """
    n = len(vehicles)
    out = np.full((n, 4), -1, dtype=np.int64)
    if n == 0:
        return out
    m, c = radar_to_camera(radar_height_m)
    cam = vehicle_corners(vehicles) @ m.T + c                                   # (V, 8, 3)
    pts, valid = _clipped_points(cam)
    uv = project(np.where(valid[..., None], pts, 1.0))                          # (V, 20, 2)
    lo = np.where(valid[..., None], uv, np.inf).min(1)
    hi = np.where(valid[..., None], uv, -np.inf).max(1)
    w, h = FULL_SIZE
    seen = valid.any(1) & (hi[:, 0] >= 0) & (lo[:, 0] <= w - 1) & (hi[:, 1] >= 0) & (lo[:, 1] <= h - 1)
    lo, hi = lo[seen], hi[seen]
    box = np.stack([np.clip(lo[:, 0], 0, w - 1), np.clip(lo[:, 1], 0, h - 1),
                    np.clip(hi[:, 0], 0, w - 1), np.clip(hi[:, 1], 0, h - 1)], 1)
    out[seen] = np.rint(box).astype(np.int64)
    return out


# ---- rendering ----------------------------------------------------------------------------------
_SKY_CACHE: dict[tuple[int, int], np.ndarray] = {}


def _sky() -> np.ndarray:
    w, h = IMAGE_SIZE
    if (w, h) not in _SKY_CACHE:
        t = np.linspace(0.0, 1.0, h)[:, None]
        rows = (_SKY_TOP * (1 - t) + _SKY_HORIZON * t).astype(np.uint8)          # (H, 3)
        _SKY_CACHE[(w, h)] = np.ascontiguousarray(np.broadcast_to(rows[:, None, :], (h, w, 3)))
    return _SKY_CACHE[(w, h)]


def _clip_polygon(poly: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon ``(K, 3)`` to ``z >= NEAR_M``."""
    out = []
    k = len(poly)
    for i in range(k):
        p, q = poly[i], poly[(i + 1) % k]
        pin, qin = p[2] >= NEAR_M, q[2] >= NEAR_M
        if pin:
            out.append(p)
        if pin != qin:
            s = (NEAR_M - p[2]) / (q[2] - p[2])
            out.append(p + s * (q - p))
    return np.asarray(out).reshape(-1, 3)


def _shade(rgb, f: float) -> tuple[int, int, int]:
    return tuple(int(min(255, max(0, round(x * f)))) for x in rgb)


def _road_strip(frame: RoadFrame, lat: tuple[float, float], s_rel: np.ndarray) -> np.ndarray:
    """Radar-frame ground points ``(2, S, 3)`` of two lateral offsets ``lat`` at arc lengths
    ``s_rel`` ahead of the radar along the road's centre line."""
    road = frame.road
    k = road.curvature_1pm
    x0, y0 = road.radar_xy
    if k == 0.0:
        s_radar = x0
    else:                                          # angle of the radar about the circle's centre
        sg = math.copysign(1.0, k)
        s_radar = math.atan2(sg * x0, sg * (1.0 / k - y0)) / k
    s = s_radar + s_rel
    out = []
    for l in lat:
        ks = k * s
        a = s * np.sinc(ks / np.pi)
        b = 0.5 * k * s * s * np.sinc(ks / (2 * np.pi)) ** 2
        wx, wy = a - l * np.sin(ks), b + l * np.cos(ks)
        out.append(_world_to_radar(frame, wx, wy))
    return np.stack(out)


def _world_to_radar(frame: RoadFrame, wx: np.ndarray, wy: np.ndarray) -> np.ndarray:
    """Radar-frame ``(..., 3)`` positions of world ground points."""
    road = frame.road
    ch, sh = math.cos(road.radar_heading_rad), math.sin(road.radar_heading_rad)
    dx, dy = wx - road.radar_xy[0], wy - road.radar_xy[1]
    return np.stack([ch * dx + sh * dy, -sh * dx + ch * dy, np.full_like(dx, -frame.radar_height_m)], -1)


def _quads(strip: np.ndarray, m: np.ndarray, c: np.ndarray, every: int = 1) -> np.ndarray:
    """Camera-frame quads ``(Q, 4, 3)`` between consecutive samples of a ``(2, S, 3)`` strip."""
    cam = strip @ m.T + c
    i = np.arange(0, cam.shape[1] - 1, every)
    return np.stack([cam[0, i], cam[0, i + 1], cam[1, i + 1], cam[1, i]], 1)


def _image_polygons(polys: np.ndarray) -> list[list[float] | None]:
    """Flat image-pixel vertex lists ``[u0, v0, u1, ...]`` of camera-frame polygons ``(P, K, 3)``;
    None where nothing shows.

    Polygons wholly in front of the near plane are projected together; the few that cross it are
    clipped one by one; those wholly behind it or outside the image are dropped.
    """
    if len(polys) == 0:
        return []
    w, h = IMAGE_SIZE
    z = polys[..., 2]
    front = (z >= NEAR_M).all(1)
    uv = np.clip(project(np.where(front[:, None, None], polys, 1.0), _SCALE), -1e4, 1e4)
    inside = (uv[..., 0].max(1) >= 0) & (uv[..., 0].min(1) <= w) & (uv[..., 1].max(1) >= 0) & (uv[..., 1].min(1) <= h)
    out: list = [None] * len(polys)
    lists = uv.reshape(len(polys), -1).tolist()
    for i in np.flatnonzero(front & inside).tolist():
        out[i] = lists[i]
    for i in np.flatnonzero(~front & (z >= NEAR_M).any(1)).tolist():
        p = _clip_polygon(polys[i])
        if len(p) >= 3:
            out[i] = np.clip(project(p, _SCALE), -1e4, 1e4).reshape(-1).tolist()
    return out


def render_camera(frame: RoadFrame, *, lane_width_m: float = 3.5) -> np.ndarray:
    """The camera image of a road frame, uint8 ``(540, 960, 3)`` RGB (module docstring).

    Parameters
    ----------
    frame : RoadFrame
    lane_width_m : float
        Spacing of the lane lines from the centre line (the scene's lane width).
    """
    if not lane_width_m > 0:
        raise ValueError(f"lane_width_m must be > 0, got {lane_width_m}")
    w, h = IMAGE_SIZE
    m, c = radar_to_camera(frame.radar_height_m)
    img = Image.fromarray(_sky())
    draw = ImageDraw.Draw(img)

    def fill(polys: np.ndarray, colours) -> None:
        for k, p in enumerate(_image_polygons(polys)):
            if p is not None:
                draw.polygon(p, fill=colours if isinstance(colours[0], int) else colours[k])

    # ground: the horizon is where a back-projected ray is horizontal in the radar frame
    kinv = np.linalg.inv(np.asarray(CAMERA_MATRIX) * np.array([[_SCALE], [_SCALE], [1.0]]))
    row = (m.T @ kinv)[2]                                 # radar-z of the ray through (u, v, 1)
    v_of = lambda u: -(row[0] * u + row[2]) / row[1]      # noqa: E731
    draw.polygon([(0, v_of(0.0)), (w, v_of(float(w))), (w, h), (0, h)], fill=_GROUND)

    # road surface and lane lines, near to far samples of arc length ahead of the radar
    s_rel = np.concatenate([np.arange(-1.0, 30.0, 1.0), np.arange(30.0, 120.0, 3.0),
                            np.arange(120.0, 400.0, 10.0)])
    right, left = frame.road.bounds_m
    fill(_quads(_road_strip(frame, (right, left), s_rel), m, c), _ROAD)
    if frame.road.crossing_m is not None:                 # a cross street (straight roads run along world x)
        xc, hw = frame.road.crossing_m
        wy = np.linspace(-150.0, 150.0, 61)
        strip = np.stack([_world_to_radar(frame, np.full_like(wy, xc - hw), wy),
                          _world_to_radar(frame, np.full_like(wy, xc + hw), wy)])
        fill(_quads(strip, m, c), _ROAD)
    half = 0.07
    inner = [k * lane_width_m for k in range(math.ceil(right / lane_width_m), math.floor(left / lane_width_m) + 1)
             if right + 0.5 < k * lane_width_m < left - 0.5]
    dash = np.arange(-1.0, 150.0, 1.5)                    # 3 m dashes, 3 m gaps (every other quad)
    for l, solid in [(x, x == 0.0) for x in inner] + [(right + 0.3, True), (left - 0.3, True)]:
        fill(_quads(_road_strip(frame, (l - half, l + half), dash), m, c, every=1 if solid else 2), _MARK)

    # objects, far to near: vehicles as boxes, static reflectors above the ground as posts
    veh = frame.vehicles
    corners = vehicle_corners(veh) @ m.T + c if len(veh) else np.zeros((0, 8, 3))
    seen = np.flatnonzero(corners[..., 2].max(1) >= NEAR_M) if len(veh) else np.zeros(0, np.int64)
    owner = frame.owner.numpy()
    xyz = scatterer_xyz(frame)
    posts = np.flatnonzero((owner == -1) & (xyz[:, 2] + frame.radar_height_m > 0.3))   # not ghosts (-2)
    base = np.concatenate([xyz[posts, :2], np.full((len(posts), 1), -frame.radar_height_m)], 1) @ m.T + c
    top = (xyz[posts] + np.array([0.0, 0.0, 0.3])) @ m.T + c
    r = 0.06 * (m @ np.array([0.0, -1.0, 0.0]))           # half a post's width along radar "right"
    post_uv = _image_polygons(np.stack([base - r, base + r, top + r, top - r], 1))
    depth = np.concatenate([np.linalg.norm(corners[seen].mean(1), axis=-1), np.linalg.norm(base, axis=-1)])
    order = np.argsort(-depth, kind="stable")
    for k in order.tolist():
        if k < len(seen):
            i = int(seen[k])
            _draw_vehicle(fill, corners[i], int(veh.ids[i]))
        elif post_uv[k - len(seen)] is not None:
            draw.polygon(post_uv[k - len(seen)], fill=_POST)
    return np.asarray(img)


def scatterer_xyz(frame: RoadFrame) -> np.ndarray:
    """Radar-frame positions ``(N, 3)`` of the frame's scatterers (float64)."""
    sc = frame.scatterers
    r = sc.range_m.double().numpy()
    az = np.deg2rad(sc.azimuth_deg.double().numpy())
    el = np.deg2rad(sc.elevation_deg.double().numpy())
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], -1)


def _draw_vehicle(fill, cam: np.ndarray, vid: int) -> None:
    """Visible faces of one box (camera-frame corners ``(8, 3)``), shaded, with windows."""
    body = _BODY_COLOURS[vid % len(_BODY_COLOURS)]
    centre = cam.mean(0)
    polys, colours = [], []
    for f, idx in enumerate(_FACES):
        q = cam[list(idx)]
        fc = q.mean(0)
        if np.dot(fc - centre, fc) >= 0:                 # outward normal points away from the camera
            continue
        polys.append(q)
        colours.append(_shade(body, _FACE_SHADE[f]))
        if f < 4:                                        # vertical faces: a dark window band
            # each vertical face lists bottom, top, top, bottom or bottom, bottom, top, top
            if idx[1] >= 4:
                lo0, hi0, hi1, lo1 = q
            else:
                lo0, lo1, hi1, hi0 = q
            a0, a1 = lo0 + 0.6 * (hi0 - lo0), lo0 + 0.88 * (hi0 - lo0)
            b0, b1 = lo1 + 0.6 * (hi1 - lo1), lo1 + 0.88 * (hi1 - lo1)
            inset = lambda p, r: p + 0.1 * (r - p)        # noqa: E731
            polys.append(np.stack([inset(a0, b0), inset(b0, a0), inset(b1, a1), inset(a1, b1)]))
            colours.append(_shade((40, 50, 60), _FACE_SHADE[f]))
    if polys:
        fill(np.stack(polys), colours)


def jpeg_bytes(image: np.ndarray, quality: int = 90) -> bytes:
    """JPEG encoding of an RGB uint8 image."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be uint8 (H, W, 3), got {image.dtype} {image.shape}")
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=int(quality))
    return buf.getvalue()
