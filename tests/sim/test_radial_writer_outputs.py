"""The RADIal release's other modalities in a simulated root: camera images, laser point clouds,
.npz cubes; their completeness checks on resume; the switches."""
import json

import numpy as np
import pytest
from PIL import Image

from radarpc.data.radial import RADIal
from radarpc.data.radial_format import LASER_PCL_COLUMNS, camera_path, fft_path, laser_pcl_path
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_camera import IMAGE_SIZE, render_camera
from radarpc.sim.radial_lidar import laser_scan
from radarpc.sim.scenes import scene_mix
from radarpc.sim.radial_writer import RadialSimulator, SimulatedRADIal, write_radial_dataset

N_SEQ, N_FR, SEED = 3, 2, 5
CITY = scene_mix("city")            # the densest traffic: labelled vehicles in view


@pytest.fixture(scope="module")
def npz_root(tmp_path_factory):
    return write_radial_dataset(tmp_path_factory.mktemp("sim") / "root", TINY, N_SEQ, N_FR, SEED,
                                progress=False, cube_format="npz", scenes=CITY)


def test_every_frame_has_every_file(npz_root):
    sim = RadialSimulator(TINY, N_SEQ, N_FR, SEED, scenes=CITY)
    for num in range(N_SEQ * N_FR):
        assert not fft_path(npz_root, num).exists()
        with np.load(fft_path(npz_root, num, ".npz"), allow_pickle=False) as z:
            assert z.files == ["arr_0"]                                  # RADIal's key
            cube = z["arr_0"]
        assert cube.shape == TINY.rd_shape and cube.dtype == np.complex64
        with Image.open(camera_path(npz_root, num)) as im:
            assert im.format == "JPEG" and im.mode == "RGB" and im.size == IMAGE_SIZE == (960, 540)
            img = np.asarray(im, dtype=np.float64)
        las = np.load(laser_pcl_path(npz_root, num), allow_pickle=False)
        assert las.dtype == np.float32 and las.ndim == 2 and las.shape[1] == len(LASER_PCL_COLUMNS) == 8
        q, i = sim.locate(num)
        fr = sim.scene_frame(q, i)
        np.testing.assert_array_equal(las, laser_scan(fr))
        # the JPEG is the render of the same scene frame (quality 90: a few grey levels on average)
        assert np.abs(img - render_camera(fr, lane_width_m=sim.preset(q).lane_width_m)).mean() < 4.0
    assert json.loads((npz_root / "outputs.json").read_text()) == {"cube_format": "npz", "camera": True,
                                                                   "laser_PCL": True}


def test_npz_cubes_read_back_bit_identical(npz_root):
    disk = RADIal(npz_root, split="all")
    fly = SimulatedRADIal(TINY, N_SEQ, N_FR, SEED, split="all", scenes=CITY)
    for i in range(len(disk)):
        assert disk.frame_ids[i] == fly.frame_ids[i]
        np.testing.assert_array_equal(disk.cube(i).numpy(), fly.cube(i).numpy())


def test_labels_carry_the_camera_boxes(npz_root):
    text = (npz_root / "labels.csv").read_text().splitlines()[1:]
    boxes = np.array([[float(v) for v in line.split(",")[1:5]] for line in text])
    seen = boxes[:, 0] >= 0
    assert seen.any()
    b = boxes[seen]
    assert ((b[:, 0] <= b[:, 2]) & (b[:, 1] <= b[:, 3])).all()
    assert (b[:, [0, 2]] <= 1919).all() and (b[:, [1, 3]] <= 1079).all()
    assert (boxes[~seen] == -1).all()


def test_resume_redraws_only_a_damaged_image(npz_root, tmp_path):
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(npz_root, root)
    cube_before = fft_path(root, 3, ".npz").stat().st_mtime_ns
    good = camera_path(root, 3).read_bytes()
    camera_path(root, 3).write_bytes(good[: len(good) // 2])             # truncated JPEG
    laser_pcl_path(root, 4).unlink()
    counts = {}
    write_radial_dataset(root, TINY, N_SEQ, N_FR, SEED, progress=False, cube_format="npz", scenes=CITY,
                         on_finish=lambda w, k: counts.update(w=w, k=k))
    assert camera_path(root, 3).read_bytes() == good
    assert laser_pcl_path(root, 4).is_file()
    assert fft_path(root, 3, ".npz").stat().st_mtime_ns == cube_before   # the cube was kept
    assert counts == {"w": 2, "k": N_SEQ * N_FR - 2}


def test_switches_and_bad_format(tmp_path):
    root = write_radial_dataset(tmp_path / "bare", TINY, 1, 2, SEED, progress=False, camera=False, laser=False)
    assert not (root / "camera").exists() and not (root / "laser_PCL").exists()
    assert fft_path(root, 0).is_file()
    text = (root / "labels.csv").read_text()                              # boxes are geometry: still filled
    assert text == write_radial_dataset(tmp_path / "full", TINY, 1, 2, SEED, progress=False).joinpath(
        "labels.csv").read_text()
    with pytest.raises(ValueError, match=r"cube_format must be one of \('npy', 'npz'\), got 'npy.gz'"):
        write_radial_dataset(tmp_path / "x", TINY, 1, 1, SEED, progress=False, cube_format="npy.gz")
