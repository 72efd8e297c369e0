"""mf_lpr_ros: LiDAR place recognition and relocalisation by matched filtering of BEV descriptors."""

__version__ = "0.1.0"
