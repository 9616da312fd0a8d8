"""The boresight mirror and the rotation of point frames, and the superposition of RD frames: what
they change, against independent computations, and their per-(seed, epoch, item) draws."""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch

from radarpc.data.augment import (FREESPACE_COLUMN_DEG, MirroredFrames, RotatedFrames, SuperposedFrames, mirror_frame,
                                  rotate_frame, superpose_frames)
from radarpc.data.point_dataset import PointCloudDataset
from radarpc.data.radial_format import LABEL_TENSOR_COLUMNS
from radarpc.dsp.beamform import sector_pool
from radarpc.models.targets import TargetConfig, encode_targets
from radarpc.pipelines.pointclouds import convert_dataset
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_writer import write_radial_dataset
from radarpc.sim.scenes import scene_mix
from radarpc.experiments.radial_detection.config import ExperimentConfig
from radarpc.models import ModelSpec

COL = {c: k for k, c in enumerate(LABEL_TENSOR_COLUMNS)}
LATERAL = ("radar_A_deg", "radar_Y_m", "laser_Y_m")


@pytest.fixture(scope="module")
def frames(tiny_city_root, tiny_city_store):
    # the session's TINY root of 3 x 3 city frames, seed 3 (the 25.6 m of the tiny sensor hold a few
    # vehicles), and its store at tau 1.5 with sector4 (TINY grid: 61 x 5)
    return PointCloudDataset(tiny_city_store, tiny_city_root)


def test_mirror_negates_lateral_quantities_only(frames):
    seen_points = seen_labels = 0
    for f in (frames[i] for i in range(len(frames))):
        m = mirror_frame(f, (4, 1))
        p, q = f.points, m.points
        assert torch.equal(q.azimuth_deg, -p.azimuth_deg) and torch.equal(q.y, -p.y)
        for name in ("range_m", "elevation_deg", "velocity_mps", "amplitude", "snr", "x", "z", "range_bin",
                     "doppler_bin", "doppler_full", "offset"):
            assert torch.equal(getattr(q, name), getattr(p, name)), name
        assert torch.equal(q.sector, p.sector.flip(1))                           # 4 x 1 sectors
        for c, k in COL.items():
            want = -f.labels[:, k] if c in LATERAL else f.labels[:, k]
            assert torch.equal(m.labels[:, k], want), c
        assert torch.equal(m.freespace, f.freespace.flip(-1))
        twice = mirror_frame(m, (4, 1))
        assert torch.equal(twice.points.azimuth_deg, p.azimuth_deg) and torch.equal(twice.labels, f.labels)
        assert torch.equal(twice.points.sector, p.sector) and torch.equal(twice.freespace, f.freespace)
        seen_points += p.num_points
        seen_labels += len(f.labels)
    assert seen_points > 0 and seen_labels > 0                                  # the checks ran on data


@pytest.mark.parametrize("grid, sectors", [((181, 1), (32, 1)), ((751, 11), (8, 2)), ((61, 5), (7, 3))])
def test_reversed_sectors_are_the_sectors_of_the_mirrored_spectrum(frames, grid, sectors):
    # independent computation: pool the mirrored angle spectrum (azimuth rows reversed on a grid
    # symmetric about 0), against mirror_frame's reversal of the original descriptor
    g = torch.Generator().manual_seed(0)
    f = frames[0]
    n = f.points.num_points
    spectrum = torch.rand(n, grid[0] * grid[1], generator=g)                        # (P, n_az n_el)
    mirrored = spectrum.reshape(n, *grid).flip(1).reshape(n, -1)
    f = dataclasses.replace(f, points=dataclasses.replace(f.points, sector=sector_pool(spectrum, grid, sectors)))
    assert torch.equal(mirror_frame(f, sectors).points.sector, sector_pool(mirrored, grid, sectors))


def test_mirrored_labels_encode_to_the_mirrored_target_map():
    # azimuth cells are symmetric about 0 (224 x 0.8 deg over +-89.6): the probability of a mirrored
    # label lands in the mirrored cells; labels are off the cell edges, so floor() is unambiguous
    cfg = TargetConfig()
    g = torch.Generator().manual_seed(1)
    labels = torch.zeros(6, len(LABEL_TENSOR_COLUMNS))
    labels[:, COL["radar_R_m"]] = 5 + 90 * torch.rand(6, generator=g)
    labels[:, COL["radar_A_deg"]] = -80 + 160 * torch.rand(6, generator=g)
    mirrored = labels.clone()
    mirrored[:, COL["radar_A_deg"]] *= -1
    a, b = encode_targets(labels, cfg), encode_targets(mirrored, cfg)
    assert a[0].sum() > 0 and torch.equal(b[0], a[0].flip(-1))


def test_draws_depend_on_seed_epoch_and_item_only(frames):
    aug = MirroredFrames(frames, 0.5, seed=7)
    draws = []
    for epoch in range(400):
        aug.set_epoch(epoch)
        draws.append([aug.is_mirrored(i) for i in range(len(frames))])
    draws = np.array(draws)
    n = draws.size
    assert abs(draws.mean() - 0.5) < 5 * np.sqrt(0.25 / n)                       # 5 binomial sigmas
    again = MirroredFrames(frames, 0.5, seed=7)
    again.set_epoch(3)
    assert [again.is_mirrored(i) for i in range(len(frames))] == draws[3].tolist()
    assert all(MirroredFrames(frames, 1.0, seed=7).is_mirrored(i) for i in range(len(frames)))
    assert not any(MirroredFrames(frames, 0.0, seed=7).is_mirrored(i) for i in range(len(frames)))
    # the draw is the documented one: numpy's generator seeded by (seed, epoch, item)
    assert draws[3].tolist() == [bool(np.random.default_rng([7, 3, i]).random() < 0.5) for i in range(len(frames))]


def test_streams_draw_independently_under_one_seed(frames):
    # stream 0 draws as a dataset without streams; another stream (a second root's position in a
    # concatenation) draws (seed, epoch, item, stream): over 400 epochs its draws agree with
    # stream 0's about half the time, not always
    zero, one = MirroredFrames(frames, 0.5, seed=7, stream=0), MirroredFrames(frames, 0.5, seed=7, stream=1)
    agree = []
    for epoch in range(400):
        zero.set_epoch(epoch)
        one.set_epoch(epoch)
        for i in range(len(frames)):
            assert one.is_mirrored(i) == bool(np.random.default_rng([7, epoch, i, 1]).random() < 0.5)
            agree.append(zero.is_mirrored(i) == one.is_mirrored(i))
    assert abs(np.mean(agree) - 0.5) < 5 * np.sqrt(0.25 / len(agree))
    assert "stream=1" in repr(one) and "stream" not in repr(zero)


def test_loader_workers_draw_the_epoch_set_before_the_loader(frames):
    aug = MirroredFrames(frames, 0.5, seed=1)
    for epoch in (0, 5):
        aug.set_epoch(epoch)
        loader = torch.utils.data.DataLoader(aug, batch_size=2, num_workers=2, collate_fn=list)
        got = [it for batch in loader for it in batch]
        for i, it in enumerate(got):
            sign = -1 if aug.is_mirrored(i) else 1
            assert torch.equal(it.points.azimuth_deg, sign * frames[i].points.azimuth_deg)
            assert torch.equal(it.freespace, frames[i].freespace.flip(-1) if sign < 0 else frames[i].freespace)


def test_bad_input(frames):
    with pytest.raises(ValueError, match=r"mirror probability must be in \[0, 1\], got 1.5"):
        MirroredFrames(frames, 1.5, seed=0)
    with pytest.raises(ValueError, match="stream must be >= 0, got -1"):
        MirroredFrames(frames, 0.5, seed=0, stream=-1)
    with pytest.raises(ValueError, match="4-wide sector descriptor; give its"):
        mirror_frame(frames[0], None)
    with pytest.raises(ValueError, match="4-wide sector descriptor"):
        mirror_frame(frames[0], (2, 1))
    with pytest.raises(ValueError, match="point inputs only"):
        ExperimentConfig(name="x", model=ModelSpec("fftradnet-tiny"), mirror_probability=0.5)
    with pytest.raises(ValueError, match=r"mirror_probability must be in \[0, 1\]"):
        ExperimentConfig(name="x", model=ModelSpec("fftradnet-tiny"), mirror_probability=-0.1)


def test_an_asymmetric_azimuth_table_is_refused(frames, tmp_path):
    # a sensor whose calibration grid is not centred on the boresight: reversing the sector
    # descriptor is no mirror there
    sensor = dataclasses.replace(TINY, az_grid_deg=(-58.0, 62.0, 61))
    root = write_radial_dataset(tmp_path / "root", sensor, 1, 1, seed=3, progress=False, scenes=scene_mix("city"))
    convert_dataset(root, tmp_path / "pc.parquet", tau=1.5, enrich=("sector4",), progress=False)
    shifted = PointCloudDataset(tmp_path / "pc.parquet", root)
    with pytest.raises(ValueError, match=re.escape("Azimuth_table that is not symmetric about 0 deg "
                                                   "(61 azimuths, -58.000 .. 62.000 deg)")):
        MirroredFrames(shifted, 0.5, seed=0)
    MirroredFrames(frames, 0.5, seed=0)                                      # the simulator's table passes


# ---------------------------------------------------------------------------------------------
# rotation about the vertical axis
# ---------------------------------------------------------------------------------------------

EPS32 = 2.0 ** -24                                                   # float32 unit roundoff


@pytest.mark.parametrize("k", [3, -5])
def test_rotation_turns_positions_and_keeps_the_rest(frames, k):
    # independent computation: the rotated points and labels keep their distance from the radar
    # and their polar angle grows by delta (atan2 of the rotated x, y); each value is one float64
    # computation rounded to float32, so a few unit roundoffs bound every difference
    delta = k * FREESPACE_COLUMN_DEG
    seen_points = seen_labels = 0
    for f in (frames[i] for i in range(len(frames))):
        g = rotate_frame(f, delta)
        p, q = f.points, g.points
        assert torch.allclose(q.azimuth_deg.double(), p.azimuth_deg.double() + delta,
                              rtol=0, atol=2 * EPS32 * (p.azimuth_deg.abs().max().item() + abs(delta)))
        rho_p, rho_q = torch.hypot(p.x.double(), p.y.double()), torch.hypot(q.x.double(), q.y.double())
        assert torch.allclose(rho_q, rho_p, rtol=4 * EPS32, atol=0)
        far = rho_p > 1e-3
        turned = torch.atan2(q.y.double(), q.x.double()) - torch.atan2(p.y.double(), p.x.double())
        turned = torch.remainder(turned[far] + np.pi, 2 * np.pi) - np.pi
        assert torch.allclose(turned, torch.full_like(turned, np.deg2rad(delta)), rtol=0, atol=8 * EPS32)
        for name in ("range_m", "elevation_deg", "velocity_mps", "amplitude", "snr", "z", "range_bin",
                     "doppler_bin", "doppler_full", "offset", "sector", "is_neighbour"):
            assert torch.equal(getattr(q, name), getattr(p, name)), name
        # labels: the box point (R sin A, R cos A) and the radar X, Y turn by delta, the LiDAR
        # point keeps its offset from the radar point, everything else stays
        L, M = f.labels.double(), g.labels.double()
        assert torch.allclose(M[:, COL["radar_A_deg"]], L[:, COL["radar_A_deg"]] + delta, rtol=0, atol=2 * EPS32 * 100)
        xy = lambda T, a, b: (T[:, COL[a]], T[:, COL[b]])
        for x_col, y_col in (("radar_X_m", "radar_Y_m"), ("laser_X_m", "laser_Y_m")):
            (x0, y0), (x1, y1) = xy(L, x_col, y_col), xy(M, x_col, y_col)
            if x_col == "radar_X_m":
                assert torch.allclose(torch.hypot(x1, y1), torch.hypot(x0, y0), rtol=4 * EPS32, atol=0)
                assert torch.allclose(torch.atan2(y1, x1) - torch.atan2(y0, x0),
                                      torch.full_like(x0, np.deg2rad(delta)), rtol=0, atol=8 * EPS32)
        off0 = torch.stack(xy(L, "laser_X_m", "laser_Y_m"), 1) - torch.stack(xy(L, "radar_X_m", "radar_Y_m"), 1)
        off1 = torch.stack(xy(M, "laser_X_m", "laser_Y_m"), 1) - torch.stack(xy(M, "radar_X_m", "radar_Y_m"), 1)
        assert torch.allclose(off1, off0, rtol=0, atol=16 * EPS32 * 110)        # |coordinates| < 110 m
        kept = [c for c in COL if c not in ("radar_A_deg", "radar_X_m", "radar_Y_m", "laser_X_m", "laser_Y_m")]
        assert all(torch.equal(g.labels[:, COL[c]], f.labels[:, COL[c]]) for c in kept)
        # freespace: column j of the rotated map is column j - k of the original, the uncovered
        # edge columns repeat the edge
        w = f.freespace.shape[-1]
        for j in range(w):
            assert torch.equal(g.freespace[:, j], f.freespace[:, min(max(j - k, 0), w - 1)]), j
        back = rotate_frame(g, -delta)
        assert torch.allclose(back.labels, f.labels, rtol=8 * EPS32, atol=8 * EPS32 * 110)
        seen_points += int(far.sum())
        seen_labels += len(f.labels)
    assert seen_points > 0 and seen_labels > 0                                  # the checks ran on data


def test_rotated_labels_encode_to_the_shifted_target_map(frames):
    # a rotation by two target columns (2 x 0.8 deg = 4 freespace columns) moves each label's
    # probability patch two cells towards larger azimuth and keeps its offsets: the sign of the
    # labels' azimuth agrees with the map's column order, as the freespace shift assumes
    cfg = TargetConfig()
    g = torch.Generator().manual_seed(2)
    labels = torch.zeros(6, len(LABEL_TENSOR_COLUMNS))
    labels[:, COL["radar_R_m"]] = 5 + 90 * torch.rand(6, generator=g)
    cell = torch.randint(8, 200, (6,), generator=g)                       # well inside the 224 columns
    labels[:, COL["radar_A_deg"]] = (cell - 112 + 0.1 + 0.8 * torch.rand(6, generator=g)) * cfg.azimuth_cell_deg
    frame = dataclasses.replace(frames[0], labels=labels)
    n = round(2 * cfg.azimuth_cell_deg / FREESPACE_COLUMN_DEG)
    a = encode_targets(labels, cfg)
    b = encode_targets(rotate_frame(frame, n * FREESPACE_COLUMN_DEG).labels, cfg)
    assert a[0].sum() == 6 * 9 and torch.equal(b[0][:, 2:], a[0][:, :-2]) and b[0][:, :2].sum() == 0
    # the offsets differ by the rounding of the shifted azimuth (|A| < 90 deg) over reg_std
    tol = 4 * EPS32 * 90 / min(cfg.reg_std)
    assert torch.allclose(b[1:, :, 2:], a[1:, :, :-2], rtol=0, atol=tol)


def test_rotation_draws_depend_on_seed_epoch_item_and_stream(frames):
    aug = RotatedFrames(frames, 2.0, seed=7)
    assert aug.max_columns == 5
    draws = []
    for epoch in range(300):
        aug.set_epoch(epoch)
        draws.append([aug.angle_deg(i) for i in range(len(frames))])
    cols = np.rint(np.array(draws) / FREESPACE_COLUMN_DEG).astype(int)
    counts = np.bincount(cols.ravel() + 5, minlength=11)
    n = cols.size                                                              # 11 equally likely values
    assert counts.size == 11 and np.all(np.abs(counts - n / 11) < 5 * np.sqrt(n / 11 * (10 / 11)))
    # the documented generator: numpy's seeded by (seed, epoch, item, stream, 1)
    assert cols[3].tolist() == [int(np.random.default_rng([7, 3, i, 0, 1]).integers(-5, 5, endpoint=True))
                                for i in range(len(frames))]
    # another stream agrees with stream 0 about as often as independent draws do (1 in 11)
    one = RotatedFrames(frames, 2.0, seed=7, stream=1)
    agree = []
    for epoch in range(300):
        one.set_epoch(epoch)
        agree += [one.angle_deg(i) == draws[epoch][i] for i in range(len(frames))]
    assert abs(np.mean(agree) - 1 / 11) < 5 * np.sqrt((1 / 11) * (10 / 11) / len(agree))
    assert RotatedFrames(frames, 0.39, seed=7).max_columns == 0
    assert RotatedFrames(frames, 0.4, seed=7).max_columns == 1
    # items are rotated as drawn; the epoch reaches a wrapped mirror too
    both = RotatedFrames(MirroredFrames(frames, 0.5, seed=7), 2.0, seed=7)
    both.set_epoch(4)
    assert both.frames.epoch == 4
    for i in range(len(frames)):
        want = rotate_frame(both.frames[i], both.angle_deg(i))
        got = both[i]
        assert torch.equal(got.points.azimuth_deg, want.points.azimuth_deg) and torch.equal(got.labels, want.labels)


def test_rotation_bad_input(frames):
    with pytest.raises(ValueError, match="multiple of the freespace column, 0.4 deg, got 0.3"):
        rotate_frame(frames[0], 0.3)
    with pytest.raises(ValueError, match="rotation max_deg must be a finite angle >= 0, got -1.0"):
        RotatedFrames(frames, -1.0, seed=0)
    with pytest.raises(ValueError, match="stream must be >= 0, got -2"):
        RotatedFrames(frames, 1.0, seed=0, stream=-2)
    with pytest.raises(ValueError, match="rotation_max_deg applies to point inputs only"):
        ExperimentConfig(name="x", model=ModelSpec("fftradnet-tiny"), rotation_max_deg=2.0)
    with pytest.raises(ValueError, match="rotation_max_deg must be a finite angle >= 0, got nan"):
        ExperimentConfig(name="x", model=ModelSpec("pillars-tiny"), rotation_max_deg=float("nan"))
    with pytest.raises(ValueError, match="cannot rotate the 'sector' feature"):
        ExperimentConfig(name="x", model=ModelSpec("pillars-tiny", {"features": ["r", "a", "sector"]}), rotation_max_deg=2.0)


# ---- superposition of RD frames ------------------------------------------------------------------
def _scene(idx):
    from radarpc.sim.rd import Scatterers
    t = lambda x: torch.tensor([x[i] for i in idx], dtype=torch.float64)  # noqa: E731
    return Scatterers(range_m=t([3.37, 10.05, 17.61, 5.2, 22.9]), azimuth_deg=t([10.0, -25.0, 40.0, 0.0, -55.0]),
                      elevation_deg=t([0.0, 5.0, -3.0, 2.0, 12.0]), velocity_mps=t([2.3, -7.7, 15.0, 0.4, 27.1]),
                      rcs_m2=t([1.0, 10.0, 0.5, 3.0, 20.0]))


def test_superposed_cubes_are_the_cube_of_both_scenes():
    # the exact ADC-domain synthesis (noise off) of the union of two scenes against the sum of
    # each scene's cube; complex128 throughout, so only rounding separates them
    from radarpc.sim.adc import synthesize_rd_exact
    a, b, both = (synthesize_rd_exact(TINY, _scene(idx)) for idx in ([0, 1, 2], [3, 4], [0, 1, 2, 3, 4]))
    lab_a, lab_b = torch.ones(3, 14), 2 * torch.ones(2, 14)
    fs_a = torch.tensor([[True, True, False], [False, True, True]])
    fs_b = torch.tensor([[True, False, False], [True, True, False]])
    rd, lab, fs = superpose_frames((a, lab_a, fs_a), (b, lab_b, fs_b))
    assert float((rd - both).abs().max()) <= 1e-9 * float(both.abs().max())
    assert float((a - both).abs().max()) > 1e-2 * float(both.abs().max())       # each scene alone is not both
    assert torch.equal(lab, torch.cat([lab_a, lab_b]))
    assert fs.tolist() == [[True, False, False], [False, True, False]]         # free where both are free


@pytest.fixture(scope="module")
def cube_frames(tiny_city_root):
    from radarpc.data.radial import RADIal
    return RADIal(tiny_city_root, split="all")             # 3 x 3 city frames, seed 3


def test_superposed_frames_draw_partners_by_seed_epoch_and_item(cube_frames):
    n = len(cube_frames)
    aug = SuperposedFrames(cube_frames, 0.5, seed=7)
    draws = []
    for epoch in range(300):
        aug.set_epoch(epoch)
        partners = [aug.partner(i) for i in range(n)]
        assert all(j is None or (0 <= j < n and j != i) for i, j in enumerate(partners))
        draws.append(partners)
    share = np.mean([j is not None for row in draws for j in row])
    assert abs(share - 0.5) < 5 * np.sqrt(0.25 / (300 * n))                      # 5 binomial sigmas
    # every other frame is a partner: over 300 epochs frame 0 meets each of the n - 1 others
    assert {row[0] for row in draws if row[0] is not None} == set(range(1, n))
    again = SuperposedFrames(cube_frames, 0.5, seed=7)
    again.set_epoch(4)
    assert [again.partner(i) for i in range(n)] == draws[4]
    assert all(SuperposedFrames(cube_frames, 1.0, seed=7).partner(i) is not None for i in range(n))
    assert all(SuperposedFrames(cube_frames, 0.0, seed=7).partner(i) is None for i in range(n))
    other = SuperposedFrames(cube_frames, 0.5, seed=7, stream=1)
    other.set_epoch(4)
    assert [other.partner(i) for i in range(n)] != draws[4]                      # another stream's draws


def test_superposed_items_sum_the_partner_frame(cube_frames):
    aug = SuperposedFrames(cube_frames, 0.5, seed=2)
    seen = 0
    for epoch in range(3):
        aug.set_epoch(epoch)
        for i in range(len(cube_frames)):
            rd, lab, fs = aug[i]
            rd_i, lab_i, fs_i = cube_frames[i]
            j = aug.partner(i)
            if j is None:
                assert torch.equal(rd, rd_i) and torch.equal(lab, lab_i) and torch.equal(fs, fs_i)
                continue
            seen += 1
            rd_j, lab_j, fs_j = cube_frames[j]
            assert torch.equal(rd, rd_i + rd_j)
            assert torch.equal(lab, torch.cat([lab_i, lab_j])) and torch.equal(fs, fs_i & fs_j)
    assert seen > 0


def test_superposition_bad_input(cube_frames, tmp_path):
    with pytest.raises(ValueError, match=r"superposition probability must be in \[0, 1\], got 2"):
        SuperposedFrames(cube_frames, 2.0, seed=0)
    with pytest.raises(ValueError, match="at least 2 frames"):
        SuperposedFrames(torch.utils.data.Subset(cube_frames, [0]), 0.5, seed=0)
    rd, lab, fs = cube_frames[0]
    with pytest.raises(ValueError, match="only complex RD cubes of one shape superpose"):
        superpose_frames((rd, lab, fs), (rd[:-1], lab, fs))
    with pytest.raises(ValueError, match="only complex RD cubes"):
        superpose_frames((rd, lab, fs), (rd.real, lab, fs))
    with pytest.raises(ValueError, match="frames of different targets"):
        superpose_frames((rd, lab, fs), (rd, lab, fs[:-1]))
    with pytest.raises(ValueError, match="RD cubes only"):
        ExperimentConfig(name="x", model=ModelSpec("pillars-tiny"), superpose_probability=0.5)
    # a sparse-RD root (radarpc pointcloud --sparse-rd-out): sparse cubes do not superpose
    from radarpc.pipelines.sparse_rd import write_sparse_rd
    from radarpc.experiments.radial_detection.task import detection_dataset
    sparse = tmp_path / "sparse"
    write_sparse_rd(cube_frames.root, sparse, tau=4.0, progress=False)
    cfg = ExperimentConfig(name="x", model=ModelSpec("fftradnet-tiny"), superpose_probability=0.5)
    with pytest.raises(ValueError, match=f"{re.escape(str(sparse))} is a sparse-RD root"):
        detection_dataset(cfg, sparse, split="all", augment_seed=0)
    with pytest.raises(ValueError, match=r"superpose_probability must be in \[0, 1\]"):
        ExperimentConfig(name="x", model=ModelSpec("fftradnet-tiny"), superpose_probability=-0.5)
