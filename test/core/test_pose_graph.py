"""The GTSAM pose graph: closures remove drift, a false closure is gated out, stamps map onto
keyframes; slam-eval end to end on a generated sequence."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("gtsam", reason="gtsam not installed (pip install gtsam)")

from mf_lpr_ros.config import preset  # noqa: E402
from mf_lpr_ros.core.pose import compose_planar, relative_planar  # noqa: E402
from mf_lpr_ros.core.pose_graph import KeyframeGraph, PoseGraph, absolute_trajectory_error  # noqa: E402
from mf_lpr_ros.datasets import open_source  # noqa: E402
from mf_lpr_ros.evaluation.protocol import Protocol  # noqa: E402
from mf_lpr_ros.evaluation.slam import DriftModel, slam_eval  # noqa: E402
from mf_lpr_ros.sim.synthetic import route, write_kitti_sequence  # noqa: E402


def _loop(n: int = 200, radius_m: float = 30.0) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[radius_m * np.cos(t), radius_m * np.sin(t), t + np.pi / 2]


def _drifted(truth: np.ndarray, scale: float = 1.01, yaw_bias_deg: float = 0.05) -> np.ndarray:
    odometry = [truth[0]]
    for a, b in zip(truth[:-1], truth[1:]):
        step = relative_planar(a, b)
        step[:2] *= scale
        step[2] += math.radians(yaw_bias_deg)
        odometry.append(compose_planar(odometry[-1], step))
    return np.array(odometry)


def _graph(odometry, truth, closures, false_closure=None) -> PoseGraph:
    graph = PoseGraph()
    for pose in odometry:
        graph.add_keyframe(pose)
    for query in closures:
        reference = query - closures[0]
        graph.add_closure(query, reference, relative_planar(truth[reference], truth[query]),
                          np.eye(3) * 1e-3)
    if false_closure is not None:
        graph.add_closure(*false_closure, np.zeros(3), np.eye(3) * 1e-3)
    return graph


def test_true_closures_remove_drift_and_a_false_one_is_gated_out():
    truth = _loop()
    odometry = _drifted(truth)
    closures = list(range(180, 200, 2))
    before = absolute_trajectory_error(odometry, truth)
    clean = _graph(odometry, truth, closures)
    after = absolute_trajectory_error(clean.optimise(), truth)
    assert after < before / 3 and clean.closures_used == len(closures)

    # Keyframes 100 and 10 are 40 m apart; the planted closure says they coincide.
    planted = _graph(odometry, truth, closures, false_closure=(100, 10))
    bent = absolute_trajectory_error(planted.optimise(), truth)
    assert bent == pytest.approx(after, abs=0.05)
    assert [c.active for c in planted.closures] == [True] * len(closures) + [False]


def test_keyframe_graph_moves_a_closure_onto_the_nearest_keyframes():
    truth = _loop(400)
    graph = KeyframeGraph(keyframe_spacing_m=2.0)
    stamps = np.arange(len(truth)) * 0.1
    kept = [graph.add_odometry(stamp, pose) for stamp, pose in zip(stamps, truth)]
    assert kept[0] and sum(kept) == len(truth) // 5      # 0.47 m steps: 2 m every fifth
    # A closure between two samples that are not keyframes: the keyframe edge must equal the
    # true relative pose of the keyframes nearest in time.
    query, reference = next(i for i in range(350, 400) if not kept[i]), \
        next(i for i in range(20, 60) if not kept[i])
    graph.add_closure(stamps[query], stamps[reference],
                      relative_planar(truth[reference], truth[query]), np.eye(3) * 1e-3)
    closure = graph.graph.closures[0]
    keyframe_stamps = np.array(graph.keyframe_stamps)
    truth_of_key = truth[np.round(keyframe_stamps / 0.1).astype(int)]
    np.testing.assert_allclose(
        closure.relative, relative_planar(truth_of_key[closure.reference_key],
                                          truth_of_key[closure.query_key]), atol=1e-9)
    with pytest.raises(ValueError, match="outside the odometry"):
        graph.add_closure(stamps[-1] + 5.0, stamps[0], np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="not after"):
        graph.add_odometry(stamps[3], truth[3])


@pytest.fixture(scope="module")
def two_laps(tmp_path_factory, world):
    """A generated KITTI-layout sequence: two laps of the same loop, 1 m lateral offset."""
    folder = tmp_path_factory.mktemp("two_laps")
    lap = route(90)
    second = route(90, lateral_offset_m=1.0)
    write_kitti_sequence(folder, world, np.vstack([lap, second]), seed=4)
    return folder


def test_slam_eval_reduces_drift_with_verified_closures(two_laps):
    result = slam_eval(open_source(two_laps), preset("kitti"),
                       Protocol(5.0, exclude_recent_frames=60),
                       drift=DriftModel(scale_error=0.02, yaw_bias_deg_per_m=0.05), progress=False)
    assert result["closures_published"] >= 20
    assert result["closures_false"] == 0
    assert result["closures_used"] == result["closures_published"]
    assert result["ate_optimised_m"] < result["ate_odometry_m"] / 3
    assert result["recall_published"] > 0.5


def test_slam_eval_cli_writes_json_and_figure(two_laps, tmp_path, capsys):
    from mf_lpr_ros.cli import main

    out, figure = tmp_path / "slam.json", tmp_path / "slam.png"
    assert main(["slam-eval", "--reference", str(two_laps), "--tolerance", "5", "--preset",
                 "kitti", "--exclude-recent-frames", "60", "--query-every", "2",
                 "--drift-yaw-bias-deg-per-m", "0.05", "--json", str(out), "--figure",
                 str(figure), "--quiet"]) == 0
    saved, printed = json.loads(out.read_text()), capsys.readouterr().out
    for key in ("ate_odometry_m", "ate_optimised_m", "closures_used", "closures_false"):
        assert key in saved and key in printed
    assert saved["drift_model"]["yaw_bias_deg_per_m"] == 0.05
    assert figure.stat().st_size > 10_000
