"""ColoRadar's on-disk calibration format: parse and write the files of a ``calib/`` folder.

ColoRadar ships ``calib/single_chip/`` and ``calib/cascade/`` (``waveform_cfg.txt``,
``antenna_cfg.txt``, ``heatmap_cfg.txt``, ``coupling_calib.txt``) and ``calib/transforms/``;
the simulator writes the same files (:func:`write_calib`), so a real ``calib/`` folder and a
simulated one read the same way (:func:`load_calib`) into the sensor dataclasses of
:mod:`radarpc.sensors.coloradar`.

File formats (as read by ColoRadar's own tools):

* ``waveform_cfg.txt`` / ``heatmap_cfg.txt``: one ``key value [value ...]`` per line, blank and
  ``#`` lines ignored. Waveform keys: ``num_rx num_tx num_adc_samples_per_chirp
  num_chirps_per_frame adc_sample_frequency start_frequency idle_time adc_start_time
  ramp_end_time frequency_slope`` (SI units: Hz, s, Hz/s). Heatmap keys: ``num_range_bins
  num_elevation_bins num_azimuth_bins range_bin_width azimuth_bins elevation_bins`` (angles in
  radians, ascending).
* ``antenna_cfg.txt``: ``num_rx N``, ``num_tx N``, ``F_design f`` (GHz), then ``rx i az el`` and
  ``tx i az el`` rows; positions are in half wavelengths of ``F_design``.
* ``coupling_calib.txt``: ``key:value`` lines (``num_tx``, ``num_rx``, ``num_range_bins``,
  ``num_doppler_bins``, ``data``); ``data:`` holds interleaved real/imag values,
  ``num_tx * num_rx * num_range_bins`` complex numbers, ``num_range_bins`` being the heatmap's
  (half the ADC samples per chirp; see
  :attr:`radarpc.sensors.coloradar.ColoRadarChipConfig.coupling_shape`). The simulator writes
  zeros (it models no Tx-Rx leakage).
* ``transforms/base_to_X.txt`` (``X`` in ``single_chip``, ``cascade``, ``lidar``, ``imu``): first
  line the translation ``x y z`` (m), second line the rotation quaternion ``qx qy qz qw`` (scalar
  last, Hamilton). The transform maps points of sensor ``X``'s frame into the rig ``base`` frame:
  ``p_base = R(q) p_X + t``. The dataset also ships ``base_to_vicon.txt`` (the motion-capture
  marker frame of its Vicon runs); its values are not public outside the dataset, so it is
  neither written nor read here.

Validation: integer keys (``num_rx``, bin counts, ...) must be integers (``4`` or ``4.0``; ``4.5``
is a :class:`radarpc.io.DataFileError` naming the file and key, never truncated); NaN/inf and
missing keys are errors. An ADC window that ends after ``ramp_end_time`` is only a
``RuntimeWarning``: recorded configuration files round their timings, and a real ``calib/`` must
stay readable.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from radarpc.io import DataFileError, atomic_write
from radarpc.sensors.coloradar import (
    AntennaConfig,
    ColoRadarCalib,
    ColoRadarChipConfig,
    HeatmapConfig,
    Transform,
    WaveformConfig,
)

__all__ = [
    "CALIB_FILES",
    "parse_waveform_cfg",
    "parse_antenna_cfg",
    "parse_heatmap_cfg",
    "parse_coupling_calib",
    "read_transform",
    "write_waveform_cfg",
    "write_antenna_cfg",
    "write_heatmap_cfg",
    "write_coupling_calib",
    "write_phase_frequency_calib",
    "write_transform",
    "load_chip_config",
    "load_calib",
    "write_calib",
]


# ------------------------------------------------------------------------------------------------
# parsing
# ------------------------------------------------------------------------------------------------
def _read_key_values(path: Path) -> dict[str, list[str]]:
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "calibration file is missing")
    out: dict[str, list[str]] = {}
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DataFileError(path, f"cannot be read as text ({e})") from e
    for line in text.splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        toks = s.split()
        out[toks[0]] = toks[1:]
    return out


def _strict_int(token: str) -> int:
    """``'4'`` or ``'4.0'``/``'4e0'`` -> 4; ``'4.5'`` or ``'nan'`` -> ``ValueError`` (never truncated)."""
    try:
        return int(token)
    except ValueError:
        v = float(token)
        if not (math.isfinite(v) and v.is_integer()):
            raise ValueError(f"{token!r} is not an integer") from None
        return int(v)


def _get(kv: dict[str, list[str]], path: Path, key: str, kind=float, *, many: bool = False):
    if key not in kv or not kv[key]:
        raise DataFileError(path, f"expected a line '{key} <value>' but it is missing or empty")
    try:
        vals = [_strict_int(v) if kind is int else kind(v) for v in kv[key]]
    except ValueError as e:
        raise DataFileError(path, f"key {key!r}: cannot parse {kv[key][:4]} as {kind.__name__}") from e
    if any(not math.isfinite(v) for v in vals):
        raise DataFileError(path, f"key {key!r} holds NaN or infinite values")
    return tuple(vals) if many else vals[0]


def parse_waveform_cfg(path: str | os.PathLike) -> WaveformConfig:
    """Read ColoRadar's ``waveform_cfg.txt``; missing keys or bad values raise ``DataFileError``."""
    path = Path(path)
    kv = _read_key_values(path)
    try:
        return WaveformConfig(
            num_tx=_get(kv, path, "num_tx", int), num_rx=_get(kv, path, "num_rx", int),
            num_adc_samples_per_chirp=_get(kv, path, "num_adc_samples_per_chirp", int),
            num_chirps_per_frame=_get(kv, path, "num_chirps_per_frame", int),
            adc_sample_frequency=_get(kv, path, "adc_sample_frequency"),
            start_frequency=_get(kv, path, "start_frequency"), idle_time=_get(kv, path, "idle_time"),
            adc_start_time=_get(kv, path, "adc_start_time"), ramp_end_time=_get(kv, path, "ramp_end_time"),
            frequency_slope=_get(kv, path, "frequency_slope"))
    except DataFileError:
        raise
    except ValueError as e:
        raise DataFileError(path, str(e)) from e


def parse_antenna_cfg(path: str | os.PathLike) -> AntennaConfig:
    """Read ColoRadar's ``antenna_cfg.txt`` (``rx i az el`` / ``tx i az el`` rows)."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "calibration file is missing")
    n = {}
    rows: dict[str, dict[int, tuple[float, float]]] = {"rx": {}, "tx": {}}
    f_design = None
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        toks = line.split()
        if not toks or toks[0].startswith("#"):
            continue
        try:
            if toks[0] in ("num_rx", "num_tx"):
                n[toks[0]] = _strict_int(toks[1])
            elif toks[0].lower() == "f_design":
                f_design = float(toks[1])
            elif toks[0] in ("rx", "tx"):
                rows[toks[0]][_strict_int(toks[1])] = (float(toks[2]), float(toks[3]))
        except (IndexError, ValueError) as e:
            raise DataFileError(path, f"line {ln} {line.strip()!r} cannot be parsed ({e})") from e
    for k in ("num_rx", "num_tx"):
        if k not in n:
            raise DataFileError(path, f"expected a line '{k} <int>' but it is missing")
    if f_design is None:
        raise DataFileError(path, "expected a line 'F_design <GHz>' but it is missing")
    out = {}
    for kind in ("tx", "rx"):
        want = n[f"num_{kind}"]
        if sorted(rows[kind]) != list(range(want)):
            raise DataFileError(path, f"expected {kind} rows 0..{want - 1}, found indices {sorted(rows[kind])}")
        out[kind] = tuple(rows[kind][i] for i in range(want))
    try:
        return AntennaConfig(n["num_tx"], n["num_rx"], f_design, out["tx"], out["rx"])
    except ValueError as e:
        raise DataFileError(path, str(e)) from e


def parse_heatmap_cfg(path: str | os.PathLike) -> HeatmapConfig:
    """Read ColoRadar's ``heatmap_cfg.txt`` (bin tables in radians)."""
    path = Path(path)
    kv = _read_key_values(path)
    try:
        return HeatmapConfig(
            num_range_bins=_get(kv, path, "num_range_bins", int),
            num_elevation_bins=_get(kv, path, "num_elevation_bins", int),
            num_azimuth_bins=_get(kv, path, "num_azimuth_bins", int),
            range_bin_width=_get(kv, path, "range_bin_width"),
            azimuth_bins=_get(kv, path, "azimuth_bins", many=True),
            elevation_bins=_get(kv, path, "elevation_bins", many=True))
    except DataFileError:
        raise
    except ValueError as e:
        raise DataFileError(path, str(e)) from e


def parse_coupling_calib(path: str | os.PathLike, chip: ColoRadarChipConfig | None = None) -> np.ndarray:
    """Read ``coupling_calib.txt`` -> complex ``(num_tx, num_rx, num_range_bins)``.

    With ``chip``, the shape must also be the chip's :attr:`ColoRadarChipConfig.coupling_shape`
    (the size ColoRadar's tools reshape the file to).
    """
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "calibration file is missing")
    kv: dict[str, str] = {}
    for line in path.read_text().splitlines():
        if ":" in line and not line.lstrip().startswith("#"):
            k, v = line.split(":", 1)
            kv[k.strip()] = v.strip()
    try:
        ntx, nrx, nr = (int(kv[k]) for k in ("num_tx", "num_rx", "num_range_bins"))
        data = np.array([float(v) for v in kv["data"].split(",") if v.strip()])
    except (KeyError, ValueError) as e:
        raise DataFileError(path, f"expected num_tx, num_rx, num_range_bins and data lines ({e})") from e
    if data.size != 2 * ntx * nrx * nr:
        raise DataFileError(path, f"data holds {data.size} values, expected 2 * {ntx} * {nrx} * {nr} = {2 * ntx * nrx * nr}")
    if not np.isfinite(data).all():
        raise DataFileError(path, "data holds NaN or infinite values")
    if chip is not None and (ntx, nrx, nr) != chip.coupling_shape:
        raise DataFileError(path, f"holds {ntx} x {nrx} x {nr} complex values, but the {chip.name} config implies "
                                  f"{' x '.join(map(str, chip.coupling_shape))} (num_tx x num_rx x heatmap_cfg.txt's "
                                  "num_range_bins)")
    return (data[0::2] + 1j * data[1::2]).reshape(ntx, nrx, nr)


def read_transform(path: str | os.PathLike) -> Transform:
    """Read ``base_to_X.txt``: translation line ``x y z``, then quaternion line ``qx qy qz qw``."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "calibration file is missing")
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2 or len(lines[0]) != 3 or len(lines[1]) != 4:
        raise DataFileError(path, "expected a translation line 'x y z' then a quaternion line 'qx qy qz qw'")
    try:
        t = tuple(float(v) for v in lines[0])
        q = tuple(float(v) for v in lines[1])
        return Transform(t, q)
    except ValueError as e:
        raise DataFileError(path, str(e)) from e


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------
def _fmt(v: float) -> str:
    if float(v).is_integer() and abs(v) < 1e15:
        return str(int(v))
    return repr(float(v))


def write_waveform_cfg(path: str | os.PathLike, wf: WaveformConfig) -> None:
    """Write ``waveform_cfg.txt`` (single space between key and value, as ColoRadar's files)."""
    keys = ["num_rx", "num_tx", "num_adc_samples_per_chirp", "num_chirps_per_frame", "adc_sample_frequency",
            "start_frequency", "idle_time", "adc_start_time", "ramp_end_time", "frequency_slope"]
    with atomic_write(path, "w") as f:
        f.write("".join(f"{k} {_fmt(getattr(wf, k))}\n" for k in keys))


def write_antenna_cfg(path: str | os.PathLike, ant: AntennaConfig) -> None:
    lines = [f"num_rx {ant.num_rx}", f"num_tx {ant.num_tx}", f"F_design {_fmt(ant.design_frequency_ghz)}"]
    lines += [f"rx {i} {_fmt(a)} {_fmt(e)}" for i, (a, e) in enumerate(ant.rx_positions)]
    lines += [f"tx {i} {_fmt(a)} {_fmt(e)}" for i, (a, e) in enumerate(ant.tx_positions)]
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def write_heatmap_cfg(path: str | os.PathLike, hm: HeatmapConfig) -> None:
    """Write ``heatmap_cfg.txt``; bin-table lines end with a space before the newline, like the
    dataset's own files (some readers drop the last token of a list line)."""
    lines = [f"num_range_bins {hm.num_range_bins}", f"num_elevation_bins {hm.num_elevation_bins}",
             f"num_azimuth_bins {hm.num_azimuth_bins}", f"range_bin_width {_fmt(hm.range_bin_width)}",
             "azimuth_bins " + " ".join(repr(float(a)) for a in hm.azimuth_bins) + " ",
             "elevation_bins " + " ".join(repr(float(a)) for a in hm.elevation_bins) + " "]
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def write_coupling_calib(path: str | os.PathLike, coupling: np.ndarray, num_doppler_bins: int) -> None:
    """Write ``coupling_calib.txt`` from complex ``(num_tx, num_rx, num_range_bins)``."""
    c = np.asarray(coupling)
    if c.ndim != 3 or not np.iscomplexobj(c):
        raise ValueError(f"coupling must be complex (num_tx, num_rx, num_range_bins), got {c.dtype} {c.shape}")
    flat = np.stack([c.real.ravel(), c.imag.ravel()], axis=1).ravel()
    with atomic_write(path, "w") as f:
        f.write(f"num_tx:{c.shape[0]}\nnum_rx:{c.shape[1]}\nnum_range_bins:{c.shape[2]}\n"
                f"num_doppler_bins:{int(num_doppler_bins)}\n")
        f.write("data:" + ",".join(repr(float(v)) for v in flat) + "\n")


def write_phase_frequency_calib(path: str | os.PathLike, chip: ColoRadarChipConfig) -> None:
    """Write an identity ``phase_frequency_calib.txt`` (cascade; JSON ``antennaCalib``)."""
    n = chip.num_tx * chip.num_rx
    doc = {"antennaCalib": {
        "numTx": chip.num_tx, "numRx": chip.num_rx,
        "frequencySlope": chip.waveform.frequency_slope, "samplingRate": chip.waveform.adc_sample_frequency,
        "frequencyCalibrationMatrix": [0.0] * n, "phaseCalibrationMatrix": [1.0, 0.0] * n}}
    with atomic_write(path, "w") as f:
        json.dump(doc, f, indent=1)


def write_transform(path: str | os.PathLike, tf: Transform) -> None:
    with atomic_write(path, "w") as f:
        f.write(" ".join(repr(float(v)) for v in tf.translation) + "\n")
        f.write(" ".join(repr(float(v)) for v in tf.quaternion) + "\n")


# ------------------------------------------------------------------------------------------------
# calibration folder
# ------------------------------------------------------------------------------------------------
CALIB_FILES = ("waveform_cfg.txt", "antenna_cfg.txt", "heatmap_cfg.txt")


def load_chip_config(folder: str | os.PathLike, name: str | None = None) -> ColoRadarChipConfig:
    """Read ``waveform_cfg.txt``, ``antenna_cfg.txt``, ``heatmap_cfg.txt`` of one radar folder."""
    folder = Path(folder)
    wf = parse_waveform_cfg(folder / "waveform_cfg.txt")
    ant = parse_antenna_cfg(folder / "antenna_cfg.txt")
    hm = parse_heatmap_cfg(folder / "heatmap_cfg.txt")
    try:
        return ColoRadarChipConfig(name or folder.name, wf, ant, hm)
    except ValueError as e:
        raise DataFileError(folder, str(e)) from e


def load_calib(calib_dir: str | os.PathLike, *, cascade: bool | None = None) -> ColoRadarCalib:
    """Load a ColoRadar ``calib/`` folder (real or simulated).

    Parameters
    ----------
    calib_dir : path-like
        The ``calib`` folder (``single_chip/``, ``cascade/``, ``transforms/``).
    cascade : bool, optional
        True: the cascade files and ``transforms/base_to_cascade.txt`` are required; False: not
        read; None (default): the cascade chip config is read if ``cascade/`` exists and its
        transform if ``base_to_cascade.txt`` exists (single-chip work never needs it;
        :meth:`ColoRadarCalib.lidar_to_cascade` raises when it is absent).

    ``transforms/base_to_imu.txt`` is read when present (radarpc does not need it; roots written
    before it was simulated lack it).

    Raises
    ------
    DataFileError
        Naming the missing or malformed file.
    """
    calib_dir = Path(calib_dir)
    if not calib_dir.is_dir():
        raise DataFileError(calib_dir, "calibration folder is missing (expected ROOT/calib/)")
    sc = load_chip_config(calib_dir / "single_chip", "single_chip")
    tdir = calib_dir / "transforms"
    b_sc = read_transform(tdir / "base_to_single_chip.txt")
    b_l = read_transform(tdir / "base_to_lidar.txt")
    cc, b_cc = None, None
    if cascade or (cascade is None and (calib_dir / "cascade").is_dir()):
        cc = load_chip_config(calib_dir / "cascade", "cascade")
        if cascade or (tdir / "base_to_cascade.txt").is_file():
            b_cc = read_transform(tdir / "base_to_cascade.txt")
    b_imu = read_transform(tdir / "base_to_imu.txt") if (tdir / "base_to_imu.txt").is_file() else None
    return ColoRadarCalib(sc, cc, b_sc, b_l, b_cc, b_imu)


def write_calib(calib_dir: str | os.PathLike, calib: ColoRadarCalib) -> None:
    """Write a ColoRadar-layout ``calib/`` folder (each file atomically)."""
    calib_dir = Path(calib_dir)
    chips = [("single_chip", calib.single_chip)] + ([("cascade", calib.cascade)] if calib.cascade else [])
    for sub, chip in chips:
        d = calib_dir / sub
        write_waveform_cfg(d / "waveform_cfg.txt", chip.waveform)
        write_antenna_cfg(d / "antenna_cfg.txt", chip.antenna)
        write_heatmap_cfg(d / "heatmap_cfg.txt", chip.heatmap)
        write_coupling_calib(d / "coupling_calib.txt", np.zeros(chip.coupling_shape, np.complex128),
                             chip.waveform.num_chirps_per_frame)
        if sub == "cascade":
            write_phase_frequency_calib(d / "phase_frequency_calib.txt", chip)
    write_transform(calib_dir / "transforms" / "base_to_single_chip.txt", calib.base_to_single_chip)
    write_transform(calib_dir / "transforms" / "base_to_lidar.txt", calib.base_to_lidar)
    if calib.base_to_cascade is not None:
        write_transform(calib_dir / "transforms" / "base_to_cascade.txt", calib.base_to_cascade)
    if calib.base_to_imu is not None:
        write_transform(calib_dir / "transforms" / "base_to_imu.txt", calib.base_to_imu)
