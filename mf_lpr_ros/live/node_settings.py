"""Every ROS node parameter that is not a method parameter (those are descriptor.*, search.* and
spacing_m: mf_lpr_ros/params.py and mf_lpr_ros/config.py): its name, default, meaning and check,
and the frozen settings each node reads them into, with every check of their combinations.

ROS-free: mf_lpr_ros/ros/params.py declares these parameters on a node and hands their values
to the node's settings class; docs/PARAMETERS.md is generated from them (mf-lpr docs --write
docs). Checks that need the map (its descriptor) stay in the localiser's configure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.pose import check_quaternion, pose_matrix
from mf_lpr_ros.errors import InvalidPoseError, ParameterFault
from mf_lpr_ros.live.localiser import Localiser

# pose_source value -> (topic, message type name).
POSE_SOURCES = {"odom": ("odom", "nav_msgs/Odometry"),
                "pose": ("pose", "geometry_msgs/PoseStamped"),
                "pose_with_covariance": ("pose", "geometry_msgs/PoseWithCovarianceStamped")}
NO_POSES = "none"
LOOP_CLOSURE_FORMATS = ("mf_lpr", "lio_sam")
LIO_SAM_TOPIC = "lio_loop/loop_closure_detection"
PUBLISH_MODES = ("on_request", "continuous")
IF_EXISTS = ("error", "append", "overwrite")


@dataclass(frozen=True)
class NodeParameter:
    """One node parameter: declared with this default and description, refused (naming it and
    what it must be) when `allowed` says no."""

    name: str
    default: Any
    description: str
    allowed: Callable[[Any], bool] | None = None
    expectation: str = ""

    def check(self, value: Any) -> Any:
        if self.allowed is not None and not self.allowed(value):
            raise ParameterFault(f"parameter {self.name} must be {self.expectation}, "
                                 f"got {value!r}")
        return value


def _positive(name: str, default: float, description: str) -> NodeParameter:
    return NodeParameter(name, default, description, lambda v: v > 0, "> 0")


def _non_negative(name: str, default: float, description: str) -> NodeParameter:
    return NodeParameter(name, default, description, lambda v: v >= 0, ">= 0")


def _one_of(name: str, default: str, description: str, values: tuple[str, ...]) -> NodeParameter:
    return NodeParameter(name, default, description, lambda v: v in values, f"one of {values}")


PRESET = NodeParameter("preset", "default", "parameter preset (config/<preset>.yaml); "
                       "descriptor.*, search.* and spacing_m given explicitly override it")
RELIABLE_QOS = NodeParameter("reliable_qos", False, "subscribe reliably (lossless from reliable "
                             "publishers such as bag replays; cannot connect to best-effort "
                             "publishers)")


def input_parameters(pose_default: str, pose_use: str,
                     map_frame_use: str) -> tuple[NodeParameter, ...]:
    """The scan and pose inputs both LiDAR nodes share. pose_default: "odom", or NO_POSES when
    poses are optional; pose_use and map_frame_use: what the node uses them for."""
    sources = ((NO_POSES,) if pose_default == NO_POSES else ()) + tuple(sorted(POSE_SOURCES))
    return (
        _one_of("pose_source", pose_default, "odom (nav_msgs/Odometry on 'odom'), pose "
                "(PoseStamped on 'pose') or pose_with_covariance" +
                (", or none" if pose_default == NO_POSES else "") + f": {pose_use}", sources),
        NodeParameter("extrinsic", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                      "base_T_sensor as [x, y, z, qx, qy, qz, qw]: the sensor's pose on the robot",
                      lambda v: len(v) == 7 and all(math.isfinite(x) for x in v),
                      "7 finite numbers [x, y, z, qx, qy, qz, qw]"),
        _positive("max_pose_gap_s", 1.0, "largest gap between pose samples interpolated across"),
        _positive("max_points", 2_000_000, "scans with more points are rejected"),
        NodeParameter("sensor_frame_id", "", "accept only scans in this frame ('' = any)"),
        NodeParameter("map_frame_id", "", map_frame_use),
        _non_negative("future_tolerance_s", 60.0, "reject scans stamped further ahead of the "
                      "node's clock (0 = no check)"),
        RELIABLE_QOS,
    )


@dataclass(frozen=True)
class InputSettings:
    """The scan and pose inputs (input_parameters), read."""

    pose_source: str
    extrinsic: np.ndarray
    max_pose_gap_s: float
    max_points: int
    sensor_frame_id: str
    map_frame_id: str
    future_tolerance_s: float
    reliable: bool

    @property
    def has_poses(self) -> bool:
        return self.pose_source != NO_POSES

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> InputSettings:
        extrinsic = np.asarray(values["extrinsic"], dtype=float)
        try:
            check_quaternion(extrinsic[3:], "extrinsic")
        except InvalidPoseError as error:
            raise ParameterFault(f"parameter extrinsic: {error}") from None
        return cls(values["pose_source"], pose_matrix(extrinsic[:3], extrinsic[3:]),
                   values["max_pose_gap_s"], values["max_points"], values["sensor_frame_id"],
                   values["map_frame_id"], values["future_tolerance_s"], values["reliable_qos"])


def _mode_parameter() -> NodeParameter:
    return _one_of("mode", "relocalise", "relocalise (against a map file) or loop_closure "
                   "(the map grows from the robot's own posed scans)", Localiser.MODES)


@dataclass(frozen=True)
class LocaliserSettings:
    """Everything the localiser node reads at start-up (PARAMETERS, plus preset, descriptor.*,
    search.* and spacing_m as config); from_values checks every combination that does not need
    the map."""

    config: Config
    explicit: dict
    mode: str
    map_path: str
    inputs: InputSettings
    exclude_recent_s: float
    min_score: float
    diagnostics_period_s: float
    publish_markers: bool
    publish_mode: str
    request_timeout_s: float
    loop_closure_formats: frozenset[str]

    PARAMETERS = (
        _mode_parameter(),
        NodeParameter("map_path", "", "map file to relocalise against (relocalise mode)"),
        *input_parameters(NO_POSES, "the live scans' odometry, needed by loop_closure mode (to "
                          "grow the map), by submaps (descriptor.submap_m), by odometry "
                          "consistency and by descriptor.level (roll/pitch)",
                          "frame of published poses ('' = the map's)"),
        _non_negative("exclude_recent_s", 30.0, "loop_closure: ignore references younger than "
                      "this"),
        NodeParameter("min_score", 0.0, "accept matches scoring at least this"),
        _positive("diagnostics_period_s", 1.0, "seconds between diagnostics"),
        NodeParameter("publish_markers", True, "publish RViz markers on 'markers'"),
        _one_of("publish_mode", "auto", "on_request: publish relocalisation once per "
                "~/relocalise call (nav2); continuous: for every accepted scan; auto: on_request "
                "in relocalise mode, continuous in loop_closure mode", ("auto", *PUBLISH_MODES)),
        _positive("request_timeout_s", 10.0, "a ~/relocalise call fails when no scan passes "
                  "verification within this many seconds (with submaps: answers from the best "
                  "partial window at this time)"),
        NodeParameter("loop_closure_format", ["mf_lpr"], "loop-closure messages to publish: "
                      "mf_lpr (labelled array on 'loop_closure'), lio_sam ([query_s, "
                      f"reference_s] on '{LIO_SAM_TOPIC}'); several allowed",
                      lambda v: len(v) > 0 and set(v) <= set(LOOP_CLOSURE_FORMATS),
                      f"a non-empty list of {LOOP_CLOSURE_FORMATS}"),
    )

    @classmethod
    def from_values(cls, config: Config, explicit: dict,
                    values: dict[str, Any]) -> LocaliserSettings:
        mode = values["mode"]
        inputs = InputSettings.from_values(values)
        formats = frozenset(values["loop_closure_format"])
        if "lio_sam" in formats and mode != "loop_closure":
            raise ParameterFault("parameter loop_closure_format lio_sam needs mode loop_closure: "
                                 "LIO-SAM maps both stamps to its own keyframes, so the "
                                 "reference must come from the same session")
        if mode == "loop_closure" and not inputs.has_poses:
            raise ParameterFault("parameter pose_source must name a pose stream in loop_closure "
                                 "mode (the map grows from the robot's posed scans)")
        if mode == "loop_closure" and config.auto:
            raise ParameterFault("parameter preset: auto derives the descriptor when a map is "
                                 "built (map_builder, mf-lpr build-map); in loop_closure mode "
                                 "the map grows from the first scan on, so name a preset")
        if mode == "relocalise" and not values["map_path"]:
            raise ParameterFault("parameter map_path must name a map file in relocalise mode")
        if config.search.map_headings != "known":
            raise ParameterFault("parameter search.map_headings must be 'known' in the "
                                 "localiser: its poses and closures are the references' poses "
                                 "composed with the alignments, which need the map's headings "
                                 "('unknown' is for retrieval-only evaluation: mf-lpr evaluate, "
                                 "suite)")
        publish_mode = values["publish_mode"]
        if publish_mode == "auto":
            publish_mode = "continuous" if mode == "loop_closure" else "on_request"
        return cls(config, explicit, mode, values["map_path"], inputs,
                   values["exclude_recent_s"], values["min_score"],
                   values["diagnostics_period_s"], values["publish_markers"], publish_mode,
                   values["request_timeout_s"], formats)


@dataclass(frozen=True)
class MapBuilderSettings:
    """Everything the map-builder node reads at start-up (PARAMETERS, plus the config)."""

    config: Config
    map_path: str
    if_exists: str
    save_period_s: float
    keep_clouds: bool
    inputs: InputSettings
    global_map_topic: str
    sensor_height_m: float

    PARAMETERS = (
        NodeParameter("map_path", "mf_lpr_map.mfmap", "map file to write", bool, "a file path"),
        _one_of("if_exists", "error", "when map_path exists: error, append (extend it) or "
                "overwrite", IF_EXISTS),
        _positive("save_period_s", 10.0, "seconds between periodic saves"),
        NodeParameter("keep_clouds", False, "store reference clouds (enables ICP "
                      "refinement); a map whose search verifies by ICP keeps them anyway"),
        *input_parameters("odom", "the poses of the reference scans",
                          "frame of the map ('' = the pose messages' frame)"),
        NodeParameter("global_map_topic", "", "a PointCloud2 global map topic (transient local) "
                      "to render a reference grid from, instead of building from scans "
                      "('' = off)"),
        _positive("sensor_height_m", 1.8, "with global_map_topic: the sensor's height above the "
                  "ground"),
    )

    @classmethod
    def from_values(cls, config: Config, values: dict[str, Any]) -> MapBuilderSettings:
        if values["global_map_topic"] and config.auto:
            raise ParameterFault("parameter preset: auto measures scans; a global map has none, "
                                 "so name a preset with global_map_topic")
        return cls(config, values["map_path"], values["if_exists"], values["save_period_s"],
                   values["keep_clouds"], InputSettings.from_values(values),
                   values["global_map_topic"], values["sensor_height_m"])


@dataclass(frozen=True)
class PoseGraphSettings:
    """The example back end's parameters."""

    keyframe_spacing_m: float
    publish_period_s: float
    reliable: bool

    PARAMETERS = (
        _non_negative("keyframe_spacing_m", 1.0, "a keyframe every this much travel"),
        _positive("publish_period_s", 1.0, "seconds between path messages"),
        RELIABLE_QOS,
    )

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> PoseGraphSettings:
        return cls(values["keyframe_spacing_m"], values["publish_period_s"],
                   values["reliable_qos"])


# Node executable -> (its settings class, whether it also takes preset, descriptor.*, search.*
# and spacing_m): what docs/PARAMETERS.md lists.
NODE_SETTINGS = {"map_builder": (MapBuilderSettings, True),
                 "localiser": (LocaliserSettings, True),
                 "managed_localiser": (LocaliserSettings, True),
                 "pose_graph": (PoseGraphSettings, False)}
