"""ColoRadar radars: the TI AWR1843 single chip and the TI MMWCAS 12 Tx / 16 Rx cascade.

Sensor dataclasses only: :class:`ColoRadarChipConfig` (waveform, antenna, heatmap of one radar),
:class:`Transform` (rig extrinsics), :class:`ColoRadarCalib` (everything of ``calib/`` radarpc
uses), :class:`RadarFOV` and the presets (:data:`AWR1843`, :data:`CASCADE`, :data:`DEFAULT_CALIB`).

The files of a ``calib/`` folder are read and written by :mod:`radarpc.data.coloradar_format`.

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
  Doppler in m/s). A chip's :class:`HeatmapConfig` is the dataset's heatmap grid (its
  ``heatmap_cfg.txt``), not RaLD's processing grid: RaLD's single-chip cube (128 range x 8 azimuth
  x 2 elevation FFT bins) is set by :func:`radarpc.dsp.tdm.radar_cube`'s own sizes.
* ``coupling_calib.txt`` holds ``num_tx x num_rx x num_range_bins`` complex values with
  ``num_range_bins`` the heatmap's (positive) range bins, half the range FFT of
  ``num_adc_samples_per_chirp`` samples: ``2 num_tx num_rx num_range_bins = num_tx num_rx
  num_adc_samples_per_chirp`` numbers (:attr:`ColoRadarChipConfig.coupling_shape`).
"""
from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np

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
    "AWR1843",
    "CASCADE",
    "AWR1843_FOV",
    "BASE_TO_SINGLE_CHIP",
    "BASE_TO_LIDAR",
    "BASE_TO_CASCADE",
    "BASE_TO_IMU",
    "DEFAULT_CALIB",
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
    def coupling_shape(self) -> tuple[int, int, int]:
        """Complex shape of ``coupling_calib.txt``: ``(num_tx, num_rx, heatmap num_range_bins)``.

        ColoRadar's tools read the ``data:`` line two ways that agree on the dataset's files:
        arpg/coloradar-library as ``num_tx num_rx num_range_bins`` interleaved (re, im) pairs with
        the heatmap's positive range bins, azinke/coloradar as ``num_tx num_rx 1
        num_adc_samples_per_chirp`` numbers; both hold when the heatmap keeps half of the
        ``num_adc_samples_per_chirp``-point range FFT, as the dataset's heatmaps do.
        """
        return (self.num_tx, self.num_rx, self.heatmap.num_range_bins)

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
    """Radar frustum used to crop LiDAR ground truth (RaLD: 0-15.86 m, +-90 deg, +-20 deg).

    The one frustum definition: :func:`radarpc.data.coloradar.frustum_mask` crops the LiDAR to it
    and RaLD's occupancy grid discretises it (:meth:`radarpc.rald.frustum.FrustumGrid.from_fov`).
    """

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
# the calibration of the rig
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ColoRadarCalib:
    """Everything of ColoRadar's ``calib/`` folder that radarpc uses or writes."""

    single_chip: ColoRadarChipConfig
    cascade: ColoRadarChipConfig | None
    base_to_single_chip: Transform
    base_to_lidar: Transform
    base_to_cascade: Transform | None
    base_to_imu: Transform | None = None    # the IMU (MicroStrain GX5) frame; read by ColoRadar's tools

    def lidar_to_single_chip(self) -> Transform:
        """``T_radar<-lidar = T_base_radar^-1 T_base_lidar`` (``p_radar = T p_lidar``)."""
        return self.base_to_single_chip.inverse() @ self.base_to_lidar

    def lidar_to_cascade(self) -> Transform:
        if self.base_to_cascade is None:
            raise ValueError("this calibration has no base_to_cascade transform "
                             "(calib/transforms/base_to_cascade.txt was absent; load_calib(..., cascade=True) requires it)")
        return self.base_to_cascade.inverse() @ self.base_to_lidar



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
    # virtual array with a 4-element raised row). Heatmap: the dataset's single-chip grid, which
    # keeps half of the 128-point range FFT (64 bins of c f_s / (2 S 128) = 0.124905712903 m, the
    # size rule of coupling_calib.txt that arpg/coloradar-library and azinke/coloradar both
    # read) over 64 azimuth x 8 elevation half-bin-centred beams (arpg/coloradar-library's
    # single-chip beam counts, whose cascade counts, 128 x 32, are the cascade heatmap's).
    wf = WaveformConfig(num_tx=3, num_rx=4, num_adc_samples_per_chirp=128, num_chirps_per_frame=128,
                        adc_sample_frequency=10_666_000.0, start_frequency=77e9, idle_time=110e-6,
                        adc_start_time=7e-6, ramp_end_time=19.1e-6, frequency_slope=1.00000000377e14)
    ant = AntennaConfig(3, 4, 76.8, ((0.0, 0.0), (4.0, 0.0), (2.0, 1.0)),
                        tuple((float(k), 0.0) for k in range(4)))
    d = 0.5 * wf.center_frequency / (ant.design_frequency_ghz * 1e9)
    hm = HeatmapConfig(num_range_bins=64, num_elevation_bins=8, num_azimuth_bins=64,
                       range_bin_width=0.124905712903, azimuth_bins=beam_angles(64, d, half_bin=True),
                       elevation_bins=beam_angles(8, d, half_bin=True))
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
"""TI AWR1843 single chip as used by RaLD (3 Tx, 4 Rx, 128 chirps x 128 samples, 77 GHz); heatmap
grid 8 el x 64 az x 64 range as the dataset's (RaLD's cube grid is :mod:`radarpc.dsp.tdm`'s)."""

CASCADE = _cascade()
"""TI MMWCAS 12 Tx x 16 Rx cascade; heatmaps 32 el x 128 az x 128 range."""

AWR1843_FOV = RadarFOV()
"""RaLD's crop: range <= 127 range bins (15.863 m), azimuth +-90 deg, elevation +-20 deg."""

# Rig transforms of ColoRadar's calib/transforms/ (base = the rig's imu_viz_link frame), with the
# 12 significant digits the dataset's files hold: the single chip and LiDAR as quoted by RaLD's
# preprocessing; the cascade and the IMU as the recordings' /tf messages give them and public code
# using the dataset copies them (the cascade shares the single chip's orientation).
BASE_TO_SINGLE_CHIP = Transform((-0.145, 0.09, -0.025), (0.0, 0.0, 0.706825181105, 0.707388269167))
BASE_TO_LIDAR = Transform((-0.075, -0.02, 0.03618), (0.0, 0.0, 0.721382357437, -0.692536998563))
BASE_TO_CASCADE = Transform((0.03, 0.12, -0.09), (0.0, 0.0, 0.706825181105, 0.707388269167))
BASE_TO_IMU = Transform((0.0, 0.0, 0.0), (0.707105451466, 0.707108048814, 0.000209535067884, 0.00020953429822))

DEFAULT_CALIB = ColoRadarCalib(AWR1843, CASCADE, BASE_TO_SINGLE_CHIP, BASE_TO_LIDAR, BASE_TO_CASCADE,
                               BASE_TO_IMU)
