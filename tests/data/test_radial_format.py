"""RADIal calibration files: radarpc's ``calibration.npz`` and RADIal's pickled table."""
import numpy as np
import pytest

from radarpc.data.radial_format import load_calibration, save_calibration
from radarpc.io import DataFileError
from radarpc.sensors.radial import RADIAL, TINY
from radarpc.sim.radial_calibration import make_calibration


def test_calibration_npz_round_trip_with_radial_keys(tmp_path):
    calib = make_calibration(TINY)
    path = tmp_path / "calibration.npz"
    save_calibration(path, calib)
    with np.load(path, allow_pickle=False) as z:
        assert set(z.files) == {"Signal", "H", "Azimuth_table", "Elevation_table"}
        assert z["Signal"].shape == (61, 8, 5) and z["H"].shape == (1, 8)
    back = load_calibration(path)
    np.testing.assert_array_equal(back.signal, calib.signal)
    np.testing.assert_array_equal(back.window, calib.window)
    back.check_sensor(TINY)
    with pytest.raises(ValueError, match="8 virtual channels.*192"):
        back.check_sensor(RADIAL)


def test_calibration_bad_files(tmp_path):
    with pytest.raises(DataFileError, match="missing"):
        load_calibration(tmp_path / "nope.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, Signal=np.zeros((3, 8, 2), np.complex64))
    with pytest.raises(DataFileError, match=r"bad.npz.*lacks keys \['Azimuth_table', 'Elevation_table', 'H'\]"):
        load_calibration(bad)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file")
    with pytest.raises(DataFileError, match="junk.npz"):
        load_calibration(junk)
    pickled = tmp_path / "CalibrationTable.npy"
    np.save(pickled, np.array({"Signal": 1}, dtype=object), allow_pickle=True)
    with pytest.raises(DataFileError, match="trust_pickle=True"):
        load_calibration(pickled)


def test_trusted_pickled_table_is_read(tmp_path):
    calib = make_calibration(TINY)
    table = {"Signal": calib.signal, "H": calib.window[None], "Azimuth_table": calib.azimuth_deg,
             "Elevation_table": calib.elevation_deg}
    path = tmp_path / "CalibrationTable.npy"
    np.save(path, np.array(table, dtype=object), allow_pickle=True)
    back = load_calibration(path, trust_pickle=True)
    np.testing.assert_array_equal(back.signal, calib.signal)
