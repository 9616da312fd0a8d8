"""Benchmark: spectral point clouds from full-size RADIal cubes, batched torch vs straightforward numpy.

Prints one JSON object per target density (0.007, 0.057, 0.56 by default) with, for the plain
cloud and for ``enrich=("rd3", "sector32")``: frames/s, ms/frame, points/frame, achieved density,
device, threads, the frames/s of two numpy baselines on the same frames and the speed ratios; plus
the process's peak RSS. Each configuration is timed with every beamformer that can run it
(:mod:`radarpc.dsp.beamform`): ``exact`` (whole float32 spectrum) and, without sector
descriptors, ``screened`` (certified bfloat16 screen), rows ``"<config>/<mode>"``; ``is_default``
marks the one ``beamforming="auto"`` picks on that device, and ``agree_with_exact`` is the
fraction of points whose direction equals the exact mode's.

The numpy baseline follows RADIal's ``SignalProcessing/rpl.py`` (one frame at a time:
``np.abs`` sum over Rx, CA-CFAR with ``scipy.signal.convolve2d``, a Python loop over peaks
building their Doppler index lists, one complex matmul with the calibration matrix, argmax), with
radarpc's default envelope (the seed's sum over the ``n_tx`` replica bins of each consolidated
cell, after a whole-map Tx-0 gap search, instead of rpl.py's sum over every slot), the same
window/guard convention and per-frame density
control as radarpc (tau chosen on the CFAR peaks ``S(tau)``, or with ``rd3`` on the encoded
neighbourhood set ``S*(tau)`` through a scipy max filter, see :func:`numpy_tau`), so that both
produce the same points (checked and reported as ``agree``).
It already runs the dominant beamforming as one BLAS matmul per frame. The second baseline,
``numpy_loop``, processes each peak on its own in a Python loop (matrix-vector beamforming).

With ``--radial-repo PATH`` (a local copy of valeoai/RADIal), it first prints ``rpl_comparison``:
RADIal's own ``SignalProcessing/rpl.py`` ``'PC'`` (run from that path, never copied; its
calibration is a pickled-dict ``.npy`` this script writes from its own simulated table) against
radarpc's beamforming modes with RADIal's CFAR (``CFAR_PRESETS['radial']``) on the same full-size
simulated cubes (``RadialSimulator``) and a 751 x 11 table: ms/frame, ratios, what ``auto`` runs,
and whether the points (range bin, Tx-0 Doppler bin, azimuth, elevation) are identical.

Usage::

    python benchmarks/pointcloud.py --threads 2 --frames 16 --batch 8
    python benchmarks/pointcloud.py --radial-repo path/to/RADIal --rpl-frames 8 --densities
"""
from __future__ import annotations

import argparse
import os
import sys


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2, help="torch / BLAS threads")
    p.add_argument("--frames", type=int, default=16, help="distinct simulated frames")
    p.add_argument("--batch", type=int, default=8, help="frames per forward call")
    p.add_argument("--repeats", type=int, default=5, help="timed passes (best and median reported)")
    p.add_argument("--numpy-frames", type=int, default=4, help="frames timed with the numpy baseline")
    p.add_argument("--loop-frames", type=int, default=4, help="frames timed with the per-peak-loop baseline")
    p.add_argument("--numpy-repeats", type=int, default=3,
                   help="timed passes of each numpy baseline over its frames (the best is reported)")
    p.add_argument("--densities", type=float, nargs="*", default=[0.007, 0.057, 0.56],
                   help="target densities of the main table (none: skip it, e.g. for --batch-sweep alone)")
    p.add_argument("--scatterers", type=int, default=60, help="point scatterers per simulated frame")
    p.add_argument("--device", default=None, help="torch device (default: cpu, and cuda if available)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch-sweep", type=int, nargs="*", default=[],
                   help="also time the default configuration at these batch sizes (density 0.057)")
    p.add_argument("--stages", action="store_true",
                   help="also print the per-stage wall time of one batch at density 0.057 (CPU)")
    p.add_argument("--radial-repo", default=None,
                   help="path of a local copy of valeoai/RADIal: also run its SignalProcessing/rpl.py 'PC' "
                        "side by side with radarpc under RADIal's CFAR settings (--rpl-frames simulated frames)")
    p.add_argument("--rpl-frames", type=int, default=4, help="simulated frames of the rpl.py comparison")
    p.add_argument("--rpl-modes", nargs="*", default=["exact", "subspace", "screened", "auto"],
                   help="radarpc beamforming modes timed in the rpl.py comparison")
    return p.parse_args()


ARGS = _parse() if __name__ == "__main__" else None
if ARGS is not None:  # BLAS threads must be fixed before numpy/torch load their thread pools
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(ARGS.threads)

import contextlib  # noqa: E402
import importlib  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import tempfile  # noqa: E402
import types  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy import signal  # noqa: E402
from scipy.ndimage import binary_dilation, maximum_filter  # noqa: E402

from radarpc.dsp import SpectralPointCloud  # noqa: E402
from radarpc.dsp.accel import DISABLE_ENV  # noqa: E402
from radarpc.dsp.accel.native import native_available  # noqa: E402
from radarpc.dsp.accel.screened import MAX_SCREEN_CANDIDATES, beamform_peaks_screened, screen_bound  # noqa: E402
from radarpc.dsp.beamform import beamform_peaks  # noqa: E402
from radarpc.dsp.beamform_modes import resolve_beamforming  # noqa: E402
from radarpc.dsp.cfar import ca_cfar  # noqa: E402
from radarpc.dsp.ddma import ddma_envelope, rx_magnitude_sum, virtual_snapshots  # noqa: E402
from radarpc.dsp.density import neighbourhood_mask  # noqa: E402
from radarpc.dsp.pointcloud import CFAR_PRESETS  # noqa: E402
from radarpc.sensors.radial import RADIAL, Calibration, DDMARadarConfig, steering_vectors  # noqa: E402
from radarpc.sim.radial_calibration import make_calibration  # noqa: E402
from radarpc.machine import cpu_model, numeric_libraries  # noqa: E402


# ---- the straightforward numpy implementation (rpl.py style) ---------------------------------------
def numpy_tau(snr: np.ndarray, cfg: DDMARadarConfig, density: float, rd_n: int | None) -> float:
    """Per-frame threshold of the encoded set, written independently of ``radarpc.dsp.density``.

    Without ``rd_n``: midpoint between the ``m``-th and ``(m + 1)``-th largest SNR,
    ``m = round(density * Nr * ND / n_tx)``. With ``rd_n = n``: the encoded set is
    ``P*(tau) = {D > tau}``, ``D`` the ``n x n`` max-filtered SNR (cells outside the grid count as
    ``-inf``); among the reachable counts (0 and ``#{D >= u}`` for every distinct value ``u`` of
    ``D``) take the one closest to ``m`` (a tie goes to the smaller count) and put tau midway
    between the two distinct values of ``D`` around it.
    """
    m = int(round(density * cfg.n_range * cfg.n_doppler / cfg.n_tx))
    if rd_n is None:
        top = np.sort(snr.ravel())[::-1]
        return 0.5 * (top[m - 1] + top[m])
    d = maximum_filter(snr, size=(rd_n, rd_n), mode="constant", cval=-np.inf)
    values, counts = np.unique(d, return_counts=True)                  # ascending distinct values
    reachable = np.concatenate([np.cumsum(counts[::-1])[::-1], [0]])   # #{D >= values[i]}, then 0
    dist = np.abs(reachable - m)
    i = int(np.flatnonzero(dist == dist.min()).max())                  # closest; a tie -> the smaller count
    if i == len(values):                                               # count 0: nothing exceeds the max
        return float(values[-1])
    if i == 0:                                                         # every cell: below the minimum
        return float(values[0]) - 1.0
    return 0.5 * (float(values[i - 1]) + float(values[i]))


class NumpyPointCloud:
    """Per-frame numpy spectral point cloud, written like RADIal's ``rpl.py``."""

    def __init__(self, cfg: DDMARadarConfig, calib: Calibration, density: float,
                 window=(9, 9), guard=(3, 3), rd_n: int | None = None, sectors: int | None = None):
        self.cfg, self.density, self.rd_n, self.sectors = cfg, density, rd_n, sectors
        hw, hg = window[0] // 2, guard[0] // 2
        self.mask = np.ones((window[0], window[1]))
        self.mask[hw - hg:hw + hg + 1, hw - hg:hw + hg + 1] = 0
        self.count = signal.convolve2d(np.ones((cfg.n_range, cfg.slot_width)), self.mask, mode="same")
        self.calib_mat = np.moveaxis(calib.signal, 2, 1).reshape(-1, calib.n_virtual)  # (n_az*n_el, n_virtual)
        self.window = calib.window
        self.az, self.el = calib.azimuth_deg, calib.elevation_deg
        self.n_el = len(calib.elevation_deg)
        self.dividend = np.arange(0, cfg.n_doppler, cfg.slot_width)

    def envelope(self, rd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``A = sum_rx |R|`` ``(Nr, Nd)``, the Tx-0 bin ``d0`` of every consolidated cell
        ``(Nr, W)`` (the slot after which the ``n_empty_slots`` slots have the least power) and the
        CA-CFAR SNR of the seed's envelope ``E(r, l) = sum_m A(r, d0 + doppler_offsets[m])``."""
        cfg = self.cfg
        power_spectrum = np.sum(np.abs(rd), axis=2)                                    # (Nr, Nd)
        slots = power_spectrum.reshape(cfg.n_range, cfg.n_slots, cfg.slot_width)      # (Nr, n_slots, W)
        gap = sum(np.roll(slots, -k, axis=1) for k in range(1, cfg.n_empty_slots + 1))  # slots s+1..s+g
        d0 = np.argmin(gap, axis=1) * cfg.slot_width + np.arange(cfg.slot_width)       # (Nr, W)
        cols = (d0[:, :, None] + np.asarray(cfg.doppler_offsets)) % cfg.n_doppler      # (Nr, W, n_tx)
        reduced = np.take_along_axis(power_spectrum, cols.reshape(cfg.n_range, -1), axis=1) \
            .reshape(cols.shape).sum(-1)                                               # E: (Nr, W)
        p = reduced ** 2
        snr = p / (signal.convolve2d(p, self.mask, mode="same") / self.count)
        return power_spectrum, d0, snr

    def __call__(self, rd: np.ndarray) -> dict[str, np.ndarray]:
        cfg = self.cfg
        power_spectrum, d0_map, snr = self.envelope(rd)
        tau = numpy_tau(snr, cfg, self.density, self.rd_n)           # on S, or on S* with rdN
        peaks = snr > tau
        kept = peaks
        if self.rd_n is not None:
            kept = binary_dilation(peaks, np.ones((self.rd_n, self.rd_n), dtype=bool))
        range_bins, doppler_conv = np.where(kept)
        d0 = d0_map[range_bins, doppler_conv]                        # Tx-0 bins from the envelope's search
        doppler_indexes = []
        for d in d0:                                                                     # per-peak loop
            seq = np.remainder(d + self.dividend, cfg.n_doppler)
            doppler_indexes.append(np.concatenate([[seq[0]], seq[cfg.n_empty_slots + 1:]]))
        mimo = rd[[[r] for r in range_bins], doppler_indexes, :].reshape(len(d0), -1)
        mimo = mimo * self.window
        aspec = np.abs(self.calib_mat @ mimo.T)                                         # (n_dir, P)
        k = np.argmax(aspec, axis=0)
        out = {"range_bin": range_bins, "doppler_full": d0, "k": k,
               "amplitude": aspec[k, np.arange(len(k))],
               "azimuth_deg": self.az[k // self.n_el], "elevation_deg": self.el[k % self.n_el]}
        if self.sectors is not None:
            grid = aspec.T.reshape(len(k), len(self.az), self.n_el)
            n_az = len(self.az)
            out["sector"] = np.stack([grid[:, (u * n_az) // self.sectors: -(-((u + 1) * n_az) // self.sectors)]
                                      .max(axis=(1, 2)) for u in range(self.sectors)], axis=1)
        return out


class NumpyLoopPointCloud(NumpyPointCloud):
    """The same, but every peak processed on its own in a Python loop (Tx-0 search, snapshot,
    matrix-vector beamforming, argmax, sectors): the most literal reading of the seed's equations."""

    def __call__(self, rd: np.ndarray) -> dict[str, np.ndarray]:
        cfg = self.cfg
        power_spectrum, _, snr = self.envelope(rd)
        kept = snr > numpy_tau(snr, cfg, self.density, self.rd_n)
        if self.rd_n is not None:
            kept = binary_dilation(kept, np.ones((self.rd_n, self.rd_n), dtype=bool))
        g = cfg.n_empty_slots
        out: dict[str, list] = {"range_bin": [], "doppler_full": [], "k": [], "amplitude": [],
                                "azimuth_deg": [], "elevation_deg": [], "sector": []}
        n_az = len(self.az)
        for r, l in zip(*np.nonzero(kept)):
            x = power_spectrum[r, l::cfg.slot_width]
            sums = [sum(x[(s + 1 + i) % cfg.n_slots] for i in range(g)) for s in range(cfg.n_slots)]
            d0 = int(np.argmin(sums)) * cfg.slot_width + l
            v = np.concatenate([rd[r, (d0 + off) % cfg.n_doppler] for off in cfg.doppler_offsets]) * self.window
            spec = np.abs(self.calib_mat @ v)
            k = int(np.argmax(spec))
            out["range_bin"].append(r)
            out["doppler_full"].append(d0)
            out["k"].append(k)
            out["amplitude"].append(spec[k])
            out["azimuth_deg"].append(self.az[k // self.n_el])
            out["elevation_deg"].append(self.el[k % self.n_el])
            if self.sectors is not None:
                grid = spec.reshape(n_az, self.n_el)
                out["sector"].append([grid[(u * n_az) // self.sectors: -(-((u + 1) * n_az) // self.sectors)].max()
                                      for u in range(self.sectors)])
        return {k: np.asarray(v) for k, v in out.items()}


# ---- helpers ---------------------------------------------------------------------------------------
def simulate(cfg: DDMARadarConfig, n: int, k: int, seed: int) -> torch.Tensor:
    """``n`` full-size frames of ``k`` random point scatterers each plus thermal noise."""
    try:
        from radarpc.sim.rd import Scatterers, synthesize_rd
    except ImportError:  # simulator absent: noise plus injected on-grid targets
        return _noise_and_targets(cfg, n, k, seed)
    g = torch.Generator().manual_seed(seed)
    scenes = []
    for _ in range(n):
        u = torch.rand(5, k, generator=g)
        scenes.append(Scatterers(range_m=3 + u[0] * 0.9 * cfg.max_range_m, azimuth_deg=(u[1] - 0.5) * 150,
                                 elevation_deg=(u[2] - 0.5) * 8,
                                 velocity_mps=(u[3] - 0.5) * 1.9 * cfg.max_velocity_mps,
                                 rcs_m2=0.5 + 30 * u[4] ** 2))
    return synthesize_rd(cfg, scenes, noise=True, generator=g)


def _noise_and_targets(cfg: DDMARadarConfig, n: int, k: int, seed: int) -> torch.Tensor:
    from radarpc.sensors.radial import steering_vectors
    rng = np.random.default_rng(seed)
    rd = (rng.standard_normal((n, *cfg.rd_shape)) + 1j * rng.standard_normal((n, *cfg.rd_shape))) / np.sqrt(2)
    for b in range(n):
        for _ in range(k):
            r, d = rng.integers(cfg.n_range), rng.integers(cfg.n_doppler)
            a = steering_vectors(cfg, rng.uniform(-75, 75), 0.0).reshape(cfg.n_tx, cfg.n_rx)
            amp = 10 ** rng.uniform(0.5, 2.5)
            for m, off in enumerate(cfg.doppler_offsets):
                rd[b, r, (d + off) % cfg.n_doppler] += amp * a[m]
    return torch.from_numpy(rd.astype(np.complex64))


def time_numpy(impl, frames: np.ndarray, repeats: int) -> tuple[list[dict], float]:
    """Outputs of a numpy baseline on ``frames`` and its best wall time over ``repeats`` passes
    (the same best-of rule as radarpc's timing)."""
    best, out = float("inf"), []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = [impl(f) for f in frames]
        best = min(best, time.perf_counter() - t0)
    return out, best


def time_torch(spc: SpectralPointCloud, batches: list[torch.Tensor], repeats: int, device: torch.device):
    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    out = [spc(b) for b in batches]                   # warm-up
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = [spc(b) for b in batches]
        sync()
        times.append(time.perf_counter() - t0)
    return times, out


def stage_times(spc: SpectralPointCloud, batch: torch.Tensor, repeats: int) -> dict[str, float]:
    """Best-of-``repeats`` wall time per frame (ms) of each stage of ``spc.forward`` on ``batch``,
    rebuilt from the same public functions; ``sector pooling`` is the beamforming time with sectors
    minus the time without."""
    cfg, c = spc.sensor, spc.config
    tables = spc.tables(batch.device)
    best: dict[str, float] = {}

    def tick(name: str, t0: float) -> float:
        t1 = time.perf_counter()
        best[name] = min(best.get(name, float("inf")), t1 - t0)
        return t1

    for _ in range(repeats + 1):                                   # first pass: warm-up, overwritten
        t = time.perf_counter()
        a = rx_magnitude_sum(batch)                                # (B, Nr, Nd)
        t = tick("sum_rx |RD| (whole cube)", t)
        env = ddma_envelope(a, cfg)
        e = env.envelope(c.envelope)                               # (B, Nr, W)
        t = tick("Tx-0 gap search + replica envelope", t)
        snr = ca_cfar(e.square(), c.window, c.guard).snr
        tau = spc.thresholds(snr)
        kept = snr > tau[:, None, None]
        if c.neighbourhood is not None:
            kept = neighbourhood_mask(kept, c.neighbourhood)
        t = tick("CA-CFAR + density threshold (+ rdN mask)", t)
        b, r, l = torch.nonzero(kept, as_tuple=True)
        d0 = env.tx0_doppler(b, r, l)
        v = virtual_snapshots(batch, cfg, b, r, d0)                # (P, n_virtual)
        t = tick("snapshot gather", t)
        beamform_peaks(v, tables, spc.grid, None, workspace=spc.workspace)
        t = tick("beamforming GEMM + argmax", t)
        if c.sectors is not None:
            beamform_peaks(v, tables, spc.grid, c.sectors, workspace=spc.workspace)
            t = tick("beamforming with sectors", t)
        else:
            beamform_peaks_screened(v, tables, spc.grid, workspace=spc.workspace)
            t = tick("screened beamforming", t)
            if native_available():                                 # the same on the torch paths
                prev = os.environ.get(DISABLE_ENV)
                os.environ[DISABLE_ENV] = "1"
                try:
                    beamform_peaks_screened(v, tables, spc.grid, workspace=spc.workspace)
                    t = tick("screened beamforming, torch selection (RADARPC_NO_NATIVE=1)", t)
                    rx_magnitude_sum(batch)
                    t = tick("sum_rx |RD|, torch (RADARPC_NO_NATIVE=1)", t)
                finally:
                    if prev is None:
                        del os.environ[DISABLE_ENV]
                    else:
                        os.environ[DISABLE_ENV] = prev
        spc(batch)
        tick("whole forward", t)
        if _ == 0:
            best.clear()
    n = batch.shape[0]
    out = {k: round(1e3 * val / n, 2) for k, val in best.items()}
    if c.sectors is not None:
        out["sector pooling"] = round(out.pop("beamforming with sectors") - out["beamforming GEMM + argmax"], 2)
    out["points_per_frame"] = round(int(kept.sum()) / n, 1)
    return out


def screen_statistics(spc: SpectralPointCloud, batch: torch.Tensor, sectors: int = 32) -> dict[str, float]:
    """What the screened beamformer's bound leaves on the points of ``batch`` (``spc``'s
    detection), recomputed here independently of its selection code: the float64 exact spectrum,
    this machine's bfloat16 screen GEMM and :func:`screen_bound`. Returns the mean number of
    candidate directions and azimuths per point, the fraction of points with more than
    ``MAX_SCREEN_CANDIDATES`` azimuths (left to the exact GEMM), the largest observed
    ``| |s^| - |s| | / bound``, and the mean number of directions that could hold one of
    ``sectors`` azimuth-sector maxima (what screening the sector descriptor would leave)."""
    enc = spc.encode(batch)
    b, r, l = torch.nonzero(enc.kept, as_tuple=True)
    v = virtual_snapshots(batch, spc.sensor, b, r, enc.envelope.tx0_doppler(b, r, l)).contiguous()
    t = spc.tables(batch.device)
    n_az, n_el = t.grid
    k_dir = t.n_dir
    y = torch.mm(torch.view_as_real(v).reshape(len(v), -1).to(torch.bfloat16), t.screen_bf16).double()
    q = torch.hypot(y[:, :k_dir], y[:, k_dir:])                                 # (P, K) el-major
    exact = (v.to(torch.complex128) @ torch.complex(t.re.double(), t.im.double())).abs()
    alpha, beta = screen_bound(v, t.row_norm_max)
    beta = beta.double()[:, None]
    ratio = float(((q - exact).abs() / (alpha * q + beta)).max())
    upper, lower = (1 + alpha) * q + beta, (1 - alpha) * q - beta
    cand = upper >= lower.amax(1, keepdim=True)                                  # (P, K)
    n_azimuths = cand.view(-1, n_el, n_az).any(1).sum(1)
    light = (n_azimuths >= 1) & (n_azimuths <= MAX_SCREEN_CANDIDATES)
    sec = 0
    for u in range(sectors):                                                    # adaptive-pooling sectors
        cols = torch.arange(u * n_az // sectors, -(-(u + 1) * n_az // sectors))
        up, lo = upper.view(-1, n_el, n_az)[:, :, cols], lower.view(-1, n_el, n_az)[:, :, cols]
        sec = sec + (up.flatten(1) >= lo.flatten(1).amax(1, keepdim=True)).sum(1)
    return {"points": len(v), "candidate_directions_per_point": round(float(cand[light].sum(1).double().mean()), 2),
            "candidate_azimuths_per_point": round(float(n_azimuths[light].double().mean()), 2),
            "fraction_left_to_exact_gemm": round(float((~light).double().mean()), 4),
            "max_error_over_bound": round(ratio, 3),
            f"sector{sectors}_candidate_directions_per_point": round(float(sec.double().mean()), 1),
            "directions": k_dir}


# ---- side by side with RADIal's own rpl.py ------------------------------------------------------
def real_size_calibration(cfg: DDMARadarConfig, seed: int = 7) -> Calibration:
    """A measured-like table of RADIal's real size (751 azimuths at 0.2 deg over +-75 deg, 11
    elevations over +-15 deg): the sensor's own when its grid already is that size, else steering
    vectors with random per-channel gain/phase errors and 1 % complex noise per entry."""
    if tuple(int(n) for n in (cfg.az_grid_deg[2], cfg.el_grid_deg[2])) == (751, 11):
        return make_calibration(cfg)
    rng = np.random.default_rng(seed)
    az, el = np.linspace(-75.0, 75.0, 751), np.linspace(-15.0, 15.0, 11)
    a = steering_vectors(cfg, az[:, None], el[None, :])                        # (751, 11, V)
    gain = 10 ** (rng.normal(0, 0.5, a.shape[-1]) / 20) * np.exp(1j * np.deg2rad(rng.normal(0, 5, a.shape[-1])))
    a = a * gain * (1 + 0.01 * (rng.standard_normal(a.shape) + 1j * rng.standard_normal(a.shape)) / np.sqrt(2))
    return Calibration(signal=np.conj(np.moveaxis(a, 2, 1)).astype(np.complex64),
                       window=np.hamming(a.shape[-1]).astype(np.float32),
                       azimuth_deg=az.astype(np.float32), elevation_deg=el.astype(np.float32))


def load_rpl(repo: str, calib: Calibration, workdir: str):
    """RADIal's ``RadarSignalProcessing(method='PC')`` from ``repo``, on ``calib`` written as the
    pickled-dict ``.npy`` rpl.py loads (a file this benchmark wrote itself). rpl.py imports CuPy
    and mkl_fft at module level but its CPU 'PC' path from RD cubes uses neither: missing ones are
    replaced by empty modules for the import."""
    path = os.path.join(workdir, "CalibrationTable.npy")
    np.save(path, np.array({"Signal": calib.signal, "H": calib.window[None, :].astype(np.float32),
                            "Azimuth_table": calib.azimuth_deg, "Elevation_table": calib.elevation_deg},
                           dtype=object), allow_pickle=True)
    src = os.path.join(os.path.abspath(repo), "SignalProcessing")
    if not os.path.isfile(os.path.join(src, "rpl.py")):
        raise SystemExit(f"--radial-repo {repo!r}: no SignalProcessing/rpl.py there")
    for name in ("cupy", "mkl_fft"):
        try:
            importlib.import_module(name)
        except ImportError:
            sys.modules[name] = types.ModuleType(name)
    sys.path.insert(0, src)
    try:
        rpl = importlib.import_module("rpl")
    finally:
        sys.path.remove(src)
    with contextlib.redirect_stdout(io.StringIO()):                            # it prints its device
        return rpl.RadarSignalProcessing(path, method="PC", device="cpu")


def rpl_comparison(args: argparse.Namespace, cfg: DDMARadarConfig) -> dict:
    """ms/frame of rpl.py's 'PC' and of radarpc's beamforming modes on the same full-size
    simulated cubes with RADIal's CFAR (``CFAR_PRESETS['radial']``), the ratios, and whether the
    points (range bin, Tx-0 Doppler bin, azimuth, elevation) are identical."""
    from radarpc.sim.radial_writer import RadialSimulator
    calib = real_size_calibration(cfg)
    sim = RadialSimulator(cfg, 1, args.rpl_frames, seed=args.seed)
    frames = torch.stack([sim.frame(0, i).rd for i in range(args.rpl_frames)])  # (F, Nr, Nd, Nrx)
    frames_np = frames.numpy()
    with tempfile.TemporaryDirectory() as d:
        rsp = load_rpl(args.radial_repo, calib, d)
    get_pcl = rsp._RadarSignalProcessing__get_PCL                            # RD cube -> points
    ref, rpl_s = time_numpy(get_pcl, frames_np, args.numpy_repeats)
    az_tab = np.deg2rad(calib.azimuth_deg.astype(np.float64))
    el_tab = np.deg2rad(calib.elevation_deg.astype(np.float64))

    def rpl_points(pc: np.ndarray) -> set:
        r = np.rint(pc[:, 0] / 103.0 * cfg.n_range).astype(int)
        a = np.abs(pc[:, 2][:, None] - az_tab[None]).argmin(1)
        e = np.abs(pc[:, 3][:, None] - el_tab[None]).argmin(1)
        return set(zip(r.tolist(), pc[:, 1].astype(int).tolist(), a.tolist(), e.tolist()))

    theirs = [rpl_points(pc) for pc in ref]
    report = {"rpl_comparison": {"frames": args.rpl_frames, "angle_grid": list(calib.grid_shape),
                                 "cfar": "radial (rpl.py: 19 x 19 window, 7 x 7 guard, 2 dB, all-slot envelope)",
                                 "points_per_frame_rpl": round(sum(len(t) for t in theirs) / len(theirs), 1),
                                 "rpl_ms_per_frame": round(1e3 * rpl_s / len(frames_np), 2),
                                 "threads": args.threads, "cpu": cpu_model(), "results": []}}
    out = report["rpl_comparison"]
    batches = [frames[i:i + args.batch] for i in range(0, args.rpl_frames, args.batch)]
    points = {}
    for mode in args.rpl_modes:
        spc = SpectralPointCloud(cfg, calib, **CFAR_PRESETS["radial"], beamforming=mode)
        chosen = resolve_beamforming(mode, torch.device("cpu"), None, spc.tables("cpu"))  # auto measures here
        times, clouds = time_torch(spc, batches, args.repeats, torch.device("cpu"))
        ms = 1e3 * min(times) / args.rpl_frames
        mine = []
        for c in clouds:
            for b in range(len(c)):
                f = c.frame(b)
                a = torch.as_tensor(calib.azimuth_deg)[None] - f.azimuth_deg[:, None]
                e = torch.as_tensor(calib.elevation_deg)[None] - f.elevation_deg[:, None]
                mine.append(set(zip(f.range_bin.tolist(), f.doppler_full.tolist(), a.abs().argmin(1).tolist(),
                                    e.abs().argmin(1).tolist())))
        points[mode] = mine
        same = sum(len(m & t) for m, t in zip(mine, theirs))
        total = sum(max(len(m), len(t)) for m, t in zip(mine, theirs))
        out["results"].append({"mode": mode, "runs": chosen, "ms_per_frame": round(ms, 2),
                               "speedup_vs_rpl": round(out["rpl_ms_per_frame"] / ms, 2),
                               "points_identical_to_rpl": round(same / max(total, 1), 5),
                               "points_identical_to_exact": (None if "exact" not in points else
                                                             points[mode] == points["exact"])})
    out["load_avg_1min"] = os.getloadavg()[0]
    return report


def main(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    if args.radial_repo:
        print(json.dumps(rpl_comparison(args, RADIAL)), flush=True)
    cfg = RADIAL
    calib = make_calibration(cfg)
    frames = simulate(cfg, args.frames, args.scatterers, args.seed)                 # (F, 512, 256, 16)
    devices = [torch.device(args.device)] if args.device else \
        [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    frames_np = frames[: args.numpy_frames].numpy()
    configs = {"plain": (), "rd3+sector32": ("rd3", "sector32")}
    for density in args.densities:
        report: dict = {"density_target": density, "frames": args.frames, "batch": args.batch,
                        "frame_shape": list(cfg.rd_shape), "angle_grid": list(calib.grid_shape),
                        "threads": args.threads, "cpu": cpu_model(),
                        "libraries": numeric_libraries(), "load_avg_1min": os.getloadavg()[0], "results": []}
        for name, enrich in configs.items():
            npc = NumpyPointCloud(cfg, calib, density, rd_n=3 if "rd3" in enrich else None,
                                  sectors=32 if "sector32" in enrich else None)
            npc(frames_np[0])
            ref, np_s = time_numpy(npc, frames_np, args.numpy_repeats)
            np_fps = len(frames_np) / np_s
            loop = NumpyLoopPointCloud(cfg, calib, density, rd_n=npc.rd_n, sectors=npc.sectors)
            n_loop = max(1, min(args.loop_frames, len(frames_np)))
            ref_loop, loop_s = time_numpy(loop, frames_np[:n_loop], args.numpy_repeats)
            loop_fps = n_loop / loop_s
            assert np.array_equal(ref_loop[0]["doppler_full"], ref[0]["doppler_full"])
            # every beamformer that can run this config: sector descriptors always run "exact"
            modes = ("exact",) if "sector32" in enrich else ("exact", "subspace", "screened")
            for device, mode in ((d, m) for d in devices for m in modes):
                spc = SpectralPointCloud(cfg, calib, density=density, enrich=enrich, beamforming=mode).to(device)
                batches = [frames[i:i + args.batch].to(device) for i in range(0, args.frames, args.batch)]
                times, out = time_torch(spc, batches, args.repeats, device)
                best, med = min(times), statistics.median(times)
                clouds = [c.to("cpu") for c in out]
                pts = sum(c.num_points for c in clouds) / args.frames
                dens = float(torch.cat([c.density for c in clouds]).mean())
                # agreement with the numpy baseline on its frames (same cells, d0 and direction)
                agree, total = 0, 0
                first = clouds[0]
                for b, r in enumerate(ref[: len(first)]):
                    c = first.frame(b)
                    mine = set(zip(c.range_bin.tolist(), c.doppler_full.tolist(), c.azimuth_deg.tolist(),
                                   c.elevation_deg.tolist()))
                    theirs = set(zip(r["range_bin"].tolist(), r["doppler_full"].tolist(),
                                     r["azimuth_deg"].astype(np.float32).tolist(),
                                     r["elevation_deg"].astype(np.float32).tolist()))
                    agree += len(mine & theirs)
                    total += max(len(mine), len(theirs))
                fps_best = args.frames / best
                extra = {}
                if mode == "exact":
                    exact_clouds = clouds
                else:  # same cells by construction; fraction of points whose direction equals exact's
                    ea = torch.cat([c.azimuth_deg for c in exact_clouds])
                    ee = torch.cat([c.elevation_deg for c in exact_clouds])
                    fa = torch.cat([c.azimuth_deg for c in clouds])
                    fe = torch.cat([c.elevation_deg for c in clouds])
                    extra["agree_with_exact"] = round(float(((ea == fa) & (ee == fe)).double().mean()), 5)
                default = resolve_beamforming("auto", device, spc.config.sectors, spc.tables(device))
                report["results"].append({
                    "config": f"{name}/{mode}", "device": str(device), "beamforming": mode,
                    "is_default": mode == default,
                    "frames_per_s": round(fps_best, 1), "frames_per_s_median": round(args.frames / med, 1),
                    "ms_per_frame": round(1e3 * best / args.frames, 2),
                    "points_per_frame": round(pts, 1), "density_achieved": round(dens, 5),
                    "numpy_frames_per_s": round(np_fps, 2), "speedup_vs_numpy": round(fps_best / np_fps, 1),
                    "numpy_loop_frames_per_s": round(loop_fps, 2),
                    "speedup_vs_numpy_loop": round(fps_best / loop_fps, 1),
                    "agree_with_numpy": round(agree / max(total, 1), 4), **extra})
        report["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
        print(json.dumps(report), flush=True)
    if args.batch_sweep:
        sweep = {"batch_sweep": [], "density_target": 0.057, "frames": args.frames, "threads": args.threads,
                 "device": "cpu", "load_avg_1min": os.getloadavg()[0]}
        for name, enrich in configs.items():
            spc = SpectralPointCloud(cfg, calib, density=0.057, enrich=enrich)     # beamforming="auto"
            mode = resolve_beamforming("auto", torch.device("cpu"), spc.config.sectors, spc.tables("cpu"))
            for bs in args.batch_sweep:
                batches = [frames[i:i + bs] for i in range(0, args.frames, bs)]
                times, _ = time_torch(spc, batches, args.repeats, torch.device("cpu"))
                sweep["batch_sweep"].append({"config": f"{name}/{mode}", "batch": bs,
                                             "frames_per_s": round(args.frames / min(times), 1),
                                             "ms_per_frame": round(1e3 * min(times) / args.frames, 2)})
        print(json.dumps(sweep), flush=True)
    if args.stages:
        batch = frames[: args.batch]
        stages = {name: stage_times(SpectralPointCloud(cfg, calib, density=0.057, enrich=enrich), batch,
                                    args.repeats)
                  for name, enrich in configs.items()}
        screen = screen_statistics(SpectralPointCloud(cfg, calib, density=0.057), batch)
        print(json.dumps({"stages_ms_per_frame": stages, "screen_statistics": screen,
                          "density_target": 0.057, "batch": args.batch,
                          "threads": args.threads, "device": "cpu",
                          "load_avg_1min": os.getloadavg()[0]}), flush=True)


if __name__ == "__main__":
    main(ARGS)
    sys.exit(0)
