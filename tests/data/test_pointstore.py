"""Parquet point store: round trip of every column and the metadata, empty frames, row groups,
bad files."""
from __future__ import annotations

import copy
import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from radarpc.data.pointstore import (
    FLOAT_COLUMNS,
    INT_COLUMNS,
    METADATA_KEY,
    REQUIRED_COLUMNS,
    PointStore,
    PointStoreMetadata,
    PointStoreWriter,
    collate_clouds,
)
from radarpc.points import PointCloudBatch
from radarpc.io import DataFileError
from radarpc.sensors.radial import TINY
from testkit import same_cloud

POINT_TENSORS = FLOAT_COLUMNS + INT_COLUMNS + ("is_neighbour",)


def make_batch(counts, *, seed=0, sector=4, rd_patch=9) -> PointCloudBatch:
    """A hand-built batch of ``len(counts)`` frames with random values in every field."""
    g = torch.Generator().manual_seed(seed)
    n = int(sum(counts))
    f = {name: torch.randn(n, generator=g) * 10 for name in FLOAT_COLUMNS}
    f["range_bin"] = torch.randint(0, TINY.n_range, (n,), generator=g)
    f["doppler_bin"] = torch.randint(0, TINY.slot_width, (n,), generator=g)
    f["doppler_full"] = torch.randint(0, TINY.n_doppler, (n,), generator=g)
    f["is_neighbour"] = torch.rand(n, generator=g) > 0.5
    f["sector"] = torch.rand(n, sector, generator=g) if sector else None
    f["rd_patch"] = torch.rand(n, rd_patch, generator=g) if rd_patch else None
    b = len(counts)
    return PointCloudBatch(offset=torch.tensor(np.cumsum(counts), dtype=torch.int64),
                           tau=torch.rand(b, generator=g) + 1, density=torch.rand(b, generator=g) * 0.1, **f)


def make_meta(**kw) -> PointStoreMetadata:
    d = dict(sensor=TINY, density_mode="per-frame", tau=None, target_density=0.05, achieved_density=0.0,
             peak_density=0.0,
             enrich=("rd3", "sector4"), window=(9, 9), guard=(3, 3), source_root="/data/root", split="all")
    d.update(kw)
    return PointStoreMetadata(**d)


def frame_slice(batch: PointCloudBatch, b: int, name: str) -> torch.Tensor:
    off = [0] + batch.offset.tolist()
    return getattr(batch, name)[off[b]:off[b + 1]]


def test_round_trip_every_column_dtype_and_metadata(tmp_path):
    counts = [3, 0, 5, 1]
    batch = make_batch(counts)
    path = tmp_path / "pc.parquet"
    with PointStoreWriter(path, make_meta(), row_group_frames=2) as w:
        w.write(batch, frames=[10, 11, 12, 13], sequences=["A", "A", "B", "B"])
    store = PointStore(path)
    assert len(store) == 4 and store.frames == [10, 11, 12, 13]
    assert store.sequences == ["A", "A", "B", "B"]
    assert store.num_row_groups == 2                      # whole frames per row group: 2 + 2
    m = store.metadata
    assert m.sensor == TINY and m.enrich == ("rd3", "sector4") and m.window == (9, 9) and m.guard == (3, 3)
    assert m.density_mode == "per-frame" and m.target_density == 0.05 and m.source_root == "/data/root"
    assert m.achieved_density == pytest.approx(float(batch.density.double().mean()))
    assert m.created and m.radarpc_version
    np.testing.assert_allclose(store.frame_table.tau, batch.tau.double().numpy())
    np.testing.assert_array_equal(store.frame_table.n_points, counts)
    peaks = [int((~frame_slice(batch, b, "is_neighbour")).sum()) for b in range(4)]
    np.testing.assert_array_equal(store.frame_table.n_peaks, peaks)
    assert m.peak_density == pytest.approx(np.mean(peaks) * TINY.n_tx / (TINY.n_range * TINY.n_doppler))
    for i in range(4):
        c = store[i]
        assert c.offset.tolist() == [counts[i]]
        for name in POINT_TENSORS + ("sector", "rd_patch"):
            want = frame_slice(batch, i, name)
            got = getattr(c, name)
            assert got.dtype == want.dtype, name
            assert torch.equal(got, want), name
        assert float(c.tau[0]) == pytest.approx(float(batch.tau[i]))
        # the CFAR-peak density |S(tau)| = n_tx |P(tau)| comes back from the frame's peak count
        assert float(c.peak_density[0]) == pytest.approx(peaks[i] * TINY.n_tx / (TINY.n_range * TINY.n_doppler))
        assert float(c.density[0]) == pytest.approx(float(batch.density[i]))
    # on-disk Arrow types
    schema = pq.read_schema(path)
    assert schema.names[: len(REQUIRED_COLUMNS)] == list(REQUIRED_COLUMNS)
    assert schema.field("frame").type == pa.int64()
    assert pa.types.is_dictionary(schema.field("sequence").type)
    assert schema.field("x").type == pa.float32() and schema.field("doppler_bin").type == pa.int32()
    assert schema.field("sector").type == pa.list_(pa.float32(), 4)
    assert schema.field("rd_patch").type == pa.list_(pa.float32(), 9)
    # independent read with plain pyarrow: row count, frame column, x values
    t = pq.read_table(path)
    assert t.num_rows == sum(counts)
    assert t.column("frame").to_pylist() == [10] * 3 + [12] * 5 + [13]
    np.testing.assert_array_equal(t.column("x").to_numpy(), batch.x.numpy())


def test_batched_read_and_iteration(tmp_path):
    counts = [2, 4, 0, 3]
    batch = make_batch(counts, seed=3, sector=0, rd_patch=0)
    path = tmp_path / "pc.parquet"
    with PointStoreWriter(path, make_meta(enrich=()), row_group_frames=1) as w:
        w.write(batch, frames=[5, 6, 7, 8], sequences=["s"] * 4)
    store = PointStore(path)
    assert "sector" not in store.schema.names and store[0].sector is None
    both = store.read_frames([3, 1])
    assert both.offset.tolist() == [3, 7]
    assert torch.equal(both.range_m, torch.cat([frame_slice(batch, 3, "range_m"), frame_slice(batch, 1, "range_m")]))
    assert [int(c.offset[0]) for c in store] == counts
    # DataLoader over the store with collate_clouds == read_frames
    loader = torch.utils.data.DataLoader(store, batch_size=3, collate_fn=collate_clouds)
    first = next(iter(loader))
    ref = store.read_frames([0, 1, 2])
    assert first.offset.tolist() == [2, 6, 6]
    assert torch.equal(first.x, ref.x) and torch.equal(first.density, ref.density)
    assert torch.equal(first.peak_density, ref.peak_density) and first.peak_density.shape == (3,)
    # a cloud without peak_density (built by hand) collates to None rather than a partial vector
    mixed = collate_clouds([store[0], make_batch([1], sector=0, rd_patch=0)])
    assert mixed.peak_density is None and mixed.density.shape == (2,)
    with pytest.raises(ValueError, match="with and without 'sector'"):
        collate_clouds([store[0], make_batch([1])])
    assert store.index_of(7) == 2
    with pytest.raises(KeyError, match="frame 99"):
        store.index_of(99)


def test_empty_frames_and_empty_store(tmp_path):
    path = tmp_path / "empty.parquet"
    with PointStoreWriter(path, make_meta()) as w:
        w.write(make_batch([0, 0]), frames=[1, 2], sequences=["A", "A"])
    store = PointStore(path)
    assert len(store) == 2 and store.num_row_groups == 0
    c = store[1]
    assert c.offset.tolist() == [0] and c.x.shape == (0,) and c.sector.shape == (0, 4)
    path2 = tmp_path / "none.parquet"
    PointStoreWriter(path2, make_meta()).close()
    assert len(PointStore(path2)) == 0


def _no_file_reads(rg):
    raise AssertionError(f"row group {rg} read from the file")


def test_preloaded_items_are_the_items_of_the_file(tmp_path):
    counts = [3, 0, 5, 1, 4, 2, 6]
    path = tmp_path / "pc.parquet"
    with PointStoreWriter(path, make_meta(), row_group_frames=3) as w:
        w.write(make_batch(counts, seed=7), frames=list(range(20, 27)), sequences=["A"] * 4 + ["B"] * 3)
    plain, held = PointStore(path), PointStore(path)
    # the estimate shares each row group's uncompressed footer size out by rows
    md = pq.ParquetFile(path).metadata
    sizes = [md.row_group(g).total_byte_size for g in range(md.num_row_groups)]
    assert held.num_row_groups == 3 and held.decoded_bytes() == pytest.approx(sum(sizes), abs=3)
    assert held.decoded_bytes([0]) == pytest.approx(sizes[0] * 3 / 8, abs=1) and held.decoded_bytes([1]) == 0
    assert held.preload([4, 0, 1, -1]) > 0                 # items 0 (row group 0), 4 and 6 (1, 2); 1 is empty
    assert all(same_cloud(held[i], plain[i]) for i in range(7))
    assert same_cloud(held.read_frames([6, 2, 0]), plain.read_frames([6, 2, 0]))
    # preloaded items come from memory, the others from the file
    held.read_row_group = _no_file_reads
    assert same_cloud(held.read_frames([0, 4, 1, 6]), plain.read_frames([0, 4, 1, 6]))
    with pytest.raises(AssertionError, match="row group 1 read from the file"):
        held[3]
    # workers started by fork share the preloaded rows
    loader = torch.utils.data.DataLoader(held, batch_size=2, sampler=[6, 0, 4, 1], collate_fn=collate_clouds,
                                         num_workers=2, multiprocessing_context="fork")
    got = list(loader)
    assert same_cloud(got[0], plain.read_frames([6, 0])) and same_cloud(got[1], plain.read_frames([4, 1]))
    # a copy through __getstate__ (what pickling sends a spawned worker) reads from the file again
    del held.read_row_group
    clone = copy.deepcopy(held)
    assert clone._memory is None and all(same_cloud(clone[i], plain[i]) for i in range(7))
    # another call replaces what was held; bad items name the file
    assert held.preload([]) == 0
    held.read_row_group = _no_file_reads
    with pytest.raises(AssertionError, match="row group 0"):
        held[0]
    with pytest.raises(IndexError, match=rf"{path.name}: item indices must be in \[-7, 7\), got 2..9"):
        held.preload([2, 9])


def test_atomic_write_and_abort(tmp_path):
    path = tmp_path / "pc.parquet"
    with pytest.raises(RuntimeError, match="boom"):
        with PointStoreWriter(path, make_meta()) as w:
            w.write(make_batch([2]), frames=[0], sequences=["A"])
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []                  # neither the file nor a temp file is left


def test_writer_rejects_bad_input(tmp_path):
    w = PointStoreWriter(tmp_path / "a.parquet", make_meta())
    with pytest.raises(ValueError, match="2 frames in the batch but 1 frame ids"):
        w.write(make_batch([1, 1]), frames=[0], sequences=["A"])
    bad = make_batch([2])
    bad.x[0] = float("nan")
    with pytest.raises(ValueError, match="'x' holds NaN"):
        w.write(bad, frames=[0], sequences=["A"])
    back = make_batch([2, 1])
    back.offset = torch.tensor([3, 2])
    with pytest.raises(ValueError, match="non-decreasing"):
        w.write(back, frames=[5, 6], sequences=["A", "A"])
    w.write(make_batch([1]), frames=[0], sequences=["A"])
    with pytest.raises(ValueError, match="frames written twice"):
        w.write(make_batch([1]), frames=[0], sequences=["A"])
    with pytest.raises(ValueError, match=r"sector must be \(2, 4\)"):
        w.write(make_batch([2], sector=5), frames=[1], sequences=["A"])
    w.abort()
    with pytest.raises(ValueError, match="target_density must be in"):
        make_meta(target_density=1.5)
    with pytest.raises(ValueError, match="density_mode"):
        make_meta(density_mode="sometimes")


def test_bad_files_name_the_file(tmp_path):
    txt = tmp_path / "not.parquet"
    txt.write_bytes(b"this is not parquet at all")
    with pytest.raises(DataFileError, match="not.parquet: is not a readable Parquet file"):
        PointStore(txt)
    with pytest.raises(DataFileError, match="missing"):
        PointStore(tmp_path / "absent.parquet")
    plain = tmp_path / "plain.parquet"
    pq.write_table(pa.table({"a": [1, 2]}), plain)
    with pytest.raises(DataFileError, match="not a radarpc point store"):
        PointStore(plain)
    # a store whose 'snr' column was dropped (metadata kept)
    good = tmp_path / "good.parquet"
    with PointStoreWriter(good, make_meta()) as w:
        w.write(make_batch([2, 1]), frames=[0, 1], sequences=["A", "A"])
    t = pq.read_table(good)
    kv = pq.ParquetFile(good).metadata.metadata
    cut = tmp_path / "cut.parquet"
    t2 = t.drop_columns(["snr"])
    pq.write_table(t2.replace_schema_metadata({METADATA_KEY: kv[METADATA_KEY]}), cut)
    with pytest.raises(DataFileError, match=r"cut.parquet: lacks point store columns \['snr'\]"):
        PointStore(cut)
    # wrong type
    wrong = tmp_path / "wrong.parquet"
    t3 = t.set_column(t.schema.get_field_index("x"), "x", t.column("x").cast(pa.float64()))
    pq.write_table(t3.replace_schema_metadata({METADATA_KEY: kv[METADATA_KEY]}), wrong)
    with pytest.raises(DataFileError, match="column 'x' has type double, expected float"):
        PointStore(wrong)
    # frame table disagreeing with the rows
    doc = json.loads(kv[METADATA_KEY])
    doc["frames"]["n_points"][0] += 1
    lie = tmp_path / "lie.parquet"
    pq.write_table(t.replace_schema_metadata({METADATA_KEY: json.dumps(doc).encode()}), lie)
    with pytest.raises(DataFileError, match="holds 3 rows but its frame table counts 4"):
        PointStore(lie)
    # frame table naming other frames than the rows hold (row-group statistics disagree)
    doc = json.loads(kv[METADATA_KEY])
    doc["frames"]["frame"] = [100, 101]
    moved = tmp_path / "moved.parquet"
    pq.write_table(t.replace_schema_metadata({METADATA_KEY: json.dumps(doc).encode()}), moved)
    with pytest.raises(DataFileError, match="row group 0 holds frames 0..1 but the frame table puts frames 100..101"):
        PointStore(moved)
    # truncated file
    trunc = tmp_path / "trunc.parquet"
    trunc.write_bytes(good.read_bytes()[:-40])
    with pytest.raises(DataFileError, match="trunc.parquet"):
        PointStore(trunc)


def test_metadata_records_envelope_and_settings(tmp_path):
    settings = {"tau": None, "density": 0.05, "calibration_frames": 2, "envelope": "all-slots", "window": [19, 19]}
    meta = make_meta(envelope="all-slots", settings=settings)
    path = tmp_path / "s.parquet"
    with PointStoreWriter(path, meta) as w:
        w.write(make_batch([2, 1]), [0, 1], ["s", "s"])
    back = PointStore(path).metadata
    assert back.envelope == "all-slots" and back.settings == settings
    d = make_meta().to_dict()
    assert d["envelope"] == "replicas" and d["settings"] == {}
    # a store written before the envelope option summed every slot (RADIal rpl.py)
    del d["envelope"], d["settings"]
    assert PointStoreMetadata.from_dict(d).envelope == "all-slots"
    with pytest.raises(ValueError, match="envelope must be one of"):
        make_meta(envelope="sum")
    with pytest.raises(ValueError, match="settings must be a dict"):
        make_meta(settings=[1])
