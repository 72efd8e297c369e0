"""Commands that make and inspect maps: build-map, accumulate, info."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mf_lpr_ros.cli.common import (
    SOURCE_HELP,
    add_common,
    add_scheduler,
    cluster,
    config_from_arguments,
)
from mf_lpr_ros.config import Config
from mf_lpr_ros.core.auto_params import SINGLE_SCAN_WARNING_KEY
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.references import passed_over_summary
from mf_lpr_ros.core.search import cache_prefilter
from mf_lpr_ros.datasets import open_source


def cmd_build_map(args: argparse.Namespace) -> int:
    from mf_lpr_ros.pipeline.mapping import build_map

    config = config_from_arguments(args)
    if args.global_map:
        return _build_global_map(args, config)
    if args.sources:
        return _build_maps(args, config)
    if not args.source:
        raise ValueError("build-map needs a SOURCE (scans with poses), --sources A B ... or "
                         "--global-map CLOUD")
    sequence = open_source(args.source, args.cloud_topic, args.pose_topic)
    reference_map = build_map(sequence, config, keep_clouds=args.keep_clouds,
                              progress=not args.quiet)
    _save(reference_map, args.out, config)
    if "auto" in reference_map.metadata:
        print(reference_map.metadata["auto"]["choice"])
    if SINGLE_SCAN_WARNING_KEY in reference_map.metadata:
        print(f"warning: {reference_map.metadata[SINGLE_SCAN_WARNING_KEY]}", file=sys.stderr)
    _warn_passed_over(reference_map)
    print(f"wrote {args.out}: {len(reference_map)} references from {len(sequence)} scans "
          f"(voxel {reference_map.params.voxel_size} m, spacing {config.spacing_m} m)")
    return 0


def _build_maps(args: argparse.Namespace, config: Config) -> int:
    from mf_lpr_ros.pipeline.bulk import SourceSpec, build_maps

    if args.source:
        raise ValueError("give the sources either as SOURCE or as --sources, not both")
    specs = [SourceSpec(path, args.cloud_topic, args.pose_topic) for path in args.sources]
    with cluster(args) as client:
        maps = build_maps(specs, config, combine=not args.one_map_each,
                          keep_clouds=args.keep_clouds, client=client, progress=not args.quiet)
    if args.one_map_each:
        out_dir = Path(args.out)
        out_dir.mkdir(parents=True, exist_ok=True)
        for spec, reference_map in zip(specs, maps):
            path = out_dir / f"{Path(spec.path).name}.mfmap"
            _save(reference_map, path, config)
            _warn_passed_over(reference_map)
            print(f"wrote {path}: {len(reference_map)} references")
    else:
        _save(maps[0], args.out, config)
        _warn_passed_over(maps[0])
        print(f"wrote {args.out}: {len(maps[0])} references from {len(specs)} sources")
    return 0


def _save(reference_map: ReferenceMap, path: str | Path, config: Config) -> None:
    """Save the map, and beside it the prefilter's features when its search reads them from
    the cache (a map above search.reference_spectra's threshold): the first localiser to
    start on it then loads them as a restart does, instead of computing them."""
    reference_map.save(path)
    status = cache_prefilter(Path(path), config.search, len(reference_map))
    if status is not None:
        print(f"prefilter features of {path}: {status}")


def _warn_passed_over(reference_map: ReferenceMap) -> None:
    summary = passed_over_summary(reference_map.metadata)
    if summary is not None:
        print(f"warning: {summary}", file=sys.stderr)


def _build_global_map(args: argparse.Namespace, config: Config) -> int:
    from mf_lpr_ros.pipeline.global_cloud import read_trajectory
    from mf_lpr_ros.pipeline.global_map import RenderParams, build_global_map

    trajectory = read_trajectory(args.trajectory) if args.trajectory else None
    render = RenderParams(spacing_m=args.spacing_m or RenderParams.spacing_m,
                          sensor_height_m=args.sensor_height_m,
                          horizontal_fov_deg=args.horizontal_fov_deg,
                          reach_m=args.reach_m)
    with cluster(args) as client:
        reference_map = build_global_map(args.global_map, config, trajectory=trajectory,
                                         render=render, progress=not args.quiet,
                                         workers=args.workers, client=client,
                                         tiles_folder=args.tiles_dir,
                                         keep_clouds=args.keep_clouds)
    _save(reference_map, args.out, config)
    area = reference_map.metadata["grid_area_km2"]
    print(f"wrote {args.out}: {len(reference_map)} references rendered from {args.global_map} "
          f"on a {render.spacing_m} m grid over {area:.4f} km^2 (sensor "
          f"{reference_map.metadata['sensor_height_m']:.2f} m above the ground, voxel "
          f"{reference_map.params.voxel_size} m)")
    return 0


def cmd_accumulate(args: argparse.Namespace) -> int:
    from mf_lpr_ros.pipeline.global_cloud import accumulate, write_pcd

    sequence = open_source(args.source, args.cloud_topic, args.pose_topic)
    cloud = accumulate(sequence, args.voxel, progress=not args.quiet)
    write_pcd(args.out, cloud)
    print(f"wrote {args.out}: {len(cloud)} points from {len(sequence)} scans "
          f"(one per {args.voxel} m voxel)")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    reference_map = ReferenceMap.load(args.map)
    poses = reference_map.planar_poses
    print(json.dumps({
        "references": len(reference_map),
        "descriptor": reference_map.params.__dict__,
        "frame_id": reference_map.frame_id,
        "sensor_frame_id": reference_map.sensor_frame_id,
        "keeps_clouds": reference_map.has_clouds,
        "site_cloud_points": (None if reference_map.site_cloud is None
                              else len(reference_map.site_cloud.points)),
        "extent_xy_m": (poses[:, :2].min(0).tolist(), poses[:, :2].max(0).tolist())
        if len(poses) else None,
        "metadata": reference_map.metadata,
    }, indent=2))
    return 0


def register(commands: argparse._SubParsersAction) -> None:
    build = commands.add_parser(
        "build-map", help="build a reference map from a sequence or bag, or render one from a "
        "global point-cloud map (--global-map)")
    build.add_argument("source", nargs="?", help=SOURCE_HELP)
    build.add_argument("--sources", nargs="+", help="many sources: one map of them all at "
                       "--out, or one map each in the folder --out with --one-map-each")
    build.add_argument("--one-map-each", action="store_true",
                       help="with --sources: --out is a folder, one SOURCE_NAME.mfmap per source")
    add_scheduler(build)
    build.add_argument("--global-map", help="a global map (.pcd/.ply, world frame, z up): "
                       "references rendered on a grid over its traversable area")
    build.add_argument("--trajectory", help="with --global-map: the mapping run's poses (KITTI "
                       "poses.txt or TUM), seeding the area and giving the sensor height")
    build.add_argument("--sensor-height-m", type=float,
                       help="with --global-map: the sensor's height above the ground "
                            "(default: from --trajectory, else 1.8)")
    build.add_argument("--horizontal-fov-deg", type=float, default=360.0,
                       help="with --global-map: the sensor's horizontal field of view; below "
                            "360 (e.g. 70 for a Livox Avia) references face several headings, "
                            "each with only its wedge")
    build.add_argument("--reach-m", type=float,
                       help="with --global-map: render a position only when structure lies "
                            "within this distance (default: the descriptor's half width; inf: "
                            "no limit), so open fields do not become references")
    build.add_argument("--tiles-dir",
                       help="with --global-map: folder for the tiled cloud the renderers read "
                            "(default: a temporary one); with --scheduler ADDRESS, one every "
                            "worker sees at the same path")
    build.add_argument("--out", required=True, help="map file to write (atomically)")
    build.add_argument("--spacing-m", type=float, help="distance between references (default 2.0)")
    build.add_argument("--keep-clouds", action="store_true",
                       help="store reference clouds in the map (enables ICP refinement); with "
                            "--global-map, the map keeps the global cloud once and cuts "
                            "each reference's cloud from it")
    add_common(build)
    build.set_defaults(handler=cmd_build_map)
    accumulate = commands.add_parser(
        "accumulate", help="a global map (binary PCD) from a posed sequence or bag")
    accumulate.add_argument("source", help=SOURCE_HELP)
    accumulate.add_argument("--out", required=True, help="PCD file to write (atomically)")
    accumulate.add_argument("--voxel", type=float, default=0.2,
                            help="keep one point per voxel of this size, m (default 0.2)")
    accumulate.add_argument("--cloud-topic", help="PointCloud2 topic of a bag")
    accumulate.add_argument("--pose-topic", help="Odometry/PoseStamped topic of a bag")
    accumulate.add_argument("--quiet", action="store_true", help="no progress bars")
    accumulate.set_defaults(handler=cmd_accumulate)
    info = commands.add_parser("info", help="describe a map file")
    info.add_argument("map")
    info.set_defaults(handler=cmd_info)
