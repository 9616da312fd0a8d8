"""ColoRadar-format synthesis: radar scatterers, single-chip ADC frames, cascade heatmaps, LiDAR.

One scene (:mod:`radarpc.sim.indoor`) feeds every sensor:

* :func:`radar_scatterers` -- point scatterers on the surfaces visible from the radar (ray cast
  over the field of view with per-frame jitter). Radar cross-section of a patch seen at incidence
  ``theta``: ``sigma = r^2 dOmega * sigma0 * (cos(theta) + k_s exp(-(theta / theta_s)^2))`` --
  diffuse plus a specular lobe, so flat walls return strongly only near normal incidence (sparse,
  noisy radar clouds). Vertical box edges are added as strong point scatterers when visible;
  optional multipath ghosts are the mirror images of the strongest scatterers across the scene's
  dominant planes (floor, a wall). Radial velocity ``v_r = (v_obj - v_sensor) . u`` (receding > 0).
* :func:`beat_signal` / :func:`synthesize_tdm_adc` -- TDM-MIMO FMCW beat signal of all scatterers,
  every Tx x Rx x chirp x sample, vectorized in torch, chunked over scatterers::

      s[t, r, c, k] = sum_n A_n exp(j 2 pi [ f0 tau_n(t, c) - S tau_n(t, c)^2 / 2 + S tau_n t_k ])
                              exp(j 2 pi d (p_h[t, r] u_y,n + p_v[t, r] u_z,n))

  with ``tau_n(t, c) = 2 (R_n + v_n T(t, c)) / c``, ``T(t, c) = (c N_tx + t) T_c`` the chirp start
  time and ``t_k = t_adc + k / f_s``; ``A_n = g sqrt(sigma_n) / R_n^2`` (radar equation, ``g`` in
  ADC LSB). ``exact=True`` evaluates this phase for every (t, r, c, k). The default splits
  ``S tau t_k = S tau t_ctr + S tau (t_k - t_ctr)`` (``t_ctr`` the centre of the ADC window).
  With ``tau = a + b T`` the second term is ``S (a + b T_g)(t_k - t_ctr) + S b (T - T_g)(t_k - t_ctr)``;
  the last (range-migration) coupling is the only non-separable factor. The (tx, chirp) slots are
  split, in time order, into ``G`` groups of ``L`` consecutive slots with reference times ``T_g``
  (group centres); within a group the coupling ``exp(j eps)``,
  ``eps = 2 pi S b_n (T - T_g)(t_k - t_ctr)``, is replaced by its first-order expansion
  ``1 + j eps``, whose error per scatterer (relative to its amplitude) is at most::

      eps^2 / 2,   |eps| <= 2 pi S max|b_n| ((L - 1) / 2) T_c max|t_k - t_ctr|,   eps^2 / 2 <= coupling_tol

  ``L`` is chosen per chunk of scatterers from the largest ``|v_n|`` (:func:`coupling_group_size`;
  ``L`` = all slots, ``G = 1`` and no correction for a static chunk; ``L = 1`` is exact in this
  term). ``T - T_g`` does not depend on the scatterer, so within a group everything separates into a
  (slot, Rx) factor and an (n, sample) factor ``[K_g | K_g D]``, ``D = j 2 pi S b_n (t_k - t_ctr)``,
  and the sum over scatterers is one complex GEMM per group ``(slots_g rx x N) @ (N x 2 samples)``
  (twice the flops of a single uncorrected GEMM; phases in float64, reduced modulo 2 pi, cos/sin in
  float32; the group sample phasors ``K_g`` are stepped from group to group by a per-scatterer step
  phasor and re-anchored every 32 groups). Then complex Gaussian noise and int16 I/Q quantization.
* :func:`cascade_heatmap` -- ColoRadar cascade heatmaps computed in the frequency domain: for each
  scatterer the Hann-windowed range-FFT response ``|W(r - R_n / dr)|^2`` times the beamformer
  power ``|AF(az, el)|^2`` of the cascade's unique virtual elements steered at the heatmap's bin
  angles, summed incoherently over scatterers, plus exponential noise; intensity is SNR per cell
  (linear), the Doppler channel is the power-weighted radial velocity quantized to Doppler bins
  (a random bin where noise dominates). Layout float32 ``[elevation, azimuth, range, 2]``. The
  beamformer is factorized over the array's rows (real GEMMs on small cache-sized blocks of
  scatterers) and the sum over scatterers of range response x beam power is one float32 GEMM.
* :func:`lidar_scan` -- a spinning multi-beam LiDAR (OS1-64-like: 64 beams over +-16.6 deg, 1024
  azimuth steps) ray cast against the same geometry; range noise, intensity from reflectivity and
  incidence; rays without return are written as all-zero points (organized scan, as in ColoRadar).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from radarpc.sensors.coloradar import (
    AWR1843,
    CASCADE,
    DEFAULT_CALIB,
    SPEED_OF_LIGHT,
    ColoRadarCalib,
    ColoRadarChipConfig,
    Transform,
)
from radarpc.sim.indoor import MATERIALS, Scene, ray_cast

__all__ = [
    "RadarSimConfig",
    "LidarConfig",
    "Scatterers",
    "SimFrame",
    "radar_scatterers",
    "coupling_group_size",
    "beat_signal",
    "synthesize_tdm_adc",
    "cascade_heatmap",
    "lidar_directions",
    "lidar_scan",
    "sensor_pose",
    "simulate_frame",
]


@dataclass(frozen=True)
class RadarSimConfig:
    """How scatterers are drawn and how the ADC is scaled."""

    az_step_deg: float = 1.5          # ray grid over the radar FOV (jittered per frame)
    el_step_deg: float = 2.0
    fov_az_deg: float = 90.0          # half-widths of the sampled field of view
    fov_el_deg: float = 25.0
    max_range_m: float = 16.5
    min_range_m: float = 0.3
    edges: bool = True                # strong points on visible vertical box edges
    edge_spacing_m: float = 0.3
    edge_rcs_m2: float = 0.02         # per edge point, times (1 + sqrt(specular gain))
    multipath: bool = True            # mirror ghosts of the strongest scatterers
    ghost_count: int = 40
    ghost_gain: float = 0.3           # amplitude factor of a ghost
    max_scatterers: int = 4000        # keep the strongest if more
    # ADC scale: recorded 16-bit AWR1843/DCA1000 frames use a few percent of the int16 range
    # (even strong returns within about +-1600 LSB). 400 LSB puts the simulated scenes there
    # (largest |I|, |Q| about 1600 over 80 frames of every scene kind), inside the +-2048 a
    # float16 cast (azinke/coloradar's reader) keeps exact. The noise scales with the gain (it was
    # 4 LSB at 1000), so every scatterer's SNR is unchanged.
    adc_gain_lsb: float = 400.0       # amplitude (LSB) of a 1 m^2 target at 1 m
    adc_noise_lsb: float = 1.6        # thermal noise std per I and Q (LSB)
    heatmap_noise: float = 1.0        # mean noise power per heatmap cell

    def __post_init__(self) -> None:
        for k in ("az_step_deg", "el_step_deg", "max_range_m", "adc_gain_lsb", "heatmap_noise"):
            if not getattr(self, k) > 0:
                raise ValueError(f"RadarSimConfig.{k} must be > 0, got {getattr(self, k)}")
        if self.adc_noise_lsb < 0 or self.ghost_gain < 0:
            raise ValueError("adc_noise_lsb and ghost_gain must be >= 0")


@dataclass(frozen=True)
class LidarConfig:
    """Spinning LiDAR pattern (defaults: Ouster OS1-64-like)."""

    beams: int = 64
    azimuth_steps: int = 1024
    elevation_deg: tuple[float, float] = (-16.6, 16.6)
    max_range_m: float = 120.0
    range_noise_m: float = 0.015
    dropout: float = 0.01             # fraction of returns randomly lost

    def __post_init__(self) -> None:
        if self.beams < 1 or self.azimuth_steps < 1:
            raise ValueError(f"LiDAR needs beams >= 1 and azimuth_steps >= 1, got {self.beams}, {self.azimuth_steps}")
        if not self.elevation_deg[0] <= self.elevation_deg[1]:
            raise ValueError(f"elevation_deg must be (low, high), got {self.elevation_deg}")


@dataclass
class Scatterers:
    """Point scatterers in a radar's frame."""

    points: torch.Tensor      # (N, 3) sensor frame (m)
    rcs: torch.Tensor         # (N,) radar cross-section (m^2)
    phase: torch.Tensor       # (N,) scattering phase (rad)
    velocity: torch.Tensor    # (N,) radial velocity (m/s, receding > 0)

    def __post_init__(self) -> None:
        p = self.points
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"Scatterers.points must be (N, 3), got {tuple(p.shape)}")
        n = p.shape[0]
        for k in ("rcs", "phase", "velocity"):
            v = getattr(self, k)
            if tuple(v.shape) != (n,):
                raise ValueError(f"Scatterers.{k} must have shape ({n},), got {tuple(v.shape)}")
            if torch.is_complex(v) or not torch.isfinite(v).all():
                raise ValueError(f"Scatterers.{k} must be real and finite")
        if not torch.isfinite(p).all():
            raise ValueError("Scatterers.points contain NaN or infinite values")
        if (self.rcs < 0).any():
            raise ValueError("Scatterers.rcs must be >= 0")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def to_frame(self, tf: Transform) -> "Scatterers":
        """Re-express the points with ``p' = tf.apply(p)`` (same RCS, phase, velocity)."""
        r = torch.as_tensor(tf.rotation, dtype=self.points.dtype, device=self.points.device)
        t = torch.as_tensor(tf.translation, dtype=self.points.dtype, device=self.points.device)
        return Scatterers(self.points @ r.T + t, self.rcs, self.phase, self.velocity)


@dataclass
class SimFrame:
    """Everything one call of :func:`simulate_frame` produces."""

    adc: np.ndarray                 # int16 (tx, rx, chirps, samples, 2)
    heatmap: np.ndarray | None      # float32 (el, az, range, 2) of the cascade
    lidar: np.ndarray               # float32 (beams * azimuth_steps, 4) in the LiDAR frame
    scatterers: Scatterers          # single-chip frame


# ------------------------------------------------------------------------------------------------
def _rot(tf: Transform, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.as_tensor(tf.rotation, dtype=dtype, device=device),
            torch.as_tensor(tf.translation, dtype=dtype, device=device))


def sensor_pose(scene: Scene, t: float, base_to_sensor: Transform) -> tuple[Transform, np.ndarray]:
    """World <- sensor transform and world velocity ``(3,)`` of the sensor at time ``t``."""
    base = scene.trajectory.transform(t)
    return base @ base_to_sensor, scene.trajectory.velocity(t)


def radar_scatterers(scene: Scene, t: float, pose: Transform, velocity: np.ndarray, *,
                     cfg: RadarSimConfig = RadarSimConfig(), generator: torch.Generator | None = None,
                     device: torch.device | str | None = None) -> Scatterers:
    """Scatterers visible from a radar at world pose ``pose`` (world <- sensor) at time ``t``.

    Parameters
    ----------
    scene : Scene
    t : float
        Time (s); people move.
    pose : Transform
        World <- radar.
    velocity : array (3,)
        World velocity of the radar (ego motion -> Doppler of static surfaces).
    cfg : RadarSimConfig
    generator : torch.Generator, optional
        Seeds the ray jitter and the scattering phases.
    """
    dtype = torch.float32
    dev = torch.device(device) if device is not None else torch.device("cpu")
    g = generator
    geom = scene.geometry(t, dev, dtype)
    rw, tw = _rot(pose, dtype, dev)
    n_az = int(2 * cfg.fov_az_deg / cfg.az_step_deg) + 1
    n_el = int(2 * cfg.fov_el_deg / cfg.el_step_deg) + 1
    step_az, step_el = math.radians(cfg.az_step_deg), math.radians(cfg.el_step_deg)
    az = torch.linspace(-math.radians(cfg.fov_az_deg), math.radians(cfg.fov_az_deg), n_az, device=dev)
    el = torch.linspace(-math.radians(cfg.fov_el_deg), math.radians(cfg.fov_el_deg), n_el, device=dev)
    a, e = torch.meshgrid(az, el, indexing="ij")
    a = a.reshape(-1) + (torch.rand(a.numel(), generator=g, device=dev) - 0.5) * step_az
    e = e.reshape(-1) + (torch.rand(e.numel(), generator=g, device=dev) - 0.5) * step_el
    u = torch.stack([e.cos() * a.cos(), e.cos() * a.sin(), e.sin()], -1)          # (M, 3) sensor frame
    hits = ray_cast(geom, tw, u @ rw.T, max_range=cfg.max_range_m, chunk=1024)
    keep = hits.hit & (hits.t >= cfg.min_range_m)
    uw = (u @ rw.T)[keep]
    r = hits.t[keep]
    cos_i = (hits.normal[keep] * uw).sum(-1).abs().clamp(0, 1)
    theta = torch.acos(cos_i)
    mat = hits.material[keep]
    sig0 = torch.tensor([m.radar_diffuse for m in MATERIALS], dtype=dtype, device=dev)[mat]
    ks = torch.tensor([m.radar_specular for m in MATERIALS], dtype=dtype, device=dev)[mat]
    ths = torch.tensor([math.radians(m.specular_width_deg) for m in MATERIALS], dtype=dtype, device=dev)[mat]
    d_omega = step_az * step_el * e[keep].cos()
    rcs = r ** 2 * d_omega * sig0 * (cos_i + ks * torch.exp(-(theta / ths) ** 2))
    pts_w = hits.point[keep]
    vel_w = hits.velocity[keep]
    if cfg.edges and scene.boxes.shape[0]:
        ep, ercs = _edge_points(scene, geom, tw, cfg, dev, dtype)
        if ep.shape[0]:
            pts_w = torch.cat([pts_w, ep])
            rcs = torch.cat([rcs, ercs])
            vel_w = torch.cat([vel_w, torch.zeros_like(ep)])
    if cfg.multipath and scene.mirror_planes and pts_w.shape[0]:
        k = min(cfg.ghost_count, pts_w.shape[0])
        top = torch.topk(rcs, k).indices
        for n_vec, c0 in scene.mirror_planes:
            nv = torch.tensor(n_vec, dtype=dtype, device=dev)
            side_s = float((tw * nv).sum() - c0)
            dp = (pts_w[top] * nv).sum(-1) - c0
            same = torch.sign(dp) == math.copysign(1.0, side_s)
            gp = pts_w[top] - 2 * dp[:, None] * nv
            gv = vel_w[top] - 2 * (vel_w[top] * nv).sum(-1, keepdim=True) * nv
            pts_w = torch.cat([pts_w, gp[same]])
            rcs = torch.cat([rcs, rcs[top][same] * cfg.ghost_gain ** 2])
            vel_w = torch.cat([vel_w, gv[same]])
    # sensor frame, radial velocity
    pts = (pts_w - tw) @ rw                                                          # R^T (p - t)
    rng_ = pts.norm(dim=1).clamp_min(1e-6)
    uw_all = (pts_w - tw) / rng_[:, None]
    v_rel = vel_w - torch.as_tensor(np.asarray(velocity, dtype=np.float32), device=dev)
    v_r = (v_rel * uw_all).sum(-1)
    if pts.shape[0] > cfg.max_scatterers:
        idx = torch.topk(rcs, cfg.max_scatterers).indices
        pts, rcs, v_r = pts[idx], rcs[idx], v_r[idx]
    phase = torch.rand(pts.shape[0], generator=g, device=dev) * (2 * math.pi)
    return Scatterers(pts, rcs, phase, v_r)


def _edge_points(scene: Scene, geom, origin, cfg: RadarSimConfig, dev, dtype):
    b = scene.boxes
    # vertical edges of tall, wide boxes (walls, cabinets, doors, desks' bodies); thin legs and
    # frames are left to the ray-cast surface samples
    tall = (b[:, 5] > 0.2) & (np.maximum(b[:, 3], b[:, 4]) >= 0.2)
    if not tall.any():
        return torch.zeros((0, 3), dtype=dtype, device=dev), torch.zeros(0, dtype=dtype, device=dev)
    bb = b[tall]
    pts = []
    mats = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            c, s = np.cos(bb[:, 6]), np.sin(bb[:, 6])
            lx, ly = sx * bb[:, 3], sy * bb[:, 4]
            x = bb[:, 0] + c * lx - s * ly
            y = bb[:, 1] + s * lx + c * ly
            z0 = np.maximum(bb[:, 2] - bb[:, 5], 0.0)
            z1 = np.minimum(bb[:, 2] + bb[:, 5], 2.6)
            for i in range(len(bb)):
                if z1[i] <= z0[i]:
                    continue
                zs = np.arange(z0[i] + cfg.edge_spacing_m / 2, z1[i], cfg.edge_spacing_m)
                pts.append(np.stack([np.full_like(zs, x[i]), np.full_like(zs, y[i]), zs], 1))
                mats.append(np.full(len(zs), bb[i, 7]))
    if not pts:
        return torch.zeros((0, 3), dtype=dtype, device=dev), torch.zeros(0, dtype=dtype, device=dev)
    p = torch.as_tensor(np.concatenate(pts), dtype=dtype, device=dev)
    m = torch.as_tensor(np.concatenate(mats).astype(np.int64), device=dev)
    rel = p - origin
    dist = rel.norm(dim=1)
    near = (dist < cfg.max_range_m) & (dist > cfg.min_range_m)
    p, m, rel, dist = p[near], m[near], rel[near], dist[near]
    if p.shape[0] == 0:
        return p, dist
    hits = ray_cast(geom, origin, rel / dist[:, None])
    visible = hits.t >= dist - 0.08
    ks = torch.tensor([mm.radar_specular for mm in MATERIALS], dtype=dtype, device=dev)[m]
    rcs = cfg.edge_rcs_m2 * (1 + ks.sqrt())
    return p[visible], rcs[visible]


# ------------------------------------------------------------------------------------------------
def _unit_phasor(phase: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
    """``scale * exp(j phase)`` as complex64: float64 ``phase`` reduced to ``[0, 2 pi)``, then
    cos/sin in float32 (``scale`` broadcasts over the last axis)."""
    ph = torch.remainder(phase, 2 * math.pi).to(torch.float32)
    re, im = torch.cos(ph), torch.sin(ph)
    if scale is not None:
        re, im = re * scale, im * scale
    return torch.complex(re, im)


def coupling_group_size(max_speed_mps: float, chip: ColoRadarChipConfig = AWR1843, *,
                        coupling_tol: float = 1e-3) -> int:
    """Slots ``L`` per group of the fast beat-signal model (see the module docstring).

    The largest ``L`` in ``[1, N_tx N_chirps]`` with ``eps_max^2 / 2 <= coupling_tol``,
    ``eps_max = 2 pi S (2 v_max / c) ((L - 1) / 2) T_c max|t_k - t_ctr|`` (radians): the error bound
    of the first-order coupling correction relative to a scatterer's amplitude. All slots (one group)
    when ``max_speed_mps == 0``.
    """
    if not math.isfinite(max_speed_mps) or max_speed_mps < 0:
        raise ValueError(f"max_speed_mps must be finite and >= 0, got {max_speed_mps}")
    if not (coupling_tol > 0 and math.isfinite(coupling_tol)):
        raise ValueError(f"coupling_tol must be a positive finite phase in radians, got {coupling_tol}")
    w = chip.waveform
    m = w.num_tx * w.num_chirps_per_frame
    half_k = 0.5 * (w.num_adc_samples_per_chirp - 1) / w.adc_sample_frequency      # max |t_k - t_ctr|
    rate = 2 * math.pi * w.frequency_slope * (2 * max_speed_mps / SPEED_OF_LIGHT) * w.chirp_period_s * half_k
    if rate <= 0:
        return m
    return int(min(m, 1 + math.floor(2 * math.sqrt(2 * coupling_tol) / rate)))


_REANCHOR = 32   # groups between direct (float64) evaluations of the stepped sample phasors


def beat_signal(scat: Scatterers, chip: ColoRadarChipConfig = AWR1843, *, gain_lsb: float = 400.0,
                exact: bool = False, chunk: int = 1024, coupling_tol: float = 1e-3) -> torch.Tensor:
    """Noise-free complex beat signal ``(tx, rx, chirps, samples)`` (complex64, LSB units).

    See the module docstring for the formula. Computed on the scatterers' device, chunked over
    ``chunk`` scatterers: ``exact=True`` sums float64 phases of every (tx, rx, chirp, sample); the
    default builds a ``(slot, rx, n)`` and per slot group an ``(n, 2 samples)`` phasor factor and
    multiplies them (one complex64 GEMM per group), with the range-migration error bounded by
    ``coupling_tol`` times each scatterer's amplitude (groups from :func:`coupling_group_size` on
    the chunk's largest ``|v|``; the RMS error is about ``coupling_tol / 9`` of it).
    """
    if not (coupling_tol > 0 and math.isfinite(coupling_tol)):
        raise ValueError(f"coupling_tol must be a positive finite phase in radians, got {coupling_tol}")
    dev = scat.points.device
    w, ant = chip.waveform, chip.antenna
    ntx, nrx, nc, ns = w.num_tx, w.num_rx, w.num_chirps_per_frame, w.num_adc_samples_per_chirp
    m_slots = ntx * nc
    f64 = torch.float64
    p = scat.points.to(f64)
    r0 = p.norm(dim=1).clamp_min(1e-3)
    u = p / r0[:, None]
    amp = gain_lsb * scat.rcs.to(f64).clamp_min(0).sqrt() / r0 ** 2
    f0, slope, tc = w.start_frequency, w.frequency_slope, w.chirp_period_s
    d = chip.element_spacing
    tx = torch.as_tensor(np.asarray(ant.tx_positions), dtype=f64, device=dev)      # (ntx, 2)
    rx = torch.as_tensor(np.asarray(ant.rx_positions), dtype=f64, device=dev)      # (nrx, 2)
    t_chirp = ((torch.arange(nc, device=dev, dtype=f64)[None, :] * ntx
                + torch.arange(ntx, device=dev, dtype=f64)[:, None]) * tc)          # (ntx, nc)
    t_k = w.adc_start_time + torch.arange(ns, device=dev, dtype=f64) / w.adc_sample_frequency
    t_tx_all = torch.arange(ntx, device=dev, dtype=f64) * tc                         # (ntx,) Tx offset in a loop
    t_loop_all = torch.arange(nc, device=dev, dtype=f64) * (ntx * tc)                  # (nc,) loop start
    t_ctr = float(t_k.mean())
    k_off = t_k - t_ctr                                                              # (ns,)
    if exact:
        out = torch.zeros((ntx, nrx, nc, ns), dtype=torch.complex128, device=dev)
    else:
        acc = torch.zeros((m_slots * nrx, ns), dtype=torch.complex64, device=dev)     # rows (c, t, r)
    two_pi = 2 * math.pi
    if exact:   # the exact path materialises (tx, rx, chirps, samples, n): bound it to ~2e7 elements
        chunk = max(1, min(chunk, int(2e7 // (ntx * nrx * nc * ns))))
    for s in range(0, p.shape[0], chunk):
        sl = slice(s, s + chunk)
        rr, vv, uu = r0[sl], scat.velocity[sl].to(f64), u[sl]
        arr_tx = two_pi * d * (tx[:, 0:1] * uu[None, :, 1] + tx[:, 1:2] * uu[None, :, 2])      # (ntx, n)
        arr_rx = two_pi * d * (rx[:, 0:1] * uu[None, :, 1] + rx[:, 1:2] * uu[None, :, 2])      # (nrx, n)
        if exact:
            tau = 2 * (rr[None, None, :] + vv[None, None, :] * t_chirp[:, :, None]) / SPEED_OF_LIGHT  # (ntx, nc, n)
            slow = two_pi * (f0 * tau - 0.5 * slope * tau ** 2)
            coef = amp[sl] * torch.exp(1j * scat.phase[sl].to(f64))
            ph = (slow[:, None, :, None, :] + arr_tx[:, None, None, None, :] + arr_rx[None, :, None, None, :]
                  + two_pi * slope * tau[:, None, :, None, :] * t_k[None, None, None, :, None])
            out += (coef * torch.exp(1j * ph)).sum(-1)
        else:
            # S tau t_k = S tau t_ctr + S tau (t_k - t_ctr): the first part is exact per chirp.
            # With tau = a + b T (a = 2 R / c, b = 2 v / c) and F = f0 + S t_ctr the per-chirp phase is
            #   2 pi (F tau - S tau^2 / 2) = th0 + c1 T + c2 T^2,
            #   th0 = 2 pi (F a - S a^2 / 2),  c1 = 2 pi b (F - S a),  c2 = -pi S b^2,
            # with T = T_t + T_c (Tx offset t T_chirp, loop start c N_tx T_chirp). The second part uses
            # the delay at the reference time T_g of the slot's group g plus the first-order coupling
            # correction (error <= coupling_tol of the amplitude):
            #   s[(c, t), r, k] = sum_n L[(c, t), r, n] K_g[n, k] (1 + (T - T_g) D[n, k])
            #   L = A_n exp(j (phi_n + th0 + arr_tx + arr_rx + c1 T + c2 T^2))
            #   K_g = exp(j 2 pi S (a + b T_g) (t_k - t_ctr)),  D = j 2 pi S b (t_k - t_ctr)
            # Phases in float64 reduced modulo 2 pi, cos/sin in float32, products and GEMMs in complex64.
            a_n, b_n = 2 * rr / SPEED_OF_LIGHT, 2 * vv / SPEED_OF_LIGHT                      # (n,)
            n_c = a_n.shape[0]
            f_c = f0 + slope * t_ctr
            th0 = two_pi * (f_c * a_n - 0.5 * slope * a_n ** 2)
            c1 = two_pi * b_n * (f_c - slope * a_n)
            c2 = -math.pi * slope * b_n ** 2
            t_tx, t_loop = t_tx_all[:, None], t_loop_all[:, None]                            # (ntx, 1), (nc, 1)
            base = scat.phase[sl].to(f64) + th0 + arr_tx + c1 * t_tx + c2 * t_tx ** 2           # (ntx, n)
            ph_l = (c1 + 2 * c2 * t_tx)[:, None, :] * t_loop[None]                           # (ntx, nc, n)
            ph_l += (c2 * t_loop ** 2)[None] + base[:, None, :]
            left_s = _unit_phasor(ph_l.permute(1, 0, 2), amp[sl].to(torch.float32))          # (nc, ntx, n)
            left = (left_s.reshape(m_slots, 1, n_c) * _unit_phasor(arr_rx)[None]).reshape(m_slots * nrx, n_c)
            v_max = float(vv.abs().max()) if n_c else 0.0
            grp = coupling_group_size(v_max, chip, coupling_tol=coupling_tol)                # slots per group
            n_grp = -(-m_slots // grp)
            ref0 = 0.5 * (grp - 1) * tc                                                      # T_0
            step = None
            if n_grp > 1:
                step = _unit_phasor((two_pi * slope * b_n * (grp * tc))[:, None] * k_off[None, :])  # (n, ns)
            e_k = step
            corr = v_max > 0
            if corr:
                d_nk = torch.complex(torch.zeros((), dtype=torch.float32, device=dev),
                                     ((two_pi * slope * b_n)[:, None] * k_off[None, :]).to(torch.float32))  # (n, ns)
                slot_t = torch.arange(m_slots, device=dev, dtype=f64) * tc
                dt_row = (slot_t - (ref0 + (torch.arange(m_slots, device=dev) // grp) * (grp * tc)))
                dt_row = dt_row.repeat_interleave(nrx).to(torch.float32)[:, None]          # (slots rx, 1) T - T_g
            for gi in range(n_grp):
                if gi % _REANCHOR == 0:                                                      # direct K_g
                    t_ref = ref0 + gi * grp * tc
                    e_k = _unit_phasor((two_pi * slope * (a_n + b_n * t_ref))[:, None] * k_off[None, :])
                else:                                                                        # K_g = K_{g-1} step
                    e_k = e_k * step
                rows = slice(gi * grp * nrx, min((gi + 1) * grp, m_slots) * nrx)
                if corr:
                    prod = torch.matmul(left[rows], torch.cat([e_k, e_k * d_nk], 1))          # (slots_g rx, 2 ns)
                    acc[rows] += prod[:, :ns] + dt_row[rows] * prod[:, ns:]
                else:
                    acc[rows] += torch.matmul(left[rows], e_k)                               # (slots_g rx, ns)
    if not exact:
        out = acc.reshape(nc, ntx, nrx, ns).permute(1, 2, 0, 3).contiguous()
    return out.to(torch.complex64)


def synthesize_tdm_adc(scat: Scatterers, chip: ColoRadarChipConfig = AWR1843, *,
                   cfg: RadarSimConfig = RadarSimConfig(), generator: torch.Generator | None = None,
                   exact: bool = False) -> torch.Tensor:
    """Single-chip ADC frame: beat signal + complex noise, rounded to int16 I/Q.

    Returns
    -------
    torch.Tensor
        int16 ``(tx, rx, chirps, samples, 2)`` on the scatterers' device.
    """
    s = beat_signal(scat, chip, gain_lsb=cfg.adc_gain_lsb, exact=exact)
    iq = torch.view_as_real(s)
    if cfg.adc_noise_lsb > 0:
        iq = iq + cfg.adc_noise_lsb * torch.randn(iq.shape, generator=generator, device=iq.device,
                                                  dtype=iq.dtype)
    return torch.round(iq).clamp(-32768, 32767).to(torch.int16)


# ------------------------------------------------------------------------------------------------
def _hann_response_power(delta: torch.Tensor, n: int, nfft: int) -> torch.Tensor:
    """``|W(delta)|^2 / |W(0)|^2`` of an ``n``-sample periodic Hann window in an ``nfft`` FFT.

    ``W = 0.5 D(x) - 0.25 D(x - nfft/n) - 0.25 D(x + nfft/n)`` with the Dirichlet kernel
    ``D(x) = sum_k exp(-j 2 pi k x / nfft) = exp(-j (n-1) a) sin(n a) / sin(a)``, ``a = pi x / nfft``;
    the three kernels share the phase up to ``exp(+-j (n-1) pi / n)``.
    """
    sh = nfft / n

    def ratio(x: torch.Tensor) -> torch.Tensor:                     # sin(n a) / sin(a), n where sin(a) = 0
        a = x * (math.pi / nfft)
        sa = torch.sin(a)
        return torch.where(sa.abs() < 1e-6, float(n), torch.sin(n * a) / sa)

    phi = (n - 1) * math.pi / n                  # phase of D(x -+ sh) relative to D(x): exp(+-j phi)
    d0, dm, dp = ratio(delta), ratio(delta - sh), ratio(delta + sh)
    re = 0.5 * d0 - (0.25 * math.cos(phi)) * (dm + dp)
    im = (-0.25 * math.sin(phi)) * (dm - dp)
    return re.square_().addcmul_(im, im).mul_(1.0 / (0.5 * n) ** 2)


_HM_BLOCK = 64   # scatterers per beamforming block in cascade_heatmap (~2 MB of float32 at 128 x 32 bins)


def cascade_heatmap(scat: Scatterers, chip: ColoRadarChipConfig = CASCADE, *,
                    cfg: RadarSimConfig = RadarSimConfig(), generator: torch.Generator | None = None,
                    noise: bool = True, chunk: int = 1024) -> torch.Tensor:
    """Cascade heatmap float32 ``(elevation, azimuth, range, 2)`` (intensity = SNR, Doppler m/s).

    ``scat`` must be expressed in the cascade's frame; ``chunk`` scatterers are beamformed at a time.
    """
    dev = scat.points.device
    w, hm = chip.waveform, chip.heatmap
    f32 = torch.float32
    p = scat.points.to(f32)
    r0 = p.norm(dim=1).clamp_min(1e-3)
    u = p / r0[:, None]
    nr, na, ne = hm.num_range_bins, hm.num_azimuth_bins, hm.num_elevation_bins
    # per-scatterer SNR after coherent integration over samples, chirps and unique virtual elements
    vpos = np.unique(chip.virtual_positions, axis=0)                                  # (V, 2)
    n_int = w.num_adc_samples_per_chirp * w.num_chirps_per_frame * vpos.shape[0]
    amp = cfg.adc_gain_lsb * scat.rcs.to(f32).clamp_min(0).sqrt() / r0 ** 2
    # Hann range window: processing gain (sum w)^2 / sum w^2 = 2N/3 instead of N
    snr = amp ** 2 / max(2 * cfg.adc_noise_lsb ** 2, 1e-12) * n_int * (2.0 / 3.0)
    keep = r0 <= (nr + 2) * hm.range_bin_width
    p_snr, u, r0, vel = snr[keep], u[keep], r0[keep], scat.velocity[keep].to(f32)
    # range response of a Hann-windowed FFT, |W(delta)|^2 / |W(0)|^2, delta in bins
    nfft = int(round(SPEED_OF_LIGHT * w.adc_sample_frequency / (2 * w.frequency_slope * hm.range_bin_width)))
    delta = torch.arange(nr, device=dev, dtype=f32)[:, None] - (r0 / hm.range_bin_width)[None, :]   # (R, N)
    wr = _hann_response_power(delta, w.num_adc_samples_per_chirp, nfft)               # (R, N)
    # Beamformer of the unique virtual elements (p_h, p_v), grouped in rows of equal p_v:
    #   AF(n, a, e) = sum_k g_k(n, a) exp(-j 2 pi d p_v,k sin el_e)
    #   g_k(n, a)  = sum_{h in row k} exp(j 2 pi d (p_h u_y,n + p_v,k u_z,n)) exp(-j 2 pi d p_h sin az_a)
    # g_k by a real GEMM per row on [cos | sin] of the element phases; [Re AF | Im AF] by one GEMM
    # with the 2K x 2E elevation steering; then one GEMM sums over scatterers:
    #   both[r, (a, e)] = sum_n [w_rn; w_rn v_n] SNR_n |AF_n(a, e)|^2 / V^2.
    d = chip.element_spacing
    two_pi_d = 2 * math.pi * d
    s_az = torch.sin(torch.as_tensor(hm.azimuth_bins, dtype=f32, device=dev))
    s_el = torch.sin(torch.as_tensor(hm.elevation_bins, dtype=f32, device=dev))
    rows = np.unique(vpos[:, 1])
    nk = len(rows)
    order = np.lexsort((vpos[:, 0], vpos[:, 1]))                                     # elements by row
    hp_all = torch.as_tensor(vpos[order, 0], dtype=f32, device=dev)                   # (V,)
    pv_all = torch.as_tensor(vpos[order, 1], dtype=f32, device=dev)                   # (V,)
    counts = [int((vpos[:, 1] == pv).sum()) for pv in rows]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
    # columns of [cos | sin] (n, 2V) regrouped as [cos row 0, sin row 0, cos row 1, ...]
    perm = torch.as_tensor(np.concatenate([np.r_[st:st + c, vpos.shape[0] + st:vpos.shape[0] + st + c]
                                           for st, c in zip(starts, counts)]), device=dev)
    steer = []                                                                        # (2 H_k, 2 A) each
    for st, c in zip(starts, counts):
        th = two_pi_d * hp_all[st:st + c, None] * s_az[None, :]                      # (H_k, A)
        cth, sth = torch.cos(th), torch.sin(th)
        steer.append(torch.cat([torch.cat([cth, -sth], 1), torch.cat([sth, cth], 1)], 0))
    th_e = -two_pi_d * torch.as_tensor(rows, dtype=f32, device=dev)[:, None] * s_el[None, :]   # (K, E)
    ce, se = torch.cos(th_e), torch.sin(th_e)
    # rows 2k, 2k+1 of y multiply Re g_k, Im g_k: AF_re = sum Re g ce - Im g se, AF_im = sum Re g se + Im g ce
    y = torch.stack([torch.cat([ce, se], 1), torch.cat([-se, ce], 1)], 1).reshape(2 * nk, 2 * ne)   # (2K, 2E)
    wr.mul_(p_snr[None, :] / vpos.shape[0] ** 2)                                      # w_r SNR_n / V^2
    w2 = torch.cat([wr, wr * vel[None, :]], 0)                                        # (2R, N)
    hp_d, pv_d = two_pi_d * hp_all, two_pi_d * pv_all
    both = torch.zeros((2 * nr, na * ne), dtype=f32, device=dev)
    # work buffers allocated once (fresh large allocations cost page faults on every block)
    bf_buf = torch.empty((min(chunk, u.shape[0]), na, ne), dtype=f32, device=dev)    # |AF|^2
    x_buf = torch.empty((_HM_BLOCK, na, 2 * nk), dtype=f32, device=dev)               # Re, Im g_k
    af_buf = torch.empty((_HM_BLOCK * na, 2 * ne), dtype=f32, device=dev)             # Re, Im AF
    for c0 in range(0, u.shape[0], chunk):                     # chunks bound memory to ~chunk * A * E
        n_c = min(chunk, u.shape[0] - c0)
        bf = bf_buf[:n_c]                                                             # |AF|^2
        for b0 in range(0, n_c, _HM_BLOCK):                    # blocks small enough to stay in cache
            uc = u[c0 + b0:c0 + b0 + _HM_BLOCK]
            n = uc.shape[0]
            ph = torch.addcmul(uc[:, 1:2] * hp_d, uc[:, 2:3], pv_d)                   # (n, V) element phases
            cs = torch.cat([torch.cos(ph), torch.sin(ph)], 1)[:, perm]                # (n, 2V)
            g = [(cs[:, 2 * st:2 * (st + c)] @ stk).reshape(n, 2, na).transpose(1, 2)  # (n, A, 2) Re, Im g_k
                 for st, c, stk in zip(starts, counts, steer)]
            x = torch.cat(g, 2, out=x_buf[:n])                                        # (n, A, 2K)
            af = torch.mm(x.reshape(n * na, 2 * nk), y, out=af_buf[:n * na]).reshape(n, na, 2 * ne)
            blk = bf[b0:b0 + n]
            torch.mul(af[:, :, :ne], af[:, :, :ne], out=blk)
            blk.addcmul_(af[:, :, ne:], af[:, :, ne:])
        both.addmm_(w2[:, c0:c0 + n_c], bf.reshape(n_c, na * ne))
    inten, vsum = both[:nr], both[nr:]                                                # (R, A E) each
    vmax, nd = w.max_velocity_mps, w.num_chirps_per_frame
    vbin = 2 * vmax / nd
    # power-weighted radial velocity, wrapped to the unambiguous interval and quantized (in place)
    dop = vsum.div_(inten.clamp_min(1e-12))
    dop.add_(vmax).remainder_(2 * vmax).sub_(vmax)
    dop.div_(vbin).round_().mul_(vbin)
    if noise:
        nz = torch.rand(inten.shape, generator=generator, device=dev).clamp_min_(1e-12).log_().neg_().mul_(cfg.heatmap_noise)
        rand_v = (torch.randint(0, nd, inten.shape, generator=generator, device=dev) - nd // 2).to(f32).mul_(vbin)
        dop = torch.where(inten > nz, dop, rand_v)
        inten = inten.add_(nz)
    out = torch.empty((ne, na, nr, 2), dtype=f32, device=dev)                          # (E, A, R, 2)
    out[..., 0] = inten.reshape(nr, na, ne).permute(2, 1, 0)
    out[..., 1] = dop.reshape(nr, na, ne).permute(2, 1, 0)
    return out


# ------------------------------------------------------------------------------------------------
def lidar_directions(cfg: LidarConfig = LidarConfig(), device: torch.device | str | None = None) -> torch.Tensor:
    """Unit ray directions ``(beams * azimuth_steps, 3)`` in the LiDAR frame, row ``beam * steps + j``.

    Beams are evenly spaced over ``elevation_deg`` (top beam first); azimuth goes around from
    +x counter-clockwise.
    """
    el = torch.linspace(math.radians(cfg.elevation_deg[1]), math.radians(cfg.elevation_deg[0]), cfg.beams,
                        device=device)
    az = torch.arange(cfg.azimuth_steps, device=device, dtype=torch.float32) * (2 * math.pi / cfg.azimuth_steps)
    e, a = torch.meshgrid(el, az, indexing="ij")
    return torch.stack([e.cos() * a.cos(), e.cos() * a.sin(), e.sin()], -1).reshape(-1, 3)


def lidar_scan(scene: Scene, t: float, pose: Transform, *, cfg: LidarConfig = LidarConfig(),
               generator: torch.Generator | None = None, device: torch.device | str | None = None) -> torch.Tensor:
    """One LiDAR revolution at world pose ``pose`` (world <- lidar): float32 ``(M, 4)`` x, y, z,
    intensity in the LiDAR frame; rays without return are all-zero rows."""
    dev = torch.device(device) if device is not None else torch.device("cpu")
    geom = scene.geometry(t, dev)
    rw, tw = _rot(pose, torch.float32, dev)
    dl = lidar_directions(cfg, dev)
    hits = ray_cast(geom, tw, dl @ rw.T, max_range=cfg.max_range_m)
    r = hits.t + cfg.range_noise_m * torch.randn(hits.t.shape, generator=generator, device=dev)
    keep = hits.hit & (torch.rand(hits.t.shape, generator=generator, device=dev) >= cfg.dropout) & (r > 0.2)
    refl = torch.tensor([m.lidar_reflectivity for m in MATERIALS], device=dev)[hits.material.clamp_min(0)]
    cos_i = (hits.normal * (dl @ rw.T)).sum(-1).abs()
    inten = 200.0 * refl * cos_i / (1 + (hits.t.clamp(max=1e4) / 20.0) ** 2) + 2 * torch.rand(
        hits.t.shape, generator=generator, device=dev)
    xyz = dl * r.clamp(max=1e4)[:, None]
    out = torch.cat([xyz, inten[:, None]], 1)
    return torch.where(keep[:, None], out, torch.zeros_like(out)).to(torch.float32)


# ------------------------------------------------------------------------------------------------
def simulate_frame(scene: Scene, t: float, *, calib: ColoRadarCalib = DEFAULT_CALIB,
                   radar: RadarSimConfig = RadarSimConfig(), lidar: LidarConfig = LidarConfig(),
                   heatmap: bool = True, seed: int = 0, device: torch.device | str | None = None) -> SimFrame:
    """Simulate every sensor of the rig at one time ``t`` (the unit the benchmark times).

    Returns single-chip ADC (int16), cascade heatmap (float32, if ``heatmap`` and the calibration
    has a cascade) and LiDAR scan (float32, LiDAR frame), all as NumPy arrays.
    """
    dev = torch.device(device) if device is not None else torch.device("cpu")
    gen = torch.Generator(device=dev)
    gen.manual_seed(int(seed))
    pose_sc, vel = sensor_pose(scene, t, calib.base_to_single_chip)
    scat = radar_scatterers(scene, t, pose_sc, vel, cfg=radar, generator=gen, device=dev)
    adc = synthesize_tdm_adc(scat, calib.single_chip, cfg=radar, generator=gen).cpu().numpy()
    hm = None
    if heatmap and calib.cascade is not None and calib.base_to_cascade is not None:
        sc_to_cc = calib.base_to_cascade.inverse() @ calib.base_to_single_chip
        hm = cascade_heatmap(scat.to_frame(sc_to_cc), calib.cascade, cfg=radar, generator=gen).cpu().numpy()
    pose_l, _ = sensor_pose(scene, t, calib.base_to_lidar)
    cloud = lidar_scan(scene, t, pose_l, cfg=lidar, generator=gen, device=dev).cpu().numpy()
    return SimFrame(adc, hm, cloud, scat)
