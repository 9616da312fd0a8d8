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
)
from radarpc.io import DataFileError
from radarpc.sensors.coloradar import AWR1843, CASCADE, DEFAULT_CALIB


def test_calib_round_trip(tmp_path):
    write_calib(tmp_path / "calib", DEFAULT_CALIB)
    got = load_calib(tmp_path / "calib")
    assert got == DEFAULT_CALIB
    c = parse_coupling_calib(tmp_path / "calib" / "single_chip" / "coupling_calib.txt")
    assert c.shape == (3, 4, 128) and np.iscomplexobj(c) and not c.any()


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
    hm.write_text(hm.read_text().replace("num_range_bins 128", "num_range_bins 1e2.5"))
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
