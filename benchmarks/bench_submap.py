"""What submaps cost a live query: the localiser fed every scan of a sequence (observe), every
n-th searched (localise), with single scans and with submaps of a few windows.

    .venv/bin/python benchmarks/bench_submap.py [--data ../shared/data] [--source hku_mb_livox]
        [--windows 0 3 5] [--every 5]

The map holds the sequence's first half (references every spacing_m, described as the window
asks); the second half queries it. Printed per window: median and p95 ms of observe (thinning
and storing a scan), of localise (submap assembly, descriptor, search, verification), the
descriptor stage alone, the submap's points, and the memory the window keeps.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from bench_search import print_table

from mf_lpr_ros.config import preset
from mf_lpr_ros.datasets import Sequence, open_source
from mf_lpr_ros.live.localiser import Localiser
from mf_lpr_ros.pipeline.mapping import build_map


def measure(source: Path, window_m: float, every: int) -> tuple:
    base = preset("default")
    config = dataclasses.replace(base, descriptor=dataclasses.replace(base.descriptor,
                                                                      submap_m=window_m))
    sequence = open_source(source)
    half = len(sequence) // 2
    first = _Part(sequence, half)
    reference_map = build_map(first, config, progress=False)
    localiser = Localiser(reference_map, config, odometry_known=True)
    observe_ms, localise_ms, descriptor_ms, points = [], [], [], []
    for scan in sequence.iter_scans(range(half, len(sequence))):
        started = time.perf_counter()
        localiser.observe(scan.stamp, scan.points, scan.pose)
        observe_ms.append((time.perf_counter() - started) * 1e3)
        if (scan.index - half) % every:
            continue
        started = time.perf_counter()
        result = localiser.localise(scan.stamp, scan.points, scan.pose)
        localise_ms.append((time.perf_counter() - started) * 1e3)
        descriptor_ms.append(result.descriptor_ms)
        if localiser.submap is not None and localiser.submap.holds(scan.stamp):
            points.append(len(localiser.submap.points_at(scan.stamp).points))
        else:
            points.append(len(scan.points))
    kept = 0 if localiser.submap is None else localiser.submap.nbytes
    return (f"{window_m:g}", len(reference_map), len(localise_ms),
            *np.percentile(observe_ms, [50, 95]), *np.percentile(localise_ms, [50, 95]),
            float(np.median(descriptor_ms)), int(np.median(points)), kept / 1e6)


class _Part(Sequence):
    """The first scans of a sequence as a sequence of their own."""

    def __init__(self, sequence: Sequence, count: int) -> None:
        self.base = sequence
        self.name = sequence.name
        self.stamps = sequence.stamps[:count]
        self.poses = sequence.poses[:count]

    def _read(self, indices):
        return self.base.iter_scans(indices)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared"
                                              / "data"))
    parser.add_argument("--source", default="hku_mb_livox")
    parser.add_argument("--windows", type=float, nargs="+", default=[0.0, 3.0, 5.0])
    parser.add_argument("--every", type=int, default=5)
    args = parser.parse_args()
    rows = [measure(Path(args.data) / args.source, window, args.every) for window in args.windows]
    header = ("submap_m", "refs", "queries", "observe ms p50", "observe ms p95",
              "localise ms p50", "localise ms p95", "descriptor ms", "points", "window MB")
    print_table(header, rows)


if __name__ == "__main__":
    main()
