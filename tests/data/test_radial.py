"""Tests of the RADIal reader on tiny hand-made roots (numpy + PIL + csv, TINY sensor)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from radarpc.data.radial import (
    RADIal,
    check_root,
    find_fft_file,
    freespace_to_model,
    load_freespace,
    load_rd,
    random_split_indices,
    read_labels,
    read_skip_file,
    split_of_sequence,
    write_skip_file,
)
from radarpc.data.radial_format import (
    LABEL_COLUMNS,
    LABEL_TENSOR_COLUMNS,
    OFFICIAL_SPLITS,
    fft_path,
    freespace_path,
    simulated_sequence_name,
    simulated_split,
)
from radarpc.io import DataFileError
from radarpc.data.radial_format import save_calibration
from radarpc.sensors.radial import RADIAL, TINY
from radarpc.sim.radial_calibration import make_calibration
from testkit import TINY_ROOT


# ---- a hand-made root -------------------------------------------------------------------------
def vehicle(r: float, a: float, d: float, difficult: int = 0) -> dict:
    """A label row of a vehicle at range r, azimuth a (deg), Doppler d."""
    x, y = r * np.cos(np.deg2rad(a)), r * np.sin(np.deg2rad(a))
    return {"x1_pix": -1, "y1_pix": -1, "x2_pix": -1, "y2_pix": -1,
            "laser_X_m": x + 0.5, "laser_Y_m": y, "laser_Z_m": -0.3,
            "radar_X_m": x, "radar_Y_m": y, "radar_R_m": r, "radar_A_deg": a, "radar_D": d,
            "radar_P_db": 40.0 + r / 10, "Difficult": difficult}


def cube_of(num: int, sensor=TINY) -> np.ndarray:
    """Deterministic complex64 cube whose [0, 0, 0] identifies frame ``num``."""
    rng = np.random.default_rng(num)
    c = (rng.normal(size=sensor.rd_shape) + 1j * rng.normal(size=sensor.rd_shape)).astype(np.complex64)
    c[0, 0, 0] = num + 0.5j
    return c


def mask_of(num: int) -> np.ndarray:
    """Deterministic 512 x 900 uint8 mask (255 = free)."""
    m = np.zeros((512, 900), np.uint8)
    m[: 40 + 3 * num, 200 + num: 700 - num] = 255
    return m


def write_root(root: Path, frames: list[tuple[int, str, list[dict]]], *, simulated: bool = True,
               n_sequences: int | None = None, fft_suffix: str = ".npy", sensor=TINY) -> Path:
    """Write labels.csv, radar_FFT, radar_Freespace (+ sensor.json, calibration.npz if simulated)."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "radar_FFT").mkdir(exist_ok=True)
    (root / "radar_Freespace").mkdir(exist_ok=True)
    with open(root / "labels.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(LABEL_COLUMNS)
        for k, (num, seq, vehicles) in enumerate(frames):
            rows = vehicles or [None]
            for v in rows:
                vals = {c: -1 for c in LABEL_COLUMNS}
                if v is not None:
                    vals.update(v)
                vals.update(numSample=num, dataset=seq, dataset_index=k)
                w.writerow([vals[c] for c in LABEL_COLUMNS])
            if fft_suffix == ".npy":
                np.save(fft_path(root, num), cube_of(num, sensor))
            else:
                np.savez(fft_path(root, num, ".npz"), cube_of(num, sensor))
            Image.fromarray(mask_of(num)).save(freespace_path(root, num))
    if simulated:
        d = sensor.to_dict()
        names = {s for _, s, _ in frames}
        n_seq = n_sequences if n_sequences is not None else len(names)
        d.update(seed=0, n_sequences=n_seq, frames_per_sequence=max(len(frames) // n_seq, 1),
                 radarpc_version="0.1.0")
        (root / "sensor.json").write_text(json.dumps(d))
        save_calibration(root / "calibration.npz", make_calibration(sensor))
    return root


def sim_frames(n_seq: int, per_seq: int) -> list[tuple[int, str, list[dict]]]:
    out = []
    for q in range(n_seq):
        for j in range(per_seq):
            num = 10 * q + j
            vehicles = [vehicle(5.0 + num, -10.0 + q, 1.5 * j)] if j % 2 == 0 else []
            if j == 0:
                vehicles.append(vehicle(12.0, 20.0, -3.0, difficult=1))
            out.append((num, simulated_sequence_name(0, q), vehicles))
    return out


@pytest.fixture
def sim_root(tmp_path: Path) -> Path:
    # 6 sequences x 3 frames: frame j=0 has an easy and a difficult vehicle, j=1 none, j=2 one.
    return write_root(tmp_path / "sim", sim_frames(6, 3))


# ---- labels.csv -------------------------------------------------------------------------------
def test_read_labels_values(sim_root: Path) -> None:
    t = read_labels(sim_root / "labels.csv")
    # 6 seq x (2 rows + 1 empty row + 1 row)
    assert len(t) == 6 * 4
    assert t.row(0) == {"numSample": 0, "x1_pix": -1.0, "y1_pix": -1.0, "x2_pix": -1.0, "y2_pix": -1.0,
                        **{k: pytest.approx(v) for k, v in vehicle(5.0, -10.0, 0.0).items()
                           if k not in ("x1_pix", "y1_pix", "x2_pix", "y2_pix", "Difficult")},
                        "dataset": "SIM@s0_q000", "dataset_index": 0, "Difficult": 0}
    assert list(t.has_vehicle[:4]) == [True, True, False, True]


@pytest.mark.parametrize("header, needle", [
    (list(LABEL_COLUMNS[:-1]), "missing columns ['Difficult']"),
    (list(LABEL_COLUMNS) + ["extra"], "extra columns ['extra']"),
    (list(LABEL_COLUMNS[1:]) + ["numSample"], "wrong order"),
])
def test_read_labels_bad_header(tmp_path: Path, header: list[str], needle: str) -> None:
    p = tmp_path / "labels.csv"
    p.write_text(",".join(header) + "\n")
    with pytest.raises(DataFileError, match="labels.csv") as e:
        read_labels(p)
    assert needle in str(e.value)


def test_read_labels_bad_value_names_line(tmp_path: Path) -> None:
    p = tmp_path / "labels.csv"
    good = ["1"] + ["-1"] * 13 + ["SEQ", "0", "0"]
    bad = list(good)
    bad[10] = "abc"  # radar_R_m
    p.write_text(",".join(LABEL_COLUMNS) + "\n" + ",".join(good) + "\n" + ",".join(bad) + "\n")
    with pytest.raises(DataFileError, match=r"labels.csv: line 3: column 'radar_R_m' holds 'abc'"):
        read_labels(p)
    p.write_text(",".join(LABEL_COLUMNS) + "\n" + ",".join(good[:-1]) + "\n")
    with pytest.raises(DataFileError, match=r"line 2: 16 fields, expected 17"):
        read_labels(p)
    with pytest.raises(DataFileError, match="missing"):
        read_labels(tmp_path / "nope.csv")


# ---- the dataset ------------------------------------------------------------------------------
def test_items_values(sim_root: Path) -> None:
    ds = RADIal(sim_root, split="all")
    assert ds.sensor == TINY and ds.meta is not None and ds.meta.n_sequences == 6
    assert ds.frame_ids == sorted(10 * q + j for q in range(6) for j in range(3))
    assert ds.sequences[:3] == ["SIM@s0_q000"] * 3
    rd, lab, fs = ds[ds.index_of(20)]
    assert rd.dtype == torch.complex64 and rd.shape == TINY.rd_shape
    np.testing.assert_array_equal(rd.numpy(), cube_of(20))
    assert lab.dtype == torch.float32 and lab.shape == (2, 14)
    want = [vehicle(25.0, -8.0, 0.0), vehicle(12.0, 20.0, -3.0, 1)]
    np.testing.assert_allclose(lab.numpy(), [[v[c] for c in LABEL_TENSOR_COLUMNS] for v in want], rtol=1e-6)
    assert fs.dtype == torch.bool and fs.shape == (256, 224)
    np.testing.assert_array_equal(fs.numpy(), freespace_to_model(mask_of(20)))
    # a frame without vehicles: (0, 14); its raw -1 row is still visible
    _, lab1, _ = ds[ds.index_of(21)]
    assert lab1.shape == (0, 14)
    raw = ds.frame_labels(ds.index_of(21))
    assert len(raw) == 1 and raw[0]["radar_R_m"] == -1.0 and raw[0]["numSample"] == 21
    assert [r["Difficult"] for r in ds.frame_labels(ds.index_of(20))] == [0, 1]
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_device_and_collate(sim_root: Path) -> None:
    from radarpc.data.radial import radial_collate

    ds = RADIal(sim_root, split="all", device="cpu")
    rd, labels, fs = radial_collate([ds[0], ds[1]])
    assert rd.shape == (2, *TINY.rd_shape) and fs.shape == (2, 256, 224)
    assert [tuple(x.shape) for x in labels] == [(2, 14), (0, 14)]
    assert rd.device.type == "cpu"


def test_simulated_split(sim_root: Path) -> None:
    seen: dict[str, list[int]] = {}
    for split in ("train", "val", "test"):
        ds = RADIal(sim_root, split=split)
        seen[split] = ds.frame_ids
        for num, seq in zip(ds.frame_ids, ds.sequences):
            assert simulated_split(num // 10, 6) == split
            assert seq == simulated_sequence_name(0, num // 10)
    # 6 sequences: 0,1,2,3 train, 4 val, 5 test (the rule of simulated_split)
    assert [len(seen[s]) for s in ("train", "val", "test")] == [12, 3, 3]
    assert sorted(sum(seen.values(), [])) == RADIal(sim_root, split="all").frame_ids


def test_official_split_on_record_names(tmp_path: Path) -> None:
    val, test = OFFICIAL_SPLITS["val"], OFFICIAL_SPLITS["test"]
    names = [val[0], "RECORD@2020-11-21_11.54.31", test[2], val[3], "RECORD@2020-11-22_08.45.18"]
    frames = [(100 + 2 * k + j, n, [vehicle(10.0, 0.0, 0.0)]) for k, n in enumerate(names) for j in range(2)]
    root = write_root(tmp_path / "real", frames, simulated=False)
    assert RADIal(root, "all").sensor == RADIAL  # no sensor.json: the real radar
    got = {s: RADIal(root, s, sensor=TINY).sequences for s in ("train", "val", "test")}
    assert sorted(set(got["val"])) == sorted([val[0], val[3]])
    assert got["test"] == [test[2]] * 2
    assert sorted(set(got["train"])) == ["RECORD@2020-11-21_11.54.31", "RECORD@2020-11-22_08.45.18"]
    rd, _, _ = RADIal(root, "test", sensor=TINY)[0]
    np.testing.assert_array_equal(rd.numpy(), cube_of(104))


def test_split_of_sequence_rules() -> None:
    assert split_of_sequence(OFFICIAL_SPLITS["test"][0], []) == "test"
    assert split_of_sequence(OFFICIAL_SPLITS["val"][1], []) == "val"
    assert split_of_sequence("RECORD@2020-11-21_13.44.44", []) == "train"
    names = [simulated_sequence_name(3, q) for q in range(4)]
    # n inferred from the names (4): q003 test, q002 val
    assert [split_of_sequence(n, names) for n in names] == ["train", "train", "val", "test"]
    # n from sensor.json wins: with 10 sequences, q003 is train and q004 val
    assert split_of_sequence(names[3], names, n_sequences=10) == "train"
    assert split_of_sequence(simulated_sequence_name(3, 4), names, n_sequences=10) == "val"


def test_random_split(sim_root: Path) -> None:
    ids = RADIal(sim_root, "all").frame_ids
    parts = {s: RADIal(sim_root, s, random_split=(0.7, 0.15, 0.15), seed=3).frame_ids
             for s in ("train", "val", "test")}
    assert [len(parts[s]) for s in ("train", "val", "test")] == [int(0.7 * 18), int(0.15 * 18), 18 - 12 - 2]
    assert sorted(sum(parts.values(), [])) == ids
    again = RADIal(sim_root, "train", random_split=(0.7, 0.15, 0.15), seed=3).frame_ids
    assert again == parts["train"]
    assert RADIal(sim_root, "train", random_split=(0.7, 0.15, 0.15), seed=4).frame_ids != parts["train"]
    # the same frames as torch.utils.data.random_split (FFTRadNet's random mode)
    ref = torch.utils.data.random_split(range(18), [12, 2, 4], generator=torch.Generator().manual_seed(3))
    assert parts["val"] == [ids[k] for k in sorted(ref[1].indices)]
    with pytest.raises(ValueError, match="summing to 1"):
        random_split_indices(10, (0.5, 0.2, 0.2), 0)


def test_skip(sim_root: Path, tmp_path: Path) -> None:
    full = RADIal(sim_root, "train").frame_ids
    assert RADIal(sim_root, "train", skip=[0, 21, 999]).frame_ids == [n for n in full if n not in (0, 21)]
    f = tmp_path / "skip.txt"
    write_skip_file(f, [21, 0, 21])
    assert f.read_text() == "0\n21\n" and read_skip_file(f) == [0, 21]
    assert RADIal(sim_root, "train", skip=f).frame_ids == [n for n in full if n not in (0, 21)]
    # skipping after a random split never moves the other frames between splits
    a = RADIal(sim_root, "val", random_split=(0.5, 0.25, 0.25), seed=1).frame_ids
    b = RADIal(sim_root, "val", random_split=(0.5, 0.25, 0.25), seed=1, skip=[a[0]]).frame_ids
    assert b == a[1:]
    f.write_text("3\nfour\n")
    with pytest.raises(DataFileError, match=r"skip.txt: line 2: 'four'"):
        RADIal(sim_root, skip=f)


def test_difficult_false(sim_root: Path, tmp_path: Path) -> None:
    ds = RADIal(sim_root, "all", difficult=False)
    _, lab, _ = ds[ds.index_of(0)]
    assert lab.shape == (1, 14) and lab[0, LABEL_TENSOR_COLUMNS.index("Difficult")] == 0
    assert 1 in ds.frame_ids  # empty frames are kept
    # a frame whose only vehicle is difficult is dropped
    root = write_root(tmp_path / "d", [(0, "SIM@s0_q000", [vehicle(9.0, 0.0, 0.0, 1)]),
                                       (1, "SIM@s0_q000", [vehicle(9.0, 0.0, 0.0, 0)])])
    assert RADIal(root, "all", difficult=False).frame_ids == [1]
    assert RADIal(root, "all", difficult=True).frame_ids == [0, 1]


def test_npz_cubes(tmp_path: Path) -> None:
    root = write_root(tmp_path / "z", sim_frames(3, 1), fft_suffix=".npz")
    assert find_fft_file(root, 20).suffix == ".npz"
    ds = RADIal(root, "all")
    np.testing.assert_array_equal(ds[2][0].numpy(), cube_of(20))


def test_calibration_property(sim_root: Path, tmp_path: Path) -> None:
    ds = RADIal(sim_root, "all")
    np.testing.assert_array_equal(ds.calibration.signal, make_calibration(TINY).signal)
    real = write_root(tmp_path / "real", [(0, "RECORD@x", [])], simulated=False)
    with pytest.raises(DataFileError, match="calibration.npz"):
        RADIal(real, "all").calibration
    (real / "CalibrationTable.npy").write_bytes(b"not opened without trust_pickle")
    with pytest.raises(DataFileError, match="CalibrationTable.npy.*trust_pickle"):
        RADIal(real, "all").calibration


def test_sensor_mismatch_and_bad_args(sim_root: Path) -> None:
    with pytest.raises(ValueError, match="RD shape"):
        RADIal(sim_root, sensor=RADIAL)
    with pytest.raises(ValueError, match="split must be one of"):
        RADIal(sim_root, split="validation")
    (sim_root / "sensor.json").write_text('{"name": "x", "n_range": "many"')
    with pytest.raises(DataFileError, match="sensor.json"):
        RADIal(sim_root)


# ---- freespace --------------------------------------------------------------------------------
def test_freespace_to_model_matches_pil() -> None:
    rng = np.random.default_rng(0)
    mask = (rng.random((512, 900)) < 0.5).astype(np.uint8) * 255
    # RADIal: CenterCrop((512, 448)) then Resize((256, 224), NEAREST) of the PIL image, == 255
    im = Image.fromarray(mask)
    left = round((900 - 448) / 2)
    ref = np.asarray(im.crop((left, 0, left + 448, 512)).resize((224, 256), Image.NEAREST)) == 255
    out = freespace_to_model(mask)
    assert out.dtype == np.bool_ and out.shape == (256, 224)
    np.testing.assert_array_equal(out, ref)
    np.testing.assert_array_equal(freespace_to_model(mask == 255), ref)


def test_freespace_to_model_hand_indices() -> None:
    # PIL samples output pixel centres: output (r, c) reads input row 2r+1, column 226 + 2c + 1.
    m = np.zeros((512, 900), np.uint8)
    m[1, 227] = 255    # -> (0, 0)
    m[511, 673] = 255  # -> (255, 223)
    m[0, 226] = 255    # never sampled
    m[101, 400] = 255  # even column: never sampled
    m[101, 401] = 255  # -> (50, 87)
    out = freespace_to_model(m)
    assert sorted(zip(*np.nonzero(out))) == [(0, 0), (50, 87), (255, 223)]
    with pytest.raises(ValueError, match=r"\(512, 900\)"):
        freespace_to_model(np.zeros((256, 224), np.uint8))
    with pytest.raises(ValueError, match="dtype float64"):
        freespace_to_model(np.zeros((512, 900)))


# ---- bad files --------------------------------------------------------------------------------
def _truncate(p: Path) -> None:
    b = p.read_bytes()
    p.write_bytes(b[: len(b) // 2])


@pytest.mark.parametrize("damage, needle", [
    ("missing_fft", "RD cube of frame 20 is missing"),
    ("truncated_fft", "truncated|corrupt"),
    ("wrong_shape", "expected shape 64x32x4, found 64x32x3"),
    ("real_dtype", "expected a complex array, found dtype float32"),
    ("nan", "NaN"),
    ("missing_freespace", "freespace mask is missing"),
    ("truncated_freespace", "truncated or not a readable PNG"),
    ("small_freespace", "expected a 512 x 900 mask, found 256 x 900"),
])
def test_bad_file_errors(sim_root: Path, damage: str, needle: str) -> None:
    fft, fsp = fft_path(sim_root, 20), freespace_path(sim_root, 20)
    if damage == "missing_fft":
        fft.unlink()
    elif damage == "truncated_fft":
        _truncate(fft)
    elif damage == "wrong_shape":
        np.save(fft, cube_of(20)[..., :3])
    elif damage == "real_dtype":
        np.save(fft, cube_of(20).real)
    elif damage == "nan":
        c = cube_of(20)
        c[3, 4, 1] = np.nan
        np.save(fft, c)
    elif damage == "missing_freespace":
        fsp.unlink()
    elif damage == "truncated_freespace":
        _truncate(fsp)
    elif damage == "small_freespace":
        Image.fromarray(mask_of(20)[:256]).save(fsp)
    ds = RADIal(sim_root, "all")
    name = fsp.name if "freespace" in damage else fft.name
    with pytest.raises(DataFileError, match=needle) as e:
        ds[ds.index_of(20)]
    assert name in str(e.value)
    ds[ds.index_of(21)]  # other frames still load
    report = check_root(sim_root)
    assert report.bad_frames == [20] and len(report.problems) == 1
    assert report.problems[0].path.name == name
    assert RADIal(sim_root, "all", skip=report.bad_frames).frame_ids == [n for n in ds.frame_ids if n != 20]


def test_load_rd_and_freespace_direct(tmp_path: Path) -> None:
    p = tmp_path / "c.npy"
    np.save(p, cube_of(1).astype(np.complex128))
    out = load_rd(p, TINY)
    assert out.dtype == np.complex64 and out.shape == TINY.rd_shape
    g = tmp_path / "m.png"
    m = mask_of(1)
    m[0, 0] = 7
    Image.fromarray(m).save(g)
    with pytest.raises(DataFileError, match=r"m.png: expected mask values 0 and 255, found also \[7\]"):
        load_freespace(g)
    assert load_freespace(g, validate=False)[0, 0] == 7
    Image.fromarray(np.zeros((512, 900, 3), np.uint8)).save(g)
    with pytest.raises(DataFileError, match="single-channel"):
        load_freespace(g)


def test_check_root_lists_everything(sim_root: Path) -> None:
    fft_path(sim_root, 0).unlink()
    np.save(fft_path(sim_root, 11), cube_of(11).real)
    freespace_path(sim_root, 11).unlink()
    (sim_root / "calibration.npz").unlink()
    r = check_root(sim_root, progress=False)
    assert not r.ok and r.n_frames == 18 and r.bad_frames == [0, 11]
    names = sorted(p.path.name for p in r.problems)
    assert names == ["calibration.npz", "fft_000000.npy", "fft_000011.npy", "freespace_000011.png"]
    text = r.format()
    assert "4 problem(s), 2 bad frame(s)" in text and "frame 11:" in text
    (sim_root / "labels.csv").write_text("a,b\n")
    r = check_root(sim_root)
    assert [p.path.name for p in r.problems][-1] == "labels.csv"


# ---- round trip with the simulator's writer ---------------------------------------------------
def test_reads_what_the_simulator_writes(tiny_root: Path) -> None:
    from radarpc.sim.radial_writer import SimulatedRADIal

    root = tiny_root                                                # the session's TINY root (read-only)
    assert TINY_ROOT == dict(n_sequences=3, frames_per_sequence=2, seed=0)     # the frames checked below
    assert check_root(root).ok
    ds = RADIal(root, "all")
    assert ds.sensor == TINY and ds.frame_ids == list(range(6))
    assert ds.sequences == [simulated_sequence_name(0, q) for q in range(3) for _ in range(2)]
    fly = SimulatedRADIal(TINY, **TINY_ROOT, split="all")
    for i in range(len(ds)):  # bit-identical to the on-the-fly frames on the same device
        for a, b in zip(ds[i], fly[i]):
            assert a.dtype == b.dtype and torch.equal(a, b)
    for split in ("train", "val", "test"):  # 3 sequences: q0 train, q1 val, q2 test
        assert RADIal(root, split).frame_ids == SimulatedRADIal(TINY, **TINY_ROOT, split=split).frame_ids
    assert RADIal(root, "test").frame_ids == [4, 5]
    raw = ds.frame_labels(0)
    assert raw and set(raw[0]) == set(LABEL_COLUMNS) and raw[0]["dataset"] == "SIM@s0_q000"


# ---- empty splits and check_root contract -----------------------------------------------------
def test_empty_split_is_a_clear_error(tmp_path: Path) -> None:
    root = write_root(tmp_path / "two", sim_frames(2, 2))          # 2 sequences: all train
    assert len(RADIal(root, "train")) == 4
    for split in ("val", "test"):
        with pytest.raises(ValueError, match=rf"split '{split}' .* is empty: 2 sequence\(s\).*simulated_split"):
            RADIal(root, split)
    real = write_root(tmp_path / "real", [(k, "RECORD@2020-11-21_11.54.31", []) for k in range(3)],
                      simulated=False)
    with pytest.raises(ValueError, match=r"split 'test' .* 1 sequence\(s\).*OFFICIAL_SPLITS"):
        RADIal(real, "test", sensor=TINY)
    with pytest.raises(ValueError, match=r"split 'val' .*random_split"):
        RADIal(root, "val", random_split=(1.0, 0.0, 0.0))


def test_check_root_reports_a_wrong_explicit_sensor(sim_root: Path) -> None:
    from radarpc.sensors.radial import RADIAL_S
    r = check_root(sim_root, RADIAL_S)                               # never raises
    assert [p.path.name for p in r.problems] == ["sensor.json"]
    assert "RD shape" in r.problems[0].reason and r.sensor == TINY   # cubes checked with sensor.json's
    assert r.n_frames == 18


def test_check_root_flags_missing_calibration_with_unreadable_sensor_json(sim_root: Path) -> None:
    (sim_root / "sensor.json").write_text("{not json")
    (sim_root / "calibration.npz").unlink()
    names = sorted(p.path.name for p in check_root(sim_root).problems)
    assert names == ["calibration.npz", "sensor.json"]


def test_check_root_flags_a_truncated_labels_csv(sim_root: Path) -> None:
    lines = (sim_root / "labels.csv").read_text().splitlines()
    keep = [ln for ln in lines if not ln.startswith(("50,", "51,", "52,"))]   # drop sequence 5
    (sim_root / "labels.csv").write_text("\n".join(keep) + "\n")
    r = check_root(sim_root)
    assert [p.path.name for p in r.problems] == ["labels.csv"]
    assert "15 frames" in r.problems[0].reason and "6 x 3 = 18" in r.problems[0].reason
