"""Paths and array layouts of the RADIal ready-to-use release's files (camera, laser_PCL,
radar_PCL, .npz cubes)."""
import zipfile
from pathlib import Path

import numpy as np
import pytest

from radarpc.data.radial import load_rd
from radarpc.data.radial_format import (
    LASER_PCL_COLUMNS,
    RADAR_PCL_ROWS,
    camera_path,
    fft_path,
    laser_pcl_path,
    radar_pcl_path,
    save_fft_npz,
    stored_fft_path,
)
from radarpc.io import DataFileError
from radarpc.sensors.radial import TINY


def test_paths_follow_the_release(tmp_path):
    assert camera_path(tmp_path, 42) == tmp_path / "camera" / "image_000042.jpg"
    assert laser_pcl_path(tmp_path, 42) == tmp_path / "laser_PCL" / "pcl_000042.npy"
    assert radar_pcl_path(tmp_path, 42) == tmp_path / "radar_PCL" / "pcl_000042.npy"
    # the columns RADIal's loader/dataset.py lists, in its order
    assert LASER_PCL_COLUMNS[:3] == ("x", "y", "z") and len(LASER_PCL_COLUMNS) == 8
    assert RADAR_PCL_ROWS == ("range", "azimuth", "elevation", "power", "doppler", "x", "y", "z", "v")


@pytest.mark.parametrize("compress", [True, False])
def test_npz_round_trip(tmp_path, compress):
    rng = np.random.default_rng(0)
    cube = (rng.standard_normal(TINY.rd_shape) + 1j * rng.standard_normal(TINY.rd_shape)).astype(np.complex64)
    fft_path(tmp_path, 3).parent.mkdir(parents=True)
    np.save(fft_path(tmp_path, 3), cube)
    p = save_fft_npz(tmp_path, 3, cube, compress=compress)
    assert p == fft_path(tmp_path, 3, ".npz") and stored_fft_path(tmp_path, 3) == p
    assert not fft_path(tmp_path, 3).exists()                       # the .npy a reader would prefer is gone
    with zipfile.ZipFile(p) as z:
        kinds = {i.compress_type for i in z.infolist()}
    assert kinds == ({zipfile.ZIP_DEFLATED} if compress else {zipfile.ZIP_STORED})
    with np.load(p, allow_pickle=False) as z:
        assert z.files == ["arr_0"]
        np.testing.assert_array_equal(z["arr_0"], cube)
    np.testing.assert_array_equal(load_rd(p, TINY), cube)


def test_npz_of_the_wrong_shape_is_refused(tmp_path):
    p = save_fft_npz(tmp_path, 0, np.zeros((3, 4, 5), np.complex64), compress=False)
    with pytest.raises(DataFileError, match=str(Path(p).name)):
        load_rd(p, TINY)
