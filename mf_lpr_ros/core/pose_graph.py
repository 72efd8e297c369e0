"""A planar pose graph on GTSAM: odometry between keyframes plus loop closures, optimised with
Levenberg-Marquardt. What a SLAM back end does with our closures, for slam-eval and the
pose_graph example node.

One false closure must not bend the graph, whatever reached it: after each optimisation the
closure whose residual is the largest, if it lies beyond the chi-square gate, is switched off
and the graph is optimised again, until every closure left agrees with the rest. (A robust
kernel alone is not enough: under drift a true closure starts as far from the odometry as a
false one, and the kernel would discount both.)

GTSAM is optional (pip install gtsam); optional.require names the install when it is missing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mf_lpr_ros.core.pose import compose_planar, relative_planar, wrap_angle
from mf_lpr_ros.optional import require

# 99.9 % quantile of chi-square with 3 degrees of freedom: a closure whose Mahalanobis residual
# stays beyond it after optimisation contradicts the rest of the graph.
_CHI2_GATE_3DOF = 16.27
_MAX_GATING_ROUNDS = 20
# A closure's stamp may lie this far outside the odometry received (one odometry period or so).
_STAMP_SLACK_S = 0.5


@dataclass(frozen=True)
class PoseGraphParams:
    """Noise of the graph's factors.

    odometry_sigma_fraction, odometry_sigma_min_m: translation sigma of an odometry step, as a
        fraction of its length, never below the minimum.
    odometry_yaw_sigma_deg_per_m, odometry_yaw_sigma_min_deg: the same for its heading.
    closure_sigma_min_m, closure_yaw_sigma_min_deg: floors under a closure's own covariance
        (matched-filter peaks can claim centimetres; the BEV cell is 0.3-0.5 m).
    """

    odometry_sigma_fraction: float = 0.02
    odometry_sigma_min_m: float = 0.02
    odometry_yaw_sigma_deg_per_m: float = 0.05
    odometry_yaw_sigma_min_deg: float = 0.05
    closure_sigma_min_m: float = 0.2
    closure_yaw_sigma_min_deg: float = 0.5


@dataclass
class Closure:
    """reference_T_query (planar x, y, yaw) between two keyframes, with its 3x3 covariance."""

    query_key: int
    reference_key: int
    relative: np.ndarray
    covariance: np.ndarray
    active: bool = True


@dataclass
class PoseGraph:
    """Keyframes added in order with their odometry poses; closures between any two."""

    params: PoseGraphParams = field(default_factory=PoseGraphParams)

    def __post_init__(self) -> None:
        self._gtsam = require("gtsam")
        self.odometry: list[np.ndarray] = []
        self.closures: list[Closure] = []
        self.estimate: np.ndarray = np.zeros((0, 3))

    def __len__(self) -> int:
        return len(self.odometry)

    def add_keyframe(self, odometry_pose: np.ndarray) -> int:
        """A keyframe at a planar odometry pose; returns its key."""
        self.odometry.append(np.asarray(odometry_pose, dtype=np.float64).copy())
        if len(self.estimate):
            # The new keyframe starts where the optimised graph and its odometry step put it.
            step = relative_planar(self.odometry[-2], self.odometry[-1])
            self.estimate = np.vstack([self.estimate, compose_planar(self.estimate[-1], step)])
        else:
            self.estimate = np.array(self.odometry)
        return len(self.odometry) - 1

    def add_closure(self, query_key: int, reference_key: int, relative: np.ndarray,
                    covariance: np.ndarray) -> None:
        for key in (query_key, reference_key):
            if not 0 <= key < len(self.odometry):
                raise ValueError(f"closure names keyframe {key}; the graph has "
                                 f"{len(self.odometry)}")
        self.closures.append(Closure(query_key, reference_key,
                                     np.asarray(relative, dtype=np.float64),
                                     np.asarray(covariance, dtype=np.float64)))

    @property
    def closures_used(self) -> int:
        return sum(closure.active for closure in self.closures)

    def optimise(self) -> np.ndarray:
        """Optimised planar poses (n, 3) of every keyframe; closures that fail the gate are
        switched off (Closure.active) and stay off."""
        if not self.odometry:
            return np.zeros((0, 3))
        start = self.estimate
        for _ in range(_MAX_GATING_ROUNDS):
            self.estimate = self._solve(start)
            active = [c for c in self.closures if c.active]
            if not active:
                break
            residuals = [self._closure_residual(c) for c in active]
            worst = int(np.argmax(residuals))
            if residuals[worst] <= _CHI2_GATE_3DOF:
                break
            active[worst].active = False
        return self.estimate

    def _solve(self, start: np.ndarray) -> np.ndarray:
        gtsam = self._gtsam
        graph = gtsam.NonlinearFactorGraph()
        initial = gtsam.Values()
        first = self.odometry[0]
        graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*first),
                                         gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))))
        for key, pose in enumerate(self.odometry):
            initial.insert(key, gtsam.Pose2(*start[key]))
            if key:
                step = relative_planar(self.odometry[key - 1], pose)
                graph.add(gtsam.BetweenFactorPose2(key - 1, key, gtsam.Pose2(*step),
                                                   self._odometry_noise(step)))
        for closure in self.closures:
            if closure.active:
                graph.add(gtsam.BetweenFactorPose2(
                    closure.reference_key, closure.query_key, gtsam.Pose2(*closure.relative),
                    gtsam.noiseModel.Gaussian.Covariance(self._closure_covariance(closure))))
        parameters = gtsam.LevenbergMarquardtParams()
        parameters.setMaxIterations(100)
        result = gtsam.LevenbergMarquardtOptimizer(graph, initial, parameters).optimize()
        return np.array([[p.x(), p.y(), p.theta()]
                         for p in (result.atPose2(key) for key in range(len(self.odometry)))])

    def _odometry_noise(self, step: np.ndarray):
        p = self.params
        length = float(np.hypot(step[0], step[1]))
        sigma_m = max(p.odometry_sigma_min_m, p.odometry_sigma_fraction * length)
        sigma_yaw = math.radians(max(p.odometry_yaw_sigma_min_deg,
                                     p.odometry_yaw_sigma_deg_per_m * length))
        return self._gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_m, sigma_m, sigma_yaw]))

    def _closure_covariance(self, closure: Closure) -> np.ndarray:
        p = self.params
        floor = np.diag([p.closure_sigma_min_m ** 2, p.closure_sigma_min_m ** 2,
                         math.radians(p.closure_yaw_sigma_min_deg) ** 2])
        covariance = closure.covariance if np.all(np.isfinite(closure.covariance)) else floor
        return covariance + floor

    def _closure_residual(self, closure: Closure) -> float:
        """Squared Mahalanobis distance of the closure from the current estimate."""
        implied = relative_planar(self.estimate[closure.reference_key],
                                  self.estimate[closure.query_key])
        error = implied - closure.relative
        error[2] = float(wrap_angle(error[2]))
        return float(error @ np.linalg.solve(self._closure_covariance(closure), error))


def aligned_positions(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """estimate's positions (n, 2) moved by the rigid planar transform that best aligns them with
    truth's (Umeyama without scale)."""
    estimate, truth = np.asarray(estimate)[:, :2], np.asarray(truth)[:, :2]
    mean_e, mean_t = estimate.mean(0), truth.mean(0)
    u, _, vt = np.linalg.svd((truth - mean_t).T @ (estimate - mean_e))
    rotation = u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return (estimate - mean_e) @ rotation.T + mean_t


def absolute_trajectory_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """RMSE of positions (m) after aligned_positions."""
    gaps = aligned_positions(estimate, truth) - np.asarray(truth)[:, :2]
    return float(np.sqrt(np.mean(np.sum(gaps ** 2, axis=1))))


class KeyframeGraph:
    """A PoseGraph fed as a SLAM back end is fed: odometry samples (stamp, planar pose) in time
    order, and loop closures between two stamps. A keyframe is kept every keyframe_spacing_m of
    travel; a closure is moved onto the keyframes nearest its two stamps through the odometry
    between them (stamps outside the odometry received so far are refused)."""

    def __init__(self, keyframe_spacing_m: float = 1.0,
                 params: PoseGraphParams | None = None) -> None:
        if not keyframe_spacing_m >= 0:
            raise ValueError(f"keyframe_spacing_m must be >= 0, got {keyframe_spacing_m}")
        self.spacing_m = keyframe_spacing_m
        self.graph = PoseGraph(params or PoseGraphParams())
        self._stamps: list[float] = []
        self._odometry: list[np.ndarray] = []
        self.keyframe_stamps: list[float] = []
        self._keyframe_samples: list[int] = []

    def add_odometry(self, stamp: float, pose: np.ndarray) -> bool:
        """Record an odometry sample; True when it became a keyframe."""
        if self._stamps and stamp <= self._stamps[-1]:
            raise ValueError(f"odometry stamp {stamp:.6f} is not after the previous one")
        pose = np.asarray(pose, dtype=np.float64)
        self._stamps.append(float(stamp))
        self._odometry.append(pose)
        if self._keyframe_samples:
            last = self._odometry[self._keyframe_samples[-1]]
            if np.hypot(*(pose[:2] - last[:2])) < self.spacing_m:
                return False
        self._keyframe_samples.append(len(self._stamps) - 1)
        self.keyframe_stamps.append(float(stamp))
        self.graph.add_keyframe(pose)
        return True

    def add_closure(self, query_stamp: float, reference_stamp: float, relative: np.ndarray,
                    covariance: np.ndarray) -> None:
        """reference_T_query (planar) between the sensor at two stamps, with its covariance."""
        query_sample, query_key = self._locate(query_stamp)
        reference_sample, reference_key = self._locate(reference_stamp)
        odometry = self._odometry
        # keyframe(ref)_T_ref o ref_T_query o query_T_keyframe(query), the outer two by odometry.
        between = compose_planar(
            compose_planar(relative_planar(odometry[self._keyframe_samples[reference_key]],
                                           odometry[reference_sample]), relative),
            relative_planar(odometry[query_sample],
                            odometry[self._keyframe_samples[query_key]]))
        self.graph.add_closure(query_key, reference_key, between, covariance)

    def _locate(self, stamp: float) -> tuple[int, int]:
        """(the odometry sample nearest stamp, the keyframe nearest it in time)."""
        if not self._stamps or not \
                self._stamps[0] - _STAMP_SLACK_S <= stamp <= self._stamps[-1] + _STAMP_SLACK_S:
            raise ValueError(f"stamp {stamp:.3f} lies outside the odometry received "
                             "so far")
        sample = int(np.argmin(np.abs(np.asarray(self._stamps) - stamp)))
        key = int(np.argmin(np.abs(np.asarray(self.keyframe_stamps) - stamp)))
        return sample, key

    def optimise(self) -> np.ndarray:
        return self.graph.optimise()

    @property
    def estimate(self) -> np.ndarray:
        return self.graph.estimate
