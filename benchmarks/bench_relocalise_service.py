"""The ~/relocalise Trigger service over real DDS, as nav2 would call it.

A map of the first half of a real sequence (BALM handheld bag) is loaded by a localiser in
on_request mode; the second half's scans that the map covers stream at 10 Hz with their
odometry, and the service is called again and again. Prints the latency from the call to the
reply (it includes waiting for the next scan, at most one sensor period, plus the search and
verification), whether each call succeeded, and the pose errors against the bag's poses.

    .venv/bin/python benchmarks/bench_relocalise_service.py [BAG] [--requests 20]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.pose import planar, wrap_angle
from mf_lpr_ros.datasets.rosbag import RosbagSequence
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan
from mf_lpr_ros.ros.demo import format_rows
from mf_lpr_ros.ros.graph import RosGraph
from mf_lpr_ros.ros.localiser import LocaliserNode
from mf_lpr_ros.ros.messages import odometry_message, points_to_pointcloud2, seconds_to_stamp

DEFAULT_BAG = Path(__file__).resolve().parents[2] / "shared" / "data" / "balm_realworld_bag"
PERIOD_S = 0.1


def run(bag: Path, requests: int, preset_name: str) -> list[tuple[str, str]]:
    sequence = RosbagSequence(bag)
    half = len(sequence) // 2
    with tempfile.TemporaryDirectory() as folder:
        map_path = Path(folder) / "half.mfmap"
        builder = MapBuilder(preset(preset_name), map_path, keep_clouds=True)
        for scan in sequence.iter_scans(range(half)):
            builder.offer(PairedScan(scan.index, scan.stamp, scan.points, scan.pose))
        builder.save()
        mapped = builder.map.poses[:, :2, 3]
        covered = [scan for scan in sequence.iter_scans(range(half, len(sequence)))
                   if np.linalg.norm(mapped - scan.pose[:2, 3], axis=1).min() <= 2.0]
        graph = RosGraph()
        try:
            node = graph.start(LocaliserNode, preset=preset_name, map_path=str(map_path),
                               pose_source="odom")
            clouds = graph.publisher(PointCloud2, "points")
            odometry = graph.publisher(Odometry, "odom")
            client = graph.node.create_client(Trigger, "/localiser/relocalise")
            graph.wait_for_subscribers(clouds)
            graph.wait_for_subscribers(odometry)
            client.wait_for_service(timeout_sec=10)
            truth: dict[float, np.ndarray] = {}
            stop = threading.Event()

            def stream() -> None:
                stamp = 1e6
                while not stop.is_set():
                    for scan in covered:
                        if stop.wait(PERIOD_S):
                            return
                        stamp += PERIOD_S
                        truth[round(stamp, 3)] = planar(scan.pose)
                        message_stamp = seconds_to_stamp(stamp)
                        odometry.publish(odometry_message(message_stamp, "map", "velodyne",
                                                          scan.pose))
                        clouds.publish(points_to_pointcloud2(scan.points, message_stamp,
                                                             "velodyne"))

            thread = threading.Thread(target=stream, daemon=True)
            thread.start()
            latencies, translation, yaw, failures = [], [], [], 0
            for _ in range(requests):
                started = time.perf_counter()
                future = client.call_async(Trigger.Request())
                graph.wait_for(future.done, 30)
                latencies.append((time.perf_counter() - started) * 1e3)
                reply = future.result()
                if not reply.success:
                    failures += 1
                    continue
                answer = json.loads(reply.message)
                true_pose = truth[round(answer["stamp"], 3)]
                translation.append(float(np.hypot(answer["x"] - true_pose[0],
                                                  answer["y"] - true_pose[1])))
                yaw.append(abs(float(np.degrees(wrap_angle(answer["yaw"] - true_pose[2])))))
            stop.set()
            thread.join()
            published = node.counters["poses_published"]
        finally:
            graph.close()
    latencies, translation, yaw = np.array(latencies), np.array(translation), np.array(yaw)
    return [
        ("bag, preset", f"{bag.name} ({len(covered)} covered scans of the second half), "
                        f"{preset_name}"),
        ("requests / succeeded / poses published", f"{requests} / {requests - failures} / "
                                                    f"{published}"),
        ("call -> reply latency median / p95 / max (ms)",
         f"{np.median(latencies):.0f} / {np.percentile(latencies, 95):.0f} / "
         f"{latencies.max():.0f}"),
        ("translation error median / max (m)",
         f"{np.median(translation):.3f} / {translation.max():.3f}" if len(translation) else "-"),
        ("yaw error median / max (deg)",
         f"{np.median(yaw):.2f} / {yaw.max():.2f}" if len(yaw) else "-"),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", nargs="?", default=str(DEFAULT_BAG))
    parser.add_argument("--requests", type=int, default=20)
    parser.add_argument("--preset", default="handheld")
    args = parser.parse_args()
    print(format_rows(run(Path(args.bag), args.requests, args.preset)))


if __name__ == "__main__":
    main()
