"""Small builders shared by test modules in different folders."""

from __future__ import annotations

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
