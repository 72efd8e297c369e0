"""Soak: scans at 20 Hz for a long time into a localiser whose search is slower than 50 ms.

The search is held to at least --minimum-search-ms (default 150) so that it is the bottleneck on
any machine: a faster search would leave nothing to drop and the newest-scan-only policy untested.

Reports, every few seconds, the process memory, scans received / searched / dropped and the
latency from a scan's arrival to its result; prints a table and saves a figure. Memory must
stay flat and latency bounded (newest-scan-only), with the drops counted.

    .venv/bin/python benchmarks/bench_soak.py [--minutes 10] [--references 1500] [--hz 20]
        [--minimum-search-ms 150]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.ros.graph import RosGraph
from mf_lpr_ros.ros.localiser import LocaliserNode
from mf_lpr_ros.ros.messages import points_to_pointcloud2, seconds_to_stamp
from mf_lpr_ros.sim.synthetic import make_world, scan_world


def rss_mb() -> float:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def held_to_at_least(search, minimum_s: float):
    """search, sleeping after it until minimum_s has passed since it started."""
    def slowed(*args, **kwargs):
        started = time.monotonic()
        result = search(*args, **kwargs)
        time.sleep(max(0.0, started + minimum_s - time.monotonic()))
        return result
    return slowed


# Where every received scan ends up.
_ACCOUNTED = ("scans_searched", "scans_dropped", "scans_rejected", "search_errors")


def soak(seconds: float, references: int, hz: float, sample_every_s: float = 5.0,
         trace: bool = False, minimum_search_ms: float = 150.0) -> list[dict]:
    """Run the soak; one dict per sample (t, rss_mb, received, searched, dropped, latency and,
    with trace, traced_mb: memory held by Python and numpy objects, free of allocator noise).
    With trace, a last sample (t = None) is taken once the stream stopped and the node is idle:
    what is still held then, against the idle start, is what the run retained, and the scan
    counters, which then account for every scan received."""
    import tracemalloc

    from sensor_msgs.msg import PointCloud2

    config = preset("kitti")
    rng = np.random.default_rng(0)
    reference_map = ReferenceMap(config.descriptor)
    for index in range(references):
        reference_map.append(rng.random((120, 120)) < 0.1, np.eye(4), float(index))
    world = make_world(seed=3)
    scans = [scan_world(world, float(x), 0.0, 0.0, rng)[0] for x in np.linspace(-30, 30, 20)]
    samples = []
    with tempfile.TemporaryDirectory() as folder:
        map_path = Path(folder) / "soak.mfmap"
        reference_map.save(map_path)
        graph = RosGraph()
        try:
            node = graph.start(LocaliserNode, preset="kitti", map_path=str(map_path),
                               publish_mode="continuous")
            node.localiser.localise = held_to_at_least(node.localiser.localise,
                                                       minimum_search_ms / 1000.0)
            publisher = graph.publisher(PointCloud2, "points")
            graph.wait_for_subscribers(publisher)
            stop = threading.Event()

            def publish() -> None:
                index, started = 0, time.monotonic()
                while not stop.is_set():
                    publisher.publish(points_to_pointcloud2(
                        scans[index % len(scans)], seconds_to_stamp(1000.0 + index / hz), "lidar"))
                    index += 1
                    time.sleep(max(0.0, started + index / hz - time.monotonic()))

            thread = threading.Thread(target=publish, daemon=True)
            if trace:
                tracemalloc.start()
            started = time.monotonic()
            thread.start()
            while time.monotonic() - started < seconds:
                time.sleep(sample_every_s)
                recent = list(node.result_latencies_ms)[-50:]
                samples.append({"t": time.monotonic() - started, "rss_mb": rss_mb(),
                                "received": node.counters["scans_received"],
                                "searched": node.counters["scans_searched"],
                                "dropped": node.counters["scans_dropped"],
                                "latency_ms": float(np.median(recent)) if recent else float("nan"),
                                "latency_max_ms": float(np.max(recent)) if recent else float("nan"),
                                "traced_mb": tracemalloc.get_traced_memory()[0] / 2**20
                                if trace else float("nan")})
            stop.set()
            thread.join()
            if trace:
                # The stream's last messages may still be in delivery when the publisher stops.
                graph.wait_for(lambda: node.is_idle() and node.counters["scans_received"] == sum(
                    node.counters[name] for name in _ACCOUNTED), 30)
                samples.append({"t": None, "traced_mb": tracemalloc.get_traced_memory()[0] / 2**20,
                                "received": node.counters["scans_received"],
                                "searched": node.counters["scans_searched"],
                                "dropped": node.counters["scans_dropped"]})
                tracemalloc.stop()
        finally:
            graph.close()
    return samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--references", type=int, default=1500)
    parser.add_argument("--hz", type=float, default=20.0)
    parser.add_argument("--minimum-search-ms", type=float, default=150.0)
    parser.add_argument("--figure", default="out/bench_soak.png")
    args = parser.parse_args()
    samples = soak(args.minutes * 60, args.references, args.hz,
                   minimum_search_ms=args.minimum_search_ms)
    print("| t s | RSS MB | received | searched | dropped | latency median / max ms (last 50) |")
    print("|---|---|---|---|---|---|")
    for s in samples[:: max(1, len(samples) // 20)] + samples[-1:]:
        print(f"| {s['t']:.0f} | {s['rss_mb']:.0f} | {s['received']} | {s['searched']} | "
              f"{s['dropped']} | {s['latency_ms']:.0f} / {s['latency_max_ms']:.0f} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s["t"] for s in samples])
    fig, (memory_ax, latency_ax) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    memory_ax.plot(t, [s["rss_mb"] for s in samples])
    memory_ax.set_ylabel("process RSS [MB]")
    latency_ax.plot(t, [s["latency_ms"] for s in samples], label="median of last 50")
    latency_ax.plot(t, [s["latency_max_ms"] for s in samples], label="max of last 50")
    latency_ax.set_ylabel("scan -> result [ms]")
    latency_ax.set_xlabel("time [s]")
    latency_ax.legend()
    memory_ax.set_title(f"{args.hz:g} Hz into a localiser with {args.references} references")
    Path(args.figure).parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(args.figure, dpi=100)
    print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
