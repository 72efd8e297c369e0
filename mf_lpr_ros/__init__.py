"""mf_lpr_ros: LiDAR place recognition and relocalisation by matched filtering of BEV descriptors.

The public API, ROS-free (rclpy is imported by mf_lpr_ros.ros only):

    from mf_lpr_ros import build_map, open_source, preset, MatchedFilterIndex
    reference_map = build_map(open_source("kitti/00"), preset("kitti"))
    match = MatchedFilterIndex(reference_map, preset("kitti").search).query(occupancy)

README.md, section "Architecture", maps the subpackages.
"""

from mf_lpr_ros import errors
from mf_lpr_ros.config import Config, load_config, preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.search import MatchedFilterIndex, MatchResult
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.live.localiser import Localiser
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.pipeline.mapping import build_map
from mf_lpr_ros.version import __version__

__all__ = ["Config", "load_config", "preset", "ReferenceMap", "MatchedFilterIndex", "MatchResult",
           "Localiser", "MapBuilder", "build_map", "open_source", "errors", "__version__"]
