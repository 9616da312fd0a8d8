"""Sparse-RD roots: the RD cubes of a RADIal root masked to the set a point store encodes.

:func:`write_sparse_rd` writes the RD cubes masked to the set the matching point store encodes
(``S(tau)``, or ``S*(tau)`` with ``rdN``; same envelope, CFAR and per-frame taus as
:func:`radarpc.pipelines.pointclouds.convert_dataset`) as a new RADIal-layout root (labels,
freespace, calibration and sensor description linked or copied) that the unchanged
:class:`~radarpc.data.radial.RADIal` reader and the dense FFTRadNet read: the sparse-RD baseline.
Each masked cube is stored compressed (``radar_FFT/fft_*.npz``,
:func:`~radarpc.data.radial_format.save_fft_npz`), so the root's size follows the density of the
kept set, not the size of the source.
The root is a :class:`radarpc.runs.RunFolder` (locked for the run, ``sparse_rd.json`` its manifest)
and resumes frame by frame.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from radarpc import __version__
from radarpc.data.radial_format import (LABEL_COLUMNS, SPARSE_RD_MANIFEST, freespace_path, save_calibration,
                                        save_fft_npz, stored_fft_path)
from radarpc.distributed import DistEnv, rank_device
from radarpc.dsp.sparse_rd import encoded_sparse_rd
from radarpc.io import DataFileError, atomic_write
from radarpc.pipelines.pointclouds import (ConvertSettings, build_point_cloud, calibrate_tau,
                                           calibration_source_of, check_dsp_settings)
from radarpc.pipelines.sources import Source, batched, open_source, prefetched, source_fingerprint
from radarpc.runs import OutputLock, RunFolder, RunMismatchError, check_writable, is_temp_name, read_json

__all__ = ["SparseRDResult", "write_sparse_rd"]


@dataclass(frozen=True)
class SparseRDResult:
    """Outcome of :func:`write_sparse_rd`."""

    root: Path                       # the sparse-RD root
    n_frames: int                    # frames in the root
    frames_written: int              # cubes computed in this call (the others existed)
    achieved_density: float          # mean density over every frame of the root, those written now and
    #                                  those kept from an earlier run (the manifest's mean_density; nan if none)
    tau: float | None                # fixed or calibrated threshold (None in per-frame mode)
    frame_tau: dict[int, float] = dataclasses.field(default_factory=dict)      # per frame (numSample), all recorded frames
    frame_density: dict[int, float] = dataclasses.field(default_factory=dict)  # per frame, density of the kept set


def _link_or_copy(src: Path, dst: Path, *, overwrite: bool = False) -> None:
    """Hard-link ``src`` to ``dst`` (copy across file systems), atomically; an existing ``dst`` is
    kept unless ``overwrite``."""
    if dst.exists() and not overwrite:
        return
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def _write_split_labels(src: Path, dst: Path, keep: set[int]) -> None:
    """Copy ``labels.csv`` keeping only the rows of frames ``keep`` (atomic)."""
    with open(src, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.reader(f))
    if not rows or tuple(h.strip() for h in rows[0]) != LABEL_COLUMNS:
        raise DataFileError(src, "header is not RADIal's labels header")
    with atomic_write(dst, "w") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(rows[0])
        for r in rows[1:]:
            if r and int(float(r[0])) in keep:
                w.writerow(r)


def _write_png(path: Path, mask: np.ndarray) -> None:
    """A 2-D uint8 mask as a greyscale PNG, atomically."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as f:
        Image.fromarray(np.ascontiguousarray(mask, dtype=np.uint8)).save(f, format="PNG")


def _write_labels_from_dataset(ds: Any, dst: Path) -> None:
    """``labels.csv`` from a dataset object's raw rows (``frame_labels(i)``), atomic."""
    if not hasattr(ds, "frame_labels"):
        raise ValueError(f"{type(ds).__name__} has neither a root folder nor frame_labels(i): cannot write "
                         f"the sparse root's labels.csv")
    with atomic_write(dst, "w") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(LABEL_COLUMNS)
        for i in range(len(ds)):
            for row in ds.frame_labels(i):
                w.writerow([row[c] for c in LABEL_COLUMNS])


def write_sparse_rd(
    source: Source,
    out_root: str | os.PathLike,
    settings: ConvertSettings | None = None,
    *,
    batch_size: int = 8,
    calibration_source: Source | None = None,
    calibrated_tau: float | None = None,
    device: torch.device | str | None = None,
    resume: bool = True,
    overwrite: bool = False,
    progress: bool = True,
    **fields: Any,
) -> SparseRDResult:
    """Write a RADIal-layout root whose RD cubes are masked to the set the point store encodes.

    ``R_sparse[r, d, c] = R[r, d, c]`` if ``(r, d)`` is in the encoded set else 0 (all Rx
    channels kept). The encoded set is exactly the one :func:`convert_dataset` with the same
    arguments turns into points: ``S(tau)`` (the ``n_tx`` replica bins of every CFAR peak), or
    with an ``rdN`` enrichment ``S*(tau)`` (the replica bins of every cell of the ``n x n``
    neighbourhoods), with the same envelope, CFAR and per-frame (or calibrated) taus; a density
    target applies to that set. ``labels.csv`` (restricted to the split's frames), the freespace
    PNGs, ``calibration.npz`` / ``CalibrationTable.npy`` and ``sensor.json`` are hard-linked (or
    copied) from the source root; for a dataset object without a ``root`` (SimulatedRADIal),
    ``labels.csv`` is written from ``frame_labels(i)``, ``calibration.npz`` and ``sensor.json``
    from its calibration and sensor, and the freespace PNGs from ``freespace_mask(i)`` (when the
    object has it; ``sparse_rd.json`` records ``"freespace"``). Each cube is written
    atomically as a compressed ``radar_FFT/fft_{numSample:06d}.npz`` (one complex64 array,
    ``arr_0``): the zero cells cost almost nothing, so at density ``d`` a cube takes roughly ``d``
    of the bytes of its dense ``.npy``. Existing cubes (``.npz``, or ``.npy`` of a root written by
    an older radarpc) are kept when ``resume`` (so a killed run resumes).

    ``sparse_rd.json`` records the source, the settings and the tau (a resumed run must match
    them), every frame's tau and achieved density (``frames``: numSample -> ``{"tau",
    "density", "peak_density"}``), their mean, and whether the run completed.

    Parameters are those of :func:`~radarpc.pipelines.pointclouds.convert_dataset` (``settings``
    whole, or its fields), plus ``calibrated_tau``: in per-dataset mode,
    the tau already calibrated for the matching store (``ConvertResult.tau``), used instead of
    calibrating again.

    Returns
    -------
    SparseRDResult
    """
    settings = ConvertSettings.given(settings, fields)
    # The mask does not depend on how directions are found, nor the root on the part size.
    settings = dataclasses.replace(settings, beamforming="auto", chunk_frames=64)
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    out_root = Path(out_root)
    ds, source_id, split_used = open_source(source, settings.split)
    settings = dataclasses.replace(settings, split=split_used)
    root = Path(ds.root) if getattr(ds, "root", None) is not None else None
    if root is not None and root.resolve() == out_root.resolve():
        raise ValueError(f"the sparse-RD root must differ from the source root {root}")
    dev = rank_device(device, DistEnv())
    check_dsp_settings(settings, ds, source_id)
    cal_src, cal_id = (None, None)
    if settings.mode == "per-dataset":
        try:
            cal_src, cal_id = calibration_source_of(source, ds, calibration_source)
        except ValueError:
            if calibrated_tau is None:                 # nothing to calibrate on
                raise
            cal_id = f"given tau {float(calibrated_tau)!r}"
    if out_root.exists() and not out_root.is_dir():
        raise NotADirectoryError(f"the sparse-RD root {out_root} exists and is not a folder")
    check_writable(out_root, "sparse-RD root")
    with OutputLock(out_root, "sparse-RD root") as lock:
        return _write_locked(ds, source_id, out_root, settings, root, dev, cal_src, cal_id, lock,
                             batch_size=int(batch_size), calibrated_tau=calibrated_tau, resume=resume,
                             overwrite=overwrite, progress=progress)


def _write_locked(ds: Any, source_id: str, out_root: Path, settings: ConvertSettings, root: Path | None,
                  dev: torch.device, cal_src: Any, cal_id: str | None, lock: OutputLock, *, batch_size: int,
                  calibrated_tau: float | None, resume: bool, overwrite: bool, progress: bool) -> SparseRDResult:
    info_path = out_root / SPARSE_RD_MANIFEST
    if out_root.is_dir() and not info_path.exists() and any(not is_temp_name(p.name) for p in out_root.iterdir()):
        raise FileExistsError(f"{out_root} is not empty and is not a sparse-RD root (no sparse_rd.json): "
                              f"refusing to write masked cubes into it; choose a new or empty folder")
    key = {"source_root": source_id, "settings": settings.output_key(), "source_files": source_fingerprint(ds),
           "calibration_source": cal_id}
    if not overwrite and info_path.exists() and not isinstance(read_json(info_path), dict):
        raise DataFileError(info_path, "is unreadable; pass overwrite=True (CLI: --overwrite) to rewrite the root")
    # sparse_rd.json is the run's manifest: the key, then the records of every frame written
    run = RunFolder(out_root, {info_path.name: key}, what="sparse-RD root", indent=1, lock=lock)
    # Another request (other settings or source root) needs overwrite; the same request on changed
    # source files is written again (as a point store is converted again).
    other = sorted({"settings" if k == "*" else k for k in run.changed_keys()}
                   - {"source_files", "calibration_source"}) if info_path.exists() else []
    try:
        run.start(overwrite=overwrite or not other, resume=resume, write_manifests=False)
    except RunMismatchError:
        raise FileExistsError(f"{out_root} holds a sparse-RD root made with other {' and '.join(other)} (see "
                              f"{info_path}); pass overwrite=True (CLI: --overwrite) to replace it, or choose "
                              f"another folder") from None
    prev = read_json(info_path) if run.resumed else None
    cal_tau = settings.tau
    if settings.mode == "per-dataset":
        if prev is not None:
            cal_tau = prev["tau"]
        elif calibrated_tau is not None:
            cal_tau = float(calibrated_tau)
        else:
            cal_tau = calibrate_tau(cal_src, settings, batch_size=batch_size, device=dev, progress=progress)
        if calibrated_tau is not None and cal_tau != float(calibrated_tau):
            raise ValueError(f"calibrated_tau={calibrated_tau} differs from the tau {cal_tau} of the existing "
                             f"sparse root {out_root}; pass resume=False to rewrite it")
    spc = build_point_cloud(ds, settings, cal_tau, dev)

    frames: dict[str, dict] = dict(prev.get("frames") or {}) if prev is not None else {}
    info = dict(key, tau=cal_tau, mode=settings.mode, radarpc_version=__version__, complete=False,
                frames=frames)
    run.write_manifest(info_path.name, info)
    if root is not None:
        for name in ("calibration.npz", "CalibrationTable.npy", "sensor.json"):
            if (root / name).is_file():
                _link_or_copy(root / name, out_root / name, overwrite=not resume)
        if not resume or not (out_root / "labels.csv").is_file():
            _write_split_labels(root / "labels.csv", out_root / "labels.csv", set(ds.frame_ids))
    else:
        if not resume or not (out_root / "calibration.npz").is_file():
            save_calibration(out_root / "calibration.npz", ds.calibration)
        if not resume or not (out_root / "sensor.json").is_file():
            with atomic_write(out_root / "sensor.json", "w") as f:
                json.dump(ds.sensor.to_dict(), f, indent=1)
        if not resume or not (out_root / "labels.csv").is_file():
            _write_labels_from_dataset(ds, out_root / "labels.csv")

    # a frame is done when its cube is on disk and recorded (a run killed between the two redoes it)
    todo = [p for p in range(len(ds)) if not (resume and str(ds.frame_ids[p]) in frames
                                              and stored_fft_path(out_root, ds.frame_ids[p]) is not None)]
    it = prefetched(ds, batched(todo, batch_size), dev)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=-(-len(todo) // batch_size), desc=f"sparse RD {Path(source_id).name}", unit="batch")
    written: list[float] = []
    with torch.no_grad():
        for pos, rd in it:                                                 # rd: (B, Nr, Nd, Nrx)
            # the point cloud's detection, its full-grid set (B, Nr, Nd) and the masked cubes (B, Nr, Nd, Nrx)
            sparse, mask_full, enc = encoded_sparse_rd(spc, rd)
            dens = mask_full.double().mean(dim=(1, 2)).cpu()               # (B,) encoded-set density
            peak = enc.peaks.flatten(1).double().sum(1).cpu() * ds.sensor.n_tx / (
                ds.sensor.n_range * ds.sensor.n_doppler)                   # (B,) |S(tau)| / (Nr ND)
            for b, p in enumerate(pos):
                num = ds.frame_ids[p]
                save_fft_npz(out_root, num, sparse[b].cpu().numpy().astype(np.complex64))
                frames[str(num)] = {"tau": float(enc.tau[b]), "density": float(dens[b]),
                                    "peak_density": float(peak[b])}
                written.append(float(dens[b]))
            run.write_manifest(info_path.name, info)                         # the records so far (resume)
    has_freespace = root is not None or callable(getattr(ds, "freespace_mask", None))
    for i, num in enumerate(ds.frame_ids):
        dst = freespace_path(out_root, num)
        if root is not None:
            if freespace_path(root, num).is_file():
                _link_or_copy(freespace_path(root, num), dst, overwrite=not resume)
        elif has_freespace and (not resume or not dst.is_file()):
            _write_png(dst, ds.freespace_mask(i))
    recorded = [frames[str(num)] for num in ds.frame_ids if str(num) in frames]
    mean_density = float(np.mean([r["density"] for r in recorded])) if recorded else None
    info.update(complete=True, frames_written_last_run=len(todo),
                mean_density_last_run=float(np.mean(written)) if written else None,
                mean_density=mean_density, freespace=has_freespace)
    run.write_manifest(info_path.name, info)
    return SparseRDResult(out_root, len(ds), len(todo), float("nan") if mean_density is None else mean_density,
                          cal_tau, frame_tau={int(k): v["tau"] for k, v in frames.items()},
                          frame_density={int(k): v["density"] for k, v in frames.items()})
