"""The learned baseline of RaLD's Table 2: a supervised radar-to-occupancy network (RPDNet-style),
trained on ColoRadar-layout roots through the one training loop, a sibling of
:mod:`radarpc.experiments.rald`.

* :mod:`.config` -- :class:`~.config.OccupancyExperiment` (``stage: occupancy``: a model of
  :data:`radarpc.models.MODELS`, RaLD's radar input, the target grid and loss weight, training) and
  its strict YAML loading;
* :mod:`.task` -- frames (RaLD's radar cube, the LiDAR truth's occupancy of the target grid), the
  weighted BCE and the validation: the task the loop trains;
* :mod:`.train` -- a run of a config in a run folder;
* :mod:`.runs` -- a trained run's weights loaded and checked (:func:`~.runs.load_occupancy_run`);
* :mod:`.generation` -- a run's clouds of a ColoRadar split (``radarpc generate RUN``), in the
  prediction-folder layout RaLD's generation writes.
"""
