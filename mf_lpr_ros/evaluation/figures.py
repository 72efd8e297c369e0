"""Figures of a suite run: PR curves, recall vs distance threshold, trajectories with correct and
wrong matches, and a BEV overlay of a query on its matched reference."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mf_lpr_ros.config import preset  # noqa: E402
from mf_lpr_ros.core.pose import planar  # noqa: E402
from mf_lpr_ros.datasets import open_source  # noqa: E402
from mf_lpr_ros.evaluation.protocol import PairResult  # noqa: E402
from mf_lpr_ros.pipeline.mapping import describe_scan  # noqa: E402

MAX_LEGEND = 8


def write_suite_figures(out: Path, pairs, methods: list[str],
                        results: dict[tuple[str, str], PairResult]) -> None:
    figures = Path(out) / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    _pr_curves(figures / "pr_curves.png", pairs, methods, results)
    _recall_vs_threshold(figures / "recall_vs_threshold.png", pairs, methods, results)
    for pair in pairs:
        _trajectory(figures / f"trajectory_{pair.name}.png", pair, methods, results)
        if "mf-lpr" in methods:
            bev_overlay(figures / f"bev_{pair.name}.png", pair, results[(pair.name, "mf-lpr")])


def _pr_curves(path: Path, pairs, methods, results) -> None:
    fig, axes = plt.subplots(1, len(methods), figsize=(4.5 * len(methods), 4), squeeze=False)
    for ax, method in zip(axes[0], methods):
        for pair in pairs:
            result = results[(pair.name, method)]
            curve = result.summary["pr_curve"]
            ax.plot(curve["recall"], curve["precision"],
                    label=f"{pair.name} (F1max {result.summary['f1_max']:.2f})")
        ax.set(title=results[(pairs[0].name, method)].method, xlabel="recall",
               ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.02))
        if len(pairs) <= MAX_LEGEND:
            ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _recall_vs_threshold(path: Path, pairs, methods, results) -> None:
    fig, ax = plt.subplots(figsize=(6, 4))
    for method in methods:
        curves = [results[(pair.name, method)].summary["recall_vs_threshold"] for pair in pairs]
        thresholds = curves[0]["threshold_m"]
        name = results[(pairs[0].name, method)].method
        for kind, style in (("corrected", "-"), ("retrieval", "--")):
            mean = np.nanmean(np.array([c[kind] for c in curves], dtype=float), axis=0)
            ax.plot(thresholds, mean, style, label=f"{name}, {kind}")
    ax.set(xlabel="distance threshold (m)", ylabel="recall@1 (mean over pairs)", ylim=(0, 1.02))
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _trajectory(path: Path, pair, methods, results) -> None:
    fig, axes = plt.subplots(1, len(methods), figsize=(5 * len(methods), 5), squeeze=False)
    tolerance = pair.protocol.tolerance_m
    for ax, method in zip(axes[0], methods):
        result = results[(pair.name, method)]
        records = result.records
        truth = np.array([r.truth for r in records]).reshape(-1, 3)
        positive = np.array([r.nearest_reference_m <= tolerance for r in records], dtype=bool)
        correct = np.array([r.rte_m <= tolerance for r in records], dtype=bool)
        ax.plot(truth[~positive, 0], truth[~positive, 1], ".", color="0.75", ms=3,
                label="no reference in reach")
        ax.plot(truth[positive & correct, 0], truth[positive & correct, 1], ".", color="tab:green",
                ms=4, label="correct")
        ax.plot(truth[positive & ~correct, 0], truth[positive & ~correct, 1], "x",
                color="tab:red", ms=4, label="wrong")
        ax.set(title=f"{result.method}: {pair.name}", aspect="equal", xlabel="x (m)",
               ylabel="y (m)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def bev_overlay(path: Path, pair, result: PairResult) -> None:
    """The first correct MF-LPR match of a pair (else its first query): the reference's occupied
    cells and the query's, placed in the world by the reference pose and by the estimated pose."""
    records = result.records
    if not records:
        return
    tolerance = pair.protocol.tolerance_m
    chosen = next((r for r in records if r.rte_m <= tolerance), records[0])
    if chosen.reference_index < 0:
        return
    config = preset(pair.preset)
    reference = open_source(pair.reference)
    query = open_source(pair.query) if pair.query is not None else reference
    query_scan = next(query.iter_scans([chosen.query_index]))
    reference_scan = next(reference.iter_scans([chosen.reference_index]))
    params = config.descriptor
    fig, ax = plt.subplots(figsize=(6, 6))
    for scan, pose, colour, label in (
            (reference_scan, planar(reference_scan.pose), "tab:blue", "reference"),
            (query_scan, np.array(chosen.estimate), "tab:orange", "query at estimate")):
        occupancy = describe_scan(scan, params, reference=False)
        rows, cols = np.nonzero(occupancy)
        centre = occupancy.shape[0] // 2
        local = np.stack([(cols - centre + 0.5), (rows - centre + 0.5)], axis=1) * params.voxel_size
        c, s = np.cos(pose[2]), np.sin(pose[2])
        world = local @ np.array([[c, s], [-s, c]]) + pose[:2]
        ax.plot(world[:, 0], world[:, 1], "s", color=colour, ms=1.5, alpha=0.5, label=label)
    ax.set(title=f"{pair.name}: query {chosen.query_index} on reference "
                 f"{chosen.reference_index} (RTE {chosen.rte_m:.2f} m)",
           aspect="equal", xlabel="x (m)", ylabel="y (m)")
    ax.legend(fontsize=7, markerscale=4)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

