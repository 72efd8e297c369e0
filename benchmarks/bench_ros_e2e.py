"""End-to-end over real DDS: a bag replayed into the localiser in loop_closure mode.

Prints closures found vs revisits, pose errors of the published closures against the bag's
poses, and the latency from a scan's arrival to its published pose.

    .venv/bin/python benchmarks/bench_ros_e2e.py [BAG] [--rate 1.0] [--preset handheld]
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray

from mf_lpr_ros.config import preset
from mf_lpr_ros.datasets.rosbag import RosbagSequence
from mf_lpr_ros.pipeline import select_references
from mf_lpr_ros.pose import planar, pose_matrix, wrap_angle
from mf_lpr_ros.ros.localiser import LocaliserNode
from mf_lpr_ros.ros.messages import decode_loop_closure, stamp_to_seconds
from mf_lpr_ros.ros.replay import replay_bag

DEFAULT_BAG = Path(__file__).resolve().parents[2] / "shared" / "data" / "balm_realworld_bag"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", nargs="?", default=str(DEFAULT_BAG))
    parser.add_argument("--rate", type=float, default=1.0)
    parser.add_argument("--preset", default="handheld")
    parser.add_argument("--exclude-recent-s", type=float, default=25.0)
    parser.add_argument("--revisit-radius-m", type=float, default=3.0)
    args = parser.parse_args()

    sequence = RosbagSequence(args.bag)
    rclpy.init()
    localiser = LocaliserNode(parameter_overrides=[
        Parameter("preset", value=args.preset), Parameter("mode", value="loop_closure"),
        Parameter("pose_source", value="odom"),
        Parameter("exclude_recent_s", value=args.exclude_recent_s)])
    driver = rclpy.create_node("bench_driver")
    closures, poses = [], {}
    driver.create_subscription(Float64MultiArray, "loop_closure", closures.append, 100)
    driver.create_subscription(PoseWithCovarianceStamped, "relocalisation",
                               lambda m: poses.__setitem__(round(stamp_to_seconds(m.header.stamp), 3), m),
                               100)
    executor = MultiThreadedExecutor(num_threads=3)
    executor.add_node(localiser)
    executor.add_node(driver)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    replay_bag(args.bag, rate=args.rate, node=driver, wait_for_subscribers=1)
    deadline = time.monotonic() + 30
    while not localiser.is_idle() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)

    truth = planar(sequence.poses)
    index_of = {round(s, 3): i for i, s in enumerate(sequence.stamps)}
    translation, yaw, closed = [], [], set()
    for closure in map(decode_loop_closure, closures):
        stamp = round(stamp_to_seconds(closure["query_stamp"]), 3)
        message = poses[stamp]
        p, q = message.pose.pose.position, message.pose.pose.orientation
        estimate = planar(pose_matrix(np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])))
        query = index_of[stamp]
        translation.append(float(np.hypot(*(estimate[:2] - truth[query][:2]))))
        yaw.append(abs(math.degrees(float(wrap_angle(estimate[2] - truth[query][2])))))
        closed.add(query)
    positions = sequence.poses[:, :2, 3]
    references = select_references(sequence.poses[:, :3, 3], preset(args.preset).spacing_m)
    revisits = set()
    for index, stamp in enumerate(sequence.stamps):
        old = references[sequence.stamps[references] <= stamp - args.exclude_recent_s]
        if len(old) and np.linalg.norm(positions[old] - positions[index], axis=1).min() \
                <= args.revisit_radius_m:
            revisits.add(index)
    counters = localiser.counters
    latency = np.array(localiser.latencies_ms)
    translation, yaw = np.array(translation), np.array(yaw)
    correct = int(((translation < 0.5) & (yaw < 2.0)).sum()) if len(translation) else 0
    rows = [
        ("bag", f"{Path(args.bag).name}, {len(sequence)} scans, rate {args.rate}x"),
        ("scans received / searched / dropped", f"{counters['scans_received']} / "
         f"{counters['scans_searched']} / {counters['scans_dropped']}"),
        (f"revisits (older reference within {args.revisit_radius_m} m)", str(len(revisits))),
        ("closures published (accepted matches)", str(len(closures))),
        ("revisits closed", f"{len(closed & revisits)} of {len(revisits)}"),
        ("closures within 0.5 m and 2 deg", f"{correct} of {len(closures)}"),
        ("translation error median / max (m)",
         f"{np.median(translation):.3f} / {translation.max():.3f}" if len(translation) else "-"),
        ("yaw error median / max (deg)",
         f"{np.median(yaw):.2f} / {yaw.max():.2f}" if len(yaw) else "-"),
        ("latency scan -> pose median / p95 / max (ms)",
         f"{np.median(latency):.1f} / {np.percentile(latency, 95):.1f} / {latency.max():.1f}"
         if len(latency) else "-"),
    ]
    width = max(len(name) for name, _ in rows)
    print(f"| {'measure'.ljust(width)} | value |\n|{'-' * (width + 2)}|-------|")
    for name, value in rows:
        print(f"| {name.ljust(width)} | {value} |")
    executor.shutdown()
    localiser.finish()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
