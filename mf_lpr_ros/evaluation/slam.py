"""Does a SLAM back end get better with our closures? A drifted odometry, the verified loop
closures MF-LPR publishes on it, and a GTSAM pose graph, scored against the ground truth.

The odometry is the ground truth's own frame-to-frame increments, corrupted by DriftModel
(seeded): what LiDAR odometry gives, without needing one. The map and every query see only that
odometry (map poses, odometry consistency), never the ground truth.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.pose import compose_planar, planar, relative_planar
from mf_lpr_ros.core.pose_graph import (
    PoseGraph,
    PoseGraphParams,
    absolute_trajectory_error,
    aligned_positions,
)
from mf_lpr_ros.datasets.base import PoseOverride, Sequence
from mf_lpr_ros.evaluation.methods import MatchedFilterMethod
from mf_lpr_ros.evaluation.protocol import Protocol, run_protocol, select
from mf_lpr_ros.optional import require


@dataclass(frozen=True)
class DriftModel:
    """Odometry from ground truth: each step's translation is scaled by (1 + scale_error) and
    gets Gaussian noise of translation_noise x its length per axis; its heading change gets a
    bias of yaw_bias_deg_per_m and Gaussian noise of yaw_noise_deg_per_m (both x its length).
    The defaults drift like a fair LiDAR odometry: ~1 % of distance, a few degrees per km."""

    scale_error: float = 0.01
    translation_noise: float = 0.01
    yaw_bias_deg_per_m: float = 0.003
    yaw_noise_deg_per_m: float = 0.01
    seed: int = 0

    def graph_params(self) -> PoseGraphParams:
        """The pose graph's odometry noise as this model makes it (a tuned back end's)."""
        return PoseGraphParams(
            odometry_sigma_fraction=math.hypot(self.scale_error, self.translation_noise),
            odometry_sigma_min_m=0.005,
            odometry_yaw_sigma_deg_per_m=self.yaw_bias_deg_per_m + self.yaw_noise_deg_per_m,
            odometry_yaw_sigma_min_deg=0.005)

    def apply(self, truth: np.ndarray) -> np.ndarray:
        """Drifted planar poses (n, 3) of planar ground truth (n, 3); the first is kept."""
        rng = np.random.default_rng(self.seed)
        steps = relative_planar(truth[:-1], truth[1:])
        length = np.hypot(steps[:, 0], steps[:, 1])
        steps[:, :2] *= 1.0 + self.scale_error
        noise_m = self.translation_noise * length
        steps[:, :2] += rng.normal(size=(len(steps), 2)) * noise_m[:, None]
        steps[:, 2] += np.radians(self.yaw_bias_deg_per_m * length
                                  + rng.normal(size=len(steps)) * self.yaw_noise_deg_per_m * length)
        drifted = [truth[0]]
        for step in steps:
            drifted.append(compose_planar(drifted[-1], step))
        return np.array(drifted)


def with_planar(poses: np.ndarray, planar_poses: np.ndarray) -> np.ndarray:
    """4x4 poses moved to other planar poses, keeping their height, roll and pitch."""
    result = poses.copy()
    turn = planar_poses[:, 2] - planar(poses)[:, 2]
    c, s = np.cos(turn), np.sin(turn)
    rotation = np.zeros((len(poses), 3, 3))
    rotation[:, 0, 0], rotation[:, 0, 1], rotation[:, 1, 0], rotation[:, 1, 1] = c, -s, s, c
    rotation[:, 2, 2] = 1.0
    result[:, :3, :3] = rotation @ poses[:, :3, :3]
    result[:, :2, 3] = planar_poses[:, :2]
    return result


def slam_eval(sequence: Sequence, config: Config, protocol: Protocol, *,
              drift: DriftModel = DriftModel(), progress: bool = True) -> dict:
    """Drift the odometry, find and verify loop closures on it, optimise, score. Returns the
    JSON keys of `mf-lpr slam-eval` plus the trajectories (planar, valid frames in order).

    A closure is false when the relative pose it gives lies farther than the tolerance from the
    ground truth's; the graph gives every closure the floor covariance of PoseGraphParams and
    the odometry the noise the drift model implies.
    """
    require("gtsam")
    if sequence.poses is None:
        raise ValueError(f"{sequence.name}: slam-eval needs ground-truth poses")
    frames = np.flatnonzero(np.isfinite(sequence.poses).all(axis=(1, 2)))
    if len(frames) < 2:
        raise ValueError(f"{sequence.name}: fewer than two scans have a pose")
    truth = planar(sequence.poses[frames])
    odometry = drift.apply(truth)
    drifted_poses = np.full_like(sequence.poses, np.nan)
    drifted_poses[frames] = with_planar(sequence.poses[frames], odometry)
    drifted = PoseOverride(sequence, drifted_poses)

    selection = select(drifted, protocol, config.spacing_m)
    records = run_protocol(MatchedFilterMethod(config), drifted, selection,
                           truth_poses=sequence.poses, progress=progress).records
    positives = sum(record.nearest_reference_m <= protocol.tolerance_m for record in records)

    key_of = {int(frame): key for key, frame in enumerate(frames)}
    graph = PoseGraph(drift.graph_params())
    for pose in odometry:
        graph.add_keyframe(pose)
    closure_false = []
    closed_revisits = 0
    for record in records:
        if not record.published:
            continue
        query, reference = key_of[record.query_index], key_of[record.reference_index]
        relative = relative_planar(odometry[reference], np.asarray(record.estimate))
        true_relative = relative_planar(truth[reference], truth[query])
        closure_false.append(math.hypot(*(relative[:2] - true_relative[:2]))
                             > protocol.tolerance_m)
        closed_revisits += not closure_false[-1] and \
            record.nearest_reference_m <= protocol.tolerance_m
        graph.add_closure(query, reference, relative, np.zeros((3, 3)))
    optimised = graph.optimise()
    used = np.array([closure.active for closure in graph.closures], dtype=bool)
    closure_false = np.array(closure_false, dtype=bool)
    return {
        "sequence": sequence.name,
        "n_keyframes": len(frames),
        "path_length_m": float(np.hypot(*np.diff(truth[:, :2], axis=0).T).sum()),
        "drift_model": asdict(drift),
        "ate_odometry_m": absolute_trajectory_error(odometry, truth),
        "ate_optimised_m": absolute_trajectory_error(optimised, truth),
        "closures_published": int(len(graph.closures)),
        "closures_false": int(closure_false.sum()),
        "closures_used": int(used.sum()),
        "closures_false_used": int((closure_false & used).sum()),
        "recall_published": closed_revisits / positives if positives else math.nan,
        "n_revisit_queries": positives,
        "trajectories": {"truth": truth.tolist(), "odometry": odometry.tolist(),
                         "optimised": optimised.tolist()},
        "closure_keys": [[c.reference_key, c.query_key] for c in graph.closures],
        "closure_used": used.tolist(),
    }


def slam_figure(result: dict, path: str | Path) -> None:
    """Ground truth, odometry and the optimised trajectory (each aligned as ATE aligns it), with
    the closures used."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    trajectories = {name: np.asarray(values)
                    for name, values in result["trajectories"].items()}
    truth = trajectories["truth"]
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.plot(truth[:, 0], truth[:, 1], color="black", lw=1.2, label="ground truth")
    for name, colour in (("odometry", "tab:red"), ("optimised", "tab:blue")):
        aligned = aligned_positions(trajectories[name], truth)
        ate = result[f"ate_{name}_m"]
        ax.plot(aligned[:, 0], aligned[:, 1], color=colour, lw=1.0,
                label=f"{name} (ATE {ate:.2f} m)")
    optimised = aligned_positions(trajectories["optimised"], truth)
    for (reference, query), used in zip(result["closure_keys"], result["closure_used"]):
        if used:
            ax.plot(*optimised[[reference, query], :2].T, color="tab:green", lw=0.4, alpha=0.5)
    ax.set_title(f"{result['sequence']}: {result['closures_used']} closures used, "
                 f"{result['closures_false']} false published")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)

