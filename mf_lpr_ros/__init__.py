"""mf_lpr_ros: LiDAR place recognition and relocalisation by matched filtering of BEV descriptors.

The public API, ROS-free (rclpy is imported by mf_lpr_ros.ros only):

    from mf_lpr_ros import build_map, open_source, preset, MatchedFilterIndex
    reference_map = build_map(open_source("kitti/00"), preset("kitti"))
    match = MatchedFilterIndex(reference_map, preset("kitti").search).query(occupancy)

README.md, section "Architecture", maps the subpackages.
"""

__version__ = "0.1.0"

from mf_lpr_ros import errors  # noqa: E402
from mf_lpr_ros.config import Config, load_config, preset  # noqa: E402
from mf_lpr_ros.core.map_store import ReferenceMap  # noqa: E402
from mf_lpr_ros.core.search import MatchedFilterIndex, MatchResult  # noqa: E402
from mf_lpr_ros.datasets import open_source  # noqa: E402
from mf_lpr_ros.live.localiser import Localiser  # noqa: E402
from mf_lpr_ros.live.map_builder import MapBuilder  # noqa: E402
from mf_lpr_ros.pipeline.mapping import build_map  # noqa: E402

__all__ = ["Config", "load_config", "preset", "ReferenceMap", "MatchedFilterIndex", "MatchResult",
           "Localiser", "MapBuilder", "build_map", "open_source", "errors", "__version__"]
