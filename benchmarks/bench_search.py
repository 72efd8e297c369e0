"""Speed and memory of the exact two-stage search, against the authors' tiled-grid algorithm.

    .venv/bin/python benchmarks/bench_search.py [--sizes 1500 5000 20000] [--queries 5]

References are generated occupancies with the density and patch cap of real scans (~9 % of
cells occupied), so the timings do not depend on any dataset. The tiled-grid baseline is a
straightforward CPU port of the authors' global stage: all low-resolution references tiled into
one image, each of the 36 rotated queries convolved over it with scipy.signal.fftconvolve.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np
from scipy.signal import fftconvolve

from mf_lpr_ros.config import DescriptorParams, SearchParams
from mf_lpr_ros.descriptor import cap_patches, pool, rotate_occupancy, weighted
from mf_lpr_ros.map_store import ReferenceMap
from mf_lpr_ros.search import MatchedFilterIndex

PARAMS = DescriptorParams(voxel_size=0.4)
OCCUPIED_FRACTION = 0.12


def generated_map(n_refs: int, rng: np.random.Generator) -> ReferenceMap:
    reference_map = ReferenceMap(PARAMS)
    size = PARAMS.size
    for i in range(n_refs):
        occupancy = cap_patches(rng.random((size, size)) < OCCUPIED_FRACTION, PARAMS, seed=i)
        pose = np.eye(4)
        pose[:2, 3] = rng.uniform(-500, 500, 2)
        reference_map.append(occupancy, pose, float(i), i)
    return reference_map


def tiled_grid_global(reference_map: ReferenceMap, query: np.ndarray, angles: np.ndarray) -> float:
    """Seconds for the authors' global stage: rotated queries convolved over tiled references."""
    low = pool(weighted(reference_map.occupancy(slice(None)), PARAMS.unoccupied_weight), PARAMS.pool)
    n, tile = len(low), low.shape[1]
    per_side = int(np.ceil(np.sqrt(n)))
    grid = np.zeros((per_side * tile, per_side * tile), dtype=np.float32)
    for i, image in enumerate(low):
        row, col = divmod(i, per_side)
        grid[row * tile:(row + 1) * tile, col * tile:(col + 1) * tile] = image
    queries = pool(weighted(rotate_occupancy(query, angles), PARAMS.unoccupied_weight), PARAMS.pool)
    started = time.perf_counter()
    peaks = [fftconvolve(grid, q[::-1, ::-1], mode="same").max() for q in queries]
    assert len(peaks) == len(angles)
    return time.perf_counter() - started


def max_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1500, 5000, 20000])
    parser.add_argument("--queries", type=int, default=5)
    parser.add_argument("--tiled-up-to", type=int, default=5000,
                        help="time the tiled-grid baseline for maps up to this size")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    search = SearchParams()
    rows = []
    for n_refs in args.sizes:
        reference_map = generated_map(n_refs, rng)
        started = time.perf_counter()
        index = MatchedFilterIndex(reference_map, search)
        index_s = time.perf_counter() - started
        timings = []
        for _ in range(args.queries):
            query = rng.random((PARAMS.size, PARAMS.size)) < OCCUPIED_FRACTION
            started = time.perf_counter()
            result = index.query(query)
            total = (time.perf_counter() - started) * 1e3
            timings.append((result.timings_ms["global"], result.timings_ms["local"], total))
        global_ms, local_ms, total_ms = np.median(np.array(timings), axis=0)
        tiled_ms = float("nan")
        if n_refs <= args.tiled_up_to:
            tiled_ms = tiled_grid_global(reference_map, query, index.global_angles) * 1e3
        rows.append((n_refs, index_s, index.nbytes / 2 ** 20,
                     reference_map.occupancy_bits.nbytes / 2 ** 20, global_ms, local_ms, total_ms,
                     tiled_ms, max_rss_mb()))
    print(f"\nexact search, {PARAMS.size}x{PARAMS.size} descriptors, 36 rotations, "
          f"max_shift {search.max_shift_m} m at {PARAMS.voxel_size} m voxels, "
          f"{args.queries} queries each (median)\n")
    header = ("refs", "index build s", "index MB", "map MB", "global ms", "local ms", "total ms",
              "tiled-grid global ms", "speed-up", "peak RSS MB")
    print(" | ".join(header))
    print(" | ".join("---" for _ in header))
    for n, build_s, index_mb, map_mb, g, loc, tot, tiled, rss in rows:
        speedup = f"{tiled / g:.1f}x" if np.isfinite(tiled) else "-"
        tiled_text = f"{tiled:.0f}" if np.isfinite(tiled) else "-"
        print(f"{n} | {build_s:.2f} | {index_mb:.0f} | {map_mb:.1f} | {g:.0f} | {loc:.0f} | {tot:.0f} | "
              f"{tiled_text} | {speedup} | {rss:.0f}")


if __name__ == "__main__":
    main()
