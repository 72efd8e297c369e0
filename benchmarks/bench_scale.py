"""The search at scale: maps of 1,500 to 1,000,000 references, each measured in fresh processes.

    .venv/bin/python benchmarks/bench_scale.py [--sizes 1500 20000 100000 250000 1000000]
        [--queries 20] [--work DIR] [--keep] [--reuse] [--rotation-step-deg 5]

Each size is generated once (generated_map_file) and, as build-map does after saving a map,
its prefilter's features are cached beside it where the search reads the reference spectra on
demand (core.search.cache_prefilter; timed apart). It is then started twice in a new process: the
first start is a localiser's first on the freshly built map, the second a restart. Per size
the table gives where the reference spectra live (search.reference_spectra "auto"), bytes on
disk (map, prefilter cache), the index's bytes in memory, both start times (map load + index),
the median query time and the second process's peak resident memory.

Generated references have the density and patch cap of real scans (bench_search.py) and lie on
a square grid 2 m apart, as a global-map grid's do, so the prefilter's expansion by map
neighbours brings as many references along as on a real grid. A pool of distinct descriptors
is rolled by a different offset for each tile of the grid, so no two references are equal.
Queries are references turned by a random quarter turn.

--grid-km2 A adds a rendered global grid: the simulator's town (its surfaces sampled, 256 m
square) tiled to A km^2, rendered at 2 m on --workers processes (build time measured), then
started twice and queried with simulated VLP-16 scans from the town's drive. The copies are
identical, so a match counts as found when it lies within 1 m of the scan modulo the tiling.
With --grid-clouds the grid keeps its site cloud (core.site_cloud, as a grid that verifies by
ICP does), and every town query is also verified by ICP against it (refine_match): the table
then adds the ICP's median ms and how many matches reach the `handheld` preset's fitness.

--reuse takes the maps a --keep run left in --work instead of making them again (their make
time is then not measured), so that search settings such as --rotation-step-deg can be
compared on the same maps.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_search import PARAMS, generated_occupancies, print_table
from tqdm import tqdm

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.descriptor import describe_points, rotate_occupancy
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import pose_matrix, quaternion_from_yaw
from mf_lpr_ros.core.prefilter_cache import cache_path
from mf_lpr_ros.core.refine import refine_match
from mf_lpr_ros.core.search import MatchedFilterIndex, cache_prefilter
from mf_lpr_ros.params import SearchParams
from mf_lpr_ros.pipeline.global_map import RenderParams, build_global_map
from mf_lpr_ros.sim.lidar import cast
from mf_lpr_ros.sim.scenes import scene_cloud
from mf_lpr_ros.sim.simulator import urban_traversals

SPACING_M = 2.0
VERIFY_FITNESS = preset("handheld").search.verify_fitness
POOL = 4096
TOWN_PERIOD_M = 256.0


def generated_map_file(n_refs: int, path: Path) -> float:
    """Write a generated map of n_refs references to path; returns the seconds it took."""
    started = time.perf_counter()
    rng = np.random.default_rng(n_refs)
    pool = next(generated_occupancies(min(POOL, n_refs), rng, block=POOL))
    n_bytes = PARAMS.size * PARAMS.size // 8
    bits = np.empty((n_refs, n_bytes), dtype=np.uint8)
    for tile, first in enumerate(tqdm(range(0, n_refs, len(pool)), desc=f"generate {n_refs}",
                                      leave=False)):
        count = min(len(pool), n_refs - first)
        rolled = np.roll(pool[:count], (tile % PARAMS.size, tile // PARAMS.size % PARAMS.size),
                         axis=(1, 2))
        bits[first: first + count] = np.packbits(rolled.reshape(count, -1), axis=1)
    side = int(np.ceil(np.sqrt(n_refs)))
    poses = np.tile(np.eye(4), (n_refs, 1, 1))
    row, col = np.divmod(np.arange(n_refs), side)
    poses[:, 0, 3], poses[:, 1, 3] = col * SPACING_M, row * SPACING_M
    ReferenceMap.from_arrays(PARAMS, bits, poses, np.arange(n_refs, dtype=float),
                             np.arange(n_refs)).save(path)
    return time.perf_counter() - started


def rendered_grid_file(km2: float, path: Path, workers: int, keep_clouds: bool) -> float:
    """Render the simulator's town tiled to km2 into path (with its site cloud when
    keep_clouds); returns the seconds it took."""
    town = urban_traversals()
    cloud = scene_cloud(town.scene)
    copies = max(1, round(np.sqrt(km2 * 1e6) / TOWN_PERIOD_M))
    offsets = np.stack(np.meshgrid(np.arange(copies), np.arange(copies)), -1).reshape(-1, 2)
    tiled = np.concatenate([cloud + np.array([dx, dy, 0.0], dtype=np.float32) * TOWN_PERIOD_M
                            for dx, dy in offsets])
    del cloud
    elevations = town.sensor.elevations_deg
    started = time.perf_counter()
    grid = build_global_map("tiled town", preset("kitti"), points=tiled, workers=workers,
                            render=RenderParams(spacing_m=SPACING_M, elevation_deg=(
                                min(elevations), max(elevations))),
                            keep_clouds=keep_clouds)
    seconds = time.perf_counter() - started
    grid.save(path)
    return seconds


def cached_at_build(path: Path) -> float:
    """Seconds to cache the prefilter's features beside the map at path, as build-map does
    once it has saved a map (next to nothing where the search keeps spectra in memory)."""
    started = time.perf_counter()
    cache_prefilter(path, SearchParams(backend="numpy"))
    return time.perf_counter() - started


def _town_queries(count: int, rng: np.random.Generator
                  ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(occupancy, x y, points) of simulated scans at random stations of the town's drive."""
    town = urban_traversals()
    params = preset("kitti").descriptor
    height = town.sensor.mount_height_m
    stations = town.first[rng.choice(len(town.first), count, replace=False)]
    scans = [cast(town.scene, town.sensor, pose_matrix(np.array([x, y, height]),
                                                      quaternion_from_yaw(yaw)), rng)
             for x, y, yaw in stations]
    return [(describe_points(points, params), station[:2], points)
            for points, station in zip(scans, stations)]


def _memory_mb() -> tuple[float, float]:
    """(resident now, peak resident) of this process in MB."""
    fields = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines())
    return (int(fields["VmRSS"].split()[0]) / 1024, int(fields["VmHWM"].split()[0]) / 1024)


def measure_start(path: Path, n_queries: int, town: bool, rotation_step_deg: float) -> dict:
    """One start of a localiser's search on the map at path, then n_queries queries (scans of
    the town when town, else turned references)."""
    started = time.perf_counter()
    index = MatchedFilterIndex(ReferenceMap.load(path),
                               SearchParams(backend="numpy", rotation_step_deg=rotation_step_deg))
    start_s = time.perf_counter() - started
    rng = np.random.default_rng(1)
    if town:
        queries = _town_queries(n_queries + 1, rng)
    else:
        # Quarter turns map cells onto cells: generated noise has no structure to survive a
        # resampling, real scans do.
        queries = [(rotate_occupancy(index.map.occupancy(int(reference)),
                                     np.array([90.0 * rng.integers(4)]))[0], int(reference), None)
                   for reference in rng.choice(len(index), n_queries + 1, replace=False)]
    timings, found, icp_ms, verified = [], 0, [], 0
    for query, truth, points in queries:
        began = time.perf_counter()
        match = index.query(query)
        timings.append((time.perf_counter() - began) * 1e3)
        if points is not None and index.map.has_clouds:
            began = time.perf_counter()
            verified += int(refine_match(match, points, index.map).fitness >= VERIFY_FITNESS)
            icp_ms.append((time.perf_counter() - began) * 1e3)
        if town:
            error = (match.pose[:2] - truth + TOWN_PERIOD_M / 2) % TOWN_PERIOD_M - TOWN_PERIOD_M / 2
            found += int(np.hypot(*error) <= 1.0)
        else:
            found += int(match.reference_index == truth)
    resident, peak = _memory_mb()
    return {"start_s": start_s, "ms": float(np.median(timings[1:])), "found": found,
            "queries": len(queries), "index_mb": index.nbytes / 2 ** 20,
            "icp_ms": float(np.median(icp_ms[1:])) if icp_ms else None, "verified": verified,
            "references": len(index), "on_demand": index.spectra_on_demand,
            "rss_mb": resident, "peak_mb": peak}


def _child(*args: str) -> dict:
    # Options before --child: its nargs="+" would take them.
    options, positional = list(args[3:]), list(args[:3])
    output = subprocess.run([sys.executable, __file__, *options, "--child", *positional],
                            check=True, stdout=subprocess.PIPE, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="*",
                        default=[1500, 20000, 100000, 250000, 1000000])
    parser.add_argument("--queries", type=int, default=20)
    parser.add_argument("--work", type=Path, help="where the generated maps go (default: a "
                        "temporary directory; 1M references take ~2 GB)")
    parser.add_argument("--keep", action="store_true", help="keep the generated maps")
    parser.add_argument("--grid-km2", type=float, help="also render the simulator's town "
                        "tiled to this many km^2 and measure it (1 km^2: ~250k references)")
    parser.add_argument("--workers", type=int, default=2, help="rendering processes")
    parser.add_argument("--grid-clouds", action="store_true", help="the grid keeps its site "
                        "cloud and town queries are verified by ICP against it")
    parser.add_argument("--reuse", action="store_true",
                        help="use the maps a --keep run left in --work")
    parser.add_argument("--rotation-step-deg", type=float,
                        default=SearchParams.rotation_step_deg,
                        help="the search's global rotation step (default: the default's)")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        action, path, number = args.child[0], Path(args.child[1]), args.child[2]
        if action == "generate":
            result = {"seconds": generated_map_file(int(number), path),
                      "cache_s": cached_at_build(path)}
        elif action == "render":
            result = {"seconds": rendered_grid_file(float(number), path, args.workers,
                                                    args.grid_clouds),
                      "cache_s": cached_at_build(path)}
        else:
            result = measure_start(path, int(number), town=action == "measure-town",
                                   rotation_step_deg=args.rotation_step_deg)
        print(json.dumps(result))
        return
    work = Path(args.work or tempfile.mkdtemp(prefix="mf_lpr_scale_"))
    work.mkdir(parents=True, exist_ok=True)
    runs = [(f"generated_{n}", "generate", str(n), "measure") for n in args.sizes]
    if args.grid_km2:
        runs.append((f"town_{args.grid_km2}km2", "render", str(args.grid_km2), "measure-town"))
    rows = []
    for name, make, size, measure in runs:
        path = work / f"{name}.mfmap"
        if args.reuse and path.exists():
            made = {"seconds": float("nan"), "cache_s": float("nan")}
        else:
            made = _child(make, str(path), size, "--workers", str(args.workers),
                          *(["--grid-clouds"] if args.grid_clouds else []))
        step = ("--rotation-step-deg", str(args.rotation_step_deg))
        first = _child(measure, str(path), str(args.queries), *step)
        second = _child(measure, str(path), str(args.queries), *step)
        cache = cache_path(path)
        label = (f"{second['references']:,}" if make == "generate" else
                 f"{second['references']:,} (town grid, {size} km^2)")
        rows.append((label, "on demand" if second["on_demand"] else "memory",
                     made["seconds"], made["cache_s"], path.stat().st_size / 2 ** 20,
                     cache.stat().st_size / 2 ** 20 if cache.exists() else 0.0,
                     second["index_mb"], first["start_s"], second["start_s"], second["ms"],
                     f"{second['found']}/{second['queries']}", second["peak_mb"],
                     "-" if second["icp_ms"] is None else
                     f"{second['icp_ms']:.1f} ({second['verified']}/{second['queries']})"))
        if not args.keep:
            path.unlink()
            cache.unlink(missing_ok=True)
    print_table(("references", "spectra", "generate / render s", "cache s", "map MB",
                 "prefilter cache MB", "index MB in RAM", "first start s", "restart s",
                 "ms/query", "found", "peak RSS MB", "ICP ms (verified)"), rows)


if __name__ == "__main__":
    main()
