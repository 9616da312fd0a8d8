"""Dataset -> point store conversion (chunks, resume, workers, torchrun sharding) and the
sparse-RD writer, on a tiny hand-written RADIal-layout root."""
from __future__ import annotations

import csv
import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from PIL import Image

from radarpc.data.pointstore import PointStore
from radarpc.data.radial import RADIal
from radarpc.data.radial_format import (LABEL_COLUMNS, fft_path, freespace_path, simulated_sequence_name,
                                        stored_fft_path)
from radarpc.pipelines.pointclouds import ConvertSettings, build_point_cloud, convert_dataset, part_path, parts_dir
from radarpc.pipelines.sparse_rd import write_sparse_rd
from radarpc.dsp.density import tau_for_density
from radarpc.io import DataFileError, load_array, save_npy_atomic
from radarpc.data.radial_format import save_calibration
from radarpc.sensors.radial import TINY, steering_vectors
from radarpc.sim.radial_calibration import make_calibration

N_SEQ, PER_SEQ = 3, 3          # sequences q0 (train), q1 (val), q2 (test); 9 frames
ZERO_FRAME = 4                 # an all-zero cube: no detection at any tau


def make_tiny_root(root, seed=0):
    """RADIal layout for the TINY sensor: noise + two DDMA point targets per frame."""
    cfg = TINY
    rng = np.random.default_rng(seed)
    save_calibration(root / "calibration.npz", make_calibration(cfg))
    meta = dict(cfg.to_dict(), seed=seed, n_sequences=N_SEQ, frames_per_sequence=PER_SEQ, radarpc_version="test")
    (root / "sensor.json").write_text(json.dumps(meta))
    rows = []
    num = 0
    for q in range(N_SEQ):
        seq = simulated_sequence_name(seed, q)
        for k in range(PER_SEQ):
            rd = (rng.normal(size=cfg.rd_shape) + 1j * rng.normal(size=cfg.rd_shape)) / np.sqrt(2)
            for _ in range(2):
                r = int(rng.integers(5, cfg.n_range - 5))
                d0 = int(rng.integers(0, cfg.n_doppler))
                az = float(rng.uniform(-40, 40))
                sv = steering_vectors(cfg, az, 0.0).reshape(cfg.n_tx, cfg.n_rx)        # (n_tx, n_rx)
                for m in range(cfg.n_tx):
                    rd[r, (d0 + int(cfg.doppler_offsets[m])) % cfg.n_doppler, :] += 40.0 * sv[m]
                rng_m = r * cfg.range_res_m
                x, y = rng_m * np.cos(np.deg2rad(az)), rng_m * np.sin(np.deg2rad(az))
                vals = dict(numSample=num, radar_X_m=x, radar_Y_m=y, radar_R_m=rng_m, radar_A_deg=az,
                            radar_D=float(cfg.velocity_of_bin(d0)), radar_P_db=30.0, laser_X_m=x,
                            laser_Y_m=y, laser_Z_m=0.0, dataset=seq, dataset_index=k, Difficult=0)
                rows.append([vals.get(c, -1) for c in LABEL_COLUMNS])
            if num == ZERO_FRAME:
                rd[:] = 0
            fft_path(root, num).parent.mkdir(parents=True, exist_ok=True)
            save_npy_atomic(fft_path(root, num), rd.astype(np.complex64))
            freespace_path(root, num).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.zeros((512, 900), np.uint8)).save(freespace_path(root, num))
            num += 1
    with open(root / "labels.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(LABEL_COLUMNS)
        w.writerows(rows)
    return root


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return make_tiny_root(tmp_path_factory.mktemp("tiny_radial"))


def stored_cube(root, num):
    """The RD cube file of frame ``num`` of ``root`` (``.npy`` or a sparse root's ``.npz``), as stored."""
    return load_array(stored_fft_path(root, num))


def read_all(path):
    """Table and metadata (without the creation date) of a store."""
    store = PointStore(path)
    meta = store.metadata.to_dict()
    meta.pop("created")
    return pq.read_table(path), meta, store.frame_table.to_dict()


def test_fixed_tau_store_equals_direct_dsp(root, tmp_path):
    out = tmp_path / "pc.parquet"
    res = convert_dataset(root, out, tau=4.0, enrich=("rd3", "sector4"), batch_size=4, chunk_frames=4,
                          progress=False)
    assert res.path == out and res.n_frames == 9 and res.chunks_converted == 3
    assert not parts_dir(out).exists()
    store = PointStore(out)
    assert store.frames == list(range(9))
    assert store.metadata.density_mode == "fixed-tau" and store.metadata.tau == 4.0
    assert store.metadata.split == "all" and store.metadata.enrich == ("rd3", "sector4")
    assert store.metadata.sensor == TINY
    # independent: run the DSP on every frame by itself and compare with what the store holds
    ds = RADIal(root, split="all")
    spc = build_point_cloud(ds, ConvertSettings(tau=4.0, enrich=("rd3", "sector4")), 4.0, "cpu")
    densities, peak_densities = [], []
    for i in range(len(ds)):
        with torch.no_grad():
            want = spc(ds[i][0].unsqueeze(0))
        got = store[i]
        assert got.offset.tolist() == want.offset.tolist(), i
        for name in ("range_bin", "doppler_bin", "doppler_full", "is_neighbour"):
            assert torch.equal(getattr(got, name), getattr(want, name).to(getattr(got, name).dtype)), name
        for name in ("range_m", "azimuth_deg", "velocity_mps", "amplitude", "snr", "x", "y", "z", "sector"):
            torch.testing.assert_close(getattr(got, name), getattr(want, name).float(), rtol=1e-5, atol=1e-5)
        densities.append(float(want.density[0]))
        peak_densities.append(int((~want.is_neighbour).sum()) * TINY.n_tx / (TINY.n_range * TINY.n_doppler))
    assert store.frame_table.n_points[ZERO_FRAME] == 0 and store[ZERO_FRAME].x.shape == (0,)
    assert store.metadata.achieved_density == pytest.approx(np.mean(densities), rel=1e-6)
    assert res.achieved_density == pytest.approx(np.mean(densities), rel=1e-6)
    assert res.peak_density == pytest.approx(np.mean(peak_densities), rel=1e-6)
    assert res.peak_density < res.achieved_density        # rd3 adds neighbourhood cells to S*


def test_resume_after_kill_gives_same_file(root, tmp_path):
    ref = tmp_path / "ref.parquet"
    convert_dataset(root, ref, density=0.1, chunk_frames=2, progress=False)
    out = tmp_path / "pc.parquet"
    seen = []

    def kill_after_two(k):
        seen.append(k)
        if len(seen) == 2:
            raise KeyboardInterrupt("simulated kill")

    with pytest.raises(KeyboardInterrupt):
        convert_dataset(root, out, density=0.1, chunk_frames=2, progress=False, on_chunk_done=kill_after_two)
    assert not out.exists()
    assert sorted(p.name for p in parts_dir(out).glob("part-*.parquet")) == ["part-00000.parquet", "part-00001.parquet"]
    res = convert_dataset(root, out, density=0.1, chunk_frames=2, progress=False)
    assert res.chunks_skipped == 2 and res.chunks_converted == 3
    t_ref, m_ref, f_ref = read_all(ref)
    t_out, m_out, f_out = read_all(out)
    assert t_out.equals(t_ref) and m_out == m_ref and f_out == f_ref
    # once finished, the same call returns at once
    again = convert_dataset(root, out, density=0.1, chunk_frames=2, progress=False)
    assert again.chunks_converted == 0 and again.already_finished and again.frames_reused == 9
    # a finished store made with other settings is refused, never silently replaced
    with pytest.raises(FileExistsError, match=r"other settings; pass overwrite=True \(CLI: --overwrite\)"):
        convert_dataset(root, out, density=0.2, chunk_frames=3, progress=False)
    assert PointStore(out).metadata.target_density == 0.1 and not parts_dir(out).exists()
    seen.clear()
    with pytest.raises(KeyboardInterrupt):
        convert_dataset(root, out, density=0.2, chunk_frames=3, progress=False, overwrite=True,
                        on_chunk_done=kill_after_two)
    assert PointStore(out).metadata.target_density == 0.1          # replaced only at the very end
    # parts of an interrupted run with other settings are stale: discarded, not an error
    res = convert_dataset(root, out, density=0.3, chunk_frames=3, progress=False, overwrite=True)
    assert res.chunks_converted == 3 and res.chunks_skipped == 0 and res.frames_reused == 0
    assert PointStore(out).metadata.target_density == 0.3
    assert not parts_dir(out).exists()


def test_per_frame_and_per_dataset_density(root, tmp_path):
    out = tmp_path / "pf.parquet"
    convert_dataset(root, out, density=0.1, density_mode="per-frame", progress=False)
    ft = PointStore(out).frame_table
    live = np.arange(9) != ZERO_FRAME
    np.testing.assert_allclose(ft.density[live], 0.1, rtol=0.1)
    out2 = tmp_path / "pd.parquet"
    convert_dataset(root, out2, density=0.1, density_mode="per-dataset", split="test", progress=False)
    store = PointStore(out2)
    assert store.frames == [6, 7, 8] and store.metadata.density_mode == "per-dataset"
    # independent: tau from the pooled CFAR SNR of the train frames (0, 1, 2)
    train = RADIal(root, split="train")
    spc = build_point_cloud(train, ConvertSettings(tau=1.0), 1.0, "cpu")
    rd = torch.stack([train[i][0] for i in range(len(train))])
    with torch.no_grad():
        snr = spc.detect(rd)[1].snr
    tau = float(tau_for_density(snr, TINY, 0.1, mode="per-dataset"))
    assert store.metadata.tau == pytest.approx(tau)
    np.testing.assert_allclose(store.frame_table.tau, tau, rtol=1e-6)
    # and, counted here: over the 3 train frames that tau passes round(0.1 * 3 Nr ND / n_tx) cells,
    # i.e. their mean density is the target up to one cell
    want = round(0.1 * 3 * TINY.n_range * TINY.n_doppler / TINY.n_tx)
    assert int((snr.numpy() > store.metadata.tau).sum()) == want


def test_density_with_rd_neighbourhood_applies_to_s_star(root, tmp_path):
    # per frame: every live frame's encoded set S*(tau) hits the target; S(tau) alone is smaller
    out = tmp_path / "pf_rd3.parquet"
    res = convert_dataset(root, out, density=0.1, enrich=("rd3",), progress=False)
    store = PointStore(out)
    live = np.arange(9) != ZERO_FRAME
    np.testing.assert_allclose(store.frame_table.density[live], 0.1, rtol=0.1)
    peak = store.frame_table.n_peaks * TINY.n_tx / (TINY.n_range * TINY.n_doppler)
    assert np.all(peak[live] < store.frame_table.density[live])
    assert res.achieved_density == pytest.approx(store.frame_table.density.mean())
    assert res.peak_density == pytest.approx(peak.mean()) and res.peak_density < res.achieved_density
    # per dataset: tau calibrated on the pooled train SNRs for S*(tau), independently recomputed
    out2 = tmp_path / "pd_rd3.parquet"
    convert_dataset(root, out2, density=0.1, density_mode="per-dataset", enrich=("rd3",), progress=False)
    train = RADIal(root, split="train")
    spc = build_point_cloud(train, ConvertSettings(tau=1.0), 1.0, "cpu")
    with torch.no_grad():
        snr = spc.detect(torch.stack([train[i][0] for i in range(len(train))]))[1].snr
    tau_star = float(tau_for_density(snr, TINY, 0.1, mode="per-dataset", neighbourhood=3))
    tau_s = float(tau_for_density(snr, TINY, 0.1, mode="per-dataset"))
    assert PointStore(out2).metadata.tau == pytest.approx(tau_star) and tau_star > tau_s
    # the train frames' mean S* density is on target
    assert PointStore(out2).frame_table.density[:3].mean() == pytest.approx(0.1, rel=0.1)


def test_two_workers_same_content_as_one(root, tmp_path):
    # 64-frame chunks would leave one worker idle on 9 frames: chunks shrink to 5 + 4 frames
    one, two = tmp_path / "one.parquet", tmp_path / "two.parquet"
    convert_dataset(root, one, tau=3.0, chunk_frames=3, progress=False)
    done = []
    res = convert_dataset(root, two, tau=3.0, chunk_frames=64, workers=2, progress=False, on_chunk_done=done.append)
    assert res.chunk_frames == 5 and res.chunks_converted == 2 and sorted(done) == [0, 1]
    t1, m1, f1 = read_all(one)
    t2, m2, f2 = read_all(two)
    assert t1.to_pylist() == t2.to_pylist() and f1 == f2                    # same rows, other row groups
    assert m1["settings"].pop("chunk_frames") == 3 and m2["settings"].pop("chunk_frames") == 5
    assert m1 == m2


def test_torchrun_ranks_shard_chunks_and_rank0_merges(root, tmp_path, monkeypatch):
    ref = tmp_path / "ref.parquet"
    convert_dataset(root, ref, tau=3.0, chunk_frames=2, progress=False)
    out = tmp_path / "dist.parquet"
    # rank 0 writes the manifest first (it would wait for rank 1's parts, so stop it after its chunks)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    monkeypatch.setenv("LOCAL_RANK", "0")
    with pytest.raises(TimeoutError, match=r"waiting for 2 of 5 file\(s\).*part-00001.parquet \(from rank 1, chunk 1\)"):
        convert_dataset(root, out, tau=3.0, chunk_frames=2, progress=False, wait_timeout_s=0.0)
    assert sorted(p.name for p in parts_dir(out).glob("part-*")) == [part_path(out, k).name for k in (0, 2, 4)]
    monkeypatch.setenv("RANK", "1")
    r1 = convert_dataset(root, out, tau=3.0, chunk_frames=2, progress=False)
    assert r1.path is None and r1.chunks_converted == 2 and not out.exists()
    monkeypatch.setenv("RANK", "0")
    r0 = convert_dataset(root, out, tau=3.0, chunk_frames=2, progress=False)
    # rank 0 reports the job's totals (every rank's parts), here all from the earlier calls
    assert r0.path == out and r0.chunks_skipped == 5 and r0.chunks_converted == 0 and r0.frames_reused == 9
    t_ref, m_ref, f_ref = read_all(ref)
    t_out, m_out, f_out = read_all(out)
    assert t_out.equals(t_ref) and m_out == m_ref and f_out == f_ref


def test_sparse_rd_root_reads_back_as_masked_cube(root, tmp_path):
    out_root = tmp_path / "srd"
    res = write_sparse_rd(root, out_root, tau=4.0, progress=False)
    assert res.n_frames == 9 and res.frames_written == 9
    src, dst = RADIal(root, split="all"), RADIal(out_root, split="all")
    assert dst.frame_ids == src.frame_ids and dst.sensor == src.sensor
    assert np.array_equal(dst.calibration.signal, src.calibration.signal)
    spc = build_point_cloud(src, ConvertSettings(tau=4.0), 4.0, "cpu")
    offsets = torch.as_tensor(TINY.doppler_offsets)
    for i in range(len(src)):
        rd, lab, fs = src[i]
        rd2, lab2, fs2 = dst[i]
        assert torch.equal(lab, lab2) and torch.equal(fs, fs2)
        # independent mask: every point's range bin x its n_tx replica Doppler bins
        with torch.no_grad():
            cloud = spc(rd.unsqueeze(0))
        mask = torch.zeros(TINY.n_range, TINY.n_doppler, dtype=torch.bool)
        bins = (cloud.doppler_full[:, None] + offsets[None, :]) % TINY.n_doppler     # (N, n_tx)
        mask[cloud.range_bin[:, None].expand_as(bins), bins] = True
        assert torch.equal(rd2, torch.where(mask[..., None], rd, torch.zeros((), dtype=rd.dtype))), i
        assert float(mask.float().mean()) == pytest.approx(float(cloud.density[0]), rel=1e-6)
    # resume: only the missing cube is recomputed
    assert stored_fft_path(out_root, 3) == fft_path(out_root, 3, ".npz")      # stored compressed
    fft_path(out_root, 3, ".npz").unlink()
    again = write_sparse_rd(root, out_root, tau=4.0, progress=False)
    assert again.frames_written == 1
    assert torch.equal(RADIal(out_root, split="all")[3][0], dst[3][0])
    with pytest.raises(FileExistsError, match=r"other settings .*overwrite=True \(CLI: --overwrite\)"):
        write_sparse_rd(root, out_root, tau=5.0, progress=False)
    with pytest.raises(FileExistsError, match="other settings"):          # --no-resume does not replace it
        write_sparse_rd(root, out_root, tau=5.0, progress=False, resume=False)
    assert json.loads((out_root / "sparse_rd.json").read_text())["tau"] == 4.0
    assert write_sparse_rd(root, out_root, tau=5.0, progress=False, overwrite=True).frames_written == 9
    assert json.loads((out_root / "sparse_rd.json").read_text())["tau"] == 5.0


def test_sparse_rd_root_size_follows_its_density(root, tmp_path):
    # The cubes are stored as zlib-compressed .npz; bound the size from the deflate format, not from
    # what one machine printed. A cube of D = 8 Nr Nd Nrx bytes at mask density d keeps k = d Nr Nd
    # runs of 8 Nrx nonzero (noise: incompressible) bytes, separated by runs of zero bytes. Deflate's
    # fixed code spends <= 9 bits per literal (zlib emits a dynamic code only when smaller; its tree,
    # <= ~300 bytes per 16 K symbols, adds < 2 %): <= 1.25 d D for the kept bytes. A zero run costs
    # one literal plus matches of <= 258 bytes at <= 31 bits each: <= 4 bytes per run (k of them,
    # = d D / (2 Nrx)) plus 31/(8 * 258) < 0.015 of the zero bytes. The zip and .npy headers take
    # < 1 KiB per file. So size <= (1.25 + 1/(2 Nrx)) d D + 0.015 D + 1024, about 0.10 D at d = 0.05.
    out = tmp_path / "srd05"
    write_sparse_rd(root, out, density=0.05, progress=False)
    frames = json.loads((out / "sparse_rd.json").read_text())["frames"]
    dense_total = sparse_total = bound_total = 0.0
    for num in range(N_SEQ * PER_SEQ):
        f = stored_fft_path(out, num)
        assert f == fft_path(out, num, ".npz") and not fft_path(out, num).exists()
        d, size, dense = frames[str(num)]["density"], f.stat().st_size, fft_path(root, num).stat().st_size
        assert d <= 0.05 + 1e-9, num
        bound = (1.25 + 1 / (2 * TINY.n_rx)) * d * dense + 0.015 * dense + 1024
        assert size <= bound, (num, size, bound, dense)
        dense_total, sparse_total, bound_total = dense_total + dense, sparse_total + size, bound_total + bound
    assert sparse_total <= bound_total <= 0.11 * dense_total      # vs 1.0 x when stored dense
    # the unchanged reader and info --check read the compressed root; the fingerprint of a root
    # of .npz cubes sees a cube of another size (it used to look for .npy only)
    from radarpc.data.radial import check_root
    from radarpc.pipelines.sources import source_fingerprint

    rep = check_root(out)
    assert rep.ok and rep.n_frames == 9, rep.format()
    fp = source_fingerprint(RADIal(out, split="all"))
    cube = load_array(fft_path(out, 2, ".npz"))
    np.savez_compressed(fft_path(out, 2, ".npz"), cube.astype(np.complex128))
    assert source_fingerprint(RADIal(out, split="all")) != fp


def test_sparse_rd_rewrite_removes_a_dense_cube_of_an_older_root(root, tmp_path):
    # a root written densely (older radarpc) resumes: its .npy cubes count as done; rewritten, a
    # frame's .npy is removed so that it cannot shadow the new .npz (the reader prefers .npy)
    out = tmp_path / "srd"
    write_sparse_rd(root, out, tau=4.0, progress=False)
    ref = {num: stored_cube(out, num) for num in range(9)}
    fft_path(out, 1, ".npz").unlink()
    save_npy_atomic(fft_path(out, 1), ref[1])                       # as the old writer stored it
    assert write_sparse_rd(root, out, tau=4.0, progress=False).frames_written == 0
    assert stored_fft_path(out, 1) == fft_path(out, 1)
    save_npy_atomic(fft_path(out, 1), ref[1] + 1)                   # stale content of another run
    assert write_sparse_rd(root, out, tau=4.0, progress=False, resume=False).frames_written == 9
    assert not fft_path(out, 1).exists() and stored_fft_path(out, 1) == fft_path(out, 1, ".npz")
    ds = RADIal(out, split="all")
    for num in range(9):
        assert np.array_equal(ds[ds.index_of(num)][0].numpy(), ref[num]), num


def test_sparse_rd_split_keeps_only_its_labels(root, tmp_path):
    out_root = tmp_path / "srd_val"
    write_sparse_rd(root, out_root, density=0.1, split="val", progress=False)
    dst = RADIal(out_root, split="all")
    assert dst.frame_ids == [3, 4, 5] and RADIal(out_root, split="val").frame_ids == [3, 4, 5]


def test_corrupt_cube_names_the_file_and_keeps_finished_parts(root, tmp_path):
    import shutil

    bad_root = tmp_path / "bad_root"
    shutil.copytree(root, bad_root)
    fft_path(bad_root, 5).write_bytes(b"\x93NUMPY truncated")
    out = tmp_path / "pc.parquet"
    with pytest.raises(DataFileError, match="fft_000005.npy"):
        convert_dataset(bad_root, out, tau=3.0, chunk_frames=3, progress=False)
    assert not out.exists() and part_path(out, 0).is_file() and not part_path(out, 1).exists()
    with pytest.raises(DataFileError, match="fft_000005.npy"):  # the same error through spawned workers
        convert_dataset(bad_root, out, tau=3.0, chunk_frames=3, workers=2, progress=False)
    # the first error stops the other worker (whether it finished chunk 2 first is a race); what
    # was finished stays
    assert not out.exists() and part_path(out, 0).is_file() and not part_path(out, 1).exists()


def test_bad_settings(root, tmp_path):
    with pytest.raises(ValueError, match=r"density must be in \(0, 1\] \(fraction of RD cells kept\), got 1.5"):
        convert_dataset(root, tmp_path / "a.parquet", density=1.5, progress=False)
    with pytest.raises(ValueError, match="exactly one of tau"):
        convert_dataset(root, tmp_path / "a.parquet", density=0.1, tau=2.0, progress=False)
    with pytest.raises(ValueError, match="exactly one of tau"):
        ConvertSettings()
    with pytest.raises(ValueError, match="tau must be a finite linear SNR threshold > 0"):
        ConvertSettings(tau=-1.0)
    with pytest.raises(ValueError, match="positive odd"):
        ConvertSettings(tau=2.0, window=(8, 9))
    with pytest.raises(ValueError, match="CFAR is 2-D"):
        ConvertSettings(tau=2.0, window=(9, 9, 9), guard=(3, 3, 3))
    with pytest.raises(ValueError, match="envelope must be one of"):
        ConvertSettings(tau=2.0, envelope="sum")
    with pytest.raises(ValueError, match="wait_timeout_s must be >= 0"):
        convert_dataset(root, tmp_path / "a.parquet", tau=2.0, wait_timeout_s=-1.0, progress=False)
    with pytest.raises(ValueError, match="lacks"):
        convert_dataset(object(), tmp_path / "a.parquet", tau=2.0, progress=False)
    with pytest.raises(ValueError, match="workers must be >= 1"):
        convert_dataset(root, tmp_path / "a.parquet", tau=2.0, workers=0, progress=False)
    with pytest.raises(ValueError, match="must differ from the source root"):
        write_sparse_rd(root, root, tau=2.0, progress=False)


def test_changed_calibration_frames_is_a_new_conversion(root, tmp_path):
    # reviewer's case: per-dataset mode, a second run with other calibration frames must not return
    # the old store; every output-shaping setting is in the metadata and compared
    out = tmp_path / "pd.parquet"
    first = convert_dataset(root, out, density=0.1, density_mode="per-dataset", chunk_frames=4, progress=False)
    assert PointStore(out).metadata.settings["calibration_frames"] is None
    same = convert_dataset(root, out, density=0.1, density_mode="per-dataset", chunk_frames=4, progress=False)
    assert same.chunks_converted == 0 and same.tau == first.tau
    with pytest.raises(FileExistsError, match="other settings"):
        convert_dataset(root, out, density=0.1, density_mode="per-dataset", chunk_frames=4, calibration_frames=2,
                        progress=False)
    two = convert_dataset(root, out, density=0.1, density_mode="per-dataset", chunk_frames=4,
                          calibration_frames=2, progress=False, overwrite=True)
    assert two.chunks_converted == 3 and two.chunks_skipped == 0
    m = PointStore(out).metadata
    assert m.settings["calibration_frames"] == 2 and m.tau == two.tau
    # independent: tau on the pooled SNR of the first 2 train frames only
    train = RADIal(root, split="train")
    spc = build_point_cloud(train, ConvertSettings(tau=1.0), 1.0, "cpu")
    with torch.no_grad():
        snr = spc.detect(torch.stack([train[i][0] for i in range(2)]))[1].snr
    assert two.tau == pytest.approx(float(tau_for_density(snr, TINY, 0.1, mode="per-dataset")))
    assert two.tau != first.tau
    # the envelope is recorded and compared too
    env = convert_dataset(root, out, density=0.1, density_mode="per-dataset", chunk_frames=4,
                          calibration_frames=2, envelope="all-slots", progress=False, overwrite=True)
    assert env.chunks_converted == 3 and PointStore(out).metadata.envelope == "all-slots"


@pytest.mark.parametrize("mode", ["per-frame", "per-dataset"])
def test_sparse_rd_masks_exactly_the_encoded_set_of_the_store(root, tmp_path, mode):
    # --density 0.1 --enrich rd3: the store picks tau on S*(tau); the sparse RD must keep S*(tau),
    # the n_tx replica bins of every point (peaks and neighbours), with the same per-frame taus
    out = tmp_path / "pc.parquet"
    res = convert_dataset(root, out, density=0.1, density_mode=mode, enrich=("rd3",), progress=False)
    srd_root = tmp_path / "srd"
    srd = write_sparse_rd(root, srd_root, density=0.1, density_mode=mode, enrich=("rd3",), progress=False,
                          calibrated_tau=res.tau if mode == "per-dataset" else None)
    store = PointStore(out)
    info = json.loads((srd_root / "sparse_rd.json").read_text())
    src, dst = RADIal(root, split="all"), RADIal(srd_root, split="all")
    offsets = torch.as_tensor(TINY.doppler_offsets)
    for i in range(len(src)):
        cloud = store[i]
        assert bool(cloud.is_neighbour.any()) or i == ZERO_FRAME
        mask = torch.zeros(TINY.n_range, TINY.n_doppler, dtype=torch.bool)
        bins = (cloud.doppler_full[:, None].long() + offsets[None, :]) % TINY.n_doppler
        mask[cloud.range_bin[:, None].long().expand_as(bins), bins] = True
        rd = src[i][0]
        assert torch.equal(dst[i][0], torch.where(mask[..., None], rd, torch.zeros((), dtype=rd.dtype))), i
        num = str(src.frame_ids[i])
        assert info["frames"][num]["tau"] == pytest.approx(float(store.frame_table.tau[i]), rel=1e-6)
        assert info["frames"][num]["density"] == pytest.approx(float(store.frame_table.density[i]), rel=1e-6)
        assert srd.frame_density[src.frame_ids[i]] == pytest.approx(float(mask.double().mean()))
    assert info["tau"] == (None if mode == "per-frame" else pytest.approx(res.tau))
    assert info["settings"]["enrich"] == ["rd3"]
    assert info["mean_density"] == pytest.approx(float(store.frame_table.density.mean()), rel=1e-6)


def test_simulated_dataset_object_converts_like_its_written_root(tiny_root, tmp_path):
    from radarpc.sim.radial_writer import SimulatedRADIal

    from testkit import TINY_ROOT

    sim_root = tiny_root                                   # TINY, 3 sequences x 2 frames, seed 0 (read-only)
    kw = dict(density=0.1, enrich=("rd3", "sector4"), chunk_frames=4, progress=False)
    a, b = tmp_path / "root.parquet", tmp_path / "object.parquet"
    convert_dataset(sim_root, a, **kw)
    convert_dataset(SimulatedRADIal(TINY, **TINY_ROOT, split="all"), b, **kw)
    ta, ma, fa = read_all(a)
    tb, mb, fb = read_all(b)
    assert ta.equals(tb) and fa == fb
    assert ma["source_root"] != mb["source_root"] and "SimulatedRADIal" in mb["source_root"]
    # per-dataset mode: the object is its split, the train split object calibrates tau
    c, d = tmp_path / "root_pd.parquet", tmp_path / "object_pd.parquet"
    rc = convert_dataset(sim_root, c, density=0.1, density_mode="per-dataset", split="test", progress=False)
    with pytest.raises(ValueError, match="calibration_source"):
        convert_dataset(SimulatedRADIal(TINY, **TINY_ROOT, split="test"), d, density=0.1,
                        density_mode="per-dataset", progress=False)
    rd_ = convert_dataset(SimulatedRADIal(TINY, **TINY_ROOT, split="test"), d, density=0.1, density_mode="per-dataset",
                          calibration_source=SimulatedRADIal(TINY, **TINY_ROOT, split="train"), progress=False)
    assert rd_.tau == rc.tau and read_all(c)[0].equals(read_all(d)[0])
    assert PointStore(d).metadata.split == "test"
    with pytest.raises(ValueError, match="does not match the dataset object's split"):
        convert_dataset(SimulatedRADIal(TINY, **TINY_ROOT, split="test"), d, tau=2.0, split="val", progress=False)
    # the sparse-RD writer takes the object too (labels from frame_labels, freespace from freespace_mask)
    s1, s2 = tmp_path / "srd_root", tmp_path / "srd_object"
    write_sparse_rd(sim_root, s1, tau=3.0, progress=False)
    write_sparse_rd(SimulatedRADIal(TINY, **TINY_ROOT, split="all"), s2, tau=3.0, progress=False)
    for num in range(6):
        assert np.array_equal(stored_cube(s1, num), stored_cube(s2, num)), num
    r1, r2 = RADIal(s1, split="all"), RADIal(s2, split="all")
    assert r1.frame_ids == r2.frame_ids and r1.sequences == r2.sequences and r2.sensor == TINY
    np.testing.assert_array_equal(r1.labels.values, r2.labels.values)
    assert np.array_equal(r1.calibration.signal, r2.calibration.signal)
    assert json.loads((s2 / "sparse_rd.json").read_text())["freespace"] is True
    for i in range(6):
        a_, b_ = r1[i], r2[i]
        assert all(torch.equal(x, y) for x, y in zip(a_, b_)), i


def _copy_root(src, dst):
    import shutil
    shutil.copytree(src, dst)
    return dst


def test_changed_source_files_are_noticed_on_resume(root, tmp_path):
    # identical files rewritten (a re-run of the simulator, another node's copy) change nothing;
    # other labels, sensor or calibration, or a cube of another size, make a new conversion
    src = _copy_root(root, tmp_path / "src")
    out = tmp_path / "pc.parquet"
    convert_dataset(src, out, tau=4.0, chunk_frames=3, progress=False)
    labels = (src / "labels.csv").read_bytes()
    (src / "labels.csv").write_bytes(labels)                      # same content, new mtime
    assert convert_dataset(src, out, tau=4.0, chunk_frames=3, progress=False).chunks_converted == 0
    (src / "labels.csv").write_bytes(labels.replace(b"\n", b"\r\n"))   # other bytes: another dataset
    assert convert_dataset(src, out, tau=4.0, chunk_frames=3, progress=False).chunks_converted == 3
    seen = []

    def stop(k):
        seen.append(k)
        raise KeyboardInterrupt("simulated kill")

    with pytest.raises(KeyboardInterrupt):
        convert_dataset(src, out, tau=3.0, chunk_frames=3, progress=False, on_chunk_done=stop, overwrite=True)
    np.save(fft_path(src, 7), np.load(fft_path(src, 7)).astype(np.complex128))   # another size
    # the interrupted run's part was made from the old files: discarded, every chunk converted again
    res = convert_dataset(src, out, tau=3.0, chunk_frames=3, progress=False, overwrite=True)
    assert res.chunks_skipped == 0 and res.chunks_converted == 3
    # per-dataset tau: a changed training cube is noticed when another split is converted
    out_val = tmp_path / "val.parquet"
    first = convert_dataset(src, out_val, density=0.1, density_mode="per-dataset", split="val", progress=False)
    cube = np.load(fft_path(src, 0))
    np.save(fft_path(src, 0), (cube * 3).astype(np.complex128))    # train frame 0: stronger, other size
    again = convert_dataset(src, out_val, density=0.1, density_mode="per-dataset", split="val", progress=False)
    assert again.chunks_converted == 1 and again.tau != first.tau
    # the sparse-RD root records the files too
    sparse = tmp_path / "sparse"
    write_sparse_rd(src, sparse, tau=4.0, progress=False)
    (src / "labels.csv").write_bytes(labels)
    # the same request on changed files: written again (nothing of the old files is kept)
    assert write_sparse_rd(src, sparse, tau=4.0, progress=False).frames_written == 9


def test_sparse_rd_resume_after_kill_keeps_every_frame_record(root, tmp_path, monkeypatch):
    import radarpc.pipelines.sparse_rd as convert

    ref = write_sparse_rd(root, tmp_path / "ref", density=0.1, batch_size=2, progress=False)
    out = tmp_path / "sparse"
    calls = []
    real_save = convert.save_fft_npz

    def dying_save(out_root, num, array):         # killed after the 5th cube, before its record
        if len(calls) == 5:
            raise KeyboardInterrupt("simulated kill")
        calls.append(num)
        real_save(out_root, num, array)

    monkeypatch.setattr(convert, "save_fft_npz", dying_save)
    with pytest.raises(KeyboardInterrupt):
        write_sparse_rd(root, out, density=0.1, batch_size=2, progress=False)
    monkeypatch.setattr(convert, "save_fft_npz", real_save)
    info = json.loads((out / "sparse_rd.json").read_text())
    assert not info["complete"] and sorted(info["frames"]) == ["0", "1", "2", "3"]   # two whole batches
    res = write_sparse_rd(root, out, density=0.1, batch_size=2, progress=False)
    assert res.frames_written == 5                  # frame 4 (cube on disk, no record) is redone
    info = json.loads((out / "sparse_rd.json").read_text())
    want = json.loads((tmp_path / "ref" / "sparse_rd.json").read_text())
    assert info["complete"] and info["frames"] == want["frames"] and info["mean_density"] == want["mean_density"]
    assert res.frame_tau == ref.frame_tau
    for num in range(9):
        assert np.array_equal(stored_cube(out, num), stored_cube(tmp_path / "ref", num)), num


def test_sparse_rd_refuses_a_folder_that_is_not_a_sparse_root(root, tmp_path):
    dense = _copy_root(root, tmp_path / "dense")
    with pytest.raises(FileExistsError, match="is not empty and is not a sparse-RD root"):
        write_sparse_rd(root, dense, tau=4.0, progress=False)
    with pytest.raises(FileExistsError, match="is not empty and is not a sparse-RD root"):
        write_sparse_rd(root, dense, tau=4.0, progress=False, resume=False)
    assert np.array_equal(np.load(fft_path(dense, 0)), np.load(fft_path(root, 0)))   # untouched
    empty = tmp_path / "empty"
    empty.mkdir()
    assert write_sparse_rd(root, empty, tau=4.0, progress=False).frames_written == 9


def test_output_path_problems_are_named_before_any_work(root, tmp_path):
    (tmp_path / "adir").mkdir()
    with pytest.raises(IsADirectoryError, match="is a directory; give the path of a .parquet file"):
        convert_dataset(root, tmp_path / "adir", tau=4.0, progress=False)
    assert not parts_dir(tmp_path / "adir").exists()
    foreign = tmp_path / "foreign.parquet"
    foreign.write_text("not a store")
    with pytest.raises(DataFileError, match=r"in the way of this conversion.*overwrite=True \(CLI: --overwrite\)"):
        convert_dataset(root, foreign, tau=4.0, progress=False)
    with pytest.raises(DataFileError, match="in the way"):                 # --no-resume does not replace it
        convert_dataset(root, foreign, tau=4.0, progress=False, resume=False)
    assert convert_dataset(root, foreign, tau=4.0, progress=False, overwrite=True).n_frames == 9
    with pytest.raises(ValueError, match="is not a torch device"):
        convert_dataset(root, tmp_path / "x.parquet", tau=4.0, progress=False, device="gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            convert_dataset(root, tmp_path / "x.parquet", tau=4.0, progress=False, device="cuda")


def test_orphaned_worker_stops_before_its_next_batch(root, tmp_path):
    # a spawned worker whose parent was killed stops, dropping its unfinished part
    import dataclasses
    import os

    import radarpc.pipelines.pointclouds as convert
    from radarpc.distributed import WorkerJob

    out = tmp_path / "pc.parquet"
    ds = RADIal(root, split="all")
    meta = convert_dataset(root, tmp_path / "ref.parquet", tau=4.0, progress=False)
    m = PointStore(meta.path).metadata.to_dict()
    job = WorkerJob(run=convert._run_chunks, payload=convert._ChunkJob(
        dataset=ds, out=str(out), settings=ConvertSettings(tau=4.0), tau=4.0, meta=m, chunk_frames=9, batch_size=2,
        device="cpu"), items=(0,), parent_pid=os.getppid())
    parts_dir(out).mkdir()
    finished = []
    convert._run_chunks(job, job.items, lambda k, n: finished.append(k))
    assert finished == [0] and part_path(out, 0).is_file()
    part_path(out, 0).unlink()
    with pytest.raises(SystemExit, match="is gone, stopping"):
        convert._run_chunks(dataclasses.replace(job, parent_pid=os.getppid() + 1), job.items, lambda k, n: None)
    assert list(parts_dir(out).iterdir()) == []


def test_two_conversions_to_one_store_never_mix(root, tmp_path):
    # a second process converting to the same --out (here with other settings) while the first
    # runs is refused at once, naming the holder; the first finishes a store of its own settings
    import subprocess
    import sys
    import textwrap
    import time

    from radarpc.runs import OutputBusyError, OutputLock

    out = tmp_path / "pc.parquet"
    ref = tmp_path / "ref.parquet"
    convert_dataset(root, ref, tau=3.0, chunk_frames=2, progress=False)
    code = textwrap.dedent(f"""
        import time
        from radarpc.pipelines.pointclouds import convert_dataset
        convert_dataset({str(root)!r}, {str(out)!r}, tau=3.0, chunk_frames=2, progress=False,
                        on_chunk_done=lambda k: time.sleep(0.5))
    """)
    child = subprocess.Popen([sys.executable, "-c", code])
    try:
        lock = OutputLock(out).path
        t0 = time.monotonic()
        while not lock.exists() and child.poll() is None and time.monotonic() - t0 < 120:
            time.sleep(0.05)
        assert lock.exists(), "the first conversion did not start"
        with pytest.raises(OutputBusyError, match=rf"pid {child.pid}.*point store"):
            convert_dataset(root, out, tau=4.0, chunk_frames=2, progress=False, overwrite=True)
        with pytest.raises(OutputBusyError):                      # the same settings too
            convert_dataset(root, out, tau=3.0, chunk_frames=2, progress=False)
    finally:
        assert child.wait(timeout=300) == 0
    t_ref, m_ref, f_ref = read_all(ref)
    t_out, m_out, f_out = read_all(out)
    assert t_out.equals(t_ref) and m_out == m_ref and f_out == f_ref
    assert not lock.exists() and not parts_dir(out).exists()


def test_a_merge_killed_half_way_leaves_nothing_behind(root, tmp_path):
    out = tmp_path / "pc.parquet"
    orphan = tmp_path / ".pc.parquet.x1y2.tmp"                     # what a kill during the merge leaves
    orphan.write_bytes(b"PAR1 half")
    res = convert_dataset(root, out, tau=3.0, chunk_frames=4, progress=False)
    assert res.n_frames == 9 and not orphan.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pc.parquet"]


def test_sparse_root_left_by_a_kill_can_be_rewritten(root, tmp_path):
    # killed during its first manifest write: only a temp file; an unreadable sparse_rd.json:
    # refused with an option that works, and rewritten with it
    out = tmp_path / "sparse"
    out.mkdir()
    (out / ".sparse_rd.json.ab12cd34.tmp").write_text("{")
    assert write_sparse_rd(root, out, tau=4.0, progress=False).frames_written == 9
    assert not list(out.glob(".*.tmp"))
    (out / "sparse_rd.json").write_text('{"source_root": ')
    for resume in (True, False):
        with pytest.raises(DataFileError, match=r"unreadable; pass overwrite=True \(CLI: --overwrite\)"):
            write_sparse_rd(root, out, tau=4.0, progress=False, resume=resume)
    assert write_sparse_rd(root, out, tau=4.0, progress=False, overwrite=True).frames_written == 9
    assert json.loads((out / "sparse_rd.json").read_text())["complete"]


def test_torchrun_ranks_wait_for_this_jobs_manifest(root, tmp_path, monkeypatch):
    # without a process group, rank 1 polls for the manifest: a stale one of an earlier job (other
    # settings) must not be taken; it waits for rank 0's of this job (TORCHELASTIC_RUN_ID)
    out = tmp_path / "pc.parquet"
    seen = []

    def stop(k):
        seen.append(k)
        raise KeyboardInterrupt("simulated kill")

    with pytest.raises(KeyboardInterrupt):                    # leaves parts and a manifest of tau=3
        convert_dataset(root, out, tau=3.0, chunk_frames=2, progress=False, on_chunk_done=stop)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "job-2")
    monkeypatch.setenv("RANK", "1")
    with pytest.raises(TimeoutError, match="rank 0"):           # rank 0 has not written job-2's yet
        convert_dataset(root, out, tau=4.0, chunk_frames=2, progress=False, wait_timeout_s=0.0)
    monkeypatch.setenv("RANK", "0")
    with pytest.raises(TimeoutError, match="from rank 1"):       # rank 0 cleans up, writes, waits for rank 1
        convert_dataset(root, out, tau=4.0, chunk_frames=2, progress=False, wait_timeout_s=0.0)
    monkeypatch.setenv("RANK", "1")
    r1 = convert_dataset(root, out, tau=4.0, chunk_frames=2, progress=False, wait_timeout_s=0.0)
    assert r1.chunks_converted == 2
    monkeypatch.setenv("RANK", "0")
    r0 = convert_dataset(root, out, tau=4.0, chunk_frames=2, progress=False)
    assert r0.path == out and PointStore(out).metadata.tau == 4.0
    # a finished store: every rank returns at once, none waits for a job that will not run
    monkeypatch.setenv("RANK", "1")
    assert convert_dataset(root, out, tau=4.0, chunk_frames=2, progress=False, wait_timeout_s=0.0).already_finished
