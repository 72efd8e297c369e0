"""localiser node: live scans -> relocalisation poses and loop closures.

    ros2 run mf_lpr_ros localiser --ros-args -p map_path:=/data/site.mfmap \\
        -r relocalisation:=/initialpose            # nav2 AMCL, on request:
    ros2 service call /localiser/relocalise std_srvs/srv/Trigger
    ros2 run mf_lpr_ros localiser --ros-args -p mode:=loop_closure -p pose_source:=odom
    ros2 run mf_lpr_ros localiser --ros-args -p mode:=loop_closure -p pose_source:=odom \\
        -p loop_closure_format:="[lio_sam]"                  # LIO-SAM's external closures

Only the newest scan is searched: a scan arriving while the search is busy replaces the waiting
one (counted as dropped), so a slow search never builds a backlog.

publish_mode on_request (the default in relocalise mode): `relocalisation` is published once
per call of the ~/relocalise Trigger service, with the first scan after the call whose match
passes verification, and the pose is returned in the reply (with a submap window: the first such
scan whose window is complete, or at request_timeout_s the best partial one; the reply's
described_from says which; at request_timeout_s, too, a match that lacked only odometry
support, which a robot standing still never gathers, the reply's verification saying so);
continuous (the default in
loop_closure mode): every accepted scan. Loop closures are published for every accepted scan
in either mode, and for an earlier scan when later matches confirm its match (odometry
consistency is symmetric: core/verification.py), with that scan's stamp.
"""

from __future__ import annotations

import json
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.auto_params import map_built_warning
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.errors import (
    InvalidCloudError,
    InvalidPoseError,
    MapParameterMismatch,
    ParameterFault,
)
from mf_lpr_ros.live.localiser import LiveMatch, Localiser, relative_transform, relocalised_pose
from mf_lpr_ros.live.node_settings import LIO_SAM_TOPIC, LocaliserSettings
from mf_lpr_ros.live.pose_buffer import PoseBuffer, ScanPoseSynchroniser
from mf_lpr_ros.ros.lidar_node import LidarNodeMixin, run_node
from mf_lpr_ros.ros.messages import (
    candidates_message,
    confidences_message,
    diagnostics_message,
    lio_sam_loop_message,
    loop_closure_message,
    match_markers,
    relocalisation_message,
    seconds_to_stamp,
)
from mf_lpr_ros.ros.qos import latched_qos, sensor_qos

_HEADER_STAMPS_KEPT = 2000
# Reliable (AMCL's /initialpose subscription) and transient local: a late subscriber still gets
# the last pose.
LATCHED_POSE_QOS = latched_qos()


@dataclass
class _PendingScan:
    stamp: Time
    seconds: float
    points: np.ndarray
    pose: np.ndarray | None
    received: float


@dataclass
class _Request:
    """A relocalisation request: answered by the first scan received after `asked` (whose
    submap window is complete). partial keeps the answer given at the timeout: the last
    verified one from an incomplete window (partial_verified), else the last match that lacked
    only odometry support."""

    asked: float
    answer: Future = field(default_factory=Future)
    partial: tuple | None = None
    partial_verified: bool = False


class LocaliserLogic(LidarNodeMixin):
    """The localiser on any rclpy node class. Its life cycle, in the order a managed node goes
    through it: read_settings (parameters; a bad one stops start-up), configure (the map,
    the search, publishers, the service, the search thread), activate (subscriptions,
    diagnostics), deactivate (they stop), cleanup (everything configure made is freed)."""

    settings: LocaliserSettings

    def read_settings(self) -> None:
        """Declare every parameter (mf_lpr_ros/live/node_settings.py), read them into
        self.settings (a bad value or combination raises ParameterFault) and freeze them."""
        config, explicit = self.declare_config()
        values = self.declare_node_parameters(LocaliserSettings.PARAMETERS)
        self.freeze_parameters()
        self.settings = LocaliserSettings.from_values(config, explicit, values)
        # Scan arrival to published pose (accepted matches), and to any result.
        self.latencies_ms: deque[float] = deque(maxlen=10_000)
        self.result_latencies_ms: deque[float] = deque(maxlen=10_000)
        self.searched_stamps: deque[float] = deque(maxlen=100_000)
        self.last: LiveMatch | None = None
        self.localiser: Localiser | None = None
        self._inputs: list = []
        self._diagnostics_timer = None
        self._wake = threading.Condition()
        # Header stamps of searched scans, to publish a closure confirmed later exactly.
        self._header_stamps: OrderedDict[float, Time] = OrderedDict()

    def configure(self, create_publisher) -> None:
        """Load the map and build the search; create_publisher is the node's publisher factory
        (create_lifecycle_publisher on a managed node). Only the checks that need the map are
        made here."""
        settings = self.settings
        inputs = settings.inputs
        reference_map = self._open_map()
        if "auto" in reference_map.metadata:
            self.get_logger().info(f"map built with {reference_map.metadata['auto']['choice']}")
        warning = map_built_warning(reference_map.metadata)
        if warning is not None:
            self.get_logger().warning(warning)
        config = Config(reference_map.params, settings.config.search, settings.config.spacing_m)
        try:
            self.localiser = Localiser(reference_map, config, mode=settings.mode,
                                       exclude_recent_s=settings.exclude_recent_s,
                                       min_score=settings.min_score,
                                       odometry_known=inputs.has_poses)
        except ValueError as error:
            raise ParameterFault(str(error)) from None
        self.map_frame_id = inputs.map_frame_id or reference_map.frame_id or "map"
        self.synchroniser = None
        if inputs.has_poses:
            self.poses = PoseBuffer(max_gap_s=inputs.max_pose_gap_s)
            self.synchroniser = ScanPoseSynchroniser(self.poses, inputs.extrinsic)
        self._publishers = []

        def publisher(message_type, topic, qos):
            created = create_publisher(message_type, topic, qos)
            self._publishers.append(created)
            return created

        self.relocalisation_pub = publisher(PoseWithCovarianceStamped, "relocalisation",
                                            LATCHED_POSE_QOS)
        self.candidates_pub = publisher(PoseArray, "~/candidates", 10)
        self.confidences_pub = publisher(Float64MultiArray, "~/candidate_confidences", 10)
        self.loop_closure_pub = publisher(Float64MultiArray, "loop_closure", 100) \
            if "mf_lpr" in settings.loop_closure_formats else None
        # Reliable and keep-last: compatible with LIO-SAM's best-effort depth-1 subscriber and
        # with the reliable ones of its forks.
        self.lio_sam_pub = publisher(Float64MultiArray, LIO_SAM_TOPIC, 10) \
            if "lio_sam" in settings.loop_closure_formats else None
        self.markers_pub = publisher(MarkerArray, "markers", 10)
        self.diagnostics_pub = publisher(DiagnosticArray, "diagnostics", 10)
        self._requests: list[_Request] = []
        # A group of its own: while a request awaits its scan, the executor keeps running the
        # scan callbacks (the default group would be held by the awaiting handler).
        self._service = self.create_service(Trigger, "~/relocalise", self._on_relocalise,
                                            callback_group=MutuallyExclusiveCallbackGroup())
        self._scan_index = 0
        self._slot: _PendingScan | None = None
        self._stopping = False
        self._busy = False
        self._worker = threading.Thread(target=self._work, name="mf_lpr_search", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"{settings.mode}: {self.localiser.reference_count} references, voxel "
            f"{config.descriptor.voxel_size} m, publishing in frame '{self.map_frame_id}', "
            f"loop closures as {sorted(settings.loop_closure_formats)}")
        if self.localiser.index.spectra_on_demand:
            self.get_logger().info(
                "reference spectra computed on demand for each query's candidates; prefilter "
                f"features: {self.localiser.index.prefilter_cache_status}")
        if self.localiser.submap is not None:
            window = self.localiser.submap.window
            if not inputs.has_poses:
                self.get_logger().warning(
                    f"the map was built with submaps (descriptor.submap_m = {window.window_m} m)"
                    " but no pose_source gives odometry: scans are described alone, and recall"
                    " will be lower; set pose_source")
            else:
                self.get_logger().info(
                    f"describing each scan with the scans of its last {window.window_m} m of "
                    f"travel (at most {window.max_scans} scans, {window.max_age_s} s)")
        if config.descriptor.level and not inputs.has_poses:
            self.get_logger().warning(
                "the map levels its scans (descriptor.level) but no pose_source gives their roll"
                " and pitch: scans are described as the sensor holds them, and a tilted sensor"
                " will match less well; set pose_source")
        if config.search.consistency_min_support > 0 and \
                not self.localiser.verifier.consistency_active:
            self.get_logger().warning(
                "odometry consistency is off: no pose_source gives the scans' odometry, so "
                "matches are verified by confidence, distinctiveness and ICP only")

    def activate(self) -> None:
        """Subscribe to the scans (and poses) and start the diagnostics."""
        settings = self.settings
        inputs = settings.inputs
        if self.synchroniser is not None:
            self._inputs.append(self.subscribe_poses(inputs.pose_source, self.poses,
                                                     self._pair, inputs.reliable))
        self._inputs.append(self.create_subscription(PointCloud2, "points", self._on_scan,
                                                     sensor_qos(5, inputs.reliable)))
        self._diagnostics_timer = self.create_timer(settings.diagnostics_period_s,
                                                    self._publish_diagnostics)

    def deactivate(self) -> None:
        """Stop listening; the map and the search stay."""
        for subscription in self._inputs:
            self.destroy_subscription(subscription)
        self._inputs = []
        if self._diagnostics_timer is not None:
            self.destroy_timer(self._diagnostics_timer)
            self._diagnostics_timer = None

    def cleanup(self) -> None:
        """Stop the search thread, answer waiting requests with a failure, free the map."""
        if self.localiser is None:
            return
        self.deactivate()
        with self._wake:
            self._stopping = True
            self._wake.notify()
            unanswered, self._requests = self._requests, []
        for request in unanswered:
            request.answer.set_result(None)
        self._worker.join(timeout=10.0)
        self.destroy_service(self._service)
        for created in self._publishers:
            self.destroy_publisher(created)
        self._publishers = []
        self.localiser = None

    def _open_map(self) -> ReferenceMap:
        settings = self.settings
        config, map_path = settings.config, settings.map_path
        if settings.mode == "loop_closure":
            return ReferenceMap(config.descriptor, frame_id="")
        reference_map = ReferenceMap.load(map_path)
        if any(name.startswith("descriptor.") for name in settings.explicit):
            try:
                reference_map.check_params(config.descriptor)
            except MapParameterMismatch as error:
                raise ParameterFault(f"map {map_path}: {error}") from None
        return reference_map

    # --- input (executor thread) -----------------------------------------------------------
    def _on_scan(self, message: PointCloud2) -> None:
        received = time.perf_counter()
        decoded = self.decode_scan(message)
        if decoded is None:
            return
        seconds, points = decoded
        if self.synchroniser is None:
            self._offer(_PendingScan(message.header.stamp, seconds, points, None, received))
            return
        self.synchroniser.add_scan(self._scan_index, seconds, points,
                                   (message.header.stamp, received))
        self._scan_index += 1
        self._pair()

    def _pair(self, final: bool = False) -> None:
        if self.synchroniser is None:
            return
        if not self.localiser.map.frame_id and self.pose_frame_id:
            self.localiser.map.frame_id = self.pose_frame_id
            self.map_frame_id = self.pose_frame_id
        for paired in self.synchroniser.ready(final=final):
            stamp, received = paired.extra
            self.localiser.observe(paired.stamp, paired.points, paired.pose)
            if self.settings.mode == "loop_closure":
                self.localiser.add_reference(paired)
            self._offer(_PendingScan(stamp, paired.stamp, paired.points, paired.pose, received))
        self.counters["scans_without_pose"] = self.synchroniser.dropped_without_pose

    def is_idle(self) -> bool:
        """No scan waiting for its pose, for the search, or being searched."""
        if self.localiser is None:
            return True
        with self._wake:
            waiting = self.synchroniser.pending if self.synchroniser is not None else 0
            return self._slot is None and not self._busy and waiting == 0

    def _offer(self, scan: _PendingScan) -> None:
        with self._wake:
            if self._slot is not None:
                self.counters["scans_dropped"] += 1
            self._slot = scan
            self._wake.notify()

    # --- search (worker thread) -------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self._wake:
                while self._slot is None and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                scan, self._slot = self._slot, None
                self._busy = True
            try:
                self._localise(scan)
            except (InvalidCloudError, InvalidPoseError, ValueError) as error:
                self.counters["scans_rejected"] += 1
                self.log_problem("search", f"scan at {scan.seconds:.3f} not localised: {error}")
            except Exception as error:  # never let one scan stop the worker
                self.counters["search_errors"] += 1
                self.get_logger().error(f"search failed on scan at {scan.seconds:.3f}: "
                                        f"{type(error).__name__}: {error}")
            finally:
                with self._wake:
                    self._busy = False

    def _localise(self, scan: _PendingScan) -> None:
        with self._wake:
            requested = any(r.asked <= scan.received for r in self._requests)
        result = self.localiser.localise(scan.seconds, scan.points, scan.pose,
                                         request=requested)
        self.last = result
        self.counters["scans_searched"] += 1
        self.searched_stamps.append(scan.seconds)
        self._header_stamps[scan.seconds] = scan.stamp
        while len(self._header_stamps) > _HEADER_STAMPS_KEPT:
            self._header_stamps.popitem(last=False)
        self.result_latencies_ms.append((time.perf_counter() - scan.received) * 1e3)
        for earlier in result.confirms:
            self._publish_closure(self._header_stamps.get(earlier.stamp) or
                                  seconds_to_stamp(earlier.stamp), earlier)
            self.counters["closures_confirmed_later"] += 1
        if result.match is None:
            return
        match = result.match
        if not result.accepted:
            self.counters["matches_rejected"] += 1
            self.get_logger().debug(f"match rejected at {scan.seconds:.3f}: {result.reason}")
            if result.support >= 0:
                self._keep_unsupported(scan, result)
            return
        reference_pose, world_T_base, answer = self._located(scan, result)
        with self._wake:
            asked = [r for r in self._requests if r.asked <= scan.received]
            answering = asked if result.window_complete else []
            self._requests = [r for r in self._requests if r not in answering]
            for request in asked:
                request.partial = (scan, match, world_T_base, answer)
                request.partial_verified = True
        if self.settings.publish_mode == "continuous" or answering:
            self._publish_pose(scan, match, world_T_base)
        for request in answering:
            request.answer.set_result(answer)
        self._publish_closure(scan.stamp, result)
        if self.settings.publish_markers:
            self.markers_pub.publish(match_markers(scan.stamp, self.map_frame_id, world_T_base,
                                                   reference_pose, True))
        self.counters["matches_accepted"] += 1
        self.latencies_ms.append((time.perf_counter() - scan.received) * 1e3)

    def _publish_closure(self, stamp: Time, result: LiveMatch) -> None:
        """The loop closure of an accepted match, in every format asked for."""
        self.counters["closures_published"] += 1
        match = result.match
        if self.loop_closure_pub is not None:
            self.loop_closure_pub.publish(loop_closure_message(
                stamp, match.reference_index, result.reference_stamp,
                relative_transform(match), match.relative_covariance, match.score,
                match.confidence))
        if self.lio_sam_pub is not None:
            self.lio_sam_pub.publish(lio_sam_loop_message(stamp, result.reference_stamp))

    def _publish_pose(self, scan: _PendingScan, match, world_T_base: np.ndarray) -> None:
        """relocalisation, then the ranked hypotheses and their confidences."""
        self.relocalisation_pub.publish(relocalisation_message(
            scan.stamp, self.map_frame_id, world_T_base, match.covariance))
        hypotheses = [relocalised_pose(h, self.localiser.reference_pose(h.reference_index),
                                       self.settings.inputs.extrinsic)
                      for h in match.hypotheses]
        self.candidates_pub.publish(candidates_message(scan.stamp, self.map_frame_id,
                                                       hypotheses))
        self.confidences_pub.publish(confidences_message(
            [h.confidence for h in match.hypotheses]))
        self.counters["poses_published"] += 1

    def _keep_unsupported(self, scan: _PendingScan, result) -> None:
        """A match that passed every test but odometry consistency (too few earlier matches
        agree): the answer at the timeout of the requests waiting for this scan, unless a
        verified one comes. A robot standing still never gathers support (its matches must be
        consistency_min_support queries a metre apart), and a lost robot often stands still
        when it asks."""
        with self._wake:
            asked = [r for r in self._requests
                     if r.asked <= scan.received and not r.partial_verified]
        if not asked:
            return
        _, world_T_base, answer = self._located(scan, result)
        with self._wake:
            for request in asked:
                request.partial = (scan, result.match, world_T_base, answer)

    def _located(self, scan: _PendingScan, result) -> tuple[np.ndarray, np.ndarray, str]:
        """The matched reference's pose, the robot's pose in the map it implies, and the reply
        a request would get from this scan."""
        reference_pose = self.localiser.reference_pose(result.match.reference_index)
        world_T_base = relocalised_pose(result.match, reference_pose,
                                        self.settings.inputs.extrinsic)
        return reference_pose, world_T_base, self._answer(scan, result, world_T_base)

    def _answer(self, scan: _PendingScan, result, world_T_base: np.ndarray) -> str:
        """The Trigger reply's message: the published pose as JSON, what the scan was
        described from (a single scan, or a complete or partial submap), and its verification
        (the verifier's verdict: "accepted", or why it was not, for an answer given at the
        timeout from a match that no later one confirmed)."""
        x, y = (float(v) for v in world_T_base[:2, 3])
        yaw = float(np.arctan2(world_T_base[1, 0], world_T_base[0, 0]))
        match = result.match
        return json.dumps({"frame_id": self.map_frame_id, "stamp": scan.seconds, "x": x, "y": y,
                           "yaw": yaw, "confidence": match.confidence,
                           "covariance_xy_yaw": match.covariance.ravel().tolist(),
                           "described_from": result.described_from,
                           "verification": result.reason})

    async def _on_relocalise(self, request: Trigger.Request, response: Trigger.Response
                             ) -> Trigger.Response:
        """Wait (without blocking the executor) for the next scan that passes verification."""
        pending = _Request(time.perf_counter())
        with self._wake:
            self._requests.append(pending)
        self.counters["requests"] += 1
        timeout_s = self.settings.request_timeout_s
        timer = self.create_timer(timeout_s, lambda: self._expire(pending))
        answer = await pending.answer
        self.destroy_timer(timer)
        response.success = answer is not None
        response.message = answer if answer is not None else (
            f"no scan passed verification within request_timeout_s = {timeout_s} s"
            f" (last result: {self.last.reason if self.last else 'no scan searched'})")
        if answer is None:
            self.counters["requests_timed_out"] += 1
        return response

    def _expire(self, pending: _Request) -> None:
        """At the timeout: the last verified answer from an incomplete window, else failure."""
        with self._wake:
            if pending not in self._requests:
                return
            self._requests.remove(pending)
        if pending.partial is None:
            pending.answer.set_result(None)
            return
        scan, match, world_T_base, answer = pending.partial
        self._publish_pose(scan, match, world_T_base)
        pending.answer.set_result(answer)

    def _publish_diagnostics(self) -> None:
        localiser = self.localiser
        if localiser is None:
            # A tick already due when cleanup freed the search (the executor runs it after the
            # timer is destroyed): nothing is left to report.
            return
        counters = dict(self.counters)
        if self.latencies_ms:
            counters["latency_median_ms"] = round(float(np.median(self.latencies_ms)), 2)
        counters["references"] = localiser.reference_count
        counters["references_rejected"] = localiser.rejected_references
        warn = "; ".join(text for text in (
            "scans dropped: search slower than the sensor" if self.counters["scans_dropped"]
            else "",
            localiser.last_reference_error) if text)
        self.diagnostics_pub.publish(diagnostics_message(
            self.get_clock().now().to_msg(), self.get_name(), counters, self.last, warn))

    def finish(self) -> None:
        if self.localiser is not None:
            self.cleanup()
        self.get_logger().info(
            f"localiser done: {self.counters['scans_received']} scans, "
            f"{self.counters['scans_searched']} searched, {self.counters['scans_dropped']} "
            f"dropped, {self.counters['matches_accepted']} accepted")


class LocaliserNode(LocaliserLogic, Node):
    """The plain localiser: configured and active from construction."""

    def __init__(self, node_name: str = "localiser", **kwargs) -> None:
        Node.__init__(self, node_name, **kwargs)
        self.init_lidar_state()
        self.read_settings()
        self.configure(self.create_publisher)
        self.activate()


def main(args: list[str] | None = None) -> int:
    return run_node(LocaliserNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
