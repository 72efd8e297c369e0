"""Declaring node parameters on an rclpy node: typed, checked at start-up, frozen afterwards.

What each node's parameters are, mean and allow, and how they combine, lives ROS-free in
mf_lpr_ros/live/node_settings.py (the nodes' own) and mf_lpr_ros/params.py (descriptor.*,
search.*); this module only declares them. A refused value raises ParameterFault, which
run_node reports and turns into exit status 2.
"""

from __future__ import annotations

import importlib
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException
from rclpy.parameter import Parameter

from mf_lpr_ros.config import (
    Config,
    config_from_flat,
    flat_parameters,
    parameter_descriptions,
    preset,
)
from mf_lpr_ros.errors import ConfigError, ParameterFault
from mf_lpr_ros.live.node_settings import POSE_SOURCES, PRESET, NodeParameter


def pose_source_topic(source: str) -> tuple[str, type]:
    """The topic and message class of a pose_source value."""
    topic, type_name = POSE_SOURCES[source]
    package, name = type_name.split("/")
    return topic, getattr(importlib.import_module(f"{package}.msg"), name)


class NodeParameters:
    """Parameter declaration for rclpy Node and LifecycleNode classes alike."""

    def declare_config(self) -> tuple[Config, dict[str, Any]]:
        """The preset named by 'preset' with every 'descriptor.*', 'search.*' and 'spacing_m'
        parameter given explicitly (params file or --ros-args -p) applied on top. Returns the
        config and the explicit values; effective values are written back for `ros2 param`."""
        base_name = self.declare_node_parameters((PRESET,))[PRESET.name]
        try:
            base = preset(base_name)
        except ConfigError as error:
            raise ParameterFault(str(error)) from None
        descriptions = parameter_descriptions()
        explicit: dict[str, Any] = {}
        for name in flat_parameters(base):
            self.declare_parameter(name, None, ParameterDescriptor(
                dynamic_typing=True, description=descriptions[name]))
            value = self.get_parameter(name).value
            if value is not None:
                explicit[name] = list(value) if isinstance(value, (list, tuple)) else value
        try:
            config = config_from_flat(explicit, base)
        except ConfigError as error:
            raise ParameterFault(str(error)) from None
        self.set_parameters([Parameter(name, value=value)
                             for name, value in flat_parameters(config).items()])
        return config, explicit

    def declare_node_parameters(self, parameters: tuple[NodeParameter, ...]) -> dict[str, Any]:
        """Declare each parameter with its default and description; its checked value by name."""
        values = {}
        for parameter in parameters:
            try:
                value = self.declare_parameter(parameter.name, parameter.default,
                                               ParameterDescriptor(
                                                   description=parameter.description)).value
            except ParameterException as error:
                raise ParameterFault(f"parameter {parameter.name}: {error}") from None
            values[parameter.name] = parameter.check(value)
        return values

    def freeze_parameters(self) -> None:
        """Parameters are read at start-up; refuse later changes instead of ignoring them."""
        self.add_on_set_parameters_callback(lambda _: SetParametersResult(
            successful=False, reason="mf_lpr_ros reads its parameters at start-up; restart "
                                     "the node to change them"))
