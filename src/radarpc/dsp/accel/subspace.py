"""The subspace beamformer: a certified float32 screen from a block low-rank factorisation of ``B``.

The directions are cut into groups of ``g`` consecutive azimuths (all elevations, ``M = g n_el``
rows of ``B``, consecutive in ``k = az n_el + el``). For each group ``G`` a rank-``r`` basis
``Q_G`` (``r x N``, top right singular vectors of ``B_G``) and coefficients ``C_G = B_G Q_G^H``
give ``B[k] = c_k Q_G + rho_k`` with a residual row ``rho_k`` computed once from the stored
(float32) factors. Per snapshot ``v``::

    y_G = Q_G v              (one float32 GEMM over all groups: G r rows instead of n_az n_el)
    z^_k = c_k . y_G         (one batched float32 GEMM per group)
    |s_k - z^_k| <= e_k = ||rho_k|| R_G + sigma_k ||v||,

with ``R_G >= ||(I - P_G) v||`` the part of ``v`` outside the group's subspace (``P_G`` the
orthogonal projector on it) and ``sigma_k`` the rest: ``|rho_k P_G v| <= ||rho_k P_G|| ||v||``
(``rho_k`` is orthogonal to the subspace up to the rounding of the stored factors) plus the
float32 rounding of both GEMMs. ``R_G`` costs nothing extra: ``||(I - P_G) v||^2 = ||v||^2 -
||P_G v||^2`` and ``||P_G v|| >= ||Q_G v|| / sqrt(lambda_max(Q_G Q_G^H))``, with ``||Q_G v||`` from
the computed ``y_G`` less its rounding bound (:func:`group_residuals`). For a point whose energy
lies in one group's subspace (a target) ``R_G`` is a small part of ``||v||`` (median ~0.2 on
RADIal-like frames), and so is the bound.

The exact maximum lies among ``{k : |z^_k| + e_k >= max_k' (|z^_k'| - e_k')}``; those candidates
are decided by :func:`radarpc.dsp.beamform.certified_argmax` (float64 with a bound, exact rational
arithmetic when that does not separate them), so ``k_j`` is the argmax of the exact spectrum, the
same as :func:`radarpc.dsp.beamform.beamform_peaks`, ties included.

The native selection (:func:`radarpc.dsp.accel.native.subspace_select_native`) adds two
certified shortcuts: a group whose bound ``max_k ||c_k|| ||y_G|| + 2 max_k e_k`` stays below the
lower bound of the groups already screened is skipped (``|z^_k| <= ||c_k|| ||y_G|| + e_k``), and
a point left with many candidates (a flat, noise-like spectrum) first has them evaluated in
float32 with a rigorous rounding bound, so only the few that can still win reach the float64
decision. Nothing assumes the table's structure: a rough table only leaves more candidates.
On RADIal's real grid (751 x 11 directions, a measured-like table with ~1 % error per entry)
groups of 32 azimuths with rank 12 leave a median of 4 candidates and screen 2 of 24 groups per point;
the sizes and the measurements behind them are in ``docs/results/pointcloud.md``.
"""
from __future__ import annotations

import math

import torch

from radarpc.dsp.accel import native
from radarpc.dsp.accel.workspace import Workspace
from radarpc.dsp.beamform import beamform_peaks, certified_argmax
from radarpc.dsp.dictionary import (SNAPSHOT_BLOCK, BeamformResult, DictionaryTables, SubspaceTables, range_exponents,
                                    row_norms, scaled_snapshots, stack_real, tables_for)

__all__ = ["SubspaceTables", "subspace_tables", "group_residuals", "beamform_peaks_subspace", "SUBSPACE_GROUP",
           "SUBSPACE_RANK", "MAX_SUBSPACE_CANDIDATES"]

SUBSPACE_GROUP = 32
"""Azimuths per group (all elevations)."""
SUBSPACE_RANK = 12
"""Basis rank per group (capped at the group's row count and ``N``)."""
MAX_SUBSPACE_CANDIDATES = 256
"""On the torch selection, a point with more candidates runs the exact beamformer (flat spectra:
the GEMM is cheaper there); the native selection has no limit, its float32 pass handles them."""

_U32 = 2.0 ** -24
# Points per screen block of the torch selection: its (G, m, 2M) screen stays a few MB.
_SCREEN_POINTS = 128
# Bytes of the first product per block: one block for a batch of ordinary frames, because every
# switch between torch's GEMM threads and the native selection's threads costs (torch's OpenMP
# workers keep spinning after a GEMM).
_Y_BYTES = 64 << 20


def subspace_tables(rows: torch.Tensor, grid: tuple[int, int], group: int = SUBSPACE_GROUP,
                    rank: int = SUBSPACE_RANK) -> SubspaceTables:
    """Factorise ``B`` (complex64 ``(n_az n_el, N)``, row ``k = az n_el + el``) group by group.

    With ``Q^``, ``c^`` the stored float32 factors and ``rho_k = B[k] - c^_k Q^`` (float64):

    - ``resid_k = ||rho_k||`` and ``||rho_k P|| <= ||rho_k Q^^H|| / sqrt(lambda_min(Q^ Q^^H))``,
      ``lambda`` within ``1 -+ ||Q^ Q^^H - I||_F``;
    - the screen's float32 rounding per real output is at most ``(gamma_2N + gamma_2r (1 + gamma_2N))
      w ||v|| ||w2 col||_1`` (``w`` the largest column norm of ``w1``: ``|y_t| <= w ||v||``,
      Cauchy-Schwarz), ``eta_k = sqrt(2)`` times that over ``||v||``; ``slack_k = ||rho_k P|| + eta_k``;
    - the first GEMM alone: ``y_error = sqrt(2r) gamma_2N w``.

    Every float64 value is inflated by ``2^-30`` and every stored float32 bound by ``2^-20``, far
    more than their rounding.
    """
    if rows.dtype != torch.complex64 or rows.ndim != 2:
        raise ValueError(f"rows must be complex64 (n_dir, N), got {rows.dtype} {tuple(rows.shape)}")
    n_az, n_el = (int(x) for x in grid)
    if n_az * n_el != rows.shape[0]:
        raise ValueError(f"grid {tuple(grid)} does not match the dictionary's {rows.shape[0]} directions")
    for name, val in (("group", group), ("rank", rank)):
        if isinstance(val, bool) or not isinstance(val, int) or val < 1:
            raise ValueError(f"{name} must be an int >= 1, got {val!r}")
    dev = rows.device
    b = rows.detach().to("cpu", torch.complex128)
    n = b.shape[1]
    m_rows = min(group, n_az) * n_el
    r = min(rank, m_rows, n)
    n_groups = math.ceil(n_az / group)
    padded = torch.zeros(n_groups * m_rows, n, dtype=torch.complex128)
    padded[:n_az * n_el] = b
    bg = padded.view(n_groups, m_rows, n)                                   # (G, M, N), zero rows past K
    _, _, vh = torch.linalg.svd(bg.to(torch.complex64), full_matrices=False)   # any basis is valid: rho says how good
    q = vh[:, :r].contiguous()                                              # (G, r, N) stored basis
    q128 = q.to(torch.complex128)
    c = (bg @ q128.conj().transpose(1, 2)).to(torch.complex64)              # (G, M, r) stored coefficients
    rho = bg - c.to(torch.complex128) @ q128                                # (G, M, N)
    inflate = 1.0 + 2.0 ** -30
    resid = torch.linalg.vector_norm(rho, dim=2).reshape(-1) * inflate
    eye = torch.eye(r, dtype=torch.complex128)
    gram_dev = torch.linalg.matrix_norm(q128 @ q128.conj().transpose(1, 2) - eye) * inflate + 2.0 ** -40   # (G,)
    if bool((gram_dev >= 0.5).any()):
        raise ValueError(f"the float32 subspace bases are far from orthonormal (||Q Q^H - I||_F up to "
                         f"{float(gram_dev.max()):.3g}, expected < 0.5): is the dictionary finite?")
    par = (torch.linalg.vector_norm(rho @ q128.conj().transpose(1, 2), dim=2)
           / torch.sqrt(1.0 - gram_dev)[:, None]).reshape(-1) * inflate
    w1 = torch.cat([stack_real(q[g].T.contiguous()) for g in range(n_groups)], dim=1)   # (2N, G 2r)
    cr, ci = c.real.transpose(1, 2), c.imag.transpose(1, 2)                 # (G, r, M)
    w2 = torch.cat([torch.cat([cr, ci], dim=2), torch.cat([-ci, cr], dim=2)], dim=1).contiguous()  # (G, 2r, 2M)
    l1 = (cr.abs() + ci.abs()).double().sum(1).reshape(-1)                  # (G M,)
    gamma = lambda q: q * _U32 / (1.0 - q * _U32)                           # noqa: E731
    w = float(torch.linalg.vector_norm(w1.double(), dim=0).max()) * inflate
    eta = math.sqrt(2.0) * (gamma(2 * n) + gamma(2 * r) * (1.0 + gamma(2 * n))) * w * l1
    up = 1.0 + 2.0 ** -20
    slack = ((par + eta) * up).to(torch.float32)
    resid32 = (resid * up).to(torch.float32)
    coef = torch.stack([w2[:, :r, :m_rows], w2[:, :r, m_rows:]], dim=1).contiguous()   # (G, 2, r, M)
    cnorm = torch.linalg.vector_norm(coef.double(), dim=(1, 2))             # (G, M) ||c_k|| of the stored factors
    cmax = (cnorm.amax(dim=1) * up).to(torch.float32)                       # rounding to float32 stays above
    return SubspaceTables(grid=(n_az, n_el), group=min(group, n_az), rank=r, w1=w1.to(dev), w2=w2.to(dev),
                          coef=coef.to(dev), resid=resid32.to(dev), slack=slack.to(dev), cmax=cmax.to(dev),
                          rmax=resid32.view(n_groups, m_rows).amax(dim=1).to(dev),
                          smax=slack.view(n_groups, m_rows).amax(dim=1).to(dev),
                          gram_max=(1.0 + gram_dev).to(dev), y_error=math.sqrt(2 * r) * gamma(2 * n) * w * up)


def group_residuals(y: torch.Tensor, vnorm2: torch.Tensor, tables: SubspaceTables) -> torch.Tensor:
    """``R_jg``, an upper bound of ``||(I - P_g) v_j||`` for every point and group (float64 ``(P, G)``).

    ``y`` float32 ``(P, >= G 2r)`` the first GEMM's output (:attr:`SubspaceTables.w1`), ``vnorm2``
    float64 ``(P,)`` ``||v_j||^2`` rounded up. ``||Q_g v|| >= ||y^_g|| - y_error ||v||`` and
    ``||P_g v||^2 >= ||Q_g v||^2 / lambda_max``, so ``R^2 = ||v||^2 - (that)^2 / gram_max`` (never below
    0, never above ``||v||``).
    """
    p = y.shape[0]
    n_groups, two_r = tables.n_groups, 2 * tables.rank
    ny = torch.linalg.vector_norm(y[:, :n_groups * two_r].view(p, n_groups, two_r).double(), dim=2)
    vn = vnorm2.sqrt() * (1.0 + 2.0 ** -40)
    low = (ny * (1.0 - (two_r + 2) * 2.0 ** -52) - tables.y_error * vn[:, None]).clamp_min(0.0)
    r2 = vnorm2[:, None] * (1.0 + 2.0 ** -40) - low * low / tables.gram_max.double()[None]
    return r2.clamp_min(0.0).sqrt() * (1.0 + 2.0 ** -40)


def _norm2(v: torch.Tensor) -> torch.Tensor:
    """``||v_j||^2`` in float64, rounded up: products of float32 values are exact, and the sum of
    ``2N`` of them is within ``2N 2^-53`` relative in any order."""
    return torch.view_as_real(v).double().square().sum(dim=(1, 2)) * (1.0 + (2 * v.shape[-1] + 2) * 2.0 ** -52)


def _select_torch(z: torch.Tensor, tables: SubspaceTables, residual: torch.Tensor, xn: torch.Tensor, k_dir: int,
                  max_candidates: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Candidate pairs ``(j, k)`` of a screen block ``z`` ``(G, m, 2M)`` and its heavy points
    (the reference of :func:`radarpc.dsp.accel.native.subspace_select_native`'s selection);
    ``residual`` ``(m, G)`` from :func:`group_residuals`."""
    n_groups, m, two_m = z.shape
    mr = two_m // 2
    a = torch.hypot(z[..., :mr].double(), z[..., mr:].double()).transpose(0, 1).reshape(m, -1)[:, :k_dir]
    r = residual.repeat_interleave(mr, dim=1)[:, :k_dir]
    e = (tables.resid[:k_dir].double()[None, :] * r + tables.slack[:k_dir].double()[None, :] * xn.double()[:, None]
         + 2.0 ** -50 * a)
    low = (a - e).amax(dim=1)
    cand = (a + e) >= low[:, None]
    count = cand.sum(dim=1)
    heavy = (count == 0) | (count > max_candidates) | ~torch.isfinite(a).all(dim=1) | ~torch.isfinite(xn)
    cand &= ~heavy[:, None]
    j, k = torch.nonzero(cand, as_tuple=True)
    return j, k, heavy


def beamform_peaks_subspace(snapshots: torch.Tensor, dictionary_t: torch.Tensor | DictionaryTables,
                            grid: tuple[int, int], *, max_candidates: int | None = None,
                            workspace: Workspace | None = None) -> BeamformResult:
    """``k_j`` and ``Ae_j`` of :func:`~radarpc.dsp.beamform.beamform_peaks`, screened in a subspace
    and certified (module docstring); the same index and amplitude as the exact beamformer.

    Snapshots whose norm lies outside ``[2^-40, 2^40]`` are first scaled by a power of two (exact).
    Points whose screen leaves more than ``max_candidates`` candidates (default: no limit on the
    native selection, :data:`MAX_SUBSPACE_CANDIDATES` on the torch one), none, or is not finite run
    :func:`~radarpc.dsp.beamform.beamform_peaks`. The factorisation is built once per
    :class:`~radarpc.dsp.beamform.DictionaryTables` (kept on it).
    """
    if snapshots.dtype != torch.complex64:
        raise ValueError(f"the subspace beamformer works on complex64 snapshots, got {snapshots.dtype}; "
                         f"use beamform_peaks for other precisions")
    t = tables_for(snapshots, dictionary_t, grid)
    if max_candidates is not None and (isinstance(max_candidates, bool) or int(max_candidates) < 1):
        raise ValueError(f"max_candidates must be an integer >= 1 or None, got {max_candidates!r}")
    ws = Workspace() if workspace is None else workspace
    st = t.subspace
    if st is None or st.w1.device != snapshots.device:
        st = t.subspace = subspace_tables(t.rows, t.grid).to(snapshots.device)
    k_dir = t.n_dir
    p, n = snapshots.shape
    dev = snapshots.device
    v = snapshots.resolve_conj().contiguous()
    vnorm = row_norms(v)
    exps = range_exponents(v, vnorm)
    if exps is not None:
        v = scaled_snapshots(v, exps)
        vnorm = row_norms(v)
    xn = (vnorm * (1.0 + 2.0 ** -14)).contiguous()                    # covers the float32 norm's rounding
    x = torch.view_as_real(v).reshape(p, 2 * n)
    index = torch.empty(p, dtype=torch.long, device=dev)
    amplitude = torch.empty(p, dtype=torch.float32, device=dev)
    heavy = torch.zeros(p, dtype=torch.bool, device=dev)
    native_ok = dev.type == "cpu" and native.native_available()
    if max_candidates is None:
        max_candidates = max(k_dir, 1) if native_ok else MAX_SUBSPACE_CANDIDATES
    n_groups, two_r = st.n_groups, 2 * st.rank
    blk = min(max(SNAPSHOT_BLOCK, _Y_BYTES // (4 * n_groups * two_r)), max(p, 1))
    y = ws.empty("subspace.y", (blk, n_groups * two_r), torch.float32, dev)
    pairs_j, pairs_k = [], []
    for i in range(0, p, blk):
        m = min(blk, p - i)
        yi = torch.mm(x[i:i + m], st.w1, out=y[:m])                    # (m, G 2r): [Re y_g | Im y_g] per group
        if native_ok:                                                  # second product, selection, decision
            idx, amp, amb, hv = native.subspace_select_native(yi, st, xn[i:i + m], v[i:i + m], t.rows, max_candidates,
                                                              row_norm_max=t.row_norm_max * (1.0 + 2.0 ** -20))
            index[i:i + m], amplitude[i:i + m], heavy[i:i + m] = idx, amp, hv
            for q in torch.nonzero(amb).flatten().tolist():           # rare: decided exactly
                zq = torch.bmm(yi[q:q + 1].view(1, n_groups, two_r).transpose(0, 1), st.w2)
                rq = group_residuals(yi[q:q + 1], _norm2(v[i + q:i + q + 1]), st)
                jj, kk, _ = _select_torch(zq, st, rq, xn[i + q:i + q + 1], k_dir, max_candidates)
                index[i + q:i + q + 1], amplitude[i + q:i + q + 1] = certified_argmax(
                    v[i + q:i + q + 1], t.rows, t.grid, jj, kk)
            continue
        for b in range(0, m, _SCREEN_POINTS):                         # torch: cache-sized screen blocks
            mb = min(_SCREEN_POINTS, m - b)
            z = torch.bmm(yi[b:b + mb].view(mb, n_groups, two_r).transpose(0, 1), st.w2)   # (G, mb, 2M)
            rb = group_residuals(yi[b:b + mb], _norm2(v[i + b:i + b + mb]), st)
            jj, kk, hv = _select_torch(z, st, rb, xn[i + b:i + b + mb], k_dir, max_candidates)
            heavy[i + b:i + b + mb] = hv
            pairs_j.append(jj + i + b)
            pairs_k.append(kk)
    if pairs_j:
        light = torch.nonzero(~heavy).flatten()
        if light.numel():
            remap = torch.cumsum(~heavy, 0) - 1
            j = torch.cat(pairs_j)
            idx, amp = certified_argmax(v[light], t.rows, t.grid, remap[j], torch.cat(pairs_k))
            index[light], amplitude[light] = idx, amp
    if bool(heavy.any()):
        rows = torch.nonzero(heavy).flatten()
        full = beamform_peaks(v[rows], t, grid, workspace=ws)
        index[rows], amplitude[rows] = full.index, full.amplitude
    if exps is not None:
        amplitude = torch.ldexp(amplitude, exps).to(torch.float32)
    return BeamformResult(index=index, amplitude=amplitude, sectors=None)
