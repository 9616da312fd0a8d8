"""Tests for radarpc.data.coloradar_format: ColoRadar's calib/ files, parsed and written."""
from __future__ import annotations

import numpy as np
import pytest

from radarpc.data.coloradar_format import (
    load_calib,
    parse_antenna_cfg,
    parse_coupling_calib,
    parse_heatmap_cfg,
    parse_waveform_cfg,
    read_transform,
    write_calib,
    write_coupling_calib,
)
from radarpc.io import DataFileError
from radarpc.sensors.coloradar import AWR1843, CASCADE, DEFAULT_CALIB, SPEED_OF_LIGHT, quaternion_to_matrix


def test_calib_round_trip(tmp_path):
    write_calib(tmp_path / "calib", DEFAULT_CALIB)
    got = load_calib(tmp_path / "calib")
    assert got == DEFAULT_CALIB and got.base_to_imu == DEFAULT_CALIB.base_to_imu is not None
    c = parse_coupling_calib(tmp_path / "calib" / "single_chip" / "coupling_calib.txt", AWR1843)
    assert c.shape == (3, 4, 64) and np.iscomplexobj(c) and not c.any()


def test_transform_files_hold_the_datasets_transforms(tmp_path):
    write_calib(tmp_path / "calib", DEFAULT_CALIB)
    tdir = tmp_path / "calib" / "transforms"
    assert sorted(p.name for p in tdir.iterdir()) == [
        "base_to_cascade.txt", "base_to_imu.txt", "base_to_lidar.txt", "base_to_single_chip.txt"]
    # the dataset's text (Python's str of each float, translation line then qx qy qz qw)
    assert (tdir / "base_to_imu.txt").read_text() == (
        "0.0 0.0 0.0\n0.707105451466 0.707108048814 0.000209535067884 0.00020953429822\n")
    assert (tdir / "base_to_cascade.txt").read_text() == "0.03 0.12 -0.09\n0.0 0.0 0.706825181105 0.707388269167\n"
    assert (tdir / "base_to_single_chip.txt").read_text() == (
        "-0.145 0.09 -0.025\n0.0 0.0 0.706825181105 0.707388269167\n")
    assert (tdir / "base_to_lidar.txt").read_text() == (
        "-0.075 -0.02 0.03618\n0.0 0.0 0.721382357437 -0.692536998563\n")
    # the IMU is mounted upside down with x and y swapped: a half turn about (1, 1, 0) / sqrt(2),
    # R = 2 n n^T - I; the file's quaternion is that to 3e-4 (its small components are 2.1e-4)
    n = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    np.testing.assert_allclose(quaternion_to_matrix(read_transform(tdir / "base_to_imu.txt").quaternion),
                               2 * np.outer(n, n) - np.eye(3), atol=1e-3)
    # roots written before base_to_imu.txt was simulated still load
    (tdir / "base_to_imu.txt").unlink()
    assert load_calib(tmp_path / "calib").base_to_imu is None


def _data_values(path) -> int:
    line = [ln for ln in path.read_text().splitlines() if ln.startswith("data:")]
    return len(line[0][len("data:"):].split(","))


def test_coupling_file_size_follows_the_tools_rule(tmp_path):
    write_calib(tmp_path / "calib", DEFAULT_CALIB)
    for sub, chip in (("single_chip", AWR1843), ("cascade", CASCADE)):
        path = tmp_path / "calib" / sub / "coupling_calib.txt"
        head = dict(ln.split(":", 1) for ln in path.read_text().splitlines() if not ln.startswith("data:"))
        w = chip.waveform
        n = _data_values(path)
        # azinke/coloradar reshapes the values to (num_tx, num_rx, 1, num_adc_samples_per_chirp);
        # arpg/coloradar-library wants num_tx * num_rx * heatmap num_range_bins (re, im) pairs
        assert n == w.num_tx * w.num_rx * w.num_adc_samples_per_chirp
        assert n == 2 * w.num_tx * w.num_rx * chip.heatmap.num_range_bins
        assert int(head["num_range_bins"]) == chip.heatmap.num_range_bins == w.num_adc_samples_per_chirp // 2
        assert int(head["num_tx"]) == w.num_tx and int(head["num_rx"]) == w.num_rx
        assert int(head["num_doppler_bins"]) == w.num_chirps_per_frame
    assert _data_values(tmp_path / "calib" / "single_chip" / "coupling_calib.txt") == 1536


def test_single_chip_heatmap_cfg_is_the_datasets_grid(tmp_path):
    write_calib(tmp_path / "calib", DEFAULT_CALIB)
    path = tmp_path / "calib" / "single_chip" / "heatmap_cfg.txt"
    kv = {ln.split()[0]: ln.split()[1:] for ln in path.read_text().splitlines()}
    assert (kv["num_range_bins"], kv["num_azimuth_bins"], kv["num_elevation_bins"]) == (["64"], ["64"], ["8"])
    # 64 positive bins of a 128-point range FFT: c f_s / (2 S 128) from the waveform's numbers (the
    # file keeps the 12 digits RaLD quotes, 3e-8 off the formula with the rounded waveform values)
    assert float(kv["range_bin_width"][0]) == pytest.approx(SPEED_OF_LIGHT * 10_666_000 / (2 * 1.00000000377e14 * 128),
                                                            rel=1e-6)
    # half-bin-centred beams: sin(angle_k) * n * d = k - n / 2 + 1 / 2, d = 0.5 f_c / F_design
    w = AWR1843.waveform
    f_c = w.start_frequency + w.frequency_slope * (w.adc_start_time + 128 / (2 * w.adc_sample_frequency))
    d = 0.5 * f_c / 76.8e9
    for key, n in (("azimuth_bins", 64), ("elevation_bins", 8)):
        ang = np.array([float(v) for v in kv[key]])
        np.testing.assert_allclose(np.sin(ang) * n * d, np.arange(n) - n / 2 + 0.5, atol=1e-12 * n)
        line = [ln for ln in path.read_text().splitlines() if ln.startswith(key + " ")]
        assert len(line) == 1 and line[0].endswith(" ")                   # the dataset's trailing space
    # RaLD's processing grid (128 range x 8 azimuth x 2 elevation) is not the file's
    assert parse_heatmap_cfg(path).shape == (8, 64, 64, 2)


def test_coupling_errors_name_the_file_and_the_size(tmp_path):
    path = tmp_path / "coupling_calib.txt"
    write_coupling_calib(path, np.zeros((3, 4, 128), np.complex128), 128)     # the old, RaLD-grid size
    assert parse_coupling_calib(path).shape == (3, 4, 128)
    with pytest.raises(DataFileError, match=r"coupling_calib.txt.*3 x 4 x 128 complex values.*single_chip "
                                            r"config implies 3 x 4 x 64"):
        parse_coupling_calib(path, AWR1843)
    path.write_text(path.read_text().replace("num_range_bins:128", "num_range_bins:64"))
    with pytest.raises(DataFileError, match=r"coupling_calib.txt.*data holds 3072 values, expected 2 \* 3 \* 4 \* 64 = 1536"):
        parse_coupling_calib(path)
    path.write_text("num_tx:3\nnum_rx:4\n")
    with pytest.raises(DataFileError, match="coupling_calib.txt.*expected num_tx, num_rx, num_range_bins and data"):
        parse_coupling_calib(path)
    with pytest.raises(ValueError, match=r"coupling must be complex \(num_tx, num_rx, num_range_bins\), got float64 \(3, 4\)"):
        write_coupling_calib(path, np.zeros((3, 4)), 128)


def test_dataset_style_files_parse(tmp_path):
    # hand-written in the dataset's style: comments, trailing space on bin lines, F_design in GHz
    (tmp_path / "heatmap_cfg.txt").write_text(
        "# heatmap\nnum_range_bins 4\nnum_elevation_bins 2\nnum_azimuth_bins 3\nrange_bin_width 0.0592943951488\n"
        "azimuth_bins -0.5 0.0 0.5 \nelevation_bins -0.1 0.1 \n")
    hm = parse_heatmap_cfg(tmp_path / "heatmap_cfg.txt")
    assert hm.azimuth_bins == (-0.5, 0.0, 0.5) and hm.elevation_bins == (-0.1, 0.1)
    assert hm.shape == (2, 3, 4, 2) and hm.range_bin_width == 0.0592943951488
    (tmp_path / "antenna_cfg.txt").write_text(
        "num_rx 4\nnum_tx 3\nF_design 77\nrx 0 0 0\nrx 1 1 0\nrx 2 2 0\nrx 3 3 0\ntx 0 0 0\ntx 2 2 1\ntx 1 4 0\n")
    ant = parse_antenna_cfg(tmp_path / "antenna_cfg.txt")
    assert ant.tx_positions == ((0, 0), (4, 0), (2, 1)) and ant.design_frequency_ghz == 77
    assert ant.virtual_positions.shape == (12, 2)
    np.testing.assert_array_equal(ant.virtual_positions[8], [2, 1])   # tx 2 + rx 0
    (tmp_path / "waveform_cfg.txt").write_text(
        "num_rx 4\nnum_tx 3\nnum_adc_samples_per_chirp 128\nnum_chirps_per_frame 128\n"
        "adc_sample_frequency 10666000\nstart_frequency 77000000000\nidle_time 1.1e-4\n"
        "adc_start_time 7e-6\nramp_end_time 1.91e-5\nfrequency_slope 1.00000000377e14\n")
    wf = parse_waveform_cfg(tmp_path / "waveform_cfg.txt")
    assert wf == AWR1843.waveform


def test_missing_key_and_file_errors(tmp_path):
    (tmp_path / "waveform_cfg.txt").write_text("num_rx 4\nnum_tx 3\n")
    with pytest.raises(DataFileError, match="waveform_cfg.txt.*num_adc_samples_per_chirp"):
        parse_waveform_cfg(tmp_path / "waveform_cfg.txt")
    with pytest.raises(DataFileError, match="nothere.txt.*missing"):
        read_transform(tmp_path / "nothere.txt")
    (tmp_path / "antenna_cfg.txt").write_text("num_rx 2\nnum_tx 1\nF_design 77\nrx 0 0 0\ntx 0 0 0\n")
    with pytest.raises(DataFileError, match="rx rows 0..1"):
        parse_antenna_cfg(tmp_path / "antenna_cfg.txt")
    (tmp_path / "t.txt").write_text("1 2 3\n0 0 nan 1\n")
    with pytest.raises(DataFileError, match="t.txt"):
        read_transform(tmp_path / "t.txt")
    write_calib(tmp_path / "calib", DEFAULT_CALIB)
    (tmp_path / "calib" / "transforms" / "base_to_lidar.txt").unlink()
    with pytest.raises(DataFileError, match="base_to_lidar.txt"):
        load_calib(tmp_path / "calib")


def test_integer_keys_parse_strictly(tmp_path):
    write_calib(tmp_path / "calib", DEFAULT_CALIB)
    wf = tmp_path / "calib" / "single_chip" / "waveform_cfg.txt"
    wf.write_text(wf.read_text().replace("num_rx 4", "num_rx 4.5"))
    with pytest.raises(DataFileError, match=r"waveform_cfg.txt.*'num_rx'.*4\.5"):
        parse_waveform_cfg(wf)
    with pytest.raises(DataFileError, match="waveform_cfg.txt"):
        load_calib(tmp_path / "calib")
    wf.write_text(wf.read_text().replace("num_rx 4.5", "num_rx 4.0"))      # an integral float is fine
    assert parse_waveform_cfg(wf).num_rx == 4
    hm = tmp_path / "calib" / "single_chip" / "heatmap_cfg.txt"
    hm.write_text(hm.read_text().replace("num_range_bins 64", "num_range_bins 1e2.5"))
    with pytest.raises(DataFileError, match=r"heatmap_cfg.txt.*'num_range_bins'"):
        parse_heatmap_cfg(hm)
    ant = tmp_path / "calib" / "single_chip" / "antenna_cfg.txt"
    ant.write_text(ant.read_text().replace("num_tx 3", "num_tx 2.5"))
    with pytest.raises(DataFileError, match=r"antenna_cfg.txt.*num_tx 2.5"):
        parse_antenna_cfg(ant)


def test_base_to_cascade_needed_only_for_the_cascade(tmp_path):
    write_calib(tmp_path / "calib", DEFAULT_CALIB)
    (tmp_path / "calib" / "transforms" / "base_to_cascade.txt").unlink()
    calib = load_calib(tmp_path / "calib")                  # single-chip work: fine
    assert calib.cascade == CASCADE and calib.base_to_cascade is None
    assert calib.lidar_to_single_chip() == DEFAULT_CALIB.lidar_to_single_chip()
    with pytest.raises(ValueError, match="base_to_cascade"):
        calib.lidar_to_cascade()
    with pytest.raises(DataFileError, match="base_to_cascade.txt.*missing"):
        load_calib(tmp_path / "calib", cascade=True)
    assert load_calib(tmp_path / "calib", cascade=False).cascade is None
