"""Metrics: point sets (Chamfer, EMD) and, from the other stages, detection and segmentation."""
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
    emd_subset,
    evaluate_clouds,
)

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
    "emd_subset",
    "evaluate_clouds",
]
