"""map_builder node: reference scans + poses -> a map file on disk.

    ros2 run mf_lpr_ros map_builder --ros-args --params-file config/default.yaml \\
        -p map_path:=/data/site.mfmap -p pose_source:=odom

Subscribes `points` (PointCloud2) and `odom` (Odometry) or `pose` (PoseStamped /
PoseWithCovarianceStamped); pairs each scan with the pose interpolated at its stamp; keeps one
every spacing_m metres; saves the map atomically every save_period_s and at shutdown. A map
done (the last save, or a rendered grid) whose search reads its spectra on demand gets its
prefilter cache beside it, as build-map writes it.

With global_map_topic set (e.g. `map`, as map servers and LIO stacks publish their cloud:
reliable, transient local), it instead waits for one global point-cloud map on that topic and
writes a grid of references rendered from it (pipeline.global_map), in a worker thread so the
node stays responsive; a later map on the topic rebuilds it.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

from sensor_msgs.msg import PointCloud2

from mf_lpr_ros.core.auto_params import SAMPLE_SCANS
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.search import cache_prefilter
from mf_lpr_ros.errors import InvalidCloudError, InvalidPoseError, MapFileError, ParameterFault
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.node_settings import POSE_SOURCES, MapBuilderSettings
from mf_lpr_ros.live.pose_buffer import PoseBuffer, ScanPoseSynchroniser
from mf_lpr_ros.params import SearchParams
from mf_lpr_ros.ros.lidar_node import LidarNode, run_node
from mf_lpr_ros.ros.qos import latched_qos, sensor_qos

# As map servers publish a map: reliable and transient local, so a map published before this
# node started still arrives.
GLOBAL_MAP_QOS = latched_qos()


class MapBuilderNode(LidarNode):
    settings: MapBuilderSettings

    def __init__(self, node_name: str = "map_builder", **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        config, _ = self.declare_config()
        values = self.declare_node_parameters(MapBuilderSettings.PARAMETERS)
        self.freeze_parameters()
        self.settings = settings = MapBuilderSettings.from_values(config, values)
        path, existing = self._open_output(Path(settings.map_path), settings.if_exists)
        if settings.global_map_topic:
            self._start_global_map_mode(config, path)
            return
        self._start_scan_mode(config, path, existing, settings.keep_clouds)

    def _open_output(self, path: Path, if_exists: str) -> tuple[Path, ReferenceMap | None]:
        """The map to extend (if_exists append) or None; refuses an existing file by default."""
        existing = None
        if path.exists():
            if if_exists == "error":
                raise ParameterFault(f"parameter map_path: {path} exists; set if_exists:=append "
                                     "to extend it or if_exists:=overwrite to replace it")
            if if_exists == "append":
                existing = ReferenceMap.load(path)
        if not os.access(path.parent if str(path.parent) else Path("."), os.W_OK):
            self.get_logger().error(f"the folder of map_path {path} is not writable; the map is "
                                    "kept in memory and saves will be retried")
        return path, existing

    def _start_scan_mode(self, config, path: Path, existing: ReferenceMap | None,
                         keep_clouds: bool) -> None:
        inputs = self.settings.inputs
        self.builder = MapBuilder(config, path, keep_clouds=keep_clouds, reference_map=existing,
                                  sensor_frame_id=inputs.sensor_frame_id,
                                  frame_id=inputs.map_frame_id or "map")
        self._auto_reported = False
        self._single_scan_reported = False
        self.poses = PoseBuffer(max_gap_s=inputs.max_pose_gap_s)
        self.synchroniser = ScanPoseSynchroniser(self.poses, inputs.extrinsic)
        self._next_index = int(self.builder.map.source_indices.max()) + 1 \
            if len(self.builder.map) else 0
        self.subscribe_poses(inputs.pose_source, self.poses, self._pair, inputs.reliable)
        self.create_subscription(PointCloud2, "points", self._on_scan,
                                 sensor_qos(50, inputs.reliable))
        self.create_timer(self.settings.save_period_s, self._periodic_save)
        extent = f"appending to {len(existing)} references" if existing else "new map"
        self.get_logger().info(
            f"building {path} ({extent}): voxel {self._voxel_text()}, spacing "
            f"{config.spacing_m} m, poses from '{POSE_SOURCES[inputs.pose_source][0]}'")

    def _start_global_map_mode(self, config, path: Path) -> None:
        self.builder = None
        self._global_config, self._global_path = config, path
        self._global_worker: threading.Thread | None = None
        self.global_maps_built = 0
        topic = self.settings.global_map_topic
        self.create_subscription(PointCloud2, topic, self._on_global_map, GLOBAL_MAP_QOS)
        self.get_logger().info(
            f"waiting for a global map on '{topic}' to render {path} (spacing "
            f"{config.spacing_m} m, sensor {self.settings.sensor_height_m} m above the ground)")

    def _on_global_map(self, message: PointCloud2) -> None:
        from mf_lpr_ros.io.pointcloud import decode_points

        if self._global_worker is not None and self._global_worker.is_alive():
            self.log_problem("global_map", "a global map arrived while the last one is still "
                             "being rendered; it is ignored")
            return
        try:
            points = decode_points(message, max_points=500_000_000)
        except (InvalidCloudError, ValueError, TypeError) as error:
            self.counters["global_maps_rejected"] += 1
            self.log_problem("global_map", f"global map rejected: {error}")
            return
        frame = message.header.frame_id or self.settings.inputs.map_frame_id or "map"
        self._global_worker = threading.Thread(target=self._render_global_map,
                                               args=(points, frame), daemon=True)
        self._global_worker.start()

    def _render_global_map(self, points, frame: str) -> None:
        from mf_lpr_ros.pipeline.global_map import RenderParams, build_global_map

        render = RenderParams(spacing_m=self._global_config.spacing_m,
                              sensor_height_m=self.settings.sensor_height_m)
        try:
            reference_map = build_global_map(f"topic {self.settings.global_map_topic}",
                                             self._global_config, points=points, render=render,
                                             progress=False, workers=1,
                                             keep_clouds=self.settings.keep_clouds)
            reference_map.frame_id = self.settings.inputs.map_frame_id or frame
            reference_map.save(self._global_path)
        except (InvalidCloudError, ValueError, OSError, MapFileError) as error:
            self.counters["global_maps_rejected"] += 1
            self.get_logger().error(f"global map not rendered: {error}")
            return
        self.get_logger().info(
            f"rendered {len(reference_map)} references from a {len(points)}-point global map "
            f"to {self._global_path}")
        self._cache_prefilter(self._global_path, self._global_config.search, len(reference_map))
        self.global_maps_built += 1

    def _cache_prefilter(self, path: Path, search: SearchParams, n_references: int) -> None:
        """The prefilter's features written beside a map whose search reads its spectra on
        demand, as build-map writes them: the localiser's first start then loads them
        instead of computing them (a 1 km^2 grid: ~27 s). Only when the map is done (a
        periodic save would compute them again every save_period_s)."""
        try:
            status = cache_prefilter(path, search, n_references)
        except (OSError, MapFileError) as error:
            self.get_logger().error(f"prefilter features of {path} not cached ({error}); the "
                                    "localiser's first start computes them")
            return
        if status is not None:
            self.get_logger().info(f"prefilter features of {path}: {status}")

    def _on_scan(self, message: PointCloud2) -> None:
        decoded = self.decode_scan(message)
        if decoded is None:
            return
        if not self.builder.map.sensor_frame_id:
            self.builder.map.sensor_frame_id = message.header.frame_id
        stamp, points = decoded
        self.synchroniser.add_scan(self._next_index, stamp, points)
        self._next_index += 1
        self._pair()

    def reject_scan(self, stamp: float, problem: str) -> None:
        super().reject_scan(stamp, problem)
        if self.builder is not None:
            # Scans are numbered as they arrive, the rejected ones too.
            self.builder.pass_over(self._next_index, stamp, problem)
            self._next_index += 1

    def _pair(self, final: bool = False) -> None:
        if not self.settings.inputs.map_frame_id and self.pose_frame_id:
            self.builder.map.frame_id = self.pose_frame_id
        for scan in self.synchroniser.ready(final=final):
            try:
                added = self.builder.offer(scan)
            except (InvalidCloudError, InvalidPoseError, ValueError) as error:
                self.counters["scans_rejected"] += 1
                self.log_problem("describe", f"scan at {scan.stamp:.3f} not used: {error}")
                continue
            self._report_auto()
            if added is not None:
                self.counters["references"] = len(self.builder.map)
                self.get_logger().debug(f"reference {added} at stamp {scan.stamp:.3f}")
        self.counters["scans_without_pose"] = self.synchroniser.dropped_without_pose

    def _voxel_text(self) -> str:
        if self.builder.waiting_for_auto:
            return f"from preset auto (derived from the first {SAMPLE_SCANS} scans)"
        descriptor = self.builder.config.descriptor
        window = f", each reference from the scans of its last {descriptor.submap_m} m" \
            if descriptor.submap_m > 0 else ""
        return f"{descriptor.voxel_size} m{window}"

    def _report_auto(self) -> None:
        if self.builder.single_scan_warning is not None and not self._single_scan_reported:
            self._single_scan_reported = True
            self.get_logger().warning(self.builder.single_scan_warning)
        if self.builder.auto_choice is not None and not self._auto_reported:
            self._auto_reported = True
            self.get_logger().info(self.builder.auto_choice)
            if self.builder.rejected_while_held:
                self.counters["scans_rejected"] += self.builder.rejected_while_held

    def _periodic_save(self) -> None:
        if self.builder.needs_save:
            self.save()

    def save(self) -> bool:
        try:
            count = self.builder.save()
        except (OSError, MapFileError) as error:
            self.counters["save_failures"] += 1
            self.get_logger().error(
                f"could not save the map to {self.builder.map_path}: {error}; the "
                f"{len(self.builder.map)} references stay in memory and the save is retried")
            return False
        self.counters["saves"] += 1
        self.get_logger().info(f"saved {count} references to {self.builder.map_path}")
        return True

    def finish(self) -> None:
        if self.builder is None:
            if self._global_worker is not None:
                self._global_worker.join()
            return
        self._pair(final=True)
        if self.builder.waiting_for_auto:
            try:
                self.builder.derive_auto()
            except InvalidCloudError as error:
                self.get_logger().error(f"preset auto: {error}; no map written")
                return
            self._report_auto()
        if self.builder.needs_save or not self.builder.map_path.exists():
            self.save()
        if not self.builder.needs_save and self.builder.map_path.exists():
            self._cache_prefilter(self.builder.map_path, self.builder.config.search,
                                  len(self.builder.map))
        dropped = self.synchroniser.dropped_without_pose
        self.get_logger().info(
            f"map_builder done: {self.counters['scans_received']} scans, "
            f"{len(self.builder.map)} references, {dropped} scans without a pose, "
            f"{self.counters['scans_rejected']} rejected")


def main(args: list[str] | None = None) -> int:
    return run_node(MapBuilderNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
