"""Shared fixtures: the real data folder (skip when absent) and a generated world."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from mf_lpr_ros.config import preset
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan
from mf_lpr_ros.sim.synthetic import make_world, route, scan_world

REPO = Path(__file__).resolve().parents[1]


def _ros_domain() -> int:
    """A DDS domain for this test process (1-230, Fast DDS's UDP range): by the run's pid, and
    under pytest-xdist (make test) one per worker of the run, so that two workers never share
    one."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw"):
        return 1 + os.getpid() % 100
    return 1 + (os.getppid() % 23) * 10 + int(worker[2:]) % 10


# Tests talk over real DDS: keep them on this host, on a domain of their own.
os.environ["ROS_DOMAIN_ID"] = str(_ros_domain())
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


# make test runs the suite in two phases (Makefile): "parallel", the tests not marked realtime,
# in worker processes; then "realtime", those alone, as a loaded machine would drop what they
# stream. Unset: every test.
TEST_PHASES = ("parallel", "realtime")


def pytest_collection_modifyitems(config, items) -> None:
    """Mark what each test needs: ros for test/ros/ and the ROS graph fixture, real_data for
    the real-data fixture (markers are registered in setup.cfg); keep the tests of
    $MF_LPR_TEST_PHASE. The files holding a slow test run first: make test hands whole files
    to its processes as each gets free, and a long file handed out last keeps one busy while
    the other waits."""
    ros_folder = Path(__file__).parent / "ros"
    for item in items:
        if ros_folder in Path(item.fspath).parents or "ros_graph" in item.fixturenames:
            item.add_marker(pytest.mark.ros)
        if "data_dir" in item.fixturenames:
            item.add_marker(pytest.mark.real_data)
    phase = os.environ.get("MF_LPR_TEST_PHASE", "")
    if phase:
        if phase not in TEST_PHASES:
            raise pytest.UsageError(f"MF_LPR_TEST_PHASE must be one of {TEST_PHASES} or unset, "
                                    f"got {phase!r}")
        realtime = phase == "realtime"
        kept, deselected = [], []
        for item in items:
            (kept if bool(item.get_closest_marker("realtime")) == realtime
             else deselected).append(item)
        if deselected:
            config.hook.pytest_deselected(items=deselected)
            items[:] = kept
    slow_files = {item.fspath for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.fspath not in slow_files)


def data_root() -> Path | None:
    candidate = Path(os.environ.get("MF_LPR_DATA", REPO.parent / "shared" / "data"))
    return candidate if candidate.is_dir() else None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    root = data_root()
    if root is None:
        pytest.skip("real data not found: set MF_LPR_DATA or place shared/data beside the repo")
    return root


@pytest.fixture
def ros_graph():
    from mf_lpr_ros.ros.graph import RosGraph

    graph = RosGraph()
    yield graph
    graph.close()


@pytest.fixture(scope="session")
def world():
    return make_world(seed=3)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="module")
def synthetic_map(tmp_path_factory, world):
    """A kitti-preset map of one traversal of the generated world, and scans (points, pose) of
    a second traversal (1 m aside, reversed)."""
    rng = np.random.default_rng(11)
    path = tmp_path_factory.mktemp("maps") / "synthetic.mfmap"
    builder = MapBuilder(preset("kitti"), path)
    for index, (x, y, yaw) in enumerate(route(45)):
        points, pose = scan_world(world, x, y, yaw, rng)
        builder.offer(PairedScan(index, 100.0 + index, points, pose))
    builder.save()
    queries = [scan_world(world, x, y, yaw, rng)
               for x, y, yaw in route(10, lateral_offset_m=1.0, reverse=True)]
    return path, queries
