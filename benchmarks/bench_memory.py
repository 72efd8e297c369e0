"""Memory under repeated searches of a large map: load a saved N-reference map (memory-mapped)
and search it again and again; the process's resident memory must not grow.

    .venv/bin/python benchmarks/bench_memory.py [--references 20000] [--searches 20]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.live.localiser import Localiser


def rss_mb() -> float:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--references", type=int, default=20000)
    parser.add_argument("--searches", type=int, default=20)
    args = parser.parse_args()
    config = preset("kitti")
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "large.mfmap"
        reference_map = ReferenceMap(config.descriptor)
        for index in range(args.references):
            reference_map.append(rng.random((120, 120)) < 0.1, np.eye(4), float(index))
        reference_map.save(path)
        del reference_map
        start = rss_mb()
        localiser = Localiser(ReferenceMap.load(path), config)
        indexed = rss_mb()
        query = rng.uniform(-20, 20, (30000, 3)).astype(np.float32)
        rows = []
        for search in range(args.searches):
            started = time.perf_counter()
            localiser.localise(0.0, query)
            rows.append((search, (time.perf_counter() - started) * 1e3, rss_mb()))
    print(f"references {args.references}: "
          f"index {localiser.index.nbytes / 2**20:.0f} MB, RSS before load {start:.0f} MB, "
          f"after indexing {indexed:.0f} MB")
    print("| search | ms | RSS MB |\n|---|---|---|")
    for search, ms, rss in rows:
        print(f"| {search} | {ms:.0f} | {rss:.0f} |")
    print(f"RSS growth from search 3 to {args.searches - 1}: {rows[-1][2] - rows[2][2]:+.1f} MB")


if __name__ == "__main__":
    main()
