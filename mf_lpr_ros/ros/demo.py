"""The demo: the whole system on simulated worlds (or a real bag), through the ROS 2 nodes.

For each simulated world: the two days are written as ROS 2 bags (cached); day 1 is replayed
over DDS into map_builder, which writes the map; day 2 is replayed in real time into the
localiser, and what it publishes is compared with the simulator's ground truth.
With a real bag: map_builder and the localiser in loop_closure mode listen to one replay.
"""

from __future__ import annotations

import importlib.util
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from std_msgs.msg import Float64MultiArray

from mf_lpr_ros.config import preset as named_preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import compose_planar, moved_points, planar, planar_error, pose_matrix
from mf_lpr_ros.core.pose_graph import absolute_trajectory_error
from mf_lpr_ros.datasets.rosbag import RosbagSequence
from mf_lpr_ros.evaluation.protocol import revisits
from mf_lpr_ros.io.messages import stamp_to_seconds
from mf_lpr_ros.ros.graph import RosGraph
from mf_lpr_ros.ros.localiser import LocaliserNode
from mf_lpr_ros.ros.map_builder import MapBuilderNode
from mf_lpr_ros.ros.messages import decode_loop_closure
from mf_lpr_ros.ros.pose_graph import PoseGraphNode
from mf_lpr_ros.ros.replay import replay_bag
from mf_lpr_ros.sim.simulator import world_bags

WORLD_PRESETS = {"urban": "kitti", "forest": "default", "sparse": "auto"}
# Worlds whose localiser also gets the day's odometry (pose_source odom): the sparse sensor's
# map is built from submaps (preset auto chooses them), and its queries need the odometry to
# make theirs. The dense worlds show single-scan relocalisation without odometry.
WORLDS_WITH_ODOMETRY = {"sparse"}
SEEN_WITHIN_M = 5.0        # a query this close to a reference should be relocalised
UNSEEN_BEYOND_M = 15.0     # a query this far from every reference must be rejected
CORRECT_WITHIN_M, CORRECT_WITHIN_DEG = 2.0, 5.0
BUILD_RATE = 5.0
# The simulated sensor's scan rate (the bags' stamps); day 2 replays at it times --rate.
SCAN_HZ = 10.0
# Geometric verification of every match (ICP fitness), with the threshold chosen on the real
# BALM sequence (config.SearchParams.verify_fitness); the maps keep their clouds for it.
VERIFY_FITNESS = 0.68
# The simulated town repeats one block design every 50 m, so true matches there are barely more
# distinctive than the same corner of the next block (0.04-0.22 against 0.00-0.03). ICP against
# the stored clouds is the test that tells them apart here; the distinctiveness test stays on
# in every preset for maps without clouds.
DEMO_MIN_DISTINCTIVENESS = 0.0


@dataclass
class WorldResult:
    name: str
    preset: str
    references: int
    queries: int
    seen: int
    unseen: int
    published: int
    correct: int
    false_unseen: int
    seen_searched: int
    unseen_searched: int
    translation_m: np.ndarray
    yaw_deg: np.ndarray
    latency_ms: np.ndarray
    dropped: int
    map_path: Path
    replay_hz: float
    estimates: dict[int, np.ndarray] = field(default_factory=dict)
    truth: np.ndarray | None = None
    reference_xy: np.ndarray | None = None


def run_world(name: str, out: Path, graph: RosGraph, progress: bool, stride: int = 1,
              rate: float = 1.0) -> WorldResult:
    folder = out / name
    first, second, truth = world_bags(name, folder, stride=stride, rate_hz=SCAN_HZ,
                                      progress=progress)
    preset = WORLD_PRESETS[name]
    map_path = folder / "map.mfmap"

    builder = graph.start(MapBuilderNode, preset=preset, map_path=str(map_path),
                          if_exists="overwrite", save_period_s=60.0, keep_clouds=True)
    report = replay_bag(first, rate=BUILD_RATE, node=graph.node, wait_for_subscribers=1,
                        progress=progress)
    graph.wait_for(lambda: builder.counters["scans_received"] >= report.published["/points"]
                   and builder.synchroniser.pending == 0, 30)
    graph.stop(builder)

    odometry = name in WORLDS_WITH_ODOMETRY
    localiser = graph.start(LocaliserNode, preset=preset, map_path=str(map_path),
                            publish_mode="continuous",
                            pose_source="odom" if odometry else "none",
                            **{"search.verify_fitness": VERIFY_FITNESS,
                               "search.min_distinctiveness": DEMO_MIN_DISTINCTIVENESS})
    poses = graph.collect(PoseWithCovarianceStamped, "relocalisation")
    replay_bag(second, rate=rate, node=graph.node, wait_for_subscribers=1, progress=progress,
               topics=["/points", "/odom"] if odometry else ["/points"])
    graph.wait_for(localiser.is_idle, 30)
    time.sleep(0.3)
    latency = np.array(localiser.latencies_ms)
    dropped = localiser.counters["scans_dropped"]
    searched_stamps = list(localiser.searched_stamps)
    graph.stop(localiser)

    reference_xy = ReferenceMap.load(map_path).poses[:, :2, 3]
    nearest = np.linalg.norm(truth[:, None, :2] - reference_xy[None], axis=2).min(1)
    seen, unseen = nearest <= SEEN_WITHIN_M, nearest > UNSEEN_BEYOND_M
    start = 1_700_086_400.0
    searched = np.zeros(len(truth), bool)
    searched[[int(round((stamp - start) * SCAN_HZ)) for stamp in searched_stamps]] = True
    estimates = {int(round((stamp_to_seconds(m.header.stamp) - start) * SCAN_HZ)): _planar(m)
                 for m in poses}
    translation, yaw, correct, false_unseen = [], [], 0, 0
    for index, estimate in estimates.items():
        error_m, error_deg = planar_error(estimate, truth[index])
        translation.append(error_m)
        yaw.append(error_deg)
        correct += bool(seen[index] and error_m <= CORRECT_WITHIN_M
                        and error_deg <= CORRECT_WITHIN_DEG)
        false_unseen += bool(unseen[index])
    return WorldResult(name, preset, len(reference_xy), len(truth), int(seen.sum()),
                       int(unseen.sum()), len(estimates), correct, false_unseen,
                       int((seen & searched).sum()), int((unseen & searched).sum()),
                       np.array(translation), np.array(yaw), latency, dropped, map_path,
                       SCAN_HZ * rate, estimates, truth, reference_xy)


def _planar(message: PoseWithCovarianceStamped) -> np.ndarray:
    p, q = message.pose.pose.position, message.pose.pose.orientation
    return planar(pose_matrix(np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])))


def run_demo(out: Path, worlds: list[str], progress: bool = True, stride: int = 1,
             rate: float = 1.0) -> list[WorldResult]:
    """Run the simulated worlds, print the table, save the figure; returns the results. rate
    speeds day 2's replay up (the localiser then drops more scans, newest-only)."""
    out.mkdir(parents=True, exist_ok=True)
    graph = RosGraph()
    try:
        results = [run_world(name, out, graph, progress, stride, rate) for name in worlds]
    finally:
        graph.close()
    print()
    print(_table(results))
    figure = out / "demo.png"
    _plot(figure, results)
    print(f"\nmaps: {', '.join(str(r.map_path) for r in results)}")
    print(f"figure: {figure}")
    return results


def _table(results: list[WorldResult]) -> str:
    def median(values: np.ndarray, fmt: str) -> str:
        return format(float(np.median(values)), fmt) if len(values) else "-"

    rows = [("world (preset)", lambda r: f"{r.name} ({r.preset})"),
            ("map references (day 1)", lambda r: str(r.references)),
            ("day-2 scans", lambda r: f"{r.queries} at {r.replay_hz:g} Hz"),
            (f"scans within {SEEN_WITHIN_M:g} m of the map", lambda r: str(r.seen)),
            ("recall@1 (pose < 2 m, 5 deg)", lambda r: f"{r.correct / max(r.seen, 1):.3f}"),
            ("recall@1 among the scans searched",
             lambda r: f"{r.correct / max(r.seen_searched, 1):.3f}"),
            ("median error of correct (m / deg)",
             lambda r: f"{median(r.translation_m[r.translation_m <= CORRECT_WITHIN_M], '.3f')} / "
                       f"{median(r.yaw_deg[r.translation_m <= CORRECT_WITHIN_M], '.2f')}"),
            (f"unseen scans (> {UNSEEN_BEYOND_M:g} m from the map)", lambda r: str(r.unseen)),
            ("unseen scans searched and rejected",
             lambda r: f"{1 - r.false_unseen / r.unseen_searched:.3f}"
             if r.unseen_searched else "-"),
            ("latency scan -> pose, median / p95 (ms)",
             lambda r: f"{median(r.latency_ms, '.1f')} / "
                       f"{np.percentile(r.latency_ms, 95):.1f}" if len(r.latency_ms) else "-"),
            ("scans dropped (newest-only)", lambda r: str(r.dropped))]
    width = max(len(name) for name, _ in rows)
    lines = [f"| {'':{width}} | " + " | ".join(r.name for r in results) + " |",
             f"|{'-' * (width + 2)}|" + "|".join("-" * (len(r.name) + 2) for r in results) + "|"]
    lines += [f"| {name:{width}} | " + " | ".join(value(r) for r in results) + " |"
              for name, value in rows[1:]]
    return "\n".join(lines)


def _plot(path: Path, results: list[WorldResult]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 2, figsize=(13, 6.5 * len(results)), squeeze=False)
    for (trajectory_ax, overlay_ax), result in zip(axes, results):
        truth = result.truth
        trajectory_ax.plot(result.reference_xy[:, 0], result.reference_xy[:, 1], ".",
                           color="0.65", ms=4, label="map references (day 1)")
        trajectory_ax.plot(truth[:, 0], truth[:, 1], "-", color="tab:blue", lw=0.8,
                           label="day 2 (ground truth)")
        if result.estimates:
            indices = np.array(sorted(result.estimates))
            estimate = np.array([result.estimates[i] for i in indices])
            error, _ = planar_error(estimate, truth[indices])
            points = trajectory_ax.scatter(estimate[:, 0], estimate[:, 1], c=np.minimum(error, 2),
                                           cmap="RdYlGn_r", s=14, vmin=0, vmax=2,
                                           label="published poses")
            fig.colorbar(points, ax=trajectory_ax, label="translation error [m] (clipped at 2)")
        trajectory_ax.set_title(f"{result.name}: day 2 relocalised in the map of day 1")
        trajectory_ax.set_aspect("equal")
        trajectory_ax.legend(loc="best", fontsize=8)
        _overlay(overlay_ax, result)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _overlay(ax, result: WorldResult) -> None:
    """Query and matched reference clouds in the map frame, placed by the published pose."""
    if not result.estimates:
        ax.set_axis_off()
        return
    folder = result.map_path.parent
    reference_map = ReferenceMap.load(result.map_path)
    index = sorted(result.estimates)[len(result.estimates) // 2]
    estimate = result.estimates[index]
    reference = int(np.argmin(np.linalg.norm(reference_map.poses[:, :2, 3] - estimate[:2], axis=1)))
    query_scan = next(RosbagSequence(folder / "day2").iter_scans([index]))
    reference_scan = next(RosbagSequence(folder / "day1").iter_scans(
        [int(reference_map.source_indices[reference])]))
    placed = pose_matrix(np.array([*estimate[:2], 0.0]),
                         np.array([0, 0, math.sin(estimate[2] / 2), math.cos(estimate[2] / 2)]))
    for scan, transform, colour, label in (
            (reference_scan, reference_scan.pose, "0.4", "reference scan (day 1)"),
            (query_scan, placed, "tab:orange", "query scan (day 2) at the published pose")):
        band = (scan.points[:, 2] > -1.2) & (scan.points[:, 2] < 3.0)
        world = moved_points(scan.points[band], transform)
        ax.scatter(world[::2, 0], world[::2, 1], s=0.3, color=colour, label=label)
    ax.set_title(f"{result.name}: BEV overlay of day-2 scan {index} on its match")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8, markerscale=15)


def run_bag_loop_closure(bag: Path, preset: str, map_path: Path, rate: float = 1.0,
                         exclude_recent_s: float = 25.0, revisit_radius_m: float = 3.0,
                         progress: bool = True) -> list[tuple[str, str]]:
    """Replay a real bag into map_builder, a loop_closure localiser and the pose_graph back end
    (when gtsam is installed); (measure, value) rows: closures vs revisits, their pose errors
    against the bag's poses, latency, the back end's path."""
    sequence = RosbagSequence(bag)
    if sequence.poses is None:
        raise ValueError(f"{bag}: loop-closure mode needs a pose topic (Odometry or PoseStamped)")
    pose_source = {"nav_msgs/msg/Odometry": "odom", "geometry_msgs/msg/PoseStamped": "pose",
                   "geometry_msgs/msg/PoseWithCovarianceStamped": "pose_with_covariance"}[
        sequence.pose_type]
    topic_of = {"odom": "odom", "pose": "pose", "pose_with_covariance": "pose"}
    remaps = ["--ros-args", "-r", f"points:={sequence.cloud_topic}",
              "-r", f"{topic_of[pose_source]}:={sequence.pose_topic}"]
    graph = RosGraph(remaps)
    try:
        builder = graph.start(MapBuilderNode, preset=preset, map_path=str(map_path),
                              if_exists="overwrite", pose_source=pose_source)
        localiser = graph.start(LocaliserNode, preset=preset, mode="loop_closure",
                                pose_source=pose_source, exclude_recent_s=exclude_recent_s)
        back_end = graph.start(PoseGraphNode, keyframe_spacing_m=0.5) \
            if importlib.util.find_spec("gtsam") else None
        closures = graph.collect(Float64MultiArray, "loop_closure")
        replay_bag(bag, rate=rate, node=graph.node, wait_for_subscribers=2, progress=progress,
                   topics=[sequence.cloud_topic, sequence.pose_topic])
        graph.wait_for(localiser.is_idle, 30)
        time.sleep(0.3)
        counters, latency = localiser.counters.copy(), np.array(localiser.latencies_ms)
        if back_end is not None:
            graph.wait_for(lambda: back_end.counters["closures_received"] == len(closures), 10)
            back_end_rows = _back_end_rows(back_end, sequence)
        graph.stop(builder)
        references = len(ReferenceMap.load(map_path))
    finally:
        graph.close()
    truth = planar(sequence.poses)
    index_of = {round(s, 3): i for i, s in enumerate(sequence.stamps)}
    translation, yaw, closed = [], [], set()
    for closure in map(decode_loop_closure, closures):
        query = index_of[round(stamp_to_seconds(closure["query_stamp"]), 3)]
        reference = index_of[round(stamp_to_seconds(closure["reference_stamp"]), 3)]
        # The closure's own planar transform, as a back end reads it: a closure confirmed by
        # later matches has no relocalisation pose (docs/ROS.md).
        implied = compose_planar(truth[reference], planar(closure["reference_T_query"]))
        error_m, error_deg = planar_error(implied, truth[query])
        translation.append(error_m)
        yaw.append(error_deg)
        closed.add(query)
    revisited = revisits(sequence.stamps, sequence.poses[:, :3, 3], named_preset(preset).spacing_m,
                         exclude_recent_s, revisit_radius_m)
    translation, yaw = np.array(translation), np.array(yaw)
    correct = int(((translation < 0.5) & (yaw < 2.0)).sum())
    return [
        ("bag", f"{bag.name}: {len(sequence)} scans, preset {preset}, rate {rate}x"),
        ("map written by map_builder", f"{map_path}: {references} references"),
        ("scans received / searched / dropped",
         f"{counters['scans_received']} / {counters['scans_searched']} / "
         f"{counters['scans_dropped']}"),
        (f"revisits (a reference >= {exclude_recent_s:g} s older within {revisit_radius_m:g} m)",
         str(len(revisited))),
        ("loop closures published", str(len(closures))),
        ("revisits closed", f"{len(closed & revisited)} of {len(revisited)}"),
        ("closures within 0.5 m and 2 deg of the bag's poses", f"{correct} of {len(closures)}"),
        ("translation error median / max (m)",
         f"{np.median(translation):.3f} / {translation.max():.3f}" if len(translation) else "-"),
        ("yaw error median / max (deg)",
         f"{np.median(yaw):.2f} / {yaw.max():.2f}" if len(yaw) else "-"),
        ("latency scan -> published closure, median / p95 (ms)",
         f"{np.median(latency):.1f} / {np.percentile(latency, 95):.1f}" if len(latency) else "-"),
        *(back_end_rows if back_end is not None else
          [("pose_graph back end", "not run: gtsam is not installed (pip install gtsam)")]),
    ]


def _back_end_rows(back_end, sequence: RosbagSequence) -> list[tuple[str, str]]:
    """The pose_graph node's keyframes and closures, and its path against the bag's poses."""
    keyframes = np.searchsorted(sequence.stamps, np.array(back_end.graph.keyframe_stamps) - 1e-4)
    ate = absolute_trajectory_error(back_end.graph.estimate, planar(sequence.poses)[keyframes])
    return [("pose_graph: keyframes / closures received / used",
             f"{len(keyframes)} / {back_end.counters['closures_received']} / "
             f"{back_end.graph.graph.closures_used}"),
            ("pose_graph: path error against the bag's poses (ATE, m)", f"{ate:.3f}")]


def choose_preset(bag: Path) -> str:
    """handheld for close-range scans (median horizontal range < 10 m), else kitti."""
    sequence = RosbagSequence(bag)
    read = [s for s in sequence.iter_scans(range(min(5, len(sequence)))) if not s.problem]
    if not read:
        raise ValueError(f"{bag}: none of its first scans could be read, so no preset can be "
                         f"chosen from them")
    ranges = np.concatenate([np.hypot(s.points[:, 0], s.points[:, 1]) for s in read])
    return "handheld" if np.median(ranges) < 10.0 else "kitti"


def format_rows(rows: list[tuple[str, str]]) -> str:
    width = max(len(name) for name, _ in rows)
    return "\n".join([f"| {'measure':{width}} | value |", f"|{'-' * (width + 2)}|-------|"]
                     + [f"| {name:{width}} | {value} |" for name, value in rows])
