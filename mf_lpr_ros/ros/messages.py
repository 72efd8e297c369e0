"""Conversions between ROS 2 messages and the core's arrays.

Loop closures travel in the formats the localiser's loop_closure_format names:
- mf_lpr: std_msgs/Float64MultiArray with one labelled dimension whose label names every
  element (LOOP_CLOSURE_LABEL); decode_loop_closure reads them back. Stamps are split into
  seconds and nanoseconds so they survive float64 exactly. The 36 covariance_* values are the
  row-major 6x6 covariance (not information) of reference_T_query over x, y, z, roll, pitch,
  yaw; the three a planar match does not observe hold UNOBSERVED_VARIANCE.
- lio_sam: std_msgs/Float64MultiArray of exactly [query_stamp_s, reference_stamp_s], what
  LIO-SAM and its forks read on lio_loop/loop_closure_detection.
"""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Float64MultiArray, Header, MultiArrayDimension, MultiArrayLayout
from visualization_msgs.msg import Marker, MarkerArray

from mf_lpr_ros.core.pose import matrix_to_quaternion, pose_matrix
from mf_lpr_ros.io.messages import seconds_to_stamp_parts, stamp_to_seconds
from mf_lpr_ros.io.pointcloud import xyz_to_pointcloud2_layout
from mf_lpr_ros.live.localiser import LiveMatch

# Variance given to the dimensions a planar match does not observe (z, roll, pitch).
UNOBSERVED_VARIANCE = 1e3

LOOP_CLOSURE_FIELDS = (
    "query_stamp_sec", "query_stamp_nanosec", "reference_index", "reference_stamp_sec",
    "reference_stamp_nanosec", "x", "y", "z", "qx", "qy", "qz", "qw", "score", "confidence",
    *(f"covariance_{i}" for i in range(36)))
LOOP_CLOSURE_LABEL = "mf_lpr_loop_closure_v1:" + ",".join(LOOP_CLOSURE_FIELDS)


def seconds_to_stamp(seconds: float) -> Time:
    sec, nanosec = seconds_to_stamp_parts(seconds)
    return Time(sec=sec, nanosec=nanosec)


def points_to_pointcloud2(points: np.ndarray, stamp: Time, frame_id: str) -> PointCloud2:
    """A dense little-endian float32 x, y, z PointCloud2."""
    fields, point_step, data = xyz_to_pointcloud2_layout(points)
    return PointCloud2(
        header=Header(stamp=stamp, frame_id=frame_id), height=1, width=len(points),
        fields=[PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                for f in fields],
        is_bigendian=False, point_step=point_step, row_step=point_step * len(points),
        data=data, is_dense=True)


def odometry_message(stamp: Time, frame_id: str, child_frame_id: str,
                     world_T_child: np.ndarray) -> Odometry:
    message = Odometry()
    message.header = Header(stamp=stamp, frame_id=frame_id)
    message.child_frame_id = child_frame_id
    set_pose(message.pose.pose, world_T_child)
    return message


def covariance_6x6(planar_covariance: np.ndarray) -> list[float]:
    """Row-major 6x6 (x, y, z, roll, pitch, yaw) from a planar (x, y, yaw) covariance."""
    full = np.diag([0.0, 0.0, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, 0.0])
    index = [0, 1, 5]
    full[np.ix_(index, index)] = planar_covariance
    return [float(v) for v in full.ravel()]


def set_pose(target, transform: np.ndarray) -> None:
    target.position.x, target.position.y, target.position.z = (float(v) for v in transform[:3, 3])
    qx, qy, qz, qw = matrix_to_quaternion(transform[:3, :3])
    target.orientation.x, target.orientation.y = float(qx), float(qy)
    target.orientation.z, target.orientation.w = float(qz), float(qw)


def relocalisation_message(stamp: Time, frame_id: str, world_T_base: np.ndarray,
                           planar_covariance: np.ndarray) -> PoseWithCovarianceStamped:
    message = PoseWithCovarianceStamped()
    message.header = Header(stamp=stamp, frame_id=frame_id)
    set_pose(message.pose.pose, world_T_base)
    message.pose.covariance = covariance_6x6(planar_covariance)
    return message


def loop_closure_message(query_stamp: Time, reference_index: int, reference_stamp: float,
                         reference_T_query: np.ndarray, relative_covariance: np.ndarray,
                         score: float, confidence: float) -> Float64MultiArray:
    reference_time = seconds_to_stamp(reference_stamp)
    quaternion = matrix_to_quaternion(reference_T_query[:3, :3])
    values = [float(query_stamp.sec), float(query_stamp.nanosec), float(reference_index),
              float(reference_time.sec), float(reference_time.nanosec),
              *(float(v) for v in reference_T_query[:3, 3]), *(float(v) for v in quaternion),
              float(score), float(confidence), *covariance_6x6(relative_covariance)]
    message = Float64MultiArray()
    message.layout.dim = [MultiArrayDimension(label=LOOP_CLOSURE_LABEL, size=len(values),
                                              stride=len(values))]
    message.data = values
    return message


def candidates_message(stamp: Time, frame_id: str, world_T_bases: list[np.ndarray]) -> PoseArray:
    """Ranked pose hypotheses, best first."""
    message = PoseArray(header=Header(stamp=stamp, frame_id=frame_id))
    for transform in world_T_bases:
        pose = Pose()
        set_pose(pose, transform)
        message.poses.append(pose)
    return message


def confidences_message(confidences: list[float]) -> Float64MultiArray:
    """The confidences of the hypotheses on ~/candidates, in the same order."""
    return Float64MultiArray(layout=MultiArrayLayout(dim=[MultiArrayDimension(
        label="confidence", size=len(confidences), stride=len(confidences))]),
        data=[float(c) for c in confidences])


def lio_sam_loop_message(query_stamp: Time, reference_stamp: float) -> Float64MultiArray:
    """[query_time_s, matched_time_s]: LIO-SAM's external loop-closure message."""
    return Float64MultiArray(data=[stamp_to_seconds(query_stamp), float(reference_stamp)])


def decode_loop_closure(message: Float64MultiArray) -> dict:
    """The loop closure as a dict: query_stamp / reference_stamp (builtin_interfaces Time),
    reference_index, reference_T_query (4x4), covariance (6x6), score, confidence."""
    if not message.layout.dim or message.layout.dim[0].label != LOOP_CLOSURE_LABEL:
        raise ValueError("not an mf_lpr loop closure (layout label differs)")
    values = dict(zip(LOOP_CLOSURE_FIELDS, message.data))
    return {
        "query_stamp": Time(sec=int(values["query_stamp_sec"]),
                            nanosec=int(values["query_stamp_nanosec"])),
        "reference_index": int(values["reference_index"]),
        "reference_stamp": Time(sec=int(values["reference_stamp_sec"]),
                                nanosec=int(values["reference_stamp_nanosec"])),
        "reference_T_query": pose_matrix(
            np.array([values["x"], values["y"], values["z"]]),
            np.array([values["qx"], values["qy"], values["qz"], values["qw"]])),
        "covariance": np.array(message.data[14:50]).reshape(6, 6),
        "score": values["score"],
        "confidence": values["confidence"],
    }


def match_markers(stamp: Time, frame_id: str, query_pose: np.ndarray,
                  reference_pose: np.ndarray, accepted: bool) -> MarkerArray:
    """RViz: an arrow at the estimated pose and a line to the matched reference."""
    header = Header(stamp=stamp, frame_id=frame_id)
    colour = ColorRGBA(r=0.1, g=0.8, b=0.2, a=1.0) if accepted else ColorRGBA(r=0.9, g=0.3,
                                                                              b=0.1, a=0.6)
    arrow = Marker(header=header, ns="mf_lpr", id=0, type=Marker.ARROW, action=Marker.ADD,
                   color=colour)
    set_pose(arrow.pose, query_pose)
    arrow.scale.x, arrow.scale.y, arrow.scale.z = 2.0, 0.4, 0.4
    link = Marker(header=header, ns="mf_lpr", id=1, type=Marker.LINE_STRIP, action=Marker.ADD,
                  color=colour)
    link.pose.orientation.w = 1.0
    link.scale.x = 0.15
    link.points = [Point(x=float(p[0, 3]), y=float(p[1, 3]), z=float(p[2, 3]))
                   for p in (query_pose, reference_pose)]
    return MarkerArray(markers=[arrow, link])


def diagnostics_message(stamp: Time, node_name: str, counters: dict[str, int | float],
                        last: LiveMatch | None, warn: str = "") -> DiagnosticArray:
    status = DiagnosticStatus(level=DiagnosticStatus.WARN if warn else DiagnosticStatus.OK,
                              name=f"{node_name}: matched-filter localisation",
                              hardware_id="mf_lpr_ros", message=warn or "running")
    values = {**counters}
    if last is not None:
        values.update({f"last_{k}_ms": round(v, 2) for k, v in last.timings_ms.items()})
        if last.match is not None:
            values.update(last_score=round(last.match.score, 4),
                          last_confidence=round(last.match.confidence, 4))
        values["last_result"] = last.reason
    status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
    return DiagnosticArray(header=Header(stamp=stamp), status=[status])
