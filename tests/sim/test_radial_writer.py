"""Simulated RADIal roots: layout, labels round trip, resume, refusal, on-the-fly == on-disk, CLI."""
import argparse
import csv
import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from radarpc import __version__
from radarpc.data.radial import RADIal, load_freespace, read_labels
from radarpc.data.radial_format import FREESPACE_SHAPE, LABEL_COLUMNS, fft_path, freespace_path
from radarpc.data.radial_format import load_calibration
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim import radial_writer
from radarpc.sim.radial_writer import RadialSimulator, SimulatedRADIal, write_radial_dataset
from radarpc.sim.scenes import CITY, DEFAULT_MIX, SceneMix
from radarpc.io import DataFileError
from radarpc.runs import OutputBusyError, RunMismatchError
from testkit import RADIAL_S_CITY_ROOT, stalling_writer_script

N_SEQ, N_FR, SEED = 3, 2, 11


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return write_radial_dataset(tmp_path_factory.mktemp("sim") / "root", TINY, N_SEQ, N_FR, SEED,
                                progress=False)


def all_files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_layout_and_files(root):
    n = N_SEQ * N_FR
    for num in range(n):
        rd = np.load(fft_path(root, num), allow_pickle=False)
        assert rd.shape == TINY.rd_shape and rd.dtype == np.complex64 and np.isfinite(rd).all()
        fs = load_freespace(freespace_path(root, num))
        assert fs.shape == FREESPACE_SHAPE and fs.dtype == np.uint8
        assert 0 < (fs == 255).mean() < 1
    meta = json.loads((root / "sensor.json").read_text())
    assert meta["seed"] == SEED and meta["n_sequences"] == N_SEQ and meta["frames_per_sequence"] == N_FR
    assert meta["radarpc_version"] == __version__ and meta["name"] == "tiny"
    assert json.loads((root / "scene.json").read_text()) == json.loads(json.dumps(DEFAULT_MIX.to_dict()))
    calib = load_calibration(root / "calibration.npz")
    np.testing.assert_array_equal(calib.signal, make_calibration(TINY).signal)
    assert not list(root.rglob("*.tmp")) and not (root.parent / ".root.lock").exists()


def test_labels_round_trip_through_csv(root):
    table = read_labels(root / "labels.csv")
    assert (root / "labels.csv").read_text().splitlines()[0] == ",".join(LABEL_COLUMNS)
    sim = RadialSimulator(TINY, N_SEQ, N_FR, SEED)
    want = [r for q in range(N_SEQ) for i in range(N_FR) for r in sim.geometry(q, i)[1]]
    assert len(table) == len(want)
    for k, row in enumerate(want):
        got = table.row(k)
        assert tuple(got[c] for c in LABEL_COLUMNS) == row
    assert sorted(set(table.num_sample.tolist())) == list(range(N_SEQ * N_FR))


def test_resume_gives_the_identical_dataset(root, tmp_path, monkeypatch):
    ref = all_files(root)
    part = tmp_path / "part"
    shutil.copytree(root, part)
    # an interrupted run: some frames and labels.csv missing, a stray temp file
    fft_path(part, 1).unlink()
    freespace_path(part, 4).unlink()
    (part / "labels.csv").unlink()
    (part / "radar_FFT" / ".fft_000002.npy.abc.tmp").write_bytes(b"partial")
    (part / ".labels.csv.def.tmp").write_text("numSample")
    untouched = fft_path(part, 3).stat().st_mtime_ns
    calls = []
    real = radial_writer.synthesize_rd
    monkeypatch.setattr(radial_writer, "synthesize_rd", lambda *a, **k: calls.append(1) or real(*a, **k))
    write_radial_dataset(part, TINY, N_SEQ, N_FR, SEED, progress=False)
    assert len(calls) == 2                                 # only frames 1 and 4 were synthesised again
    assert fft_path(part, 3).stat().st_mtime_ns == untouched
    assert all_files(part) == ref                          # the killed run's temp files are removed


def test_refuses_a_non_empty_folder_unless_overwrite(root, tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="--overwrite"):
        write_radial_dataset(other, TINY, 1, 1, 0, progress=False)
    before = all_files(root)
    # a partial run of another seed is not resumed either; the message names what differs
    with pytest.raises(RunMismatchError, match=r"sensor\.json:seed.*--overwrite"):
        write_radial_dataset(root, TINY, N_SEQ, N_FR, SEED + 1, progress=False)
    # ... nor one with another scene config
    with pytest.raises(FileExistsError, match=r"scene\.json:presets\.city\.clutter_per_100m.*--overwrite"):
        write_radial_dataset(root, TINY, N_SEQ, N_FR, SEED, progress=False,
                             scenes=SceneMix(tuple(dataclasses.replace(p, clutter_per_100m=1.0) if p is CITY else p
                                                   for p in DEFAULT_MIX.presets), DEFAULT_MIX.weights))
    assert all_files(root) == before                       # refused before anything was written
    write_radial_dataset(other, TINY, 1, 1, 0, overwrite=True, progress=False)
    assert (other / "notes.txt").read_text() == "mine" and fft_path(other, 0).is_file()
    with pytest.raises(NotADirectoryError, match="not a folder"):
        write_radial_dataset(other / "notes.txt", TINY, 1, 1, 0, progress=False)


def _count_synth(monkeypatch):
    calls = []
    real = radial_writer.synthesize_rd
    monkeypatch.setattr(radial_writer, "synthesize_rd", lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


def test_resume_regenerates_damaged_frames(root, tmp_path, monkeypatch):
    ref = all_files(root)
    part = tmp_path / "damaged"
    shutil.copytree(root, part)
    # truncated cube (header intact, data cut), a cube with a NaN, a truncated PNG
    b = fft_path(part, 0).read_bytes()
    fft_path(part, 0).write_bytes(b[: len(b) // 2])
    bad = np.load(fft_path(part, 2), allow_pickle=False)
    bad[3, 4, 1] = np.nan
    np.save(fft_path(part, 2), bad)
    p = freespace_path(part, 5).read_bytes()
    freespace_path(part, 5).write_bytes(p[: len(p) // 2])
    calls = _count_synth(monkeypatch)
    write_radial_dataset(part, TINY, N_SEQ, N_FR, SEED, progress=False)
    assert len(calls) == 3                                 # frames 0, 2 and 5 regenerated
    assert all_files(part) == ref


def test_version_bump_still_resumes(root, tmp_path, monkeypatch):
    ref = all_files(root)
    part = tmp_path / "old"
    shutil.copytree(root, part)
    meta = json.loads((part / "sensor.json").read_text())
    meta["radarpc_version"] = "0.0.0-older"
    (part / "sensor.json").write_text(json.dumps(meta))
    fft_path(part, 1).unlink()
    calls = _count_synth(monkeypatch)
    write_radial_dataset(part, TINY, N_SEQ, N_FR, SEED, progress=False)   # no FileExistsError
    assert len(calls) == 1
    assert all_files(part) == ref                          # sensor.json rewritten with this version


def test_overwrite_starts_over_even_on_a_matching_root(root, tmp_path, monkeypatch):
    ref = all_files(root)
    again = tmp_path / "again"
    shutil.copytree(root, again)
    (again / "radar_FFT" / "fft_000099.npy").write_bytes(b"stale")      # output of an older run
    calls = _count_synth(monkeypatch)
    write_radial_dataset(again, TINY, N_SEQ, N_FR, SEED, overwrite=True, progress=False)
    assert len(calls) == N_SEQ * N_FR                      # every frame synthesised again
    assert all_files(again) == ref                         # the stale cube is gone


# A second real process writes the same root and stalls inside the atomic write of its first
# freespace PNG (its temp file exists), like a job killed mid-write.
_STALLING_WRITER = stalling_writer_script(
    "radarpc.sim.radial_writer", ".png",
    "from radarpc.sensors.radial import TINY\n"
    "writer.write_radial_dataset(sys.argv[1], TINY, *map(int, sys.argv[2:]), progress=False)")


def test_second_writer_is_refused_and_a_killed_run_resumes(root, tmp_path):
    out = tmp_path / "busy"
    child = subprocess.Popen([sys.executable, "-c", _STALLING_WRITER, str(out), str(N_SEQ), str(N_FR), str(SEED)],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "writing"
        assert len(list(out.rglob(".*.tmp"))) == 1
        before = all_files(out)
        with pytest.raises(OutputBusyError, match=rf"pid {child.pid}\) is writing the dataset root .*busy"):
            write_radial_dataset(out, TINY, N_SEQ, N_FR, SEED, progress=False)
        with pytest.raises(FileExistsError, match="another radarpc process"):     # with overwrite too
            write_radial_dataset(out, TINY, N_SEQ, N_FR, SEED, overwrite=True, progress=False)
        assert all_files(out) == before                     # the refused writers touched nothing
    finally:
        child.kill()
        child.wait()
        child.stdout.close()
    write_radial_dataset(out, TINY, N_SEQ, N_FR, SEED, progress=False)   # the kill released the lock
    assert not list(out.rglob("*.tmp")) and not (tmp_path / ".busy.lock").exists()
    assert all_files(out) == all_files(root)


def test_empty_split_of_the_on_the_fly_dataset_is_a_clear_error():
    with pytest.raises(ValueError, match=r"split 'val' .* is empty: 2 sequence\(s\).*simulated_split"):
        SimulatedRADIal(TINY, 2, 1, SEED, split="val")
    assert len(SimulatedRADIal(TINY, 2, 1, SEED, split="train")) == 2


def _summary(ds):
    """A consumer written once against the common interface (RADIal or SimulatedRADIal)."""
    out = []
    for i in range(len(ds)):
        rd = ds.cube(i)                                   # (R, D, Rx) complex64
        peak = (rd.abs() ** 2).sum(-1)                    # (R, D)
        _, labels, fs = ds[i]
        out.append((ds.frame_ids[i], ds.sequences[i], int(peak.argmax()), float(peak.max()),
                    labels.numpy().tobytes(), int(fs.sum()), len(ds.frame_labels(i)),
                    ds.index_of(ds.frame_ids[i])))
    return out, ds.split, ds.sensor, ds.calibration.signal.tobytes(), str(ds.cube(0).device)


@pytest.mark.parametrize("kw", [dict(), dict(difficult=False), dict(skip=[1, 4]),
                                dict(random_split=(0.5, 0.25, 0.25))])
def test_same_code_path_on_both_datasets(root, kw):
    disk_kw = dict(kw, seed=7) if "random_split" in kw else kw
    fly_kw = dict(kw, split_seed=7) if "random_split" in kw else kw
    disk = RADIal(root, "train", **disk_kw)
    fly = SimulatedRADIal(TINY, N_SEQ, N_FR, SEED, "train", **fly_kw)
    assert _summary(disk) == _summary(fly)
    assert torch.equal(disk.cube(0), fly.cube(0)) and fly.cube(0).dtype == torch.complex64


def test_radial_s_on_disk_equals_on_the_fly(radial_s_city_root):
    # the session's radial-s root (3 sequences x 4 city frames, seed 3): the first and last frame of each
    # sequence, labelled vehicles among them
    from radarpc.sensors.radial import RADIAL_S
    disk = RADIal(radial_s_city_root, "all")
    fly = SimulatedRADIal(RADIAL_S, **RADIAL_S_CITY_ROOT, split="all")
    assert len(disk) == len(fly) == 12
    labelled = 0
    for i in (0, 3, 4, 7, 8, 11):
        for x, y in zip(disk[i], fly[i]):
            assert x.dtype == y.dtype and torch.equal(x, y)
        assert disk.frame_labels(i) == fly.frame_labels(i)
        labelled += len(fly[i][1])
    assert labelled > 0


@pytest.mark.parametrize("split", ["train", "val", "test", "all"])
def test_on_the_fly_equals_on_disk(root, split):
    disk = RADIal(root, split=split)
    fly = SimulatedRADIal(TINY, N_SEQ, N_FR, SEED, split=split)
    assert fly.frame_ids == disk.frame_ids and len(fly) == len(disk) > 0
    assert fly.sequences == disk.sequences
    assert fly.sensor == disk.sensor
    np.testing.assert_array_equal(fly.calibration.signal, disk.calibration.signal)
    for i in range(len(fly)):
        a, b = disk[i], fly[i]
        assert [x.dtype for x in b] == [torch.complex64, torch.float32, torch.bool]
        assert b[0].shape == TINY.rd_shape and b[1].shape[1] == 14 and b[2].shape == (256, 224)
        for x, y in zip(a, b):
            assert x.shape == y.shape and torch.equal(x, y)
        assert fly.frame_labels(i) == disk.frame_labels(i)
        assert fly.index_of(fly.frame_ids[i]) == i


def test_frames_are_reproducible_and_distinct():
    ds = SimulatedRADIal(TINY, N_SEQ, N_FR, SEED, split="all")
    assert torch.equal(ds[1][0], ds[1][0])
    assert not torch.equal(ds[0][0], ds[1][0])
    assert not torch.equal(ds[0][0], SimulatedRADIal(TINY, N_SEQ, N_FR, SEED + 1, split="all")[0][0])
    with pytest.raises(IndexError):
        ds[len(ds)]
    with pytest.raises(ValueError, match="split"):
        SimulatedRADIal(TINY, N_SEQ, N_FR, SEED, split="dev")
    with pytest.raises(ValueError, match="n_sequences"):
        SimulatedRADIal(TINY, 0, N_FR, SEED)


def test_cli_writes_a_root(tmp_path, capsys):
    from radarpc.cli import simulate_radial

    parser = argparse.ArgumentParser()
    simulate_radial.add_parser(parser.add_subparsers(dest="kind"))
    out = tmp_path / "cli"
    args = parser.parse_args(["radial", "--out", str(out), "--sequences", "1", "--frames-per-sequence", "2",
                              "--sensor", "tiny", "--seed", "3", "--no-progress"])
    assert args.func(args) == 0
    assert ": 2 frames (1 sequence x 2)" in capsys.readouterr().out
    assert fft_path(out, 1).is_file() and (out / "labels.csv").is_file()
    with pytest.raises(FileExistsError, match="--overwrite"):
        args.func(parser.parse_args(["radial", "--out", str(out), "--sensor", "tiny", "--seed", "4",
                                     "--no-progress"]))
    with pytest.raises(ValueError, match="--device"):
        args.func(parser.parse_args(["radial", "--out", str(tmp_path / "x"), "--device", "nodevice"]))


def test_labels_point_at_their_vehicles_in_the_rd_cube(radial_s_city_root):
    # independent of the label code: the label's range and radial velocity must find the vehicle's
    # echo (Tx 0 replica) in the synthesised cube, well above the noise floor
    from radarpc.data.radial_format import LABEL_TENSOR_COLUMNS
    from radarpc.sensors.radial import RADIAL_S
    from radarpc.sim.rd import noise_power_rd

    cfg = RADIAL_S
    ds = RADIal(radial_s_city_root, "all")          # the session's 3 x 4 city frames (the densest traffic), seed 3
    col = {c: k for k, c in enumerate(LABEL_TENSOR_COLUMNS)}
    ratios = []
    for i in range(len(ds)):
        rd, labels, _ = ds[i]
        power = (rd.abs() ** 2).sum(-1) / (cfg.n_rx * noise_power_rd(cfg))   # (R, D), 1 = noise floor
        for row in labels:
            if row[col["Difficult"]] == 1 or row[col["radar_P_db"]] < 25 or abs(row[col["radar_A_deg"]]) > 60:
                continue
            r0 = int(round(float(row[col["radar_R_m"]]) / cfg.range_res_m))
            d0 = int(round(float(cfg.doppler_bin_of_velocity(float(row[col["radar_D"]]))))) % cfg.n_doppler
            prof = power[max(r0 - 1, 0): r0 + 3].amax(0)                     # (D,) over the near face
            replicas = torch.as_tensor((d0 + cfg.doppler_offsets) % cfg.n_doppler)
            empty = torch.as_tensor([(d0 + k * cfg.slot_width) % cfg.n_doppler for k in range(1, cfg.n_empty_slots + 1)])
            # the Tx replicas of the label's velocity carry the echo, > 15 dB above the noise, and
            # more power than the DDMA slots that this velocity leaves empty (which other objects
            # at the same range may fill)
            assert float(prof[replicas].min()) > 30.0, (i, row.tolist())
            ratios.append(float(prof[replicas].mean()) / float(prof[empty].mean()))
    assert len(ratios) >= 3 and min(ratios) > 1.0
    assert float(np.median(ratios)) > 5.0          # a sign error in radar_D gives ~1


def test_ground_truth_sidecars_follow_the_labels(root):
    # sim_frames.csv: one row per frame; sim_vehicles.csv: one row per vehicle label row, same order
    from radarpc.data.radial_truth import SIM_FRAME_COLUMNS as SIM_FRAMES_COLUMNS, SIM_VEHICLE_COLUMNS as SIM_VEHICLES_COLUMNS
    from radarpc.sim.road import KIND_NAMES, STATE_NAMES

    def read(name):
        with open(root / name, newline="") as f:
            rows = list(csv.reader(f))
        return rows[0], rows[1:]

    head, frames = read("sim_frames.csv")
    assert tuple(head) == SIM_FRAMES_COLUMNS == ("numSample", "dataset", "dataset_index", "scene", "ego_speed_mps")
    sim = RadialSimulator(TINY, N_SEQ, N_FR, SEED)
    assert [int(r[0]) for r in frames] == list(range(N_SEQ * N_FR))
    for r in frames:
        q, i = sim.locate(int(r[0]))
        fr = sim.scene_frame(q, i)
        assert r[3] == sim.preset(q).name == fr.scene and float(r[4]) == round(fr.ego_speed_mps, 4)
    head, vehicles = read("sim_vehicles.csv")
    assert tuple(head) == SIM_VEHICLES_COLUMNS == ("numSample", "vehicle_id", "kind", "state", "ground_speed_mps",
                                                   "radar_R_m", "radar_A_deg")
    labels = read_labels(root / "labels.csv")
    real = [k for k in range(len(labels)) if labels.row(k)["radar_R_m"] != -1]
    assert len(vehicles) == len(real)
    for r, k in zip(vehicles, real):
        lab = labels.row(k)
        assert int(r[0]) == lab["numSample"]
        assert float(r[5]) == lab["radar_R_m"] and float(r[6]) == lab["radar_A_deg"]
        assert r[2] in KIND_NAMES and r[3] in STATE_NAMES and float(r[4]) >= 0.0
    assert "sim_frames.csv" in radial_writer._OUTPUTS and "sim_vehicles.csv" in radial_writer._OUTPUTS
    # radarpc info's reader takes them: the scene shares are those of the frames
    from radarpc.data.radial_truth import label_statistics
    st = label_statistics(labels, root)
    assert sum(st.scene_share.values()) == pytest.approx(1.0) and sum(st.state_share.values()) == pytest.approx(1.0)
    assert st.scene_share[frames[0][3]] == pytest.approx(sum(r[3] == frames[0][3] for r in frames) / len(frames))


def test_scenes_pick_the_presets_of_the_sequences(tmp_path):
    from radarpc.sim.scenes import scene_mix

    out = write_radial_dataset(tmp_path / "city", TINY, 2, 1, 4, progress=False, scenes=scene_mix("city"),
                               camera=False, laser=False)
    assert json.loads((out / "scene.json").read_text())["mix"] == {"city": 0.31}
    with open(out / "sim_frames.csv", newline="") as f:
        assert {r["scene"] for r in csv.DictReader(f)} == {"city"}
    fly = SimulatedRADIal(TINY, 2, 1, 4, "all", scenes=scene_mix("city"))
    disk = RADIal(out, "all")
    for i in range(2):
        assert all(torch.equal(x, y) for x, y in zip(disk[i], fly[i]))
    # the simulator rebuilt from the root regenerates its scenes (the mix included), e.g. for the
    # scene truth behind a detector's false alarms
    again = RadialSimulator.from_root(out)
    assert (again.cfg, again.n_sequences, again.frames_per_sequence, again.seed) == (TINY, 2, 1, 4)
    assert again.scenes == scene_mix("city") and again.scenes != DEFAULT_MIX
    table = read_labels(out / "labels.csv")
    assert [again.label_rows(q, 0) for q in range(2)] == [
        [tuple(table.row(k)[c] for c in LABEL_COLUMNS) for k in range(len(table)) if table.row(k)["numSample"] == q]
        for q in range(2)]


def test_from_root_names_what_is_missing(root, tmp_path):
    with pytest.raises(DataFileError, match=r"sensor\.json: sensor description is missing"):
        RadialSimulator.from_root(tmp_path)
    shutil.copy(root / "sensor.json", tmp_path / "sensor.json")
    with pytest.raises(DataFileError, match=r"scene\.json: scene mix is missing"):
        RadialSimulator.from_root(tmp_path)
    (tmp_path / "scene.json").write_text(json.dumps({"mix": {"city": 1.0}, "presets": {"town": {}}}))
    with pytest.raises(DataFileError, match=r"scene\.json: does not describe a scene mix .*differ"):
        RadialSimulator.from_root(tmp_path)
    meta = json.loads((root / "sensor.json").read_text())
    del meta["seed"]
    (tmp_path / "sensor.json").write_text(json.dumps(meta))
    with pytest.raises(DataFileError, match=r"sensor\.json: lacks seed"):
        RadialSimulator.from_root(tmp_path)
