"""Scene presets: their stated traffic statistics, parked / standing / crossing / turning traffic,
the preset mix and ``--scenes``."""
import argparse
import dataclasses
import math

import numpy as np
import pytest

from radarpc.sensors.radial import RADIAL
from radarpc.sim.radial_labels import frame_label_rows, labelled_vehicles, reference_points
from radarpc.sim.road import PARKED, PATH_NAMES, QUEUED, STOPPED, TRUCK, RoadScene
from radarpc.sim.scenes import CITY, COUNTRYSIDE, DEFAULT_MIX, HIGHWAY, SCENE_PRESETS, SceneMix, scene_mix

# the ranges stated in the presets' docstrings (radarpc.sim.scenes):
# (vehicles per frame, empty-frame share, parked share, stopped-or-queued share, truck share)
STATED = {
    "city": ((1.3, 2.6), (0.10, 0.45), (0.10, 0.40), (0.15, 0.55), (0.0, 0.15)),
    "countryside": ((0.5, 1.2), (0.25, 0.60), (0.0, 0.0), (0.0, 0.0), (0.05, 0.35)),
    "highway": ((0.8, 1.8), (0.15, 0.50), (0.0, 0.0), (0.0, 0.0), (0.15, 0.50)),
}


def batch_statistics(preset, seed=0, n_seq=30):
    """Over frames 0, 3, 6, 9 of sequences 0..n_seq-1 of 10 frames (labels of the full-size sensor)."""
    n, state, kind = [], [], []
    for q in range(n_seq):
        scene = RoadScene(preset, seed, q, 10, RADIAL.max_range_m)
        for i in (0, 3, 6, 9):
            fr = scene.frame(scene.frame_time(i))
            lv = labelled_vehicles(RADIAL, fr)
            n.append(len(lv))
            state += fr.vehicles.state[lv].tolist()
            kind += fr.vehicles.kind[lv].tolist()
    n, state, kind = np.array(n), np.array(state), np.array(kind)
    return (n.mean(), (n == 0).mean(), (state == PARKED).mean(), np.isin(state, (STOPPED, QUEUED)).mean(),
            (kind == TRUCK).mean())


@pytest.mark.parametrize("name", sorted(SCENE_PRESETS))
def test_presets_produce_their_stated_traffic_statistics(name):
    got = batch_statistics(SCENE_PRESETS[name])
    for value, (lo, hi), what in zip(got, STATED[name], ("vehicles/frame", "empty", "parked", "standing", "trucks")):
        assert lo <= value <= hi, (name, what, value)


def _find(preset, want, n_seq=60):
    for q in range(n_seq):
        scene = RoadScene(preset, 0, q, 10, RADIAL.max_range_m)
        for i in (0, 5, 9):
            fr = scene.frame(scene.frame_time(i))
            hit = want(scene, fr)
            if hit is not None:
                return scene, fr, hit
    raise AssertionError("no such frame in the seeded scenes")


def test_a_parked_vehicle_has_zero_ground_speed_is_labelled_and_returns_static_doppler():
    def parked_in_view(scene, fr):
        lv = labelled_vehicles(RADIAL, fr)
        p = lv[fr.vehicles.state[lv] == PARKED]
        return int(p[0]) if p.size and fr.ego_speed_mps > 2.0 else None

    scene, fr, v = _find(CITY, parked_in_view)
    veh = fr.vehicles
    assert veh.velocity_xy[v].tolist() == [0.0, 0.0] and veh.ground_speed_mps()[v] == 0.0
    # labelled like a moving vehicle: its row at its reference point, range rate from the ego alone
    rows = frame_label_rows(RADIAL, fr, seed=0, sequence=0, index=0, frames_per_sequence=1)
    ref = reference_points(veh)[v]
    r = math.hypot(ref[0], ref[1])
    from radarpc.data.radial_format import LABEL_COLUMNS
    col = {c: k for k, c in enumerate(LABEL_COLUMNS)}
    mine = [row for row in rows if row[col["radar_R_m"]] == round(r, 4)]
    assert len(mine) == 1
    assert mine[0][col["radar_D"]] == pytest.approx(-fr.ego_speed_mps * ref[0] / r, abs=1e-4)
    # its direct returns have the Doppler of static clutter: -v_ego cos(az) cos(el)
    sc, owner, path = fr.scatterers, fr.owner.numpy(), fr.path.numpy()
    sel = (owner == v) & (path == PATH_NAMES.index("direct"))
    assert sel.sum() >= 3
    az, el = np.radians(sc.azimuth_deg.numpy()[sel]), np.radians(sc.elevation_deg.numpy()[sel])
    np.testing.assert_allclose(sc.velocity_mps.numpy()[sel], -fr.ego_speed_mps * np.cos(az) * np.cos(el),
                               rtol=0, atol=1e-9)


def test_red_light_ego_and_queue_stand_while_cross_traffic_passes():
    red = dataclasses.replace(CITY, intersection_prob=1.0, red_prob=1.0, queue_vehicles=(2, 2))
    scene = RoadScene(red, 0, 3, 10, RADIAL.max_range_m)
    fr = scene.frame(0.5)
    veh = fr.vehicles
    assert fr.ego_speed_mps == 0.0 and scene.crossing_m is not None
    standing = np.isin(veh.state, (STOPPED, QUEUED))
    assert (veh.ground_speed_mps()[standing] == 0.0).all()
    # per approach lane one vehicle at the stop line and one queued behind it
    assert (veh.state == STOPPED).sum() == (veh.state == QUEUED).sum() == scene.n_same + scene.n_opp
    # the cross traffic drives along the cross street (+-90 deg to the road), at its speed
    crossing = (veh.state == 0) & (np.abs(np.abs(veh.yaw_rad) - math.pi / 2) < 1e-9)
    assert crossing.any()
    assert np.all(np.abs(veh.center_xyz[crossing, 0] - (scene.crossing_m[0] - scene.ego_state(0.5)[0][0]))
                  <= red.lane_width_m / 2 + 1e-9)


def test_turning_vehicle_follows_a_quarter_circle_with_consistent_velocity():
    green = dataclasses.replace(CITY, intersection_prob=1.0, red_prob=0.0, turn_prob=1.0)
    scene = RoadScene(green, 0, 1, 100, RADIAL.max_range_m)
    nr = scene.n_road
    k = np.flatnonzero(scene.trk_kappa != 0.0)
    assert k.size == 1
    i = nr + int(k[0])
    speed = scene.veh_speed[i]
    t_arc = (scene.trk_straight[k[0]] + 0.5 * scene.trk_arc[k[0]]) / speed          # mid-arc
    h = 1e-4
    for t in (0.0, t_arc, t_arc * 2 + 1.0):
        p0, p1 = scene._body_poses(t - h)[0][i], scene._body_poses(t + h)[0][i]
        _, yaw, vel = scene._body_poses(t)
        np.testing.assert_allclose((p1 - p0) / (2 * h), vel[i], atol=1e-6)
        np.testing.assert_allclose(vel[i], speed * np.array([math.cos(yaw[i]), math.sin(yaw[i])]), atol=1e-12)
    # it ends heading -y (a right turn) in the cross street's lane x = s_x - w / 2
    end = (scene.trk_straight[k[0]] + scene.trk_arc[k[0]]) / speed + 2.0
    pos, yaw, _ = scene._body_poses(end)
    assert yaw[i] == pytest.approx(-math.pi / 2, abs=1e-12)
    assert pos[i, 0] == pytest.approx(scene.crossing_m[0] - green.lane_width_m / 2, abs=1e-9)


def test_mix_draws_presets_in_their_proportions_and_is_reproducible():
    names = [DEFAULT_MIX.preset(5, q).name for q in range(3000)]
    w = np.array(DEFAULT_MIX.weights) / sum(DEFAULT_MIX.weights)
    for n in (3, 6, 7, 30, 100, 3000):
        for p, share in zip(DEFAULT_MIX.presets, w):
            # stratified: every run's first n sequences hold a preset within 2.5 of n * share (the
            # golden-ratio sequence's interval counts; independent draws miss by ~sqrt(n))
            assert abs(names[:n].count(p.name) - n * share) <= 2.5, (n, p.name)
    assert names[:50] == [DEFAULT_MIX.preset(5, q).name for q in range(50)]
    assert names[:50] != [DEFAULT_MIX.preset(6, q).name for q in range(50)]
    two = scene_mix("city,highway")
    assert [p.name for p in two.presets] == ["city", "highway"] and two.weights == (0.31, 0.38)
    assert {two.preset(0, q).name for q in range(40)} == {"city", "highway"}
    assert scene_mix(["countryside"]).preset(3, 7) is COUNTRYSIDE
    assert DEFAULT_MIX.to_dict()["mix"] == {"city": 0.31, "countryside": 0.32, "highway": 0.38}
    assert DEFAULT_MIX.to_dict()["presets"]["highway"]["median_rail"] is True


def test_bad_scene_names_and_mixes_are_clear_errors(capsys):
    with pytest.raises(ValueError, match=r"unknown scene preset\(s\) 'town': expected comma-separated names "
                                         r"from city, countryside, highway"):
        scene_mix("city,town")
    with pytest.raises(ValueError, match="named twice"):
        scene_mix("city,city")
    with pytest.raises(ValueError, match=r"\(none given\)"):
        scene_mix([])
    with pytest.raises(ValueError, match="distinct"):
        SceneMix((CITY, CITY), (1.0, 1.0))
    with pytest.raises(ValueError, match="weights"):
        SceneMix((CITY, HIGHWAY), (1.0, 0.0))
    with pytest.raises(ValueError, match="parking_prob"):
        dataclasses.replace(CITY, parking_prob=2.0)
    from radarpc.cli import simulate_radial

    parser = argparse.ArgumentParser(prog="radarpc simulate")
    simulate_radial.add_parser(parser.add_subparsers(dest="kind"))
    assert parser.parse_args(["radial", "--out", "x", "--scenes", "highway,city"]).scenes == scene_mix("highway,city")
    assert parser.parse_args(["radial", "--out", "x"]).scenes is None
    with pytest.raises(SystemExit):
        parser.parse_args(["radial", "--out", "x", "--scenes", "city,motorway"])
    err = capsys.readouterr().err
    assert "argument --scenes: unknown scene preset(s) 'motorway': expected comma-separated names from " \
           "city, countryside, highway" in err


def test_highway_median_is_not_free_road():
    scene = RoadScene(HIGHWAY, 0, 2, 10, RADIAL.max_range_m)
    fr = scene.frame(0.2)
    assert fr.road.median_m == (0.0, HIGHWAY.median_m) and scene.n_opp > 0
    y = np.array([-0.5 * HIGHWAY.lane_width_m, 0.5 * HIGHWAY.median_m, HIGHWAY.median_m + 1.0]) - scene.ego_l
    on = fr.road.on_road(np.stack([np.full(3, 20.0), y], 1))      # straight or gently curved: ~lateral
    assert on.tolist() == [True, False, True]


def test_a_scene_mix_survives_its_json_and_bad_dicts_name_the_problem():
    import json

    mix = SceneMix((CITY, dataclasses.replace(HIGHWAY, lanes_same=(3, 3))), (2.0, 1.0))
    assert SceneMix.from_dict(json.loads(json.dumps(mix.to_dict()))) == mix
    assert SceneMix.from_dict(json.loads(json.dumps(DEFAULT_MIX.to_dict()))) == DEFAULT_MIX
    with pytest.raises(ValueError, match=r"^scene\.json: expected \{'mix'"):
        SceneMix.from_dict({"mix": {"city": 1.0}}, where="scene.json")
    bad = mix.to_dict()
    bad["presets"]["city"]["lane_widht_m"] = 3.0
    with pytest.raises(ValueError, match=r"preset 'city': RoadSceneConfig unknown keys \['lane_widht_m'\]"):
        SceneMix.from_dict(bad)
