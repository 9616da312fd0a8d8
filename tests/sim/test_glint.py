"""Angle glint of a car's rear face: the beamwidth against the ideal array factor, a cell's azimuth
on hand-worked paths, the template's rear face and its ground paths, and the draws scored by the
metric's boxes."""
import numpy as np
import pytest
import torch

from radarpc.eval.detection import IOU_THRESHOLD
from radarpc.boxes import BOX_WIDTH_M, box_iou, ra_to_box_xy
from radarpc.sensors.radial import radial_sensor, steering_vectors
from radarpc.sim.glint import CAR_LWH_M, beamformed_azimuth, beamwidth_deg, face_paths, glint_azimuths, rear_face
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.road import RoadSceneConfig, _vehicle_template


@pytest.fixture(scope="module")
def radial():
    cfg = radial_sensor("radial")
    return cfg, make_calibration(cfg).dictionary()


def test_beamwidth_against_the_ideal_array_factor(radial):
    cfg, measured = radial
    az_t, el_t = cfg.azimuth_table_deg, cfg.elevation_table_deg
    step = float(az_t[1] - az_t[0])
    # the ideal dictionary (unit-modulus steering, Hamming taper over the horizontal positions):
    # on the elevation-0 cut its spectrum of an ideal target is the tapered array factor
    p = cfg.virtual_positions[:, 0]
    w = 0.54 - 0.46 * np.cos(2 * np.pi * (p - p.min()) / (p.max() - p.min()))
    ideal = np.conj(steering_vectors(cfg, az_t[:, None], el_t[None, :], hardware=False)).reshape(-1, cfg.n_virtual)
    b = torch.as_tensor(ideal * w, dtype=torch.complex64)
    for a0 in (0.0, 30.0):
        az = np.arange(a0 - 4, a0 + 4, 1e-4)
        af = np.abs((w * np.exp(1j * np.pi * p * (np.sin(np.radians(az)) - np.sin(np.radians(a0)))[:, None])).sum(1))
        main = np.flatnonzero(af >= af.max() / np.sqrt(2))
        # linear interpolation between grid samples misplaces a crossing by at most
        # (h^2 / 8) max|f''| / |f'| (h the grid step), f' and f'' of the array factor near it
        d1, d2 = np.gradient(af, az), np.gradient(np.gradient(af, az), az)
        near = int(step / 1e-4)
        bound = sum(step ** 2 / 8 * np.abs(d2[k - near:k + near]).max() / abs(d1[k]) for k in (main[0], main[-1]))
        got = beamwidth_deg(cfg, a0, b, hardware=False)
        assert abs(got - (az[main[-1]] - az[main[0]])) <= bound + 2e-4
        assert bound < step / 4                          # the check is tighter than the grid
    with pytest.raises(ValueError, match="end of the calibration grid"):
        beamwidth_deg(cfg, 74.9, b, hardware=False)
    # with the sensor's own calibration and hardware errors (what vehicle_glint.py reports): about 2 deg
    assert 1.5 < beamwidth_deg(cfg, 0.0, measured) < 2.5


def test_cell_azimuth_on_hand_worked_paths(radial):
    cfg, b = radial
    step = float(cfg.azimuth_table_deg[1] - cfg.azimuth_table_deg[0])
    # one path: the maximum is the grid azimuth nearest to it; two equal in-phase paths inside one
    # beamwidth, symmetric about 10 deg: at 10 deg; two resolved ones (6 deg apart): the stronger
    one = beamformed_azimuth(cfg, np.array([[40.0]]), np.array([[3.05]]), np.zeros((1, 1)), np.ones((1, 1)), b)
    assert abs(one[0] - 3.05) <= step / 2 + 1e-6
    r = np.full((2, 2), 40.0)
    peaks = beamformed_azimuth(cfg, r, np.array([[9.7, 10.3], [-3.0, 3.0]]), np.zeros((2, 2)),
                               np.array([[1.0, 1.0], [1.0, 4.0]]), b)
    assert abs(peaks[0] - 10.0) <= step / 2 + 1e-6 and abs(peaks[1] - 3.0) <= step / 2 + 1e-6
    with pytest.raises(ValueError, match="dictionary"):
        beamformed_azimuth(cfg, r, r, r, r, b[:10])
    with pytest.raises(ValueError, match=r"\(D, K\) shape"):
        beamformed_azimuth(cfg, r, r[:1], r, r, b)


def test_rear_face_and_its_ground_paths():
    assert CAR_LWH_M[1] == BOX_WIDTH_M                  # as wide as RADIal's box
    # the rear face: the template's rear-facing points (3 bumper, 2 lights, 2 corners at 45 deg),
    # RCS times sqrt(cos): 1 for the five facing back, 2^-1/4 for the corners
    lateral_z, rcs = rear_face(np.random.default_rng(3))
    body = _vehicle_template(np.random.default_rng(3), *CAR_LWH_M, truck=False, speed=10.0,
                             under_rcs=RoadSceneConfig.underbody_rcs_m2)
    back = (body.normal[:, 0] < 0) & ~body.under
    assert np.sort(rcs / body.rcs[back]).tolist() == pytest.approx([2 ** -0.25] * 2 + [1.0] * 5)
    assert np.abs(lateral_z[:, 0]).max() == pytest.approx(0.9)
    # the paths of one point 0.5 m above the road, 50 m ahead, radar 0.8 m up: direct, ground
    # bistatic (half the direct and image ranges, 4 |Gamma|^2) and ground double (|Gamma|^4)
    r, az, el, rc = face_paths(np.array([[0.3, 0.5]]), np.array([2.0]), 50.0, 0.0, 0.0, 0.8, -6.0)
    g2 = 10 ** -0.6
    direct, image = np.sqrt(50 ** 2 + 0.3 ** 2 + 0.3 ** 2), np.sqrt(50 ** 2 + 0.3 ** 2 + 1.3 ** 2)
    assert r.tolist() == pytest.approx([direct, (direct + image) / 2, image], rel=1e-12)
    assert rc.tolist() == pytest.approx([2.0, 8.0 * g2, 2.0 * g2 ** 2], rel=1e-12)
    assert az == pytest.approx(np.degrees(np.arctan2(0.3, 50.0)), rel=1e-9) and el[2] < el[1] < el[0] < 0


def test_glint_draws_scored_by_the_metric_boxes(radial):
    cfg, b = radial
    # at 10 m the corners are resolved, so many cells sit on a corner, far outside the tolerance
    r_face, peak = glint_azimuths(cfg, 10.0, 16, np.random.default_rng(0), dictionary=b)
    assert r_face.shape == peak.shape == (16,) and (np.abs(r_face - 10.0) <= 0.5).all()
    assert np.isin(peak, cfg.azimuth_table_deg).all()
    r = torch.as_tensor(r_face)
    det = ra_to_box_xy(r, torch.as_tensor(peak, dtype=torch.float64))
    lab = ra_to_box_xy(r, torch.zeros_like(r))
    matched = (box_iou(det, lab).diagonal() >= IOU_THRESHOLD).numpy()
    dx = (det[:, 0] - lab[:, 0]).numpy()
    # level boxes match within 0.6 m across; here dy = R (cos A - 1) is at most 0.02 m, which
    # still lets |dx| <= 0.59 pass ((1.8 - 0.59)(4 - 0.02) >= 4.8)
    assert not (matched & (np.abs(dx) > 0.6)).any() and (matched | (np.abs(dx) > 0.59)).all()
    assert (np.abs(dx) > 0.8).any()
    # the same generator state gives the same draws
    again = glint_azimuths(cfg, 10.0, 16, np.random.default_rng(0), dictionary=b)
    assert np.array_equal(again[0], r_face) and np.array_equal(again[1], peak)
    with pytest.raises(ValueError, match="draws"):
        glint_azimuths(cfg, 80.0, 0, np.random.default_rng(0), dictionary=b)
