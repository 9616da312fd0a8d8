"""RADIal detection and freespace: FFTRadNet, polar PointPillars and SpectralPillars.

* :mod:`.config` -- :class:`~.config.ExperimentConfig` (a model of :data:`radarpc.models.MODELS`,
  targets, loss, training) and its YAML loading;
* :mod:`.task` -- datasets, collate, loss and validation: the task the training loop trains;
* :mod:`.train` -- runs of a config in a run folder (seeds, summary);
* :mod:`.evaluation` -- a run's best weights scored on a split, and the classical detector;
* :mod:`.official` -- official FFTRadNet checkpoints and configs as a run folder.
"""
