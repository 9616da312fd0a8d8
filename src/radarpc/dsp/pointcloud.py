"""Spectral point clouds (seed sections 3.2-3.3): RD cubes -> CFAR peaks -> angle spectra -> points.

For a batch of per-Rx RD cubes ``R`` (complex ``(B, Nr, Nd, Nrx)``), :class:`SpectralPointCloud`

1. forms the envelope ``E(r, l) = sum_{d in T(r, l)} sum_rx |R(r, d, rx)|`` over the ``M = n_tx``
   replica bins of each consolidated cell (seed eq. 1; ``envelope="all-slots"`` sums every slot,
   empty ones included, as RADIal's ``rpl.py``), and each cell's Tx-0 slot (:mod:`radarpc.dsp.ddma`);
2. runs CA-CFAR on ``|E|^2`` and keeps ``P(tau) = {(r, l) : |E|^2 / mu(r, l) > tau}`` (eq. 1), with
   ``tau`` fixed or chosen per frame / per dataset so that the density of the *encoded* set hits a
   target (eqs. 2-3, :mod:`radarpc.dsp.density`): ``|S(tau)| / (Nr Nd)``, or ``|S*(tau)| / (Nr Nd)``
   with the RD-neighbourhood enrichment;
3. optionally enlarges ``P`` to ``P*(tau)``, the union of the ``n x n`` neighbourhoods of its peaks
   truncated at the envelope borders (RD-neighbourhood enrichment, eqs. 8-9);
4. for every kept cell takes its DDMA hypothesis (Tx-0 Doppler bin ``d0``, from the same gap
   search that gave the replica envelope), gathers the
   virtual snapshot ``v_j`` (eq. 4), beamforms ``s_j = |B v_j|`` (eq. 5), and takes
   ``k_j = argmax s_j``, ``Ae_j = s_j[k_j]`` (eqs. 6-7), plus optionally the sector
   descriptor (eq. 10, angle-spectrum enrichment).

Points of all frames are concatenated with an ``offset`` vector (Pointcept style). Everything is
batched torch on the input's device, without Python loops over points.

Enrichment names (``enrich=``): ``"rdN"`` (odd ``N >= 3``) adds the ``N x N`` RD-neighbourhood points
(``is_neighbour=True``) and fills ``rd_patch`` with ``E`` over the ``N x N`` cells around each
point; ``"patchN"`` fills ``rd_patch`` only; ``"sectorA"`` / ``"sectorAxE"`` adds the
``A x E``-sector angle descriptor (``E = 1`` by default).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Iterable, Sequence

import torch
import torch.nn.functional as F

from radarpc.dsp.accel.workspace import Workspace
from radarpc.dsp.beamform import check_beamforming
from radarpc.dsp.beamform_modes import beamform
from radarpc.dsp.dictionary import DictionaryTables, dictionary_tables
from radarpc.dsp.cfar import RADIAL_TAU, CFARResult, ca_cfar, check_tau, check_window
from radarpc.dsp.ddma import (DDMAEnvelope, check_envelope_kind, check_finite_envelope, check_rd,
                              ddma_envelope, rx_magnitude_sum, virtual_snapshots)
from radarpc.dsp.density import (DENSITY_MODES, check_density, check_density_value, density_of_mask,
                                 neighbourhood_mask, tau_for_density)
from radarpc.config import from_dict, to_dict
from radarpc.points import PointCloudBatch
from radarpc.sensors.radial import Calibration, DDMARadarConfig

__all__ = [
    "CFAR_PRESETS",
    "SpectralPointCloudConfig",
    "EncodedSet",
    "SpectralPointCloud",
    "RADIAL_TAU",
]

_RD = re.compile(r"rd(\d+)")
_PATCH = re.compile(r"patch(\d+)")
_SECTOR = re.compile(r"sector(\d+)(?:x(\d+))?")


CFAR_PRESETS: dict[str, dict] = {
    # RADIal rpl.py: its win_param (9, 9, 3, 3) are half widths, and its envelope sums every slot
    "radial": {"window": (19, 19), "guard": (7, 7), "envelope": "all-slots"},
}
"""Named CFAR geometries and envelopes (fields of :class:`SpectralPointCloudConfig`)."""


@dataclass(frozen=True)
class SpectralPointCloudConfig:
    """Settings of a spectral point cloud; the resolved form is what stores and runs record.

    ``density`` set -> the threshold is found from it (``tau`` is then ``None``); otherwise the fixed
    linear SNR threshold ``tau`` is used. ``window`` / ``guard`` are *full* odd side lengths:
    RADIal ``rpl.py``'s ``(9, 9, 3, 3)`` are half widths, i.e. ``window=(19, 19), guard=(7, 7)``,
    for which its ``tau = 1.585`` (2 dB) was chosen (with ``envelope="all-slots"``).
    """

    tau: float | None = RADIAL_TAU          # fixed linear SNR threshold (RADIal: 2 dB)
    density: float | None = None            # target density of the encoded set (S, or S* with rdN) instead of tau
    density_mode: str = "per-frame"         # "per-frame" or "per-dataset" (pooled over the batch)
    window: tuple[int, int] = (9, 9)        # CA-CFAR full training window (range, Doppler), odd
    guard: tuple[int, int] = (3, 3)         # CA-CFAR full guard window, odd
    enrich: tuple[str, ...] = ()            # "rdN", "patchN", "sectorA", "sectorAxE"
    envelope: str = "replicas"              # "replicas" (seed eq. 1) or "all-slots" (RADIal rpl.py)
    beamforming: str = "auto"               # "auto", "exact" or "screened": the same points (see beamform)

    def __post_init__(self) -> None:
        check_envelope_kind(self.envelope)
        check_beamforming(self.beamforming)
        w, g = check_window(_seq(self.window), _seq(self.guard))
        object.__setattr__(self, "window", w)
        object.__setattr__(self, "guard", g)
        enrich = self.enrich.split(",") if isinstance(self.enrich, str) else self.enrich
        object.__setattr__(self, "enrich", tuple(str(x).strip() for x in enrich if str(x).strip()))
        if len(w) != 2:
            raise ValueError(f"the RD envelope CFAR is 2-D: window/guard need 2 sizes, got {w}, {g}")
        if self.density_mode not in DENSITY_MODES:
            raise ValueError(f"density_mode must be one of {DENSITY_MODES}, got {self.density_mode!r}")
        if self.density is not None:
            object.__setattr__(self, "density", check_density_value(self.density))
            object.__setattr__(self, "tau", None)
        else:
            if self.tau is None:
                raise ValueError("give a threshold tau or a target density")
            object.__setattr__(self, "tau", check_tau(self.tau))
        _ = (self.neighbourhood, self.patch, self.sectors)  # parse now: bad names fail at construction
        kinds = [re.match(r"[a-z]+", e).group(0) if re.match(r"[a-z]+", e) else e for e in self.enrich]
        if len(set(kinds)) != len(kinds):
            raise ValueError(f"each enrichment kind may be given once, got {self.enrich}")

    def _match(self, pattern: re.Pattern) -> re.Match | None:
        found = None
        for e in self.enrich:
            if not (_RD.fullmatch(e) or _PATCH.fullmatch(e) or _SECTOR.fullmatch(e)):
                raise ValueError(f"unknown enrichment {e!r}; expected 'rdN' or 'patchN' (odd N >= 3), "
                                 f"'sectorA' or 'sectorAxE' (e.g. rd3, patch5, sector32, sector32x1)")
            m = pattern.fullmatch(e)
            if m:
                found = m
        return found

    @staticmethod
    def _odd(m: re.Match | None) -> int | None:
        if m is None:
            return None
        n = int(m.group(1))
        if n < 3 or n % 2 == 0:
            raise ValueError(f"enrichment {m.group(0)!r}: the neighbourhood size must be odd and >= 3")
        return n

    @property
    def neighbourhood(self) -> int | None:
        """``n`` of the RD-neighbourhood enrichment (eq. 8), or None."""
        return self._odd(self._match(_RD))

    @property
    def patch(self) -> int | None:
        """Side of the ``rd_patch`` feature (``patchN``, else ``rdN``), or None."""
        p = self._odd(self._match(_PATCH))
        return p if p is not None else self.neighbourhood

    @property
    def sectors(self) -> tuple[int, int] | None:
        """``(n_az_sec, n_el_sec)`` of the angle-spectrum enrichment (eq. 10), or None."""
        m = self._match(_SECTOR)
        if m is None:
            return None
        a, e = int(m.group(1)), int(m.group(2) or 1)
        if a < 1 or e < 1:
            raise ValueError(f"enrichment {m.group(0)!r}: sector counts must be >= 1")
        return a, e

    def to_dict(self) -> dict:
        """Plain dict (lists for tuples) for YAML/JSON/Parquet metadata; :meth:`from_dict` inverts it."""
        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "point-cloud config") -> "SpectralPointCloudConfig":
        return from_dict(cls, d, where=where)


def _seq(v) -> tuple:
    return (v,) if isinstance(v, int) or not hasattr(v, "__iter__") else tuple(v)


@dataclass
class EncodedSet:
    """Detection of a batch: what a point cloud (and the matching sparse RD) encodes.

    Attributes
    ----------
    envelope : DDMAEnvelope          both envelopes, ``A`` and every cell's Tx-0 slot
    cfar : CFARResult                CA-CFAR of ``|E|^2`` (``E`` the configured envelope)
    tau : Tensor ``(B,)``            threshold of each frame
    peaks : BoolTensor ``(B, Nr, W)``   ``P(tau)``, the CFAR peaks
    kept : BoolTensor ``(B, Nr, W)``    the encoded consolidated cells: ``P*(tau)`` with ``rdN``, else ``P(tau)``
    """

    envelope: DDMAEnvelope
    cfar: CFARResult
    tau: torch.Tensor
    peaks: torch.Tensor
    kept: torch.Tensor

    def tx0_doppler(self) -> torch.Tensor:
        """``d0`` of every kept cell in ``torch.nonzero(kept)`` order: ``(N,)`` long."""
        b, r, l = torch.nonzero(self.kept, as_tuple=True)
        return self.envelope.tx0_doppler(b, r, l)


class SpectralPointCloud(torch.nn.Module):
    """RD cubes -> spectral point clouds (no learnable parameters; the dictionary is a buffer).

    Parameters
    ----------
    sensor : DDMARadarConfig
        Radar whose cubes are processed (sizes, DDMA slots, range/velocity bins).
    calibration : Calibration
        Beamforming table; ``B = calibration.dictionary()`` and its azimuth/elevation tables.
    tau : float or None
        Fixed linear CA-CFAR threshold (default RADIal's 2 dB = 1.585, chosen by RADIal for its
        19 x 19 / 7 x 7 window and all-slot envelope); ignored if ``density`` is set.
    density : float, optional
        Target density in ``(0, n_tx / n_slots]`` instead of a fixed tau, of the set the cloud
        encodes: ``|S(tau)| / (Nr Nd)``, or ``|S*(tau)| / (Nr Nd)`` with ``rdN`` (the threshold is
        then chosen on the neighbourhood-enlarged set, see :func:`radarpc.dsp.density.tau_for_density`).
    density_mode : {"per-frame", "per-dataset"}
        With ``density``: a tau per frame, or one tau pooled over the frames of each call. For a
        dataset-wide tau, compute it once with :meth:`calibrate_tau` on the training split and build
        the module with that ``tau``.
    window, guard : (int, int)
        Full odd CA-CFAR window and guard sizes over (range, consolidated Doppler).
        RADIal ``rpl.py``'s ``(9, 9, 3, 3)`` are half widths: ``window=(19, 19), guard=(7, 7)``.
    enrich : sequence of str
        ``"rdN"``, ``"patchN"``, ``"sectorA"`` / ``"sectorAxE"`` (see the module docstring).
    envelope : {"replicas", "all-slots"}
        ``"replicas"`` (default, seed eq. 1): sum over the ``n_tx`` replica bins of each cell;
        ``"all-slots"`` = RADIal ``rpl.py``: sum over every DDMA slot, empty ones included.
    beamforming : {"auto", "exact", "screened", "subspace"}
        How ``k_j`` and ``Ae_j`` are found; all give the same points (the argmax of the exact
        spectrum, certified: :func:`radarpc.dsp.beamform.certified_argmax`), only the speed
        differs (:mod:`radarpc.dsp.beamform`). ``"exact"``: the whole float32 spectrum of every
        point. ``"screened"``: a bfloat16 GEMM with a rigorous error bound leaves a few candidate
        directions per point (fast where bfloat16 GEMMs are: AMX CPUs). ``"subspace"``: a block
        low-rank float32 screen of the dictionary with a rigorous bound (fast on large grids, e.g.
        RADIal's 751 x 11). ``"auto"`` (default): whichever a one-off measurement on this device
        and dictionary found fastest (:func:`radarpc.dsp.accel.screened.measured_choice`), or
        ``"exact"`` with the accelerated paths off. Sector descriptors need the whole spectrum and
        always run ``"exact"``.

    Examples
    --------
    >>> from radarpc.sensors.radial import TINY
    >>> from radarpc.sim.radial_calibration import make_calibration
    >>> spc = SpectralPointCloud(TINY, make_calibration(TINY), enrich=("rd3", "sector8"))
    >>> clouds = spc(torch.randn(2, 64, 32, 4, dtype=torch.complex64))
    >>> len(clouds), clouds.sector.shape[1]
    (2, 8)
    """

    def __init__(self, sensor: DDMARadarConfig, calibration: Calibration, tau: float | None = RADIAL_TAU, *,
                 density: float | None = None, density_mode: str = "per-frame",
                 window: Sequence[int] = (9, 9), guard: Sequence[int] = (3, 3),
                 enrich: Sequence[str] = (), envelope: str = "replicas", beamforming: str = "auto") -> None:
        super().__init__()
        self.config = SpectralPointCloudConfig(tau=tau, density=density, density_mode=density_mode,
                                               window=window, guard=guard, enrich=enrich, envelope=envelope,
                                               beamforming=beamforming)
        if self.config.density is not None:
            check_density(self.config.density, sensor)
        calibration.check_sensor(sensor)
        self.sensor = sensor
        # A CFAR window larger than the RD cube it slides over is a mistake, not a setting.
        if any(w > n for w, n in zip(self.config.window, (sensor.n_range, sensor.n_doppler))):
            raise ValueError(f"CFAR window {self.config.window} is larger than the {sensor.n_range} x "
                             f"{sensor.n_doppler} (range x Doppler) RD cube of sensor {sensor.name!r}: "
                             f"each side at most {sensor.n_range},{sensor.n_doppler}")
        self.grid = calibration.grid_shape                          # (n_az, n_el)
        if self.config.sectors is not None:
            sa, se = self.config.sectors
            if sa > self.grid[0] or se > self.grid[1]:
                raise ValueError(f"sector enrichment {self.config.sectors} exceeds the angle grid {self.grid}")
        self.register_buffer("dictionary_t", calibration.dictionary().transpose(0, 1).contiguous(),
                             persistent=False)                       # (n_virtual, n_az * n_el)
        self._tables: dict[tuple[torch.device, torch.dtype], DictionaryTables] = {}   # built on first use
        self.workspace = Workspace()      # beamforming scratch, reused across calls (per thread)
        self.register_buffer("azimuth_table", torch.as_tensor(calibration.azimuth_deg, dtype=torch.float32),
                             persistent=False)
        self.register_buffer("elevation_table", torch.as_tensor(calibration.elevation_deg, dtype=torch.float32),
                             persistent=False)

    def tables(self, device: torch.device | str, dtype: torch.dtype = torch.complex64) -> DictionaryTables:
        """The beamforming forms of the dictionary on ``device`` in complex ``dtype`` (cached)."""
        key = (torch.device(device), dtype)
        if key not in self._tables:
            self._tables[key] = dictionary_tables(self.dictionary_t.to(key[0]), self.grid, dtype)
        return self._tables[key]

    # ---- detection ---------------------------------------------------------------------------
    def _envelope(self, rd: torch.Tensor) -> tuple[DDMAEnvelope, torch.Tensor]:
        """Both envelopes (and Tx-0 slots) of ``rd`` ``(B, Nr, Nd, Nrx)``, and the configured ``E`` ``(B, Nr, W)``."""
        env = ddma_envelope(rx_magnitude_sum(rd), self.sensor)
        e = env.envelope(self.config.envelope)
        check_finite_envelope(e)
        return env, e

    def _cfar(self, e: torch.Tensor) -> CFARResult:
        return ca_cfar(e.square(), self.config.window, self.config.guard)

    def thresholds(self, snr: torch.Tensor) -> torch.Tensor:
        """Threshold of each frame ``(B,)`` for CFAR SNR maps ``(B, Nr, W)`` under this config."""
        c = self.config
        if c.density is None:
            return torch.full((snr.shape[0],), c.tau, dtype=snr.dtype, device=snr.device)
        tau = tau_for_density(snr, self.sensor, c.density, mode=c.density_mode, neighbourhood=c.neighbourhood)
        return tau.expand(snr.shape[0]).clone() if tau.ndim == 0 else tau

    def detect(self, rd: torch.Tensor) -> tuple[torch.Tensor, CFARResult, torch.Tensor]:
        """Envelope ``E`` ``(B, Nr, W)``, its CA-CFAR result, and the consolidated peaks ``P(tau)``
        as a bool mask ``(B, Nr, W)`` (CFAR peaks only, before any RD-neighbourhood enlargement; a
        density target with ``rdN`` sets tau on ``S*(tau)``). See :meth:`encode` for the encoded set."""
        enc = self.encode(rd)
        return enc.envelope.envelope(self.config.envelope), enc.cfar, enc.peaks

    @torch.no_grad()
    def encode(self, rd: torch.Tensor) -> EncodedSet:
        """Detection of RD cubes ``(B, Nr, Nd, Nrx)`` or ``(Nr, Nd, Nrx)``: the envelopes, the
        CFAR result, each frame's tau, ``P(tau)`` and the encoded cells (``P*(tau)`` with ``rdN``).

        :meth:`forward` makes one point per ``kept`` cell; :func:`radarpc.dsp.sparse_rd.sparse_rd_mask`
        of ``kept`` and :meth:`EncodedSet.tx0_doppler` is the full-grid set the cloud encodes.
        """
        rd = check_rd(rd, self.sensor)
        env, e = self._envelope(rd)
        res = self._cfar(e)
        tau = self.thresholds(res.snr)                             # (B,)
        peaks = res.snr > tau[:, None, None]                       # P(tau): (B, Nr, W)
        n = self.config.neighbourhood
        kept = peaks if n is None else neighbourhood_mask(peaks, n)  # P*(tau), eq. 9
        return EncodedSet(envelope=env, cfar=res, tau=tau, peaks=peaks, kept=kept)

    @torch.no_grad()
    def calibrate_tau(self, frames: Iterable[torch.Tensor], density: float | None = None) -> float:
        """One tau for a whole split: the mean density over ``frames`` hits ``density``.

        The density is that of the encoded set, ``S*(tau)`` when this module has an ``rdN``
        enrichment, else ``S(tau)``. ``frames`` yields RD cubes or batches of cubes (e.g. the
        training split); only their ``(Nr, W)`` SNR maps are kept, on CPU.
        """
        target = self.config.density if density is None else density
        if target is None:
            raise ValueError("calibrate_tau needs a target density (argument or module config)")
        check_density(target, self.sensor)
        snrs = []
        for rd in frames:
            rd = check_rd(rd, self.sensor)
            snrs.append(self._cfar(self._envelope(rd)[1]).snr.cpu())
        if not snrs:
            raise ValueError("calibrate_tau got no frames")
        return float(tau_for_density(torch.cat(snrs), self.sensor, target, mode="per-dataset",
                                     neighbourhood=self.config.neighbourhood))

    # ---- points ------------------------------------------------------------------------------
    @torch.no_grad()
    def forward(self, rd: torch.Tensor) -> PointCloudBatch:
        """Spectral point clouds of RD cubes ``(B, Nr, Nd, Nrx)`` or ``(Nr, Nd, Nrx)`` complex."""
        cfg, c = self.sensor, self.config
        rd = check_rd(rd, cfg)                                     # (B, Nr, Nd, Nrx)
        enc = self.encode(rd)
        res, tau, peaks, kept = enc.cfar, enc.tau, enc.peaks, enc.kept
        e = enc.envelope.envelope(c.envelope)                      # (B, Nr, W)
        b, r, l = torch.nonzero(kept, as_tuple=True)               # (N,) each, frame-major
        offset = torch.cumsum(kept.flatten(1).sum(1), 0)

        d0 = enc.envelope.tx0_doppler(b, r, l)                     # (N,) Tx-0 bins of the gap search
        v = virtual_snapshots(rd, cfg, b, r, d0)                   # (N, n_virtual)
        dev = rd.device                                            # tables follow the input's device
        bf = beamform(v, self.tables(dev, v.dtype), self.grid, c.sectors, mode=c.beamforming,
                      workspace=self.workspace)
        n_el = self.grid[1]
        az = self.azimuth_table.to(dev)[bf.index // n_el]
        el = self.elevation_table.to(dev)[bf.index % n_el]
        rng = r.to(torch.float32) * cfg.range_res_m
        half = cfg.n_doppler // 2
        vel = ((d0 + half) % cfg.n_doppler - half).to(torch.float32) * cfg.velocity_res_mps
        a_rad, e_rad = torch.deg2rad(az), torch.deg2rad(el)
        ground = rng * torch.cos(e_rad)
        density = density_of_mask(kept, cfg)                       # (B,) encoded set: S or S*
        patch = None
        if c.patch is not None:
            h = c.patch // 2
            ep = F.pad(e, (h, h, h, h))                            # zeros outside the grid
            o = torch.arange(-h, h + 1, device=e.device)
            rr = (r + h).view(-1, 1, 1) + o.view(1, -1, 1)
            ll = (l + h).view(-1, 1, 1) + o.view(1, 1, -1)
            patch = ep[b.view(-1, 1, 1), rr, ll].reshape(-1, c.patch * c.patch).to(torch.float32)
        return PointCloudBatch(
            offset=offset, range_bin=r, doppler_bin=l, doppler_full=d0,
            range_m=rng, azimuth_deg=az, elevation_deg=el, velocity_mps=vel,
            amplitude=bf.amplitude.to(torch.float32), snr=res.snr[b, r, l].to(torch.float32),
            x=ground * torch.cos(a_rad), y=ground * torch.sin(a_rad), z=rng * torch.sin(e_rad),
            is_neighbour=~peaks[b, r, l],
            sector=None if bf.sectors is None else bf.sectors.to(torch.float32),
            rd_patch=patch, tau=tau.to(torch.float32), density=density,
            peak_density=density if kept is peaks else density_of_mask(peaks, cfg))
