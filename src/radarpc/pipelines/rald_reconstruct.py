"""RaLD's autoencoder reconstruction of a ColoRadar split: one cloud per paired frame, decoded from the
latents the stage-1 autoencoder encodes from the frame's own LiDAR, resumably.

The upper bound of generation with this autoencoder (:mod:`radarpc.rald.reconstruct`), written as a
prediction folder that ``radarpc evaluate-points`` scores beside the generated and OS-CFAR clouds.
The folder, its ownership and resume are a generation's (:mod:`radarpc.pipelines.rald_generate`,
the same loop :func:`~radarpc.pipelines.rald_generate.fill_rald_folder`):

* ``generation.json`` -- the key: method ``rald-ae``, ``"kind": "reconstruction"`` (a generation's
  key has no kind), the dataset root (resolved) and split, the generation config without the
  sampler's fields (:data:`SAMPLER_FIELDS`: a reconstruction has no sampler), the guide config,
  the reconstruction config (the posterior decoded), the occupancy grid, ``mirror_azimuth`` and the
  caller's model identity (the stage-1 run folder, a locator not compared, and a digest of its
  weights); the method differs from a generation's, so the two never share a folder without
  ``overwrite``;
* ``{run}/{frame:06d}.npy`` -- float32 ``(N, 3)`` Cartesian points in the single-chip radar frame;
* ``generation.csv`` -- per frame as a generation's, with seconds per stage of
  :data:`~radarpc.rald.reconstruct.RECONSTRUCTION_STAGES` (encoding, decoding, refinement);
* ``index.json`` -- the frames, the key's settings and the list ``empty_frames``.

Per frame: the frame's LiDAR cropped to the field of view
(:meth:`radarpc.data.coloradar.ColoRadar.lidar_points`, the truth ``evaluate-points`` scores
against), the encoder's input ``encoder_input(lidar, generator)`` drawn with
:func:`~radarpc.rald.reconstruct.points_generator` of the frame's seed (the caller's draw: the one
the autoencoder's training makes), the guide points of the frame's radar as a generation's
(:func:`radarpc.rald.guide.guide_points`), then :func:`radarpc.rald.reconstruct.reconstruct_cloud`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import torch

from radarpc.config import to_dict
from radarpc.dsp.tdm import RadarCube
from radarpc.pipelines.rald_generate import GenerationJob, GenerationRun, fill_rald_folder, grid_key, paired_frames
from radarpc.rald.frustum import RALD_GRID, FrustumGrid
from radarpc.rald.generate import GeneratedCloud, GenerationConfig
from radarpc.rald.reconstruct import RECONSTRUCTION_STAGES, ReconstructionConfig, points_generator, reconstruct_cloud
from radarpc.rald.voxels import CartesianGrid

__all__ = ["METHOD", "KIND", "SAMPLER_FIELDS", "reconstruction_settings", "reconstruct_predictions"]

METHOD = "rald-ae"
KIND = "reconstruction"
SAMPLER_FIELDS: tuple[str, ...] = ("num_steps", "sigma_min", "sigma_max", "rho")
"""The fields of :class:`~radarpc.rald.generate.GenerationConfig` that only the diffusion sampler reads."""


def reconstruction_settings(cfg: GenerationConfig) -> dict:
    """``cfg`` as a reconstruction's key holds it: without the sampler's fields."""
    return {k: v for k, v in to_dict(cfg).items() if k not in SAMPLER_FIELDS}


def reconstruct_predictions(job: GenerationJob, ae: torch.nn.Module, *,
                            encoder_input: Callable[[np.ndarray, torch.Generator], torch.Tensor],
                            reconstruction: ReconstructionConfig = ReconstructionConfig(),
                            grid: FrustumGrid | CartesianGrid = RALD_GRID, mirror_azimuth: bool = False,
                            model: Mapping[str, object] | None = None, progress: bool = True,
                            on_warning: Callable[[str], None] | None = None) -> GenerationRun:
    """Run the reconstruction ``job`` (see the module docstring).

    Parameters
    ----------
    job : GenerationJob
        Root, split, output, the query settings (the sampler's are not read), guide, overwrite.
    ae : torch.nn.Module
        The autoencoder (:class:`~radarpc.models.vecset.VecSetAutoencoder`), on the device to run on;
        put in evaluation mode here.
    encoder_input : callable
        ``encoder_input(lidar, generator)``: the encoder's points ``(N, 3)`` (model coordinates) of
        the frame's LiDAR ``(M, 3)`` (radar frame, metres), drawn with ``generator``.
    reconstruction : ReconstructionConfig
        The posterior's sample (official) or mean.
    grid, mirror_azimuth
        The autoencoder's grid and frame (:func:`radarpc.pipelines.rald_generate.generate_predictions`).
    model : mapping, optional
        JSON-able identity of the weights, part of the key.
    progress : bool
    on_warning : callable, optional
        Each empty frame's warning line, as it happens.

    Returns
    -------
    GenerationRun
        Its ``seconds`` per reconstruction stage.

    Raises
    ------
    ValueError
        The split has no paired frame.
    radarpc.io.DataFileError
        A frame has no LiDAR point in the field of view to encode.
    radarpc.runs.RunMismatchError
        The folder holds anything but a reconstruction with this key, without ``overwrite``.
    radarpc.runs.OutputBusyError
        Another process writes the folder.
    """
    ds = paired_frames(job)
    cfg = job.generation
    key = {"method": METHOD, "kind": KIND, "root": str(Path(job.root).resolve()), "split": job.split,
           "every": ds.every, "generation": reconstruction_settings(cfg), "guide": to_dict(job.guide),
           "reconstruction": to_dict(reconstruction), "grid": grid_key(grid), "mirror_azimuth": bool(mirror_azimuth),
           "model": dict(model or {})}
    ae.eval()

    def cloud(i: int, cube: RadarCube, guide: np.ndarray, seed: int) -> GeneratedCloud:
        lidar = ds.lidar_points(i)                                         # (M, 3) radar frame, M >= 1
        points = encoder_input(lidar, points_generator(seed))                            # (N, 3) model coords
        return reconstruct_cloud(ae, points, guide, cfg, seed, posterior=reconstruction.posterior, grid=grid,
                                 mirror_azimuth=mirror_azimuth)

    return fill_rald_folder(job, ds, key, cloud, stages=RECONSTRUCTION_STAGES, desc=f"RaLD-AE {job.split}",
                            progress=progress, on_warning=on_warning)
