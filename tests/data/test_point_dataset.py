"""PointCloudDataset: a point store joined with its RADIal root, checked against independent reads."""
from __future__ import annotations

import dataclasses
import pickle
import re
import shutil

import numpy as np
import pytest
import torch

from radarpc.data.point_dataset import (PointCloudDataset, PointFrame, PointFrameBatch, check_store_root,
                                        collate_point_frames)
from radarpc.data.pointstore import PointStore
from radarpc.data.radial import RADIal, freespace_to_model, load_freespace, read_labels
from radarpc.data.radial_format import LABEL_TENSOR_COLUMNS, freespace_path
from radarpc.points import PointCloudBatch
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_writer import SimulatedRADIal, write_radial_dataset
from testkit import TINY_CITY_ROOT

try:                                           # the conversion driver is moving out of dsp/
    from radarpc.pipelines.pointclouds import convert_dataset
except ImportError:
    from radarpc.pipelines.pointclouds import convert_dataset

# the session's TINY city root (tests/conftest.py): simulated_split of 3 sequences, q000 train, q001 val,
# q002 test, labelled vehicles in train and test
N_SEQ, PER_SEQ = TINY_CITY_ROOT["n_sequences"], TINY_CITY_ROOT["frames_per_sequence"]


@pytest.fixture
def root(tiny_city_root):
    return tiny_city_root


@pytest.fixture
def store(tiny_city_store):
    # tau 1.5, a low threshold so that frames hold points; sector enrichment exercises a list column
    return PointStore(tiny_city_store)


def assert_cloud_equal(a: PointCloudBatch, b: PointCloudBatch) -> None:
    for f in dataclasses.fields(PointCloudBatch):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert (x is None) == (y is None), f.name
        if x is not None:
            assert x.dtype == y.dtype and torch.equal(x, y), f.name


def test_items_equal_independent_reads(root, store):
    ds = PointCloudDataset(store.path, root)
    reader = RADIal(root, split="all")
    table = read_labels(root / "labels.csv")
    assert len(ds) == len(store) == N_SEQ * PER_SEQ and ds.frame_ids == store.frames
    assert store.metadata.split == "all"
    assert sum(int(n) for n in store.frame_table.n_points) > 0
    for i in range(len(ds)):
        item = ds[i]
        assert isinstance(item, PointFrame)
        assert item.frame == store.frames[i] and item.sequence == store.sequences[i]
        assert_cloud_equal(item.points, store[store.index_of(item.frame)])
        _, labels, fs = reader[reader.index_of(item.frame)]
        assert item.labels.dtype == torch.float32 and item.labels.shape[1] == len(LABEL_TENSOR_COLUMNS)
        assert torch.equal(item.labels, labels)
        assert item.freespace.dtype == torch.bool and torch.equal(item.freespace, fs)
        # and against the files themselves, without the reader
        png = freespace_to_model(load_freespace(freespace_path(root, item.frame)))
        assert np.array_equal(item.freespace.numpy(), png)
        rows = np.nonzero((table.num_sample == item.frame) & table.has_vehicle)[0]
        assert torch.equal(item.labels, torch.from_numpy(table.tensor_rows(rows)))
        assert {table.dataset[k] for k in np.nonzero(table.num_sample == item.frame)[0]} == {item.sequence}
    assert ds.index_of(ds.frame_ids[-1]) == len(ds) - 1 and ds[-1].frame == ds.frame_ids[-1]
    with pytest.raises(IndexError):
        ds[len(ds)]
    with pytest.raises(KeyError, match="frame 999 is not in"):
        ds.index_of(999)


def test_reader_label_and_freespace_methods_match_getitem(root):
    reader = RADIal(root, split="all", difficult=False)
    for i in range(len(reader)):
        _, labels, fs = reader[i]
        assert torch.equal(reader.label_tensor(i), labels) and torch.equal(reader.freespace(i), fs)


def test_easy_mode_follows_the_reader(root, store):
    easy = RADIal(root, split="all", difficult=False)
    ds = PointCloudDataset(store, root, difficult=False)
    assert ds.frame_ids == [f for f in store.frames if f in easy.frame_ids]
    for i in range(len(ds)):
        assert torch.equal(ds[i].labels, easy[easy.index_of(ds.frame_ids[i])][1])


def test_collate_offsets_and_device(root, store):
    ds = PointCloudDataset(store, root)
    idx = [3, 0, 5, 1]
    items = [ds[i] for i in idx]
    batch = collate_point_frames(items)
    assert isinstance(batch, PointFrameBatch) and len(batch) == len(idx)
    # points: the store's own batched read of the same frames
    assert_cloud_equal(batch.points, store.read_frames([store.index_of(ds.frame_ids[i]) for i in idx]))
    n_points = [it.points.num_points for it in items]
    assert batch.points.offset.tolist() == np.cumsum(n_points).tolist()
    n_labels = [it.labels.shape[0] for it in items]
    assert batch.label_offset.tolist() == np.cumsum(n_labels).tolist()
    assert batch.labels.shape == (sum(n_labels), len(LABEL_TENSOR_COLUMNS))
    assert batch.label_batch_index().tolist() == [b for b, n in enumerate(n_labels) for _ in range(n)]
    for b, it in enumerate(items):
        assert torch.equal(batch.frame_labels(b), it.labels)
        assert torch.equal(batch.freespace[b], it.freespace)
        assert_cloud_equal(batch.points.frame(b), it.points)
    assert batch.freespace.shape == (len(idx),) + tuple(items[0].freespace.shape)
    assert batch.frames.tolist() == [ds.frame_ids[i] for i in idx]
    assert batch.sequences == tuple(ds.sequences[i] for i in idx)
    with pytest.raises(ValueError, match="at least one item"):
        collate_point_frames([])
    devices = ["meta"] + (["cuda"] if torch.cuda.is_available() else [])
    for dev in devices:
        moved = batch.to(dev)
        tensors = [moved.labels, moved.label_offset, moved.freespace, moved.frames] + [
            getattr(moved.points, f.name) for f in dataclasses.fields(PointCloudBatch)
            if getattr(moved.points, f.name) is not None]
        assert all(t.device.type == dev for t in tensors) and moved.sequences == batch.sequences


def test_split_filtering(root, store, tmp_path):
    for split in ("train", "val", "test"):
        ds = PointCloudDataset(store, root, split=split)
        assert ds.frame_ids == RADIal(root, split=split).frame_ids and len(ds) == PER_SEQ
    assert PointCloudDataset(store, root, split="all").frame_ids == store.frames
    # a store made from a split holds that split, and no other
    val_path = tmp_path / "val.parquet"
    convert_dataset(root, val_path, tau=1.5, split="val", progress=False)
    val = PointCloudDataset(val_path, root)
    assert val.frame_ids == RADIal(root, split="val").frame_ids
    assert PointCloudDataset(val_path, root, split="val").frame_ids == val.frame_ids
    with pytest.raises(ValueError, match=f"{val_path} holds the 'val' split of .*so no 'train' frame"):
        PointCloudDataset(val_path, root, split="train")
    with pytest.raises(ValueError, match="split must be one of"):
        PointCloudDataset(store, root, split="training")


def test_dataloader_workers_and_pickle(root, store):
    ds = PointCloudDataset(store, root)
    expect = [collate_point_frames([ds[i] for i in range(b, min(b + 4, len(ds)))]) for b in range(0, len(ds), 4)]
    again = pickle.loads(pickle.dumps(ds))
    assert_cloud_equal(again[2].points, ds[2].points)
    for workers in (0, 2):
        loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=workers,
                                             collate_fn=collate_point_frames)
        got = list(loader)
        assert len(got) == len(expect)
        for g, e in zip(got, expect):
            assert_cloud_equal(g.points, e.points)
            assert torch.equal(g.labels, e.labels) and torch.equal(g.label_offset, e.label_offset)
            assert torch.equal(g.freespace, e.freespace) and torch.equal(g.frames, e.frames)
            assert g.sequences == e.sequences


def test_refuses_a_store_of_another_root(root, store, tmp_path):
    # a copy of the root: the store names its own root, which still exists
    other = tmp_path / "copy"
    shutil.copytree(root, other)
    with pytest.raises(ValueError, match=f"point store {store.path} was made from {root.resolve()}, not from {other}"):
        PointCloudDataset(store, other)
    with pytest.raises(ValueError, match="was made from"):
        check_store_root(store, other)
    check_store_root(store, root)
    # a store made from a dataset object records its repr: joined by frame id and sequence
    obj = tmp_path / "obj.parquet"
    convert_dataset(SimulatedRADIal(TINY, **TINY_CITY_ROOT, split="all"), obj, tau=1.5, progress=False)
    ds = PointCloudDataset(obj, root)
    assert ds.frame_ids == store.frames and torch.equal(ds[1].labels, RADIal(root, split="all")[1][1])
    # ... but refused over a root without its frames, or with them in other sequences
    short = write_radial_dataset(tmp_path / "short", TINY, **dict(TINY_CITY_ROOT, frames_per_sequence=1),
                                 progress=False)
    missing = sorted(set(store.frames) - set(RADIal(short, split="all").frame_ids))
    with pytest.raises(ValueError, match=re.escape(f"point store {obj} holds {len(missing)} frame(s) that "
                                                   f"{short / 'labels.csv'} does not list (numSample {missing})")):
        PointCloudDataset(obj, short)
    seed = TINY_CITY_ROOT["seed"]
    seed1 = write_radial_dataset(tmp_path / "seed1", TINY, **dict(TINY_CITY_ROOT, seed=seed + 1), progress=False)
    with pytest.raises(ValueError, match=rf"{obj} puts frame 0 in sequence 'SIM@s{seed}_q000' but "
                                         rf"{seed1 / 'labels.csv'} puts it in 'SIM@s{seed + 1}_q000'.*not made "
                                         rf"from {seed1}"):
        PointCloudDataset(obj, seed1)
