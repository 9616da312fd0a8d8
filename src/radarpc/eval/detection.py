"""RADIal's detection and freespace metrics, with the official code's two faults fixed.

Detection (RADIal ``FFTRadNet/utils/metrics.py`` ``GetFullMetrics``; facts, not code, carried
over). Every detection and label becomes RADIal's fixed ``1.8 m x 4 m`` axis-aligned box whose
near edge is centred on the point (:func:`radarpc.boxes.ra_to_box_xy`,
``x = R sin A``, ``y = R cos A``). Labels are kept when ``5 <= R <= 100`` m; detections, as
the official code does, when the near-edge forward distance ``5 <= y = R cos A <= 100`` m. For each
confidence threshold ``t`` in 0.1, 0.2, ..., 0.9 the detections with score ``> t`` (strictly) are
scored: a detection is a true positive if its box IoU with *any* kept label is ``>= 0.5`` (two
detections on one label are both true positives; NMS at decoding makes that rare), else a false
positive; a label that no such detection reaches is a false negative. Counts are summed over
frames, then ``P_t = TP / (TP + FP)`` and ``R_t = TP / (TP + FN)``, both 0 when ``TP = 0`` (the
official convention: a threshold without true positives scores 0, also when there was nothing to
find). ``AP`` and ``AR`` are the means of ``P_t`` and ``R_t`` over the 9 thresholds and
``F1 = 2 AP AR / (AP + AR)`` (0 when both are 0).

Also reported (the seed's density sweeps): precision, recall and ``F1 = 2 P R / (P + R)`` at the
single confidence threshold 0.2.

Not in RADIal, to tell a localisation error from a missed vehicle: ``fn_near`` counts, per
threshold, the false-negative labels that a detection above the threshold comes within
``NEAR_MISS_M`` (3 m, between the two reference points) of: the vehicle was found, but its box
is off by enough to fail IoU 0.5 (e.g. 0.6 m sideways with the range right).

Range and azimuth errors differ from the official code on purpose. The official code divides by
the number of matched pairs, which is zero at a threshold without true positives, and it takes
the wrong box columns (the lateral metre difference of a corner as "range error" and the forward
metre difference as "angle error"). Here they are the true errors of matched pairs: over every
(detection, label) pair with IoU ``>= 0.5`` at a threshold, the mean ``|R_det - R_label|`` (m) and
``|A_det - A_label|`` (deg); then, as the official code, the mean over the thresholds, skipping
thresholds without a matched pair (NaN if there is none at all).

Freespace (RADIal ``run_FullEvaluation``): rows ``0..123`` of the ``256 x 224`` map (0-50 m),
prediction ``probability >= 0.5``, IoU per frame, averaged over frames. A frame whose prediction
and label are both empty has no IoU (the official code gives NaN and so a NaN mean); it is left
out of the mean here.

The accumulators keep their sums in one float64 tensor (``counts``), so data-parallel
evaluation sums them across ranks (``all_reduce``) before :meth:`DetectionMetrics.compute`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from radarpc.boxes import BOX_WIDTH_M, Detections, box_iou, ra_to_box_xy

__all__ = [
    "THRESHOLDS",
    "FIXED_THRESHOLD",
    "IOU_THRESHOLD",
    "RANGE_GATE_M",
    "NEAR_MISS_M",
    "FREESPACE_ROWS",
    "lateral_tolerance_m",
    "DetectionReport",
    "DetectionMetrics",
    "FrameMatch",
    "match_frame",
    "evaluate_detections",
    "freespace_iou",
    "FreespaceMetrics",
]

THRESHOLDS: tuple[float, ...] = tuple(k / 10 for k in range(1, 10))
"""RADIal's confidence thresholds 0.1 .. 0.9."""
FIXED_THRESHOLD = 0.2
"""The seed's single confidence threshold of its density sweeps."""
IOU_THRESHOLD = 0.5
RANGE_GATE_M = (5.0, 100.0)
NEAR_MISS_M = 3.0
"""A missed label with a detection this close (m) is a localisation miss (``fn_near``)."""
FREESPACE_ROWS = 124
"""Freespace rows scored: 0..123 of 256 (0-50 m)."""


def lateral_tolerance_m(iou_threshold: float = IOU_THRESHOLD) -> float:
    """Largest offset across (m) at which two of RADIal's boxes, level along, still match.

    Equal axis-aligned boxes ``W x L`` offset by ``dx`` across overlap ``(W - dx) L`` of a union
    ``(W + dx) L``, so ``IoU >= t`` exactly when ``dx <= W (1 - t) / (1 + t)``: 0.6 m for
    ``W = 1.8 m`` and ``t = 0.5``.

    Parameters
    ----------
    iou_threshold : float
        In (0, 1).
    """
    if not 0.0 < iou_threshold < 1.0:
        raise ValueError(f"iou_threshold must be in (0, 1), got {iou_threshold}")
    return BOX_WIDTH_M * (1 - iou_threshold) / (1 + iou_threshold)


# columns of DetectionMetrics.counts
_TP, _FP, _FN, _PAIRS, _DR, _DA, _FN_NEAR, _LABELS = range(8)


@dataclass(frozen=True)
class DetectionReport:
    """RADIal detection metrics (see the module docstring for every definition).

    Attributes
    ----------
    thresholds : confidence thresholds of the sweep
    tp, fp, fn : counts per threshold
    fn_near : per threshold, the false negatives with a detection within ``NEAR_MISS_M``
    precision, recall : per threshold
    ap, ar, f1 : means over the sweep and their F1
    range_error_m, azimuth_error_deg : mean absolute errors of matched pairs (NaN without pairs)
    fixed_threshold : the single threshold (0.2)
    precision_fixed, recall_fixed, f1_fixed : at ``fixed_threshold``
    range_error_fixed_m, azimuth_error_fixed_deg : matched-pair errors at ``fixed_threshold``
    fn_fixed, fn_near_fixed : false negatives, and those with a detection within ``NEAR_MISS_M``,
        at ``fixed_threshold``
    n_labels : labels scored (inside the range gate)
    n_frames : frames scored
    """

    thresholds: tuple[float, ...]
    tp: tuple[int, ...]
    fp: tuple[int, ...]
    fn: tuple[int, ...]
    fn_near: tuple[int, ...]
    precision: tuple[float, ...]
    recall: tuple[float, ...]
    ap: float
    ar: float
    f1: float
    range_error_m: float
    azimuth_error_deg: float
    fixed_threshold: float
    precision_fixed: float
    recall_fixed: float
    f1_fixed: float
    range_error_fixed_m: float
    azimuth_error_fixed_deg: float
    fn_fixed: int
    fn_near_fixed: int
    n_labels: int
    n_frames: int

    def to_dict(self) -> dict:
        """Plain JSON-able dict (NaN stays a float NaN; ``json.dumps`` writes it as ``NaN``)."""
        return {f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v)
                for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class FrameMatch:
    """RADIal's matching of one frame (:func:`match_frame`), float64 on the CPU.

    ``kept`` ``(K,)`` marks the detections inside the range gate (near-edge ``y``); the other
    detection fields hold those ``K'`` only, the label fields the ``M'`` labels inside the gate
    (range ``R``), and ``hit`` ``(K', M')`` is box IoU >= the IoU threshold.
    """

    kept: torch.Tensor
    score: torch.Tensor
    range_m: torch.Tensor
    azimuth_deg: torch.Tensor
    label_range_m: torch.Tensor
    label_azimuth_deg: torch.Tensor
    xy: torch.Tensor
    label_xy: torch.Tensor
    hit: torch.Tensor


def match_frame(score: torch.Tensor, range_m: torch.Tensor, azimuth_deg: torch.Tensor, labels: torch.Tensor, *,
                iou_threshold: float = IOU_THRESHOLD,
                range_gate_m: tuple[float, float] = RANGE_GATE_M) -> FrameMatch:
    """Gate one frame's detections ``(K,)`` and labels ``(M, >= 2)`` (range, azimuth in columns 0
    and 1) as RADIal does, and match their fixed boxes; in float64 on the CPU, so that a float32
    score of 0.2 is above the threshold 0.2 wherever it is computed."""
    lo, hi = range_gate_m
    score, range_m, azimuth_deg = (t.detach().to("cpu", torch.float64) for t in (score, range_m, azimuth_deg))
    lab = labels[:, :2].detach().to("cpu", torch.float64)
    lab = lab[(lab[:, 0] >= lo) & (lab[:, 0] <= hi)]
    xy = ra_to_box_xy(range_m, azimuth_deg)                                     # (K, 2)
    kept = (xy[:, 1] >= lo) & (xy[:, 1] <= hi)                                  # near-edge y, as RADIal
    xy_l = ra_to_box_xy(lab[:, 0], lab[:, 1])                                   # (M', 2)
    return FrameMatch(kept, score[kept], range_m[kept], azimuth_deg[kept], lab[:, 0], lab[:, 1], xy[kept], xy_l,
                      box_iou(xy[kept], xy_l) >= iou_threshold)                 # hit (K', M')


def _prf(tp: float, fp: float, fn: float) -> tuple[float, float]:
    if tp == 0:
        return 0.0, 0.0
    return tp / (tp + fp), tp / (tp + fn)


def _f1(p: float, r: float) -> float:
    return 2 * p * r / (p + r) if p + r > 0 else 0.0


class DetectionMetrics:
    """Accumulates RADIal's detection counts over batches; :meth:`compute` gives the report.

    Parameters
    ----------
    thresholds : confidence thresholds of the sweep (RADIal's 0.1 .. 0.9)
    fixed_threshold : the single threshold also reported (0.2)
    iou_threshold : box IoU of a true positive (0.5)
    range_gate_m : ``(min, max)`` kept range, inclusive (5, 100)

    Attributes
    ----------
    counts : float64 ``(len(thresholds) + 1, 8)``
        Per threshold (the last row is ``fixed_threshold``): TP, FP, FN, matched pairs, sum of
        ``|dR|`` (m), sum of ``|dA|`` (deg), FN with a detection within ``NEAR_MISS_M``, labels
        (the same in every row). Sum it across processes before :meth:`compute`.
    n_frames : int
    """

    def __init__(self, thresholds: tuple[float, ...] = THRESHOLDS, fixed_threshold: float = FIXED_THRESHOLD,
                 iou_threshold: float = IOU_THRESHOLD, range_gate_m: tuple[float, float] = RANGE_GATE_M) -> None:
        if not thresholds:
            raise ValueError("DetectionMetrics: thresholds must not be empty")
        self.thresholds = tuple(float(t) for t in thresholds)
        self.fixed_threshold = float(fixed_threshold)
        self.iou_threshold = float(iou_threshold)
        self.range_gate_m = (float(range_gate_m[0]), float(range_gate_m[1]))
        self.counts = torch.zeros(len(self.thresholds) + 1, 8, dtype=torch.float64)
        self.n_frames = 0

    def update(self, detections: Detections, labels: torch.Tensor, label_offset: torch.Tensor) -> None:
        """Add a batch: ``detections`` of ``B`` frames and their offset-batched labels.

        Parameters
        ----------
        detections : Detections
        labels : float ``(M, >= 2)``, columns 0 and 1 range (m) and azimuth (deg)
        label_offset : LongTensor ``(B,)``, frame ``b`` holds label rows
            ``label_offset[b-1]:label_offset[b]``
        """
        if labels.ndim != 2 or labels.shape[1] < 2:
            raise ValueError(f"labels must be (M, >= 2) with range_m, azimuth_deg in columns 0 and 1, got "
                             f"shape {tuple(labels.shape)}")
        if label_offset.numel() != len(detections):
            raise ValueError(f"detections hold {len(detections)} frames but label_offset {label_offset.numel()}")
        t = torch.tensor(self.thresholds + (self.fixed_threshold,), dtype=torch.float64)   # (T,)
        add = torch.zeros_like(self.counts)
        d_end = detections.offset.tolist()
        l_end = label_offset.tolist()
        for b in range(len(d_end)):
            d0 = d_end[b - 1] if b else 0
            l0 = l_end[b - 1] if b else 0
            m = match_frame(detections.score[d0:d_end[b]], detections.range_m[d0:d_end[b]],
                            detections.azimuth_deg[d0:d_end[b]], labels[l0:l_end[b]],
                            iou_threshold=self.iou_threshold, range_gate_m=self.range_gate_m)
            score, r_d, a_d, xy_d, hit = m.score, m.range_m, m.azimuth_deg, m.xy, m.hit      # (K,), (K, M)
            r_l, a_l, xy_l = m.label_range_m, m.label_azimuth_deg, m.label_xy
            near = (xy_d[:, None] - xy_l[None]).norm(dim=-1) <= NEAR_MISS_M      # (K, M)
            sel = score[None, :] > t[:, None]                                  # (T, K)
            pairs = sel[:, :, None] & hit[None]                                # (T, K, M)
            missed = ~pairs.any(1)                                             # (T, M)
            tp = (sel & hit.any(1)[None]).sum(1)                               # (T,)
            add[:, _TP] += tp
            add[:, _FP] += sel.sum(1) - tp
            add[:, _FN] += missed.sum(1)
            add[:, _FN_NEAR] += (missed & (sel[:, :, None] & near[None]).any(1)).sum(1)
            add[:, _LABELS] += r_l.numel()
            add[:, _PAIRS] += pairs.sum((1, 2))
            add[:, _DR] += (pairs * (r_d[:, None] - r_l[None, :]).abs()[None]).sum((1, 2))
            add[:, _DA] += (pairs * (a_d[:, None] - a_l[None, :]).abs()[None]).sum((1, 2))
        self.counts += add.to(self.counts.device)
        self.n_frames += len(d_end)

    def compute(self) -> DetectionReport:
        """The report of everything added so far."""
        c = self.counts.cpu().tolist()
        prec, rec, dr, da = [], [], [], []
        for row in c[:-1]:
            p, r = _prf(row[_TP], row[_FP], row[_FN])
            prec.append(p)
            rec.append(r)
            if row[_PAIRS] > 0:
                dr.append(row[_DR] / row[_PAIRS])
                da.append(row[_DA] / row[_PAIRS])
        ap, ar = sum(prec) / len(prec), sum(rec) / len(rec)
        fixed = c[-1]
        pf, rf = _prf(fixed[_TP], fixed[_FP], fixed[_FN])
        nan = math.nan
        return DetectionReport(
            thresholds=self.thresholds,
            tp=tuple(int(row[_TP]) for row in c[:-1]), fp=tuple(int(row[_FP]) for row in c[:-1]),
            fn=tuple(int(row[_FN]) for row in c[:-1]), fn_near=tuple(int(row[_FN_NEAR]) for row in c[:-1]),
            precision=tuple(prec), recall=tuple(rec), ap=ap, ar=ar, f1=_f1(ap, ar),
            range_error_m=sum(dr) / len(dr) if dr else nan,
            azimuth_error_deg=sum(da) / len(da) if da else nan,
            fixed_threshold=self.fixed_threshold, precision_fixed=pf, recall_fixed=rf, f1_fixed=_f1(pf, rf),
            range_error_fixed_m=fixed[_DR] / fixed[_PAIRS] if fixed[_PAIRS] else nan,
            azimuth_error_fixed_deg=fixed[_DA] / fixed[_PAIRS] if fixed[_PAIRS] else nan,
            fn_fixed=int(fixed[_FN]), fn_near_fixed=int(fixed[_FN_NEAR]), n_labels=int(fixed[_LABELS]),
            n_frames=self.n_frames)


def evaluate_detections(detections: Detections, labels: torch.Tensor, label_offset: torch.Tensor,
                        **kwargs) -> DetectionReport:
    """:class:`DetectionMetrics` (``kwargs`` its parameters) over one batch of frames."""
    m = DetectionMetrics(**kwargs)
    m.update(detections, labels, label_offset)
    return m.compute()


def freespace_iou(prob: torch.Tensor, target: torch.Tensor, rows: int = FREESPACE_ROWS,
                  threshold: float = 0.5) -> torch.Tensor:
    """Per-frame freespace IoU, RADIal's way.

    Parameters
    ----------
    prob : float ``(B, H, W)`` or ``(B, 1, H, W)``
        Predicted probability of free space (``sigmoid`` of the freespace head's logits).
    target : bool or {0, 1} ``(B, H, W)`` or ``(B, 1, H, W)``
    rows : int
        Rows ``0..rows-1`` are scored (RADIal: 124 of 256, 0-50 m).
    threshold : float
        Free where ``prob >= threshold``.

    Returns
    -------
    float64 ``(B,)``: ``|P & T| / |P | T|`` per frame, NaN where both are empty.
    """
    if prob.ndim == 4:
        prob = prob[:, 0]
    if target.ndim == 4:
        target = target[:, 0]
    if prob.ndim != 3 or prob.shape != target.shape:
        raise ValueError(f"prob and target must both be (B, H, W) or (B, 1, H, W), got {tuple(prob.shape)} "
                         f"and {tuple(target.shape)}")
    p = prob[:, :rows] >= threshold
    t = target[:, :rows].bool()
    inter = (p & t).sum((1, 2)).double()
    union = (p | t).sum((1, 2)).double()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.full_like(union, math.nan))


class FreespaceMetrics:
    """Accumulates :func:`freespace_iou` over batches; :meth:`compute` is the mean IoU over the
    frames that have one.

    Attributes
    ----------
    counts : float64 ``(2,)``: sum of per-frame IoU, number of frames with an IoU (sum it across
        processes before :meth:`compute`)
    """

    def __init__(self, rows: int = FREESPACE_ROWS, threshold: float = 0.5) -> None:
        self.rows = int(rows)
        self.threshold = float(threshold)
        self.counts = torch.zeros(2, dtype=torch.float64)

    def update(self, prob: torch.Tensor, target: torch.Tensor) -> None:
        iou = freespace_iou(prob.detach(), target.detach(), self.rows, self.threshold).cpu()
        ok = ~torch.isnan(iou)
        self.counts += torch.stack([iou[ok].sum(), ok.sum().double()]).to(self.counts.device)

    def compute(self) -> float:
        """Mean IoU (NaN when no frame had one)."""
        s, n = self.counts.tolist()
        return s / n if n else math.nan
