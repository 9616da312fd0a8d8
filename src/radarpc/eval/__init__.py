"""Metrics: point sets (Chamfer, EMD) and, from the other stages, detection and segmentation; the
prediction-folder layout they read (:mod:`radarpc.eval.predictions`)."""
from radarpc.eval.pointsets import (
    EMD_POINTS,
    EMD_SEED,
    ChamferTarget,
    CloudPair,
    FrameMetrics,
    PointSetReport,
    SceneSummary,
    chamfer_distance,
    chamfer_distance_batch,
    earth_movers_distance,
    earth_movers_distance_batch,
    earth_movers_distance_equal,
    emd_resample,
    emd_subset,
    evaluate_clouds,
)
from radarpc.eval.predictions import check_index, index_frames, prediction_pairs, prediction_path

__all__ = [
    "EMD_POINTS",
    "EMD_SEED",
    "ChamferTarget",
    "CloudPair",
    "FrameMetrics",
    "PointSetReport",
    "SceneSummary",
    "chamfer_distance",
    "chamfer_distance_batch",
    "earth_movers_distance",
    "earth_movers_distance_batch",
    "earth_movers_distance_equal",
    "emd_resample",
    "emd_subset",
    "evaluate_clouds",
    "check_index",
    "index_frames",
    "prediction_pairs",
    "prediction_path",
]
