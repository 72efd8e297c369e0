"""The nodes' settings, ROS-free: each parameter's check, and every combination refused by name
before any map is opened."""

import dataclasses

import numpy as np
import pytest

from mf_lpr_ros.config import preset
from mf_lpr_ros.errors import ParameterFault
from mf_lpr_ros.live.node_settings import (
    NODE_SETTINGS,
    LocaliserSettings,
    MapBuilderSettings,
    PoseGraphSettings,
)


def _defaults(settings_class, **overrides):
    values = {p.name: p.default for p in settings_class.PARAMETERS}
    values.update(overrides)
    return values


def _localiser(config=None, **overrides):
    values = _defaults(LocaliserSettings, **{"map_path": "site.mfmap", **overrides})
    for parameter in LocaliserSettings.PARAMETERS:
        parameter.check(values[parameter.name])
    return LocaliserSettings.from_values(config or preset("default"), {}, values)


def test_every_node_parameter_is_declared_once_per_node():
    for settings_class, _ in NODE_SETTINGS.values():
        names = [p.name for p in settings_class.PARAMETERS]
        assert len(names) == len(set(names)), settings_class


def test_defaults_pass_their_own_checks():
    for settings_class, _ in NODE_SETTINGS.values():
        for parameter in settings_class.PARAMETERS:
            assert parameter.check(parameter.default) == parameter.default


def test_localiser_defaults_resolve_publish_mode_by_mode():
    assert _localiser().publish_mode == "on_request"
    closing = _localiser(mode="loop_closure", pose_source="odom", map_path="")
    assert closing.publish_mode == "continuous" and closing.inputs.has_poses
    assert _localiser(publish_mode="continuous").publish_mode == "continuous"


@pytest.mark.parametrize("overrides, named", [
    ({"mode": "relocalise", "map_path": ""}, "map_path"),
    ({"loop_closure_format": ["lio_sam"]}, "lio_sam needs mode loop_closure"),
    ({"mode": "loop_closure"}, "pose_source"),
    ({"extrinsic": [0, 0, 0, 0, 0, 0, 2.0]}, "extrinsic"),
])
def test_localiser_combinations_are_refused_by_name(overrides, named):
    with pytest.raises(ParameterFault, match=named):
        _localiser(**overrides)


def test_a_map_of_unknown_headings_is_refused_where_poses_are_published():
    kitti = preset("kitti")
    unknown = dataclasses.replace(kitti, search=dataclasses.replace(kitti.search,
                                                                    map_headings="unknown"))
    for mode in ("relocalise", "loop_closure"):
        with pytest.raises(ParameterFault, match="search.map_headings must be 'known'"):
            _localiser(unknown, mode=mode, pose_source="odom")
    assert _localiser(kitti).config.search.map_headings == "known"


def test_auto_is_refused_in_loop_closure_mode_before_any_map():
    with pytest.raises(ParameterFault, match="preset: auto"):
        _localiser(preset("auto"), mode="loop_closure", pose_source="odom")


@pytest.mark.parametrize("name, value", [
    ("mode", "slam"), ("publish_mode", "sometimes"), ("request_timeout_s", 0.0),
    ("loop_closure_format", []), ("loop_closure_format", ["rtabmap"]), ("pose_source", "gps"),
    ("extrinsic", [0.0] * 6), ("extrinsic", [0, 0, float("nan"), 0, 0, 0, 1]),
    ("max_points", 0), ("future_tolerance_s", -1.0), ("exclude_recent_s", -1.0),
])
def test_a_bad_value_names_its_parameter(name, value):
    parameter = next(p for p in LocaliserSettings.PARAMETERS if p.name == name)
    with pytest.raises(ParameterFault, match=f"parameter {name} must be"):
        parameter.check(value)


def test_extrinsic_becomes_the_sensor_pose_on_the_robot():
    yaw = np.pi / 2
    settings = _localiser(extrinsic=[1.0, 2.0, 3.0, 0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
    assert np.allclose(settings.inputs.extrinsic[:3, 3], [1, 2, 3])
    assert np.allclose(settings.inputs.extrinsic[:2, :2], [[0, -1], [1, 0]])


def test_map_builder_refuses_auto_with_a_global_map_topic():
    values = _defaults(MapBuilderSettings, global_map_topic="map")
    with pytest.raises(ParameterFault, match="preset: auto"):
        MapBuilderSettings.from_values(preset("auto"), values)
    assert MapBuilderSettings.from_values(preset("kitti"), values).global_map_topic == "map"
    assert MapBuilderSettings.from_values(preset("auto"), _defaults(MapBuilderSettings)
                                          ).inputs.pose_source == "odom"


def test_pose_graph_settings():
    settings = PoseGraphSettings.from_values(_defaults(PoseGraphSettings, keyframe_spacing_m=2.0))
    assert settings.keyframe_spacing_m == 2.0 and settings.reliable is False
