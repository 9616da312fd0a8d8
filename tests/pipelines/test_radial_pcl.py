"""radar_PCL files from a point store: RADIal's (9, N) layout, read the way its loader reads them."""
import numpy as np
import pytest

from radarpc.data.pointstore import PointStore
from radarpc.data.radial_format import RADAR_PCL_ROWS, radar_pcl_path
from radarpc.pipelines.pointclouds import convert_dataset
from radarpc.pipelines.radial_pcl import radar_pcl_rows, write_radial_pcl
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_writer import write_radial_dataset

FIELDS = ("range_m", "azimuth_deg", "elevation_deg", "amplitude", "doppler_full", "x", "y", "z", "velocity_mps")


def test_rows_by_hand():
    cols = {k: np.array([float(i + 1), float(i + 2)]) for i, k in enumerate(FIELDS)}
    cols["amplitude"] = np.array([10.0, 1000.0])
    a = radar_pcl_rows(cols)
    assert a.shape == (9, 2) and a.dtype == np.float32
    want = {"range": [1, 2], "azimuth": [-2, -3], "elevation": [3, 4], "power": [20.0, 60.0],
            "doppler": [5, 6], "x": [6, 7], "y": [-7, -8], "z": [8, 9], "v": [9, 10]}
    for k, name in enumerate(RADAR_PCL_ROWS):
        np.testing.assert_allclose(a[k], want[name], rtol=1e-6)


def test_missing_field_is_named():
    cols = {k: np.zeros(1) for k in FIELDS if k != "doppler_full"}
    with pytest.raises(ValueError, match=r"missing \['doppler_full'\]"):
        radar_pcl_rows(cols)


@pytest.fixture(scope="module")
def root_and_store(tmp_path_factory):
    d = tmp_path_factory.mktemp("pcl")
    root = write_radial_dataset(d / "root", TINY, 2, 2, 5, progress=False, camera=False, laser=False)
    store = d / "pc.parquet"
    convert_dataset(root, store, density=0.1, split="all", progress=False)
    return root, store


def test_written_files_read_like_radials_loader(root_and_store):
    root, store = root_and_store
    run = write_radial_pcl(store, progress=False)                       # root from the store's metadata
    st = PointStore(store)
    assert run.root == root and run.n_frames == len(st) == 4
    total = 0
    for i, num in enumerate(st.frames):
        arr = np.load(radar_pcl_path(root, num), allow_pickle=False)     # plain float32, no pickle
        t = st.frame_rows(i)
        assert arr.shape == (9, t.num_rows) and arr.dtype == np.float32
        total += t.num_rows
        # what RADIal's loader/dataset.py does with the file
        pc = np.rollaxis(arr[[5, 6, 7], :], 1, 0)
        pc[:, 1] *= -1
        xyz = np.stack([t.column(c).to_numpy() for c in ("x", "y", "z")], 1)
        np.testing.assert_array_equal(pc, xyz.astype(np.float32))
        # self-consistent: x, y from range and the (right-positive) azimuth and elevation
        r, az, el = (arr[k].astype(np.float64) for k in range(3))
        ok = r > 1.0
        np.testing.assert_allclose(arr[5][ok], (r * np.cos(np.radians(el)) * np.cos(np.radians(az)))[ok],
                                   atol=1e-3)
        np.testing.assert_allclose(arr[6][ok], (r * np.cos(np.radians(el)) * np.sin(np.radians(az)))[ok],
                                   atol=1e-3)
    assert run.n_points == total > 0


def test_not_a_root(root_and_store, tmp_path):
    _, store = root_and_store
    with pytest.raises(ValueError, match="is not a RADIal root"):
        write_radial_pcl(store, tmp_path, progress=False)


def test_a_store_of_another_root_is_refused(root_and_store, tmp_path, capsys):
    """`export A.parquet --radial-pcl --root B` once wrote A's clouds into B; now it is refused,
    whether B is another dataset or A was moved away (its frames are not B's)."""
    from radarpc.cli import main

    root, store = root_and_store
    other = write_radial_dataset(tmp_path / "other", TINY, 2, 2, 6, progress=False, camera=False, laser=False)
    with pytest.raises(ValueError, match=r"was made from .*, not from .*other \(another dataset, or a copy of it\)"):
        write_radial_pcl(store, other, progress=False)
    assert not (other / "radar_PCL").exists()
    # a store whose recorded root no longer exists (moved): the frames tell the roots apart
    a = write_radial_dataset(tmp_path / "a", TINY, 2, 2, 7, progress=False, camera=False, laser=False)
    convert_dataset(a, tmp_path / "a.parquet", density=0.1, split="all", progress=False)
    a.rename(tmp_path / "a_moved")
    small = write_radial_dataset(tmp_path / "small", TINY, 1, 1, 8, progress=False, camera=False, laser=False)
    code = main(["export", str(tmp_path / "a.parquet"), "--radial-pcl", "--root", str(small)])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "holds frames that" in err and "does not list (3 of 4, e.g. numSample 1): it was made from another root" in err
    assert not list(small.glob("radar_PCL/*.npy"))
    # the moved root itself still takes its own store
    assert write_radial_pcl(tmp_path / "a.parquet", tmp_path / "a_moved", progress=False).n_frames == 4
