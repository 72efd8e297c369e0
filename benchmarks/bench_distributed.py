"""Wall time of `suite shared-data` serial and on a Dask LocalCluster (fresh output folders).

    .venv/bin/python benchmarks/bench_distributed.py [--data ../shared/data] [--workers 1 2]

Prints a table: mode, workers, wall seconds, speed-up over serial. Cluster start-up is counted.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from mf_lpr_ros.evaluation.benchmarks import SUITES
from mf_lpr_ros.evaluation.suite import run_suite
from mf_lpr_ros.pipeline.distributed import dask_client


def timed_run(root: Path, methods: list[str], workers: int | None) -> float:
    with tempfile.TemporaryDirectory() as out:
        started = time.perf_counter()
        if workers is None:
            run_suite(SUITES["shared-data"], root, Path(out), methods=methods, progress=False,
                      figures=False)
        else:
            with dask_client("local", workers) as client:
                run_suite(SUITES["shared-data"], root, Path(out), methods=methods,
                          progress=False, figures=False, client=client)
        return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path,
                        default=Path(__file__).resolve().parents[1].parent / "shared" / "data")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--methods", nargs="+", default=["mf-lpr", "scan-context"])
    args = parser.parse_args()
    serial = timed_run(args.data, args.methods, None)
    rows = [("serial", "-", serial, 1.0)]
    for workers in args.workers:
        wall = timed_run(args.data, args.methods, workers)
        rows.append(("LocalCluster", str(workers), wall, serial / wall))
    print(f"suite shared-data, methods {' '.join(args.methods)} (3 pairs x "
          f"{len(args.methods)} methods = {3 * len(args.methods)} units)\n")
    print("mode | workers | wall s | speed-up")
    print("--- | --- | --- | ---")
    for mode, workers, wall, gain in rows:
        print(f"{mode} | {workers} | {wall:.1f} | {gain:.2f}x")


if __name__ == "__main__":
    main()
