"""ColoRadar radars: the TI AWR1843 single chip and the TI MMWCAS 12 Tx / 16 Rx cascade.

A :class:`ColoRadarChipConfig` is built from the three text files that ColoRadar ships in
``calib/single_chip/`` and ``calib/cascade/`` (``waveform_cfg.txt``, ``antenna_cfg.txt``,
``heatmap_cfg.txt``); the simulator writes the same files, so a real ``calib/`` folder and a
simulated one read the same way. Rig transforms ``calib/transforms/base_to_*.txt`` are read as
:class:`Transform`.

File formats (as read by ColoRadar's own tools):

* ``waveform_cfg.txt`` / ``heatmap_cfg.txt``: one ``key value [value ...]`` per line, blank and
  ``#`` lines ignored. Waveform keys: ``num_rx num_tx num_adc_samples_per_chirp
  num_chirps_per_frame adc_sample_frequency start_frequency idle_time adc_start_time
  ramp_end_time frequency_slope`` (SI units: Hz, s, Hz/s). Heatmap keys: ``num_range_bins
  num_elevation_bins num_azimuth_bins range_bin_width azimuth_bins elevation_bins`` (angles in
  radians, ascending).
* ``antenna_cfg.txt``: ``num_rx N``, ``num_tx N``, ``F_design f`` (GHz), then ``rx i az el`` and
  ``tx i az el`` rows; positions are in half wavelengths of ``F_design``.
* ``coupling_calib.txt``: ``key:value`` lines; ``data:`` holds interleaved real/imag values,
  ``num_tx * num_rx * num_range_bins`` complex numbers.
* ``transforms/base_to_X.txt``: first line the translation ``x y z`` (m), second line the
  rotation quaternion ``qx qy qz qw`` (scalar last, Hamilton). The transform maps points of
  sensor ``X``'s frame into the rig ``base`` frame: ``p_base = R(q) p_X + t``.

Validation: integer keys (``num_rx``, bin counts, ...) must be integers (``4`` or ``4.0``; ``4.5``
is a :class:`radarpc.io.DataFileError` naming the file and key, never truncated); NaN/inf and
missing keys are errors. An ADC window that ends after ``ramp_end_time`` is only a
``RuntimeWarning``: recorded configuration files round their timings, and a real ``calib/`` must
stay readable.

Conventions shared with the simulator and the reader (:mod:`radarpc.data.coloradar`):

* Sensor frame: x forward (boresight), y left, z up. Azimuth ``az = atan2(y, x)`` (left positive),
  elevation ``el = asin(z / r)``; a direction is ``u = (cos el cos az, cos el sin az, sin el)``.
* Element spacing ``d = 0.5 * f_c / F_design`` wavelengths per half-wavelength unit, ``f_c`` the
  centre of the sampled sweep. A virtual element at ``(p_h, p_v)`` sees a target of direction
  ``u`` with phase ``exp(+j 2 pi d (p_h u_y + p_v u_z))``, so after a NumPy FFT and ``fftshift``
  the azimuth (elevation) bin index grows towards +y (+z) -- the order of ColoRadar's ascending
  ``azimuth_bins`` and of RaLD's processed cubes (bin 0 is the rightmost direction).
* ADC frames: int16, ``[num_tx, num_rx, num_chirps, num_samples, 2]`` (I, Q), TDM-MIMO (one Tx
  per chirp, Tx ``t`` of loop ``c`` starts at ``(c * num_tx + t) * (idle_time + ramp_end_time)``).
* Heatmaps: float32 ``[num_elevation_bins, num_azimuth_bins, num_range_bins, 2]`` (intensity,
  Doppler in m/s).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarpc.io import DataFileError, atomic_write

__all__ = [
    "SPEED_OF_LIGHT",
    "WaveformConfig",
    "AntennaConfig",
    "HeatmapConfig",
    "ColoRadarChipConfig",
    "Transform",
    "ColoRadarCalib",
    "RadarFOV",
    "beam_angles",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
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
    "AWR1843",
    "CASCADE",
    "AWR1843_FOV",
    "BASE_TO_SINGLE_CHIP",
    "BASE_TO_LIDAR",
    "BASE_TO_CASCADE",
    "DEFAULT_CALIB",
    "CALIB_FILES",
]

SPEED_OF_LIGHT = 299_792_458.0


# ------------------------------------------------------------------------------------------------
# dataclasses
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class WaveformConfig:
    """FMCW chirp and frame parameters (``waveform_cfg.txt``)."""

    num_tx: int                       # transmitters, time-multiplexed chirp by chirp
    num_rx: int                       # receivers
    num_adc_samples_per_chirp: int    # complex ADC samples per chirp
    num_chirps_per_frame: int         # chirp loops per frame (each loop fires every Tx once)
    adc_sample_frequency: float       # complex sample rate (Hz)
    start_frequency: float            # chirp start frequency (Hz)
    idle_time: float                  # idle time between chirps (s)
    adc_start_time: float             # delay from ramp start to first ADC sample (s)
    ramp_end_time: float              # ramp duration (s)
    frequency_slope: float            # chirp slope (Hz/s)

    def __post_init__(self) -> None:
        for k in ("num_tx", "num_rx", "num_adc_samples_per_chirp", "num_chirps_per_frame"):
            v = getattr(self, k)
            if int(v) != v or v <= 0:
                raise ValueError(f"waveform {k} must be a positive integer, got {v!r}")
        for k in ("adc_sample_frequency", "start_frequency", "ramp_end_time", "frequency_slope"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"waveform {k} must be positive and finite, got {v!r}")
        for k in ("idle_time", "adc_start_time"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"waveform {k} must be >= 0, got {v!r}")
        end = self.adc_start_time + self.num_adc_samples_per_chirp / self.adc_sample_frequency
        if end > self.ramp_end_time * (1 + 1e-6):
            # A warning, not an error: recorded configuration files round their timings (TI tools
            # store 10 ns register steps), and a real calib/ folder must stay readable. The
            # synthesis and range axis do not depend on the ramp end, only the chirp period does.
            warnings.warn(
                f"waveform: ADC window ends at {end:.4e} s, after ramp_end_time={self.ramp_end_time:.4e} s "
                "(adc_start_time + num_adc_samples_per_chirp / adc_sample_frequency should fit in the ramp); "
                "samples past the ramp end would not be a linear chirp on real hardware",
                RuntimeWarning, stacklevel=3)

    @property
    def chirp_period_s(self) -> float:
        """``T_c = idle_time + ramp_end_time``."""
        return self.idle_time + self.ramp_end_time

    @property
    def center_frequency(self) -> float:
        """Carrier at the middle of the sampled sweep: ``f0 + S (t_adc + N / (2 f_s))``."""
        return self.start_frequency + self.frequency_slope * (
            self.adc_start_time + self.num_adc_samples_per_chirp / (2 * self.adc_sample_frequency))

    @property
    def wavelength_m(self) -> float:
        return SPEED_OF_LIGHT / self.center_frequency

    def range_bin_width(self, n_fft: int | None = None) -> float:
        """Metres per bin of an ``n_fft``-point range FFT: ``c f_s / (2 S n_fft)``."""
        n = self.num_adc_samples_per_chirp if n_fft is None else int(n_fft)
        return SPEED_OF_LIGHT * self.adc_sample_frequency / (2 * self.frequency_slope * n)

    @property
    def max_velocity_mps(self) -> float:
        """Unambiguous radial velocity of TDM-MIMO: ``lambda / (4 num_tx T_c)``."""
        return self.wavelength_m / (4 * self.num_tx * self.chirp_period_s)

    def velocity_bin_width(self, n_fft: int | None = None) -> float:
        """m/s per bin of an ``n_fft``-point Doppler FFT: ``2 v_max / n_fft``."""
        n = self.num_chirps_per_frame if n_fft is None else int(n_fft)
        return 2 * self.max_velocity_mps / n


@dataclass(frozen=True)
class AntennaConfig:
    """Antenna layout (``antenna_cfg.txt``); positions in half wavelengths of ``F_design``."""

    num_tx: int
    num_rx: int
    design_frequency_ghz: float                         # ``F_design`` (GHz)
    tx_positions: tuple[tuple[float, float], ...]       # (azimuth, elevation) per Tx, file order
    rx_positions: tuple[tuple[float, float], ...]       # (azimuth, elevation) per Rx

    def __post_init__(self) -> None:
        if len(self.tx_positions) != self.num_tx or len(self.rx_positions) != self.num_rx:
            raise ValueError(f"antenna: num_tx={self.num_tx}/num_rx={self.num_rx} but "
                             f"{len(self.tx_positions)}/{len(self.rx_positions)} positions given")
        if not (math.isfinite(self.design_frequency_ghz) and self.design_frequency_ghz > 0):
            raise ValueError(f"antenna F_design must be positive (GHz), got {self.design_frequency_ghz!r}")

    @property
    def virtual_positions(self) -> np.ndarray:
        """``(num_tx * num_rx, 2)`` virtual element positions, row ``tx * num_rx + rx``."""
        tx = np.asarray(self.tx_positions, dtype=np.float64)
        rx = np.asarray(self.rx_positions, dtype=np.float64)
        return (tx[:, None, :] + rx[None, :, :]).reshape(-1, 2)


@dataclass(frozen=True)
class HeatmapConfig:
    """Heatmap grid (``heatmap_cfg.txt``): bins of a processed (elevation, azimuth, range) map."""

    num_range_bins: int
    num_elevation_bins: int
    num_azimuth_bins: int
    range_bin_width: float                  # metres per range bin
    azimuth_bins: tuple[float, ...]         # bin-centre azimuths (rad), ascending
    elevation_bins: tuple[float, ...]       # bin-centre elevations (rad), ascending

    def __post_init__(self) -> None:
        for k in ("num_range_bins", "num_elevation_bins", "num_azimuth_bins"):
            v = getattr(self, k)
            if int(v) != v or v <= 0:
                raise ValueError(f"heatmap {k} must be a positive integer, got {v!r}")
        if not (math.isfinite(self.range_bin_width) and self.range_bin_width > 0):
            raise ValueError(f"heatmap range_bin_width must be positive, got {self.range_bin_width!r}")
        if len(self.azimuth_bins) != self.num_azimuth_bins:
            raise ValueError(f"heatmap: {len(self.azimuth_bins)} azimuth_bins for num_azimuth_bins={self.num_azimuth_bins}")
        if len(self.elevation_bins) != self.num_elevation_bins:
            raise ValueError(f"heatmap: {len(self.elevation_bins)} elevation_bins for "
                             f"num_elevation_bins={self.num_elevation_bins}")

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """On-disk heatmap shape ``(elevation, azimuth, range, 2)``."""
        return (self.num_elevation_bins, self.num_azimuth_bins, self.num_range_bins, 2)

    @property
    def max_range_m(self) -> float:
        """Range of the last bin centre, ``(num_range_bins - 1) * range_bin_width``."""
        return (self.num_range_bins - 1) * self.range_bin_width


@dataclass(frozen=True)
class ColoRadarChipConfig:
    """One ColoRadar radar: waveform, antenna layout and heatmap grid."""

    name: str
    waveform: WaveformConfig
    antenna: AntennaConfig
    heatmap: HeatmapConfig

    def __post_init__(self) -> None:
        if (self.waveform.num_tx, self.waveform.num_rx) != (self.antenna.num_tx, self.antenna.num_rx):
            raise ValueError(f"{self.name}: waveform has {self.waveform.num_tx} Tx / {self.waveform.num_rx} Rx "
                             f"but antenna has {self.antenna.num_tx} / {self.antenna.num_rx}")

    @property
    def num_tx(self) -> int:
        return self.waveform.num_tx

    @property
    def num_rx(self) -> int:
        return self.waveform.num_rx

    @property
    def adc_shape(self) -> tuple[int, int, int, int, int]:
        """On-disk ADC frame shape ``(tx, rx, chirps, samples, 2)`` (int16)."""
        w = self.waveform
        return (w.num_tx, w.num_rx, w.num_chirps_per_frame, w.num_adc_samples_per_chirp, 2)

    @property
    def adc_nbytes(self) -> int:
        return int(np.prod(self.adc_shape)) * 2

    @property
    def heatmap_nbytes(self) -> int:
        return int(np.prod(self.heatmap.shape)) * 4

    @property
    def element_spacing(self) -> float:
        """``d = 0.5 f_c / F_design``: wavelengths per half-wavelength unit of position."""
        return 0.5 * self.waveform.center_frequency / (self.antenna.design_frequency_ghz * 1e9)

    @property
    def virtual_positions(self) -> np.ndarray:
        return self.antenna.virtual_positions

    def replace(self, **kw) -> "ColoRadarChipConfig":
        """Copy with some waveform/heatmap fields changed, e.g. ``replace(num_chirps_per_frame=8)``."""
        wf = {k: v for k, v in kw.items() if k in {f.name for f in dataclasses.fields(WaveformConfig)}}
        hm = {k: v for k, v in kw.items() if k in {f.name for f in dataclasses.fields(HeatmapConfig)}}
        unknown = set(kw) - set(wf) - set(hm)
        if unknown:
            raise ValueError(f"unknown chip config fields: {sorted(unknown)}")
        return dataclasses.replace(self, waveform=dataclasses.replace(self.waveform, **wf),
                                   heatmap=dataclasses.replace(self.heatmap, **hm))


@dataclass(frozen=True)
class RadarFOV:
    """Radar frustum used to crop LiDAR ground truth (RaLD: 0-15.86 m, +-90 deg, +-20 deg)."""

    max_range_m: float = 15.863025538680999
    azimuth_deg: tuple[float, float] = (-90.0, 90.0)
    elevation_deg: tuple[float, float] = (-20.0, 20.0)
    min_range_m: float = 0.0

    def __post_init__(self) -> None:
        if not (0 <= self.min_range_m < self.max_range_m):
            raise ValueError(f"FOV range must satisfy 0 <= min < max, got {self.min_range_m}, {self.max_range_m}")
        a0, a1 = self.azimuth_deg
        e0, e1 = self.elevation_deg
        if not (-180 <= a0 < a1 <= 180) or not (-90 <= e0 < e1 <= 90):
            raise ValueError(f"FOV angles out of range: azimuth {self.azimuth_deg}, elevation {self.elevation_deg}")


# ------------------------------------------------------------------------------------------------
# transforms
# ------------------------------------------------------------------------------------------------
def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion in ``(qx, qy, qz, qw)`` order (scalar last).

    ``R = I + 2 w [v]x + 2 [v]x^2`` with ``v = (qx, qy, qz)``; the quaternion is normalised first.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (4,) or not np.isfinite(q).all():
        raise ValueError(f"quaternion must be 4 finite numbers (qx, qy, qz, qw), got {q!r}")
    n = np.linalg.norm(q)
    if n < 1e-9:
        raise ValueError(f"quaternion has zero norm: {q!r}")
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(r) -> np.ndarray:
    """Inverse of :func:`quaternion_to_matrix`: ``(qx, qy, qz, qw)`` with ``qw >= 0``."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation matrix must be 3x3, got shape {r.shape}")
    tr = np.trace(r)
    if tr > 0:
        s = 2 * math.sqrt(tr + 1)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(1 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0, 0.0, 0.0, (r[k, j] - r[j, k]) / s]
        q[i] = s / 4
        q[j] = (r[j, i] + r[i, j]) / s
        q[k] = (r[k, i] + r[i, k]) / s
    q = np.asarray(q)
    return -q if q[3] < 0 else q


@dataclass(frozen=True)
class Transform:
    """Rigid transform ``p_parent = R(q) p_child + t`` (ColoRadar ``base_to_X``: child X, parent base)."""

    translation: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]   # (qx, qy, qz, qw), scalar last

    def __post_init__(self) -> None:
        quaternion_to_matrix(self.quaternion)  # validates
        if len(self.translation) != 3 or not np.isfinite(np.asarray(self.translation, float)).all():
            raise ValueError(f"translation must be 3 finite numbers, got {self.translation!r}")

    @property
    def rotation(self) -> np.ndarray:
        return quaternion_to_matrix(self.quaternion)

    @property
    def matrix(self) -> np.ndarray:
        """4 x 4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    @classmethod
    def from_matrix(cls, m) -> "Transform":
        m = np.asarray(m, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"homogeneous matrix must be 4x4, got {m.shape}")
        return cls(tuple(float(v) for v in m[:3, 3]), tuple(float(v) for v in matrix_to_quaternion(m[:3, :3])))

    def inverse(self) -> "Transform":
        return Transform.from_matrix(np.linalg.inv(self.matrix))

    def __matmul__(self, other: "Transform") -> "Transform":
        return Transform.from_matrix(self.matrix @ other.matrix)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map ``(N, 3)`` points from the child frame to the parent frame."""
        p = np.asarray(points)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got shape {p.shape}")
        return p @ self.rotation.T.astype(p.dtype) + np.asarray(self.translation, dtype=p.dtype)


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


def parse_coupling_calib(path: str | os.PathLike) -> np.ndarray:
    """Read ``coupling_calib.txt`` -> complex ``(num_tx, num_rx, num_range_bins)``."""
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


@dataclass(frozen=True)
class ColoRadarCalib:
    """Everything of ColoRadar's ``calib/`` folder that radarpc uses."""

    single_chip: ColoRadarChipConfig
    cascade: ColoRadarChipConfig | None
    base_to_single_chip: Transform
    base_to_lidar: Transform
    base_to_cascade: Transform | None

    def lidar_to_single_chip(self) -> Transform:
        """``T_radar<-lidar = T_base_radar^-1 T_base_lidar`` (``p_radar = T p_lidar``)."""
        return self.base_to_single_chip.inverse() @ self.base_to_lidar

    def lidar_to_cascade(self) -> Transform:
        if self.base_to_cascade is None:
            raise ValueError("this calibration has no base_to_cascade transform "
                             "(calib/transforms/base_to_cascade.txt was absent; load_calib(..., cascade=True) requires it)")
        return self.base_to_cascade.inverse() @ self.base_to_lidar


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
    return ColoRadarCalib(sc, cc, b_sc, b_l, b_cc)


def write_calib(calib_dir: str | os.PathLike, calib: ColoRadarCalib) -> None:
    """Write a ColoRadar-layout ``calib/`` folder (each file atomically)."""
    calib_dir = Path(calib_dir)
    chips = [("single_chip", calib.single_chip)] + ([("cascade", calib.cascade)] if calib.cascade else [])
    for sub, chip in chips:
        d = calib_dir / sub
        write_waveform_cfg(d / "waveform_cfg.txt", chip.waveform)
        write_antenna_cfg(d / "antenna_cfg.txt", chip.antenna)
        write_heatmap_cfg(d / "heatmap_cfg.txt", chip.heatmap)
        write_coupling_calib(d / "coupling_calib.txt",
                             np.zeros((chip.num_tx, chip.num_rx, chip.heatmap.num_range_bins), np.complex128),
                             chip.waveform.num_chirps_per_frame)
        if sub == "cascade":
            write_phase_frequency_calib(d / "phase_frequency_calib.txt", chip)
    write_transform(calib_dir / "transforms" / "base_to_single_chip.txt", calib.base_to_single_chip)
    write_transform(calib_dir / "transforms" / "base_to_lidar.txt", calib.base_to_lidar)
    if calib.base_to_cascade is not None:
        write_transform(calib_dir / "transforms" / "base_to_cascade.txt", calib.base_to_cascade)


# ------------------------------------------------------------------------------------------------
# defaults
# ------------------------------------------------------------------------------------------------
def beam_angles(n: int, d: float, *, half_bin: bool = False) -> tuple[float, ...]:
    """Bin-centre angles (rad, ascending) of an ``n``-point fftshift-ed spatial FFT.

    Bin ``k`` has spatial frequency ``f_k = (k - n/2 [+ 1/2]) / n`` cycles per element and angle
    ``asin(f_k / d)``, clipped to +-90 deg where the bin lies outside the visible region.
    ``half_bin=True`` gives ColoRadar's heatmap beams (centred between FFT bins).
    """
    if n <= 0 or d <= 0:
        raise ValueError(f"beam_angles needs n > 0 and d > 0, got n={n}, d={d}")
    k = np.arange(n) - n / 2 + (0.5 if half_bin else 0.0)
    return tuple(float(a) for a in np.arcsin(np.clip(k / (n * d), -1.0, 1.0)))


def _awr1843() -> ColoRadarChipConfig:
    # Waveform and layout as used by RaLD on ColoRadar's single chip (start 77 GHz, 100 MHz/us,
    # 10.666 MS/s, 128 samples x 128 loops x 3 Tx; TX0 (0,0), TX1 (4,0), TX2 (2,1) -> an 8 x 2
    # virtual array with a 4-element raised row); 128 range bins of 0.124905712903 m.
    wf = WaveformConfig(num_tx=3, num_rx=4, num_adc_samples_per_chirp=128, num_chirps_per_frame=128,
                        adc_sample_frequency=10_666_000.0, start_frequency=77e9, idle_time=110e-6,
                        adc_start_time=7e-6, ramp_end_time=19.1e-6, frequency_slope=1.00000000377e14)
    ant = AntennaConfig(3, 4, 76.8, ((0.0, 0.0), (4.0, 0.0), (2.0, 1.0)),
                        tuple((float(k), 0.0) for k in range(4)))
    d = 0.5 * wf.center_frequency / (ant.design_frequency_ghz * 1e9)
    hm = HeatmapConfig(num_range_bins=128, num_elevation_bins=2, num_azimuth_bins=8,
                       range_bin_width=0.124905712903, azimuth_bins=beam_angles(8, d),
                       elevation_bins=beam_angles(2, d))
    return ColoRadarChipConfig("single_chip", wf, ant, hm)


def _cascade() -> ColoRadarChipConfig:
    # TI MMWCAS-RF-EVM layout (rows in ColoRadar's device order dev4, dev1, dev3, dev2): 16 Rx on
    # the horizontal line, 9 Tx spaced 4 units and 3 Tx raised by 1, 4, 6 units; 256 samples at
    # 8 MS/s, 79 MHz/us -> heatmap range bins of 0.0592943951488 m (128 kept, 7.59 m); 16 loops of
    # 12 Tx at 40 us -> +-2.02 m/s. Heatmap: 32 elevation x 128 azimuth beams (half-bin centred).
    wf = WaveformConfig(num_tx=12, num_rx=16, num_adc_samples_per_chirp=256, num_chirps_per_frame=16,
                        adc_sample_frequency=8e6, start_frequency=77e9, idle_time=5e-6,
                        adc_start_time=3e-6, ramp_end_time=35e-6, frequency_slope=79e12)
    tx = ((0, 0), (4, 0), (8, 0), (9, 1), (10, 4), (11, 6), (12, 0), (16, 0), (20, 0), (24, 0), (28, 0), (32, 0))
    rx = tuple((float(a), 0.0) for a in (*range(0, 4), *range(11, 15), *range(46, 50), *range(50, 54)))
    ant = AntennaConfig(12, 16, 77.0, tuple((float(a), float(e)) for a, e in tx), rx)
    d = 0.5 * wf.center_frequency / (ant.design_frequency_ghz * 1e9)
    hm = HeatmapConfig(num_range_bins=128, num_elevation_bins=32, num_azimuth_bins=128,
                       range_bin_width=0.0592943951488, azimuth_bins=beam_angles(128, d, half_bin=True),
                       elevation_bins=beam_angles(32, d, half_bin=True))
    return ColoRadarChipConfig("cascade", wf, ant, hm)


AWR1843 = _awr1843()
"""TI AWR1843 single chip as used by RaLD (3 Tx, 4 Rx, 128 chirps x 128 samples, 77 GHz)."""

CASCADE = _cascade()
"""TI MMWCAS 12 Tx x 16 Rx cascade; heatmaps 32 el x 128 az x 128 range."""

AWR1843_FOV = RadarFOV()
"""RaLD's crop: range <= 127 range bins (15.863 m), azimuth +-90 deg, elevation +-20 deg."""

# Rig transforms published with ColoRadar (base = rig frame), as quoted by RaLD's preprocessing.
BASE_TO_SINGLE_CHIP = Transform((-0.145, 0.09, -0.025), (0.0, 0.0, 0.706825181105, 0.707388269167))
BASE_TO_LIDAR = Transform((-0.075, -0.02, 0.03618), (0.0, 0.0, 0.721382357437, -0.692536998563))
# Not from the dataset: a cascade mounted 6 cm beside the single chip with the same orientation.
BASE_TO_CASCADE = Transform((-0.145, 0.15, -0.025), (0.0, 0.0, 0.706825181105, 0.707388269167))

DEFAULT_CALIB = ColoRadarCalib(AWR1843, CASCADE, BASE_TO_SINGLE_CHIP, BASE_TO_LIDAR, BASE_TO_CASCADE)
