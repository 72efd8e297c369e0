"""What the candidate stage (the polar-spectrum prefilter and its map-neighbour expansion) loses
against the exact global search, and what each candidate count costs.

    .venv/bin/python benchmarks/bench_candidates.py [--data ../shared/data] [--every 3]
        [--top-k 32 64 128 256]

On BEVPlace's KITTI protocol of the tuning sequence (kitti_bev/00 and 00_rot: database frames
0-2999, every frame a reference, queries 3200-4540, every --every-th, positive within 5 m), for
each candidate count k: how often the exact search's match is among the candidates (so the
prefiltered search can return it), how often a true reference (within 5 m) is, how often the
prefiltered search's final match equals the exact one's, its retrieval recall@1, how many
references the exact stage then correlates, and the median query time.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from bench_search import print_table
from tqdm import tqdm

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.references import add_references
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.pipeline.mapping import describe_scan, described_scan

DATABASE, QUERIES, TOLERANCE_M = (0, 2999), (3200, 4540), 5.0


def measure(folder: Path, every: int, top_ks: list[int]) -> list[tuple]:
    config = preset("kitti")
    sequence = open_source(folder)
    reference_map = ReferenceMap(config.descriptor)
    database = range(DATABASE[0], DATABASE[1] + 1)
    add_references(reference_map, (described_scan(scan, config.descriptor) for scan in tqdm(
        sequence.iter_scans(database), total=len(database), desc=f"{folder.name}: map")))
    positions = sequence.poses[DATABASE[0]:DATABASE[1] + 1, :2, 3]
    exact = MatchedFilterIndex(reference_map, dataclasses.replace(config.search,
                                                                  prefilter_top_k=0))
    queries = []
    for scan in sequence.iter_scans(range(QUERIES[0], QUERIES[1] + 1, every)):
        distances = np.linalg.norm(positions - scan.pose[:2, 3], axis=1)
        if distances.min() <= TOLERANCE_M:
            queries.append((describe_scan(scan, config.descriptor, reference=False), distances,
                            scan.sensor_offset_m))
    exact_matches = [exact.query(occupancy, sensor_offset_m=offset).reference_index
                     for occupancy, _, offset in tqdm(queries, desc=f"{folder.name}: exact")]
    rows = [(folder.name, "exact", len(queries), 1.0, _mean(
        [d[m] <= TOLERANCE_M for (_, d, _), m in zip(queries, exact_matches)]), 1.0,
        len(reference_map), _median_ms(exact, queries[:40]))]
    for top_k in top_ks:
        index = MatchedFilterIndex(reference_map, dataclasses.replace(config.search,
                                                                      prefilter_top_k=top_k))
        kept_exact, kept_true, agree, correct, sizes = [], [], [], [], []
        for (occupancy, distances, offset), exact_match in zip(
                tqdm(queries, desc=f"{folder.name}: k={top_k}"), exact_matches):
            match = index.query(occupancy, sensor_offset_m=offset)
            candidates = (np.arange(len(reference_map)) if match.searched is None
                          else match.searched)
            sizes.append(len(candidates))
            kept_exact.append(exact_match in candidates)
            kept_true.append(bool((distances[candidates] <= TOLERANCE_M).any()))
            found = match.reference_index
            agree.append(found == exact_match)
            correct.append(distances[found] <= TOLERANCE_M)
        rows.append((folder.name, str(top_k), len(queries), _mean(kept_exact),
                     _mean(correct), _mean(agree), float(np.mean(sizes)),
                     _median_ms(index, queries[:40])))
        print(f"  k={top_k}: exact match kept {_mean(kept_exact):.3f}, a true reference kept "
              f"{_mean(kept_true):.3f}")
    return rows


def _mean(values) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def _median_ms(index: MatchedFilterIndex, queries: list) -> float:
    times = []
    for occupancy, _, offset in queries:
        started = time.perf_counter()
        index.query(occupancy, sensor_offset_m=offset)
        times.append((time.perf_counter() - started) * 1e3)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared"
                                              / "data"))
    parser.add_argument("--every", type=int, default=3)
    parser.add_argument("--top-k", type=int, nargs="+", default=[32, 64, 128, 256])
    parser.add_argument("--sets", nargs="+", default=["kitti_bev/00", "kitti_bev/00_rot"])
    args = parser.parse_args()
    rows = []
    for folder in args.sets:
        rows += measure(Path(args.data) / folder, args.every, args.top_k)
    header = ("set", "top_k", "queries", "exact match in candidates", "recall@1",
              "same match as exact", "references correlated", "ms/query")
    print_table(header, rows)


if __name__ == "__main__":
    main()
