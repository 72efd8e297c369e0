"""ament_python package: `colcon build` on ROS 2 Jazzy, or `pip install -e .` in a venv."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "mf_lpr_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    # Must agree with package.xml and mf_lpr_ros/optional.py (test_optional.py checks).
    install_requires=["setuptools", "numpy", "scipy", "pyyaml", "tqdm", "rosbags", "matplotlib",
                      "pillow", "open3d-cpu", "threadpoolctl"],
    extras_require={"gpu": ["torch"], "slam": ["gtsam"], "distributed": ["dask[distributed]"],
                    "baselines": ["map-closures"], "compressed_pcd": ["python-neo-lzf"],
                    "test": ["pytest", "pytest-xdist", "hypothesis", "ruff"]},
    zip_safe=True,
    maintainer="mf_lpr_ros developers",
    maintainer_email="mf-lpr-ros@example.org",
    description="LiDAR place recognition and relocalisation by matched filtering of BEV "
                "occupancy descriptors, for ROS 2 Jazzy.",
    license="BSD-3-Clause",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "mf-lpr = mf_lpr_ros.cli:main",
            "map_builder = mf_lpr_ros.ros.map_builder:main",
            "localiser = mf_lpr_ros.ros.localiser:main",
            "managed_localiser = mf_lpr_ros.ros.managed_localiser:main",
            "pose_graph = mf_lpr_ros.ros.pose_graph:main",
        ],
    },
)
