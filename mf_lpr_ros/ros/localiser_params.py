"""The localiser node's parameters: declared, checked against the mode, frozen."""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

from mf_lpr_ros.config import Config
from mf_lpr_ros.live.localiser import LiveMatch, Localiser
from mf_lpr_ros.ros.lidar_node import LidarNodeMixin
from mf_lpr_ros.ros.params import NO_POSES, ParameterFault

LOOP_CLOSURE_FORMATS = ("mf_lpr", "lio_sam")
LIO_SAM_TOPIC = "lio_loop/loop_closure_detection"
PUBLISH_MODES = ("on_request", "continuous")


@dataclass
class LocaliserSettings:
    """The localiser's own node parameters (the shared input ones are in self.inputs)."""

    config: Config
    explicit: dict
    map_path: str
    exclude_recent_s: float
    min_score: float
    diagnostics_period_s: float


class LocaliserParameters(LidarNodeMixin):
    """declare_settings: the localiser's parameters, in the order a managed node reads them."""

    def declare_settings(self) -> None:
        config, explicit = self.declare_config()
        self.mode = self.typed_parameter("mode", "relocalise", "relocalise or loop_closure",
                                         lambda v: v in Localiser.MODES,
                                         f"one of {Localiser.MODES}")
        map_path = self.typed_parameter("map_path", "", "map file (relocalise mode)")
        self.inputs = self.declare_inputs(
            pose_default=NO_POSES, pose_use="the live scans' odometry, needed by loop_closure "
            "mode (to grow the map) and by descriptor.level (roll/pitch)",
            map_frame_use="frame of published poses ('' = the map's)")
        exclude_recent_s = self.typed_parameter(
            "exclude_recent_s", 30.0, "loop_closure: ignore references younger than this",
            lambda v: v >= 0, ">= 0")
        min_score = self.typed_parameter("min_score", 0.0, "accept matches scoring at least this")
        diagnostics_period_s = self.typed_parameter("diagnostics_period_s", 1.0,
                                                    "seconds between diagnostics",
                                                    lambda v: v > 0, "> 0")
        self._declare_outputs()
        self.freeze_parameters()
        self._check_mode()
        self.settings = LocaliserSettings(config, explicit, map_path, exclude_recent_s, min_score,
                                  diagnostics_period_s)
        # Scan arrival to published pose (accepted matches), and to any result.
        self.latencies_ms: deque[float] = deque(maxlen=10_000)
        self.result_latencies_ms: deque[float] = deque(maxlen=10_000)
        self.searched_stamps: deque[float] = deque(maxlen=100_000)
        self.last: LiveMatch | None = None
        self.localiser: Localiser | None = None
        self._inputs: list = []
        self._diagnostics_timer = None
        self._wake = threading.Condition()

    def _declare_outputs(self) -> None:
        """What is published and when: markers, relocalisation requests, loop-closure formats."""
        self.publish_markers = self.typed_parameter("publish_markers", True,
                                                    "publish RViz markers on 'markers'")
        publish_mode = self.typed_parameter(
            "publish_mode", "auto", "on_request: publish relocalisation once per "
            "~/relocalise call (nav2); continuous: for every accepted scan; auto: on_request "
            "in relocalise mode, continuous in loop_closure mode",
            lambda v: v in ("auto", *PUBLISH_MODES), f"one of {('auto', *PUBLISH_MODES)}")
        self.publish_mode = publish_mode if publish_mode != "auto" else \
            "continuous" if self.mode == "loop_closure" else "on_request"
        self.request_timeout_s = self.typed_parameter(
            "request_timeout_s", 10.0, "a ~/relocalise call fails when no scan passes "
            "verification within this many seconds", lambda v: v > 0, "> 0")
        self.loop_closure_formats = set(self.typed_parameter(
            "loop_closure_format", ["mf_lpr"], "loop-closure messages to publish: mf_lpr "
            "(labelled array on 'loop_closure'), lio_sam ([query_s, reference_s] on "
            f"'{LIO_SAM_TOPIC}'); several allowed",
            lambda v: len(v) > 0 and set(v) <= set(LOOP_CLOSURE_FORMATS),
            f"a non-empty list of {LOOP_CLOSURE_FORMATS}"))

    def _check_mode(self) -> None:
        """Parameter combinations the mode cannot work with."""
        if "lio_sam" in self.loop_closure_formats and self.mode != "loop_closure":
            raise ParameterFault("parameter loop_closure_format lio_sam needs mode loop_closure: "
                                 "LIO-SAM maps both stamps to its own keyframes, so the "
                                 "reference must come from the same session")
        if self.mode == "loop_closure" and self.inputs.pose_source == NO_POSES:
            raise ParameterFault("parameter pose_source must name a pose stream in loop_closure "
                                 "mode (the map grows from the robot's posed scans)")
