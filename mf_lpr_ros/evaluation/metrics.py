"""The metrics (docs/METHOD.md section 5), computed the same way for every method from its per-query
records."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mf_lpr_ros.pipeline.mapping import NOT_DESCRIBED

RECALL_AT_N = 5
_CURVE_POINTS = 200


@dataclass
class QueryRecord:
    """One query under a protocol: where it truly was, what the method answered, and how far
    the references involved lie from the truth.

    truth, estimate: (x, y, yaw). reference_index: the matched reference's scan index (-1 for
    none). nearest_reference_m: the nearest reference it may match (it is a positive when
    within tolerance); retrieved_distance_m, candidate_distances_m: the matched reference and
    the best RECALL_AT_N candidates. rte_m, rre_deg: the estimate's pose error. published:
    the method would publish the match as a loop closure. ms_*: time per stage.
    distinctiveness, local_distinctiveness, reason: MF-LPR's MatchResult figures and the
    verification's reason for the verdict (NaN and "" for methods without them; the local
    figure is NaN where it was not needed): why a revisit was not published can be read off
    a run. searched_nearest_m: the nearest to the truth of the references the method's
    candidate stage kept for the full comparison; NaN when the method does not say.
    place_similarity: MF-LPR's yardstick for a match under min_confidence (NaN elsewhere).
    position_covariance: the (x, y) covariance published with estimate, as [xx, xy, yy] (NaN
    for methods that give none).
    """

    query_index: int
    stamp: float
    truth: list[float]
    estimate: list[float]
    reference_index: int
    nearest_reference_m: float
    retrieved_distance_m: float
    candidate_distances_m: list[float]
    rte_m: float
    rre_deg: float
    confidence: float
    published: bool
    ms_descriptor: float
    ms_global: float
    ms_local: float
    distinctiveness: float = math.nan
    local_distinctiveness: float = math.nan
    reason: str = ""
    searched_nearest_m: float = math.nan
    place_similarity: float = math.nan
    position_covariance: list[float] = field(default_factory=lambda: [math.nan] * 3)


# The figures that score an estimated pose, not a retrieval: NaN where poses cannot be scored.
POSE_FIGURES = ("recall_at_1_corrected", "rte_mean_m", "rte_std_m", "rre_mean_deg",
                "rre_std_deg", "success_rate", "closures_false", "precision_published",
                "recall_published", "recall_at_100_precision", "published_d2_median",
                "published_d2_p90")


def summarise(records: list[QueryRecord], tolerance_m: float, n_references: int, *,
              poses_scored: bool = True) -> dict:
    """Metrics of docs/METHOD.md section 5 from per-query records.

    recall_at_1: the retrieved reference lies within tolerance (retrieval recall).
    recall_at_1_corrected: the estimated pose lies within tolerance (the paper's recall).
    recall_at_n[k-1]: one of the best k candidates lies within tolerance.
    candidate_recall: a reference within tolerance is among those the candidate stage kept
    for the full comparison (what it loses, the search cannot retrieve, bar MF-LPR's report
    of the place nearest its match); NaN when the method does not say.
    RTE/RRE mean and std over successes (RTE < 2 m and RRE < 5 deg among correct retrievals);
    success_rate = successes / correct retrievals (BVMatch). f1_max and pr_curve over the
    confidence: an accepted correct retrieval is a true positive, any other accepted match a
    false positive. recall_vs_threshold: recall as the distance threshold varies (positives
    fixed by tolerance). Timings are medians per query searched; queries_not_described counts
    those that had nothing to describe (each a miss).

    Loop closures as published (each method's own acceptance, MF-LPR's verification):
    closures_published; closures_false, those whose estimated query position lies farther than
    tolerance from the truth (the constraint a pose graph would get is wrong);
    precision_published; recall_published, the positive queries with a correct published
    closure; recall_at_100_precision, the largest recall over confidence thresholds with no
    false match above the threshold (before verification). published_d2_median /
    published_d2_p90: how honest the published covariances are, the median and 90th
    percentile over published closures of d2, the squared Mahalanobis distance of the
    position error under its published (x, y) covariance (published_d2); were the
    covariances exact, 1.39 and 4.61. NaN for methods that publish none.

    poses_scored False (Protocol.headings_known): POSE_FIGURES are NaN, and so is the
    corrected curve of recall_vs_threshold.
    """
    def column(values) -> np.ndarray:
        return np.fromiter(values, dtype=float, count=len(records))

    positive = column(r.nearest_reference_m for r in records) <= tolerance_m
    n_positive = int(positive.sum())
    retrieved_distance = column(r.retrieved_distance_m for r in records)
    retrieved = retrieved_distance <= tolerance_m
    rte, rre = column(r.rte_m for r in records), column(r.rre_deg for r in records)
    correct = positive & retrieved
    success = correct & (rte < 2.0) & (rre < 5.0)
    candidate_hits = np.zeros((len(records), RECALL_AT_N), dtype=bool)
    for row, record in enumerate(records):
        hits = np.asarray(record.candidate_distances_m, dtype=float) <= tolerance_m
        candidate_hits[row, :len(hits)] = hits
    recall_at_n = np.logical_or.accumulate(candidate_hits, axis=1)
    recall_at_n[:, 0] = retrieved

    def rate(mask: np.ndarray) -> float:
        return float(mask[positive].mean()) if n_positive else float("nan")

    def stat(values: np.ndarray, reducer) -> float:
        return float(reducer(values)) if len(values) else float("nan")

    def median_searched(values: np.ndarray) -> float:
        # A query that was not searched (nothing to describe) took no search time to median.
        return stat(values[np.isfinite(values)], np.median)

    searched_nearest = column(r.searched_nearest_m for r in records)
    confidence = column(r.confidence for r in records)
    thresholds = np.linspace(0.0, 2.0 * tolerance_m, 41)[1:]
    ms_descriptor = column(r.ms_descriptor for r in records)
    ms_global = column(r.ms_global for r in records)
    ms_local = column(r.ms_local for r in records)
    ms_total = ms_descriptor + ms_global + ms_local
    f1, f1_confidence, curve = precision_recall(confidence, correct, n_positive)
    published = np.array([r.published for r in records], dtype=bool)
    closure_correct = rte <= tolerance_m
    n_published = int(published.sum())
    summary = {
        "n_queries": n_positive,
        "n_evaluated": len(records),
        "n_references": n_references,
        "tolerance_m": tolerance_m,
        "recall_at_1": rate(retrieved),
        "recall_at_1_corrected": rate(rte <= tolerance_m),
        "recall_at_5": rate(recall_at_n[:, -1]),
        "recall_at_n": [rate(recall_at_n[:, k]) for k in range(RECALL_AT_N)],
        "candidate_recall": rate(searched_nearest <= tolerance_m)
        if np.isfinite(searched_nearest[positive]).any() else float("nan"),
        "rte_mean_m": stat(rte[success], np.mean),
        "rte_std_m": stat(rte[success], np.std),
        "rre_mean_deg": stat(rre[success], np.mean),
        "rre_std_deg": stat(rre[success], np.std),
        "success_rate": float(success.sum() / correct.sum()) if correct.any() else float("nan"),
        "f1_max": f1,
        "confidence_at_f1_max": f1_confidence,
        "pr_curve": curve,
        "closures_published": n_published,
        "closures_false": int((published & ~closure_correct).sum()),
        "precision_published": float((published & closure_correct).sum() / n_published)
        if n_published else float("nan"),
        "recall_published": rate(published & closure_correct),
        "recall_at_100_precision": recall_at_full_precision(confidence, closure_correct, positive),
        **_published_d2(published_d2(records)[published]),
        "recall_vs_threshold": {
            "threshold_m": thresholds.tolist(),
            "retrieval": [rate(retrieved_distance <= t) for t in thresholds],
            "corrected": [rate(rte <= t) for t in thresholds]},
        "ms_per_query": median_searched(ms_total),
        "ms_descriptor": median_searched(ms_descriptor),
        "ms_global": median_searched(ms_global),
        "ms_local": median_searched(ms_local),
        "queries_not_described": sum(r.reason.startswith(NOT_DESCRIBED) for r in records),
    }
    if not poses_scored:
        summary.update(dict.fromkeys(POSE_FIGURES, math.nan))
        summary["recall_vs_threshold"]["corrected"] = [math.nan] * len(thresholds)
    return summary


def published_d2(records: list[QueryRecord]) -> np.ndarray:
    """Per record, the squared Mahalanobis distance of its position error (estimate - truth)
    under its published (x, y) covariance; NaN where either is missing or the covariance is
    singular."""
    if not records:
        return np.zeros(0)
    xx, xy, yy = np.array([r.position_covariance for r in records], dtype=float).T
    dx, dy = (np.array([r.estimate[:2] for r in records], dtype=float)
              - np.array([r.truth[:2] for r in records], dtype=float)).T
    determinant = xx * yy - xy * xy
    with np.errstate(invalid="ignore", divide="ignore"):
        d2 = (yy * dx ** 2 - 2 * xy * dx * dy + xx * dy ** 2) / determinant
    return np.where(determinant > 0, d2, np.nan)


def _published_d2(d2: np.ndarray) -> dict[str, float]:
    known = d2[np.isfinite(d2)]
    return {"published_d2_median": float(np.median(known)) if len(known) else math.nan,
            "published_d2_p90": float(np.percentile(known, 90)) if len(known) else math.nan}


def recall_at_full_precision(confidence: np.ndarray, true_match: np.ndarray,
                             positive: np.ndarray) -> float:
    """The largest recall (true matches among positives) over accept thresholds on confidence
    that accept no false match."""
    if not positive.any():
        return float("nan")
    order = np.argsort(-confidence, kind="stable")
    false_before = np.cumsum(~true_match[order])
    clean = int(np.searchsorted(false_before, 1))
    return float((true_match & positive)[order[:clean]].sum() / positive.sum())


def precision_recall(confidence: np.ndarray, true_match: np.ndarray, n_positive: int
                     ) -> tuple[float, float, dict[str, list[float]]]:
    """(F1max, the confidence threshold reaching it, the precision-recall curve) over accept
    thresholds on confidence."""
    empty = {"precision": [], "recall": [], "confidence": []}
    if n_positive == 0 or len(confidence) == 0:
        return float("nan"), float("nan"), empty
    order = np.argsort(-confidence, kind="stable")
    true_positives = np.cumsum(true_match[order])
    precision = true_positives / np.arange(1, len(order) + 1)
    recall = true_positives / n_positive
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(precision + recall > 0, 2 * precision * recall / (precision + recall), 0.0)
    best = int(np.argmax(f1))
    keep = np.unique(np.linspace(0, len(order) - 1, min(len(order), _CURVE_POINTS)).astype(int))
    curve = {"precision": precision[keep].tolist(), "recall": recall[keep].tolist(),
             "confidence": confidence[order][keep].tolist()}
    return float(f1[best]), float(confidence[order][best]), curve
