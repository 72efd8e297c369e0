"""Small builders shared by test modules in different folders."""

from __future__ import annotations

import numpy as np

from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import pose_matrix, quaternion_from_yaw
from mf_lpr_ros.params import DescriptorParams

PARAMS = DescriptorParams(voxel_size=0.4)


def make_map(rng, n=5, clouds=False):
    reference_map = ReferenceMap(PARAMS, frame_id="map", sensor_frame_id="velodyne",
                                 metadata={"source": "test"})
    for i in range(n):
        pose = pose_matrix(rng.normal(size=3), quaternion_from_yaw(rng.uniform(-3, 3)))
        cloud = rng.normal(size=(50 + i, 3)) if clouds else None
        reference_map.append(rng.random((120, 120)) < 0.2, pose, 100.0 + i, i * 3, cloud)
    return reference_map


def turned_view_map(reference_map: ReferenceMap,
                    views: list[tuple[int, float, float]]) -> ReferenceMap:
    """A map of reference_map's views, each (view, turn, shift_y) entry one reference: that
    view's occupancy under its pose turned by turn radians about the vertical (a map whose
    headings are not its views') and moved shift_y metres along y (a look-alike elsewhere)."""
    turned = ReferenceMap(reference_map.params)
    for k, (view, turn, shift_y) in enumerate(views):
        pose = reference_map.poses[view].copy()
        pose[:3, :3] = np.array([[np.cos(turn), -np.sin(turn), 0.0],
                                 [np.sin(turn), np.cos(turn), 0.0],
                                 [0.0, 0.0, 1.0]]) @ pose[:3, :3]
        pose[1, 3] += shift_y
        turned.append(reference_map.occupancy(view), pose, float(k), k)
    return turned
