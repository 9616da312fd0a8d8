"""Experiments: each one a folder of its config, its task for the training loop, and its
evaluation, built on :mod:`radarpc.training` and the model registry :mod:`radarpc.models`.

* :mod:`radarpc.experiments.radial_detection` -- vehicle detection and freespace on RADIal-format
  data (FFTRadNet on RD cubes, polar PointPillars and SpectralPillars on spectral point clouds).
"""
