"""RaLD: the LiDAR occupancy autoencoder (stage 1) and the radar-conditioned latent diffusion model
(stage 2), trained on ColoRadar-layout roots through the one training loop.

* :mod:`.config` -- :class:`~.config.AutoencoderExperiment` and :class:`~.config.DiffusionExperiment`
  (a model of :data:`radarpc.models.MODELS`, the data options, training; ``stage:`` tells them
  apart) and their strict YAML loading;
* :mod:`.task` -- datasets, collate, loss and validation of each stage: the tasks the loop trains;
* :mod:`.train` -- a run of a config in a run folder (stage 2 against a stage-1 run, ``--ae``);
* :mod:`.runs` -- a trained run's weights loaded and checked (:func:`~.runs.load_rald_ae`,
  :func:`~.runs.load_rald`);
* :mod:`.official` -- the official RaLD checkpoints of both stages, read without running pickled code,
  and written as a run folder (``radarpc import-rald``);
* :mod:`.generation` -- a stage-2 run's clouds of a ColoRadar split (``radarpc generate``);
* :mod:`.ablation` -- the paper's ablation studies as arms of configs, trained, generated, scored
  and written as result rows (``radarpc experiment rald-ablation``, ``radarpc report``).
"""
