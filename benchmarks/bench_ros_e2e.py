"""End-to-end over real DDS: a bag replayed into map_builder and the localiser in loop_closure
mode (the same run as `mf-lpr demo --data BAG`).

Prints closures found vs revisits, pose errors of the published closures against the bag's
poses, and the latency from a scan's arrival to its published closure.

    .venv/bin/python benchmarks/bench_ros_e2e.py [BAG] [--rate 1.0] [--preset handheld]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from mf_lpr_ros.ros.demo import format_rows, run_bag_loop_closure

DEFAULT_BAG = Path(__file__).resolve().parents[2] / "shared" / "data" / "balm_realworld_bag"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", nargs="?", default=str(DEFAULT_BAG))
    parser.add_argument("--rate", type=float, default=1.0)
    parser.add_argument("--preset", default="handheld")
    parser.add_argument("--exclude-recent-s", type=float, default=25.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        rows = run_bag_loop_closure(Path(args.bag), args.preset, Path(folder) / "map.mfmap",
                                    rate=args.rate, exclude_recent_s=args.exclude_recent_s)
    print(format_rows(rows))


if __name__ == "__main__":
    main()
