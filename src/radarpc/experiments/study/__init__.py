"""The spectral point-cloud paper's study: F1 against density, ablations, sparse RD against points,
and the frames/s table.

* :mod:`.config` -- the study configs (:class:`~.config.DensitySweepConfig`,
  :class:`~.config.AblationConfig`: data, sensor, densities, models as detection experiments
  with overrides and enrichments, seeds, budget; :class:`~.config.FPSConfig`: models, inputs and
  timing of the FPS study); strict YAML;
* :mod:`.grid` -- a study as a grid of runs (arms x densities x seeds), the same for both kinds;
* :mod:`.inputs` -- simulated roots, point stores and sparse-RD roots, made once and cached by content;
* :mod:`.results` -- one portable result row per finished run, its key, and the resume checks;
* :mod:`.runner` -- trains, scores and records the runs of a grid that are not finished;
* :mod:`.report` -- Markdown tables and figures from the rows;
* :mod:`.fps` -- the FPS study (the paper's Table 2): every model at every density timed at batch 1,
  each row in a fresh process (:mod:`.fps_worker`), with its report (:mod:`.fps_report`);
* :mod:`.provenance` -- the commands, configs and commits every report states.

The runs themselves are the detection experiment's (:mod:`radarpc.experiments.radial_detection`).
"""
