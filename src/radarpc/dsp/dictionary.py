"""The calibrated dictionary in the forms every beamformer uses, the beamformers' result type, and
the checks and exact range scaling of snapshots they share.

The exact beamformer (:mod:`radarpc.dsp.beamform`) and the accelerated ones
(:mod:`radarpc.dsp.accel.screened`, :mod:`radarpc.dsp.accel.subspace`) build on this module; it
imports nothing of radarpc, so that neither of them imports the other's internals.

* :class:`DictionaryTables` (:func:`dictionary_tables`): ``B`` row by row for exact dot products,
  ``B^T`` in the three real forms of Gauss's trick and rounded to bfloat16 in the stacked real form
  (:func:`stack_real`), columns elevation-major (:func:`column_to_direction`);
* :class:`SubspaceTables`: the block low-rank factorisation of the subspace beamformer, built on
  first use by :func:`radarpc.dsp.accel.subspace.subspace_tables`;
* :class:`BeamformResult`: ``k_j``, ``Ae_j`` and the sector maxima of every snapshot;
* :func:`tables_for` and :func:`check_snapshots` check snapshots against the tables;
  :func:`row_norms`, :func:`range_exponents` and :func:`scaled_snapshots` bring snapshots of extreme
  magnitude into :data:`SAFE_NORM` by exact powers of two; :data:`SNAPSHOT_BLOCK` is the number of
  snapshots a beamformer's GEMM takes at once.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["DictionaryTables", "dictionary_tables", "stack_real", "column_to_direction", "SubspaceTables",
           "BeamformResult", "SNAPSHOT_BLOCK", "SAFE_NORM", "check_snapshots", "tables_for", "row_norms",
           "range_exponents", "scaled_snapshots"]

# Snapshots per GEMM block: the (block, n_az n_el) float32 buffers stay a few MB for RADIal.
SNAPSHOT_BLOCK = 1024

# Snapshots whose 2-norm lies in [2^-40, 2^40] are beamformed as they are: every float32 value
# the beamformers form from them (squared entries that matter, |B v|^2 over the grid) stays in the
# normal range. Others are first scaled by a power of two (exact) so that their largest |Re| or
# |Im| lies in [0.5, 1), and the amplitudes scaled back (:func:`range_exponents`).
SAFE_NORM = (2.0 ** -40, 2.0 ** 40)


@dataclass
class BeamformResult:
    """Per-snapshot outputs of a beamformer (:func:`radarpc.dsp.beamform_modes.beamform`).

    Attributes
    ----------
    index : LongTensor ``(P,)``          dominant direction ``k_j`` (eq. 6)
    amplitude : Tensor ``(P,)``          ``Ae_j = s_j[k_j]`` (eq. 7)
    sectors : Tensor ``(P, n_az_sec * n_el_sec)`` or None   sector maxima of ``s_j`` (eq. 10)
    """

    index: torch.Tensor
    amplitude: torch.Tensor
    sectors: torch.Tensor | None


def stack_real(dictionary_t: torch.Tensor) -> torch.Tensor:
    """Real form of a complex ``B^T`` ``(N, K)`` for one real GEMM: ``(2N, 2K)``.

    Row ``2n`` is ``[Re B^T[n], Im B^T[n]]`` and row ``2n + 1`` is ``[-Im B^T[n], Re B^T[n]]``, so that
    ``view_as_real(v).reshape(P, 2N) @ W = [Re (B v)^T | Im (B v)^T]`` (the interleaved real view of
    the snapshots needs no copy, and the output halves are contiguous column blocks).
    """
    n, k = dictionary_t.shape
    re, im = dictionary_t.real, dictionary_t.imag
    w = torch.empty(n, 2, 2 * k, dtype=re.dtype, device=re.device)
    w[:, 0, :k], w[:, 0, k:] = re, im
    w[:, 1, :k], w[:, 1, k:] = -im, re
    return w.reshape(2 * n, 2 * k)


@dataclass
class DictionaryTables:
    """The forms of ``B^T`` the beamformers use, computed once (:func:`dictionary_tables`).

    Attributes
    ----------
    grid : (n_az, n_el)              the angle grid, ``K = n_az n_el``, direction ``k = az n_el + el``
    rows : complex ``(K, N)``        ``B``, row ``k`` = direction ``k`` (exact dot products)
    re, im, gauss : real ``(N, K)``  ``Re B^T``, ``Im B^T`` and ``Re B^T + Im B^T`` (Gauss's trick)
    screen_bf16 : bfloat16 ``(2N, 2K)``   :func:`stack_real` of ``B^T`` rounded to bfloat16

    The GEMM forms (``re``, ``im``, ``gauss``, ``screen_bf16``) hold the directions in
    elevation-major order, column ``c = el n_az + az`` (:func:`column_to_direction`), so that
    maxima over elevation are reductions over a leading axis.
    row_norm_max : float             ``max_k ||B[k]||_2``, for the screen's error bound
    subspace : SubspaceTables or None   the subspace beamformer's factorisation, built on first use
    """

    grid: tuple[int, int]
    rows: torch.Tensor
    re: torch.Tensor
    im: torch.Tensor
    gauss: torch.Tensor
    screen_bf16: torch.Tensor
    row_norm_max: float
    subspace: SubspaceTables | None = None   # built on first use by radarpc.dsp.accel.subspace

    @property
    def n_dir(self) -> int:
        return int(self.rows.shape[0])

    def to(self, device: torch.device | str) -> "DictionaryTables":
        return DictionaryTables(grid=self.grid, rows=self.rows.to(device), re=self.re.to(device),
                                im=self.im.to(device), gauss=self.gauss.to(device),
                                screen_bf16=self.screen_bf16.to(device), row_norm_max=self.row_norm_max)


def dictionary_tables(dictionary_t: torch.Tensor, grid: tuple[int, int],
                      dtype: torch.dtype = torch.complex64) -> DictionaryTables:
    """:class:`DictionaryTables` of ``B^T`` ``(n_virtual, n_az * n_el)`` complex, in ``dtype``."""
    if not dictionary_t.is_complex() or dictionary_t.ndim != 2:
        raise ValueError(f"dictionary_t must be a complex (n_virtual, n_dir) matrix, got "
                         f"{dictionary_t.dtype} {tuple(dictionary_t.shape)}")
    n_az, n_el = (int(g) for g in grid)
    if n_az < 1 or n_el < 1 or n_az * n_el != dictionary_t.shape[1]:
        raise ValueError(f"grid {tuple(grid)} does not match the dictionary's {dictionary_t.shape[1]} directions")
    bt = dictionary_t.to(dtype)
    rows = bt.transpose(0, 1).contiguous()
    norm = float(torch.linalg.vector_norm(rows.to(torch.complex128), dim=1).max()) if rows.numel() else 0.0
    bt_em = bt[:, column_to_direction(torch.arange(n_az * n_el, device=bt.device), (n_az, n_el))]
    re, im = bt_em.real.contiguous(), bt_em.imag.contiguous()
    return DictionaryTables(grid=(n_az, n_el), rows=rows, re=re, im=im, gauss=(re + im).contiguous(),
                            screen_bf16=stack_real(bt_em).to(torch.bfloat16), row_norm_max=norm)


def column_to_direction(col: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """Direction ``k = az n_el + el`` of elevation-major GEMM column ``col = el n_az + az``."""
    n_az, n_el = grid
    return (col % n_az) * n_el + torch.div(col, n_az, rounding_mode="floor")


@dataclass
class SubspaceTables:
    """The factorised dictionary of :func:`radarpc.dsp.accel.subspace.subspace_tables`, for the
    subspace beamformer (:mod:`radarpc.dsp.accel.subspace`).

    Attributes
    ----------
    grid : (n_az, n_el)
    group, rank : int          azimuths per group, basis rank ``r``
    w1 : float32 ``(2N, G 2r)``   real form of every ``Q_G^T`` (:func:`stack_real`),
                                  group ``g`` in columns ``g 2r .. (g + 1) 2r`` as ``[Re y_G | Im y_G]``
    w2 : float32 ``(G, 2r, 2M)``  real form of ``C_G^T``: ``[Re y_G | Im y_G] @ w2[g] = [Re z^ | Im z^]``
    coef : float32 ``(G, 2, r, M)``  ``Re`` and ``Im`` of ``C_G^T`` (the native kernel's layout of ``w2``)
    resid : float32 ``(G M,)``    ``||rho_k||`` per direction, rounded up (0 for the last group's padding)
    slack : float32 ``(G M,)``    ``sigma_k``: ``||rho_k P_G||`` plus the screen's float32 rounding, per
                                  unit ``||v||`` (so ``e_k = resid_k R_G + slack_k ||v||``)
    cmax, rmax, smax : float32 ``(G,)``  per group, the largest ``||c_k||``, ``resid_k`` and ``slack_k``
                                  (the group bound of the native selection)
    gram_max : float64 ``(G,)``   an upper bound of ``lambda_max(Q_G Q_G^H)`` (the stored basis is
                                  orthonormal only to float32 accuracy)
    y_error : float               ``||y^_G - Q_G v|| <= y_error ||v||`` for the float32 first GEMM
    """

    grid: tuple[int, int]
    group: int
    rank: int
    w1: torch.Tensor
    w2: torch.Tensor
    coef: torch.Tensor
    resid: torch.Tensor
    slack: torch.Tensor
    cmax: torch.Tensor
    rmax: torch.Tensor
    smax: torch.Tensor
    gram_max: torch.Tensor
    y_error: float

    @property
    def n_groups(self) -> int:
        return int(self.w2.shape[0])

    def to(self, device: torch.device | str) -> "SubspaceTables":
        return SubspaceTables(self.grid, self.group, self.rank, self.w1.to(device), self.w2.to(device),
                              self.coef.to(device), self.resid.to(device), self.slack.to(device),
                              self.cmax.to(device), self.rmax.to(device), self.smax.to(device),
                              self.gram_max.to(device), self.y_error)


def check_snapshots(snapshots: torch.Tensor, dictionary: torch.Tensor) -> None:
    """``ValueError`` unless ``snapshots`` ``(P, N)`` and ``dictionary`` ``(n_dir, N)`` are complex
    matrices sharing ``N``."""
    if not snapshots.is_complex() or not dictionary.is_complex():
        raise ValueError(f"snapshots and dictionary must be complex, got {snapshots.dtype} and "
                         f"{dictionary.dtype}")
    if snapshots.ndim != 2 or dictionary.ndim != 2 or snapshots.shape[1] != dictionary.shape[1]:
        raise ValueError(f"snapshots (P, n_virtual) and dictionary (n_dir, n_virtual) must share "
                         f"n_virtual, got {tuple(snapshots.shape)} and {tuple(dictionary.shape)}")


def tables_for(snapshots: torch.Tensor, dictionary_t: torch.Tensor | DictionaryTables,
               grid: tuple[int, int]) -> DictionaryTables:
    """The :class:`DictionaryTables` a beamformer runs with: ``dictionary_t`` itself when it is
    tables (of ``grid``), else :func:`dictionary_tables` of the matrix in the snapshots' precision;
    ``ValueError`` unless the snapshots match them in ``N`` and dtype."""
    if isinstance(dictionary_t, DictionaryTables):
        t = dictionary_t
        if tuple(t.grid) != tuple(grid):
            raise ValueError(f"grid {tuple(grid)} differs from the dictionary tables' {t.grid}")
    else:
        t = dictionary_tables(dictionary_t, grid, snapshots.dtype if snapshots.is_complex() else torch.complex64)
    check_snapshots(snapshots, t.rows)
    if t.rows.dtype != snapshots.dtype:
        raise ValueError(f"snapshots are {snapshots.dtype} but the dictionary tables are {t.rows.dtype}")
    return t


def row_norms(snapshots: torch.Tensor) -> torch.Tensor:
    """Float32 2-norms of the rows of complex ``(P, N)`` snapshots (the interleaved real view: the
    complex-input norm is ~100x slower on CPU)."""
    return torch.linalg.vector_norm(torch.view_as_real(snapshots.resolve_conj()).flatten(1), dim=1)


def range_exponents(snapshots: torch.Tensor, norms: torch.Tensor) -> torch.Tensor | None:
    """Per-row exponents ``e`` (int32 ``(P,)``) such that ``snapshots * 2^-e`` has its largest
    ``|Re|`` or ``|Im|`` in ``[0.5, 1)``, for the rows whose ``norms`` lie outside
    :data:`SAFE_NORM` (``e = 0`` for the others, and for all-zero or non-finite rows); ``None``
    when every row is inside (the common case: one reduction, no copy)."""
    lo, hi = SAFE_NORM
    out = ~((norms >= lo) & (norms <= hi))                       # NaN / inf norms are outside too
    if not bool(out.any()):
        return None
    x = torch.view_as_real(snapshots[out].resolve_conj()).flatten(1)
    amax = torch.maximum(x.amax(dim=1), -x.amin(dim=1)) if x.shape[1] else torch.zeros(len(x), device=x.device)
    _, e = torch.frexp(amax)                                     # amax = m 2^e, m in [0.5, 1)
    e = torch.where(torch.isfinite(amax), e.clamp(-126, 126), torch.zeros_like(e))
    exps = torch.zeros(snapshots.shape[0], dtype=torch.int32, device=snapshots.device)
    exps[out] = e.to(torch.int32)
    return exps


def scaled_snapshots(snapshots: torch.Tensor, exps: torch.Tensor) -> torch.Tensor:
    """``snapshots * 2^-exps`` per row, exactly (scaling by a power of two rounds nothing)."""
    x = torch.view_as_real(snapshots.resolve_conj())
    return torch.view_as_complex(torch.ldexp(x, -exps[:, None, None]).to(x.dtype).contiguous())
