"""Poses: conversions, interpolation and the pose implied by a correlation peak.

Poses are world_T_sensor. Planar poses are (x, y, yaw) with yaw counter-clockwise about z.
Quaternions are (qx, qy, qz, qw), as in ROS and TUM files.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg

from mf_lpr_ros.errors import InvalidPoseError

_EXACT_STAMP_S = 1e-4


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Angle(s) in radians wrapped to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def quaternion_to_matrix(quaternion: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) of quaternion(s) (..., 4) = (qx, qy, qz, qw), normalised."""
    q = np.asarray(quaternion, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(norm)) or np.any(norm < 1e-9):
        raise ValueError("quaternion is zero or not finite")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Quaternion(s) (..., 4) = (qx, qy, qz, qw) with qw >= 0 of rotation matrices (..., 3, 3)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    candidates = np.stack([
        np.stack([1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0],
                  m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] - m[..., 1, 2]], -1),
        np.stack([m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                  m[..., 1, 2] + m[..., 2, 1], m[..., 0, 2] - m[..., 2, 0]], -1),
        np.stack([m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                  1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2], m[..., 1, 0] - m[..., 0, 1]], -1),
        np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                  m[..., 1, 0] - m[..., 0, 1], 1 + trace], -1),
    ], -2)
    # The numerically safest candidate is the one with the largest diagonal term.
    diagonal = np.stack([m[..., 0, 0], m[..., 1, 1], m[..., 2, 2], trace], -1)
    choice = np.argmax(diagonal, axis=-1)
    q = np.take_along_axis(candidates, choice[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def yaw_of(rotation: np.ndarray) -> np.ndarray:
    """Heading (rad) of rotation matrices (..., 3, 3): the direction of the rotated x axis."""
    return np.arctan2(rotation[..., 1, 0], rotation[..., 0, 0])


def quaternion_from_yaw(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])


def pose_matrix(translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """4x4 transform(s) from translation(s) (..., 3) and quaternion(s) (..., 4)."""
    translation = np.asarray(translation, dtype=np.float64)
    matrix = np.zeros(translation.shape[:-1] + (4, 4))
    matrix[..., :3, :3] = quaternion_to_matrix(quaternion)
    matrix[..., :3, 3] = translation
    matrix[..., 3, 3] = 1.0
    return matrix


def euler_pose(translation: np.ndarray, roll_pitch_yaw: np.ndarray) -> np.ndarray:
    """4x4 transform(s) from translation(s) (..., 3) and roll, pitch, yaw (..., 3) in radians,
    R = Rz(yaw) Ry(pitch) Rx(roll) (the NCLT and Oxford RobotCar convention)."""
    translation = np.asarray(translation, dtype=np.float64)
    roll, pitch, yaw = np.moveaxis(np.asarray(roll_pitch_yaw, dtype=np.float64), -1, 0)
    cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                              np.cos(yaw), np.sin(yaw))
    matrix = np.zeros(translation.shape[:-1] + (4, 4))
    matrix[..., 0, :3] = np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1)
    matrix[..., 1, :3] = np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1)
    matrix[..., 2, :3] = np.stack([-sp, cp * sr, cp * cr], -1)
    matrix[..., :3, 3] = translation
    matrix[..., 3, 3] = 1.0
    return matrix


def planar(pose: np.ndarray) -> np.ndarray:
    """(x, y, yaw) of 4x4 pose(s) (..., 4, 4)."""
    pose = np.asarray(pose)
    return np.concatenate([pose[..., :2, 3], yaw_of(pose[..., :3, :3])[..., None]], axis=-1)


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query_stamps: np.ndarray,
                      max_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses at query stamps: linear in translation, slerp in rotation.

    stamps (N,) increasing, poses (N, 4, 4). A query is valid when it lies between two samples
    no more than max_gap_s apart, matches a sample's stamp, or lies just outside the samples'
    span, within end_hold_s(stamps, max_gap_s) of an end sample (then that sample).
    Returns (poses (M, 4, 4), valid (M,) bool); invalid entries hold the identity.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    query_stamps = np.atleast_1d(np.asarray(query_stamps, dtype=np.float64))
    result = np.tile(np.eye(4), (len(query_stamps), 1, 1))
    valid = np.zeros(len(query_stamps), dtype=bool)
    if len(stamps) == 0:
        return result, valid
    after = np.searchsorted(stamps, query_stamps, side="left").clip(1, max(len(stamps) - 1, 1))
    before = after - 1
    if len(stamps) == 1:
        after = before = np.zeros_like(after)
    t0, t1 = stamps[before], stamps[after]
    span = t1 - t0
    inside = (query_stamps >= t0) & (query_stamps <= t1) & (span <= max_gap_s)
    hold_s = end_hold_s(stamps, max_gap_s)
    near_first = np.abs(query_stamps - stamps[0]) <= hold_s
    near_last = np.abs(query_stamps - stamps[-1]) <= hold_s
    alpha = np.where(span > 0, (query_stamps - t0) / np.where(span > 0, span, 1.0), 0.0)
    alpha = np.clip(alpha, 0.0, 1.0)
    q0 = matrix_to_quaternion(poses[before, :3, :3])
    q1 = matrix_to_quaternion(poses[after, :3, :3])
    rotation = quaternion_to_matrix(_slerp(q0, q1, alpha))
    translation = (1 - alpha)[:, None] * poses[before, :3, 3] + alpha[:, None] * poses[after, :3, 3]
    result[inside, :3, :3] = rotation[inside]
    result[inside, :3, 3] = translation[inside]
    valid |= inside
    nearest = np.where(np.abs(query_stamps - t0) <= np.abs(query_stamps - t1), before, after)
    exact = ~valid & (np.abs(stamps[nearest] - query_stamps) <= _EXACT_STAMP_S)
    result[exact] = poses[nearest[exact]]
    valid |= exact
    for near, end in ((near_first & ~valid & (query_stamps <= stamps[0]), 0),
                      (near_last & ~valid & (query_stamps >= stamps[-1]), len(stamps) - 1)):
        result[near] = poses[end]
        valid |= near
    return result, valid


def end_hold_s(stamps: np.ndarray, max_gap_s: float) -> float:
    """How far outside the samples' span a query still takes the end sample's pose: half the
    median sample interval (capped at max_gap_s), the most a stamp can be off while the end
    sample is still its nearest. Holding a pose longer would place a moving sensor's scan where
    the sensor was up to max_gap_s away (10 m at 10 m/s). A single sample holds for exact
    stamps only."""
    if len(stamps) < 2:
        return _EXACT_STAMP_S
    return min(max_gap_s, 0.5 * float(np.median(np.diff(stamps))))


def _slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot).clip(-1.0, 1.0)
    angle = np.arccos(dot)
    small = angle < 1e-6
    sin_angle = np.where(small, 1.0, np.sin(angle))
    w0 = np.where(small, 1 - alpha, np.sin((1 - alpha) * angle) / sin_angle)
    w1 = np.where(small, alpha, np.sin(alpha * angle) / sin_angle)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def query_pose_from_alignment(reference_pose: np.ndarray, shift_m: np.ndarray,
                              rotation_rad: float) -> np.ndarray:
    """Planar query pose from the reference's planar pose and the matched-filter alignment
    (or poses (..., 3) from poses (..., 3), shifts (..., 2) and rotations (...)).

    The alignment says: the query's points rotated by rotation_rad (CCW) and moved by shift_m
    (metres, in the reference's sensor frame) land on the reference's points. So the query
    sensor sits at shift_m in the reference frame, heading rotation_rad relative to it:

        t_q = t_r + R(psi_r) shift,   psi_q = psi_r + rotation
    """
    reference_pose, shift_m = np.asarray(reference_pose), np.asarray(shift_m)
    x_r, y_r, psi_r = reference_pose[..., 0], reference_pose[..., 1], reference_pose[..., 2]
    c, s = np.cos(psi_r), np.sin(psi_r)
    dx, dy = shift_m[..., 0], shift_m[..., 1]
    return np.stack([x_r + c * dx - s * dy, y_r + s * dx + c * dy,
                     wrap_angle(psi_r + rotation_rad)], axis=-1).astype(np.float64)


def alignment_from_poses(reference_pose: np.ndarray, query_pose: np.ndarray
                         ) -> tuple[np.ndarray, float]:
    """(shift_m, rotation_rad): the alignment that query_pose_from_alignment turns into
    query_pose against reference_pose (planar poses)."""
    relative = relative_planar(reference_pose, query_pose)
    return relative[:2], float(relative[2])


def rotate_covariance(covariance: np.ndarray, yaw: float) -> np.ndarray:
    """A planar (x, y, yaw) covariance expressed in a frame rotated by yaw."""
    rotation = np.eye(3)
    rotation[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    return rotation @ covariance @ rotation.T


def enclosing_covariance(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """A covariance whose ellipsoid contains both first's and second's (n x n, positive
    definite): in the basis where both are diagonal, the larger of the two along each axis.
    Their sum where that basis does not exist (either singular)."""
    first, second = np.asarray(first, dtype=np.float64), np.asarray(second, dtype=np.float64)
    try:
        ratios, basis = scipy.linalg.eigh(first, second)
    except np.linalg.LinAlgError:
        return first + second
    # basis.T @ second @ basis = I, basis.T @ first @ basis = diag(ratios).
    back = np.linalg.inv(basis)
    enclosing = back.T @ np.diag(np.maximum(ratios, 1.0)) @ back
    return (enclosing + enclosing.T) / 2


def composed_covariance(first: np.ndarray, first_covariance: np.ndarray, composed: np.ndarray,
                        second_covariance: np.ndarray) -> np.ndarray:
    """The covariance (3x3, over x, y, yaw in the common frame) of composed = first (+) second,
    from first's covariance and second's (expressed in first's frame), the two independent,
    to first order: an error in first's heading swings composed about first's position."""
    first, composed = np.asarray(first, dtype=np.float64), np.asarray(composed, dtype=np.float64)
    swing = np.eye(3)
    swing[:2, 2] = [-(composed[1] - first[1]), composed[0] - first[0]]
    return (swing @ np.asarray(first_covariance, dtype=np.float64) @ swing.T
            + rotate_covariance(np.asarray(second_covariance, dtype=np.float64), first[2]))


def moved_points(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """points (N, 3) moved by the rigid transform (4x4), as float64. Its rotation is copied out
    of the 4x4 first: numpy multiplies by a strided 3x3 without BLAS, ~3x slower."""
    moved = points @ np.ascontiguousarray(transform[:3, :3].T)
    moved += transform[:3, 3]
    return moved


def level_points(points: np.ndarray, orientation: np.ndarray) -> np.ndarray:
    """Points (N, 3+) in a frame with the sensor's heading but no roll or pitch.

    orientation is world_R_sensor; the result is Rz(-yaw) world_R_sensor p, so a planar pose
    (x, y, yaw) of the sensor still describes the levelled frame.
    """
    yaw = float(yaw_of(orientation))
    heading = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0],
                        [0.0, 0.0, 1.0]])
    tilt = heading.T @ orientation
    return np.asarray(points)[:, :3] @ tilt.T


def compose_planar(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """first (+) second for planar poses (..., 3): second expressed in first's frame."""
    first, second = np.asarray(first, dtype=np.float64), np.asarray(second, dtype=np.float64)
    c, s = np.cos(first[..., 2]), np.sin(first[..., 2])
    return np.stack([first[..., 0] + c * second[..., 0] - s * second[..., 1],
                     first[..., 1] + s * second[..., 0] + c * second[..., 1],
                     wrap_angle(first[..., 2] + second[..., 2])], axis=-1)


def relative_planar(origin: np.ndarray, target: np.ndarray) -> np.ndarray:
    """origin^-1 (+) target for planar poses (..., 3): target in origin's frame."""
    origin, target = np.asarray(origin, dtype=np.float64), np.asarray(target, dtype=np.float64)
    c, s = np.cos(origin[..., 2]), np.sin(origin[..., 2])
    dx, dy = target[..., 0] - origin[..., 0], target[..., 1] - origin[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy,
                     wrap_angle(target[..., 2] - origin[..., 2])], axis=-1)


def mean_planar(poses: np.ndarray) -> np.ndarray:
    """The mean of planar poses (n, 3): their positions' mean and their headings' circular
    mean."""
    poses = np.asarray(poses, dtype=np.float64)
    heading = math.atan2(float(np.sin(poses[:, 2]).mean()), float(np.cos(poses[:, 2]).mean()))
    return np.array([*poses[:, :2].mean(axis=0), heading])


def reference_distance(first: np.ndarray, second: np.ndarray) -> float:
    """How far apart two references are, as one query's alignments on both put them: first and
    second are the query's planar pose in each reference's frame (shift x, shift y, rotation,
    as alignment_from_poses gives them). Neither reference's heading enters it."""
    between = compose_planar(first, relative_planar(second, np.zeros(3)))
    return float(np.hypot(between[0], between[1]))


def planar_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation error (m) and absolute yaw error (degrees) of planar poses (..., 3); floats
    for single poses."""
    estimate, truth = np.asarray(estimate, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    translation = np.hypot(estimate[..., 0] - truth[..., 0], estimate[..., 1] - truth[..., 1])
    yaw = np.abs(np.degrees(wrap_angle(estimate[..., 2] - truth[..., 2])))
    if translation.ndim == 0:
        return float(translation), float(yaw)
    return translation, yaw


def validate_pose(pose: np.ndarray, what: str = "pose") -> np.ndarray:
    """A finite 4x4 rigid transform, or InvalidPoseError naming the problem."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise InvalidPoseError(f"{what} must be 4x4, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise InvalidPoseError(f"{what} holds NaN or infinite values")
    rotation = pose[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3):
        raise InvalidPoseError(f"{what} has a rotation that is not orthonormal")
    return pose


def check_quaternion(quaternion: np.ndarray, what: str = "orientation") -> None:
    """Refuse quaternions that are not finite or far from unit length (sloppy publishers within
    1 % are normalised downstream)."""
    norm = float(np.linalg.norm(quaternion))
    if not math.isfinite(norm):
        raise InvalidPoseError(f"{what} quaternion holds NaN or infinite values")
    if abs(norm - 1.0) > 0.01:
        raise InvalidPoseError(f"{what} quaternion has norm {norm:.4g}, not 1")
