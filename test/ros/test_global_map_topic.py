"""Global point-cloud maps: accumulate, render references on a grid, relocalise off the path."""

import numpy as np

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.map_store import GLOBAL_MAP_KIND, ReferenceMap
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.pipeline.global_map import RenderParams

CONFIG = preset("kitti")
SIM_RENDER = RenderParams(elevation_deg=(-15.0, 15.0))


def test_map_builder_renders_a_latched_global_map_topic(ros_graph, world, tmp_path):
    from sensor_msgs.msg import PointCloud2

    from mf_lpr_ros.ros.map_builder import GLOBAL_MAP_QOS, MapBuilderNode
    from mf_lpr_ros.ros.messages import points_to_pointcloud2, seconds_to_stamp

    # Published before the node exists, as a map server latches its map.
    latched = ros_graph.node.create_publisher(PointCloud2, "map", GLOBAL_MAP_QOS)
    nan_cloud = points_to_pointcloud2(np.full((50, 3), np.nan, np.float32), seconds_to_stamp(1.0),
                                      "map")
    latched.publish(nan_cloud)
    map_path = tmp_path / "global.mfmap"
    # Searched with its spectra on demand (a grid over 50,000 references is by default), so
    # the node also writes the prefilter's features beside the grid, as build-map does.
    node = ros_graph.start(MapBuilderNode, preset="kitti", map_path=str(map_path),
                           global_map_topic="map", sensor_height_m=1.7,
                           **{"search.reference_spectra": "on_demand"})
    assert ros_graph.wait_for(lambda: node.counters["global_maps_rejected"] == 1)
    cloud = world.points[np.abs(world.points[:, :2]).max(axis=1) < 30].astype(np.float32)
    latched.publish(points_to_pointcloud2(cloud, seconds_to_stamp(2.0), "map"))
    assert ros_graph.wait_for(lambda: node.global_maps_built == 1, 120.0)
    saved = ReferenceMap.load(map_path)
    assert saved.metadata["kind"] == GLOBAL_MAP_KIND and saved.frame_id == "map"
    assert len(saved) > 20 and saved.metadata["sensor_height_m"] == 1.7
    index = MatchedFilterIndex(saved, node._global_config.search)
    assert index.prefilter_cache_status.startswith("loaded from")
