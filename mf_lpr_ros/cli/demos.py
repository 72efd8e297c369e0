"""The demos: demo (the nodes on simulated worlds or a real bag) and global-demo."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_global_demo(args: argparse.Namespace) -> int:
    from mf_lpr_ros.sim import global_demo

    rows, facts = global_demo.run(args.source, progress=not args.quiet)
    print(global_demo.format_table(rows, facts))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    # Before anything is simulated or replayed: a bad rate would only fail at the first replay.
    if not args.rate > 0:
        raise ValueError(f"--rate must be > 0, got {args.rate}")
    from mf_lpr_ros.ros import demo

    out = Path(args.out)
    if args.data:
        bag = Path(args.data)
        chosen = demo.choose_preset(bag) if args.preset == "auto" else args.preset
        out.mkdir(parents=True, exist_ok=True)
        rows = demo.run_bag_loop_closure(bag, chosen, out / f"{bag.stem}.mfmap", rate=args.rate,
                                         progress=not args.quiet)
        print()
        print(demo.format_rows(rows))
        return 0
    demo.run_demo(out, args.worlds, progress=not args.quiet, stride=args.stride, rate=args.rate)
    return 0


def register(commands: argparse._SubParsersAction) -> None:
    global_demo = commands.add_parser(
        "global-demo", help="relocalising off the mapping path in the simulator: a keyframe "
        "map against a grid rendered from the global map (mf_lpr_ros/sim/global_demo.py)")
    global_demo.add_argument("--source", default="drive", choices=["drive", "world"],
                             help="the global cloud: the mapping drive's scans accumulated "
                                  "(default), or the whole world's surfaces")
    global_demo.add_argument("--quiet", action="store_true", help="no progress bars")
    global_demo.set_defaults(handler=cmd_global_demo)
    demo = commands.add_parser(
        "demo", help="the whole system on simulated worlds, or on a real bag, through the nodes",
        description="Simulates urban, forest and sparse-sensor worlds (two days each, written as "
                    "ROS 2 bags under "
                    "--out and reused), streams day 1 through map_builder and day 2 through the "
                    "localiser over DDS, and prints recall, pose errors, rejection of unseen "
                    "places and latency, with a figure. With --data BAG: map_builder and the "
                    "localiser in loop_closure mode on one replay of a real bag.")
    demo.add_argument("--out", default="out/demo", help="folder for bags, maps and the figure")
    demo.add_argument("--worlds", nargs="+", default=["urban", "forest", "sparse"],
                      choices=["urban", "forest", "sparse"])
    demo.add_argument("--stride", type=int, default=1,
                      help="keep every N-th simulated scan (a quicker demo)")
    demo.add_argument("--data", help="a real bag with PointCloud2 and poses (loop_closure mode)")
    demo.add_argument("--preset", default="auto", help="with --data: a preset, or auto "
                      "(handheld for close-range scans, else kitti)")
    demo.add_argument("--rate", type=float, default=1.0,
                      help="replay speed-up (day 2 of the simulated worlds, or the --data bag)")
    demo.add_argument("--quiet", action="store_true")
    demo.set_defaults(handler=cmd_demo)
