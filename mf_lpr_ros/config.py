"""The configuration: descriptor and search parameters (mf_lpr_ros.params) and the map spacing,
with the named presets, YAML and ROS-parameter loading, and the preset files under config/.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from mf_lpr_ros.errors import ConfigError
from mf_lpr_ros.params import (
    DescriptorParams,
    SearchParams,
    field_descriptions,
    require_parameter,
)


@dataclass(frozen=True)
class Config:
    """Everything the pipeline needs: descriptor, search and map-building parameters.

    spacing_m: metres of travel between references when a map is built from scans (the
        paper's 2 m; 0 = every scan a reference).
    auto: the descriptor is still to be derived from the scans (preset "auto",
        mf_lpr_ros/core/auto_params.py); whatever builds a map resolves it from its first
        scans.
    """

    descriptor: DescriptorParams = field(default_factory=DescriptorParams)
    search: SearchParams = field(default_factory=SearchParams)
    spacing_m: float = 2.0
    auto: bool = False

    def __post_init__(self) -> None:
        require_parameter(self.spacing_m >= 0, "spacing_m", ">= 0", self.spacing_m)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    # KITTI HDL-64E at 1.73 m: the band above the ground plane; 0.4 m matches the KITTI BEV images.
    "kitti": {"descriptor": {"voxel_size": 0.4, "z_min": -1.2, "z_max": 3.0}},
    "nclt": {"descriptor": {"voxel_size": 0.75}},
    "oxford": {"descriptor": {"voxel_size": 1.3}},
    "wildplaces": {"descriptor": {"voxel_size": 0.3, "z_min": 1.0, "z_max": 3.0,
                                  "density_threshold": 2.0}},
    # Livox sensors (Mid-360, Avia, ...): sparse or narrow sweeps, described from submaps of the
    # last 3 m of travel (core/submap.py; the window auto gives such sensors, chosen on the
    # tuning sets: docs/RESULTS.md). Levelled with the pose's roll/pitch: a submap needs the
    # poses anyway, and such sensors are often carried by hand or on a drone (the simulated
    # handheld Mid-360: recall@1 0.956 -> 1.000; a level sensor is unchanged; session 27).
    "livox": {"descriptor": {"submap_m": 3.0, "level": True}},
    # Close-range handheld 360-degree scans (median range ~5 m, e.g. the BALM sequence).
    # Levelled with the pose's roll/pitch: a handheld sensor tilts 10 deg typically, 37 at worst.
    # ICP verifies on top of the default distinctiveness and odometry consistency: ICP fitness
    # alone let look-alikes through on a dense handheld sensor in a town, where they verified
    # both (docs/RESULTS.md, session 37).
    "handheld": {"descriptor": {"voxel_size": 0.3, "level": True},
                 "search": {"max_shift_m": 6.0, "min_confidence": 0.28, "verify_fitness": 0.68},
                 "spacing_m": 1.0},
}


CONFIG_KEYS = frozenset({"preset", "descriptor", "search", "spacing_m"})
AUTO_PRESET = "auto"
PRESET_NAMES = tuple(sorted(PRESETS)) + (AUTO_PRESET,)


def preset(name: str) -> Config:
    """The named preset (see PRESETS), or "auto": the defaults, with the descriptor left to be
    derived from the scans (Config.auto)."""
    if name == AUTO_PRESET:
        return Config(auto=True)
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {list(PRESET_NAMES)}")
    return config_from_dict(PRESETS[name])


def config_from_dict(values: Mapping[str, Any], base: Config | None = None) -> Config:
    """A Config from nested mappings; unknown keys are refused by name."""
    base = base or Config()
    _check_keys(values, {f.name for f in fields(Config)} | {"preset"}, "config")
    if "preset" in values:
        base = preset(_coerce("preset", "str", values["preset"]))
    descriptor = _merge(base.descriptor, values.get("descriptor") or {}, "descriptor")
    search = _merge(base.search, values.get("search") or {}, "search")
    spacing = _coerce("spacing_m", "float", values.get("spacing_m", base.spacing_m))
    return Config(descriptor=descriptor, search=search, spacing_m=spacing, auto=base.auto)


def load_config(path: str | Path, base: Config | None = None) -> Config:
    """A Config from a YAML file: Config.to_dict's nesting with an optional 'preset' key, either
    at the top level or inside a ROS 2 parameter file (`<node or /**>: ros__parameters: ...`,
    where other node parameters are ignored)."""
    try:
        values = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        raise ConfigError(f"cannot read config file {path}: {error}") from error
    except RecursionError:
        raise ConfigError(f"config file {path} is nested too deeply to be a configuration") \
            from None
    if not isinstance(values, dict):
        raise ConfigError(f"config file {path} must hold a mapping, not {type(values).__name__}")
    ros_sections = [v["ros__parameters"] for v in values.values()
                    if isinstance(v, dict) and isinstance(v.get("ros__parameters"), dict)]
    if ros_sections:
        values = {}
        for section in ros_sections:
            values.update({k: v for k, v in section.items() if k in CONFIG_KEYS})
    return config_from_dict(values, base)


def flat_parameters(config: Config) -> dict[str, Any]:
    """Config as ROS 2 parameter names and values: 'descriptor.voxel_size', ...; None -> +-inf."""
    flat: dict[str, Any] = {}
    for section in ("descriptor", "search"):
        for item in fields(getattr(config, section)):
            value = getattr(getattr(config, section), item.name)
            if value is None:
                value = -math.inf if item.name.endswith("_min") else math.inf
            flat[f"{section}.{item.name}"] = value
    flat["spacing_m"] = config.spacing_m
    return flat


def parameter_descriptions() -> dict[str, str]:
    """What each flat parameter (flat_parameters' names) means, from the classes' docstrings."""
    descriptions = {f"{section}.{name}": text
                    for section, params_class in (("descriptor", DescriptorParams),
                                                  ("search", SearchParams))
                    for name, text in field_descriptions(params_class).items()}
    descriptions["spacing_m"] = field_descriptions(Config)["spacing_m"]
    return descriptions


def config_from_flat(values: Mapping[str, Any], base: Config | None = None) -> Config:
    """Inverse of flat_parameters (plus an optional 'preset'); unknown names are refused."""
    nested: dict[str, Any] = {}
    for name, value in values.items():
        section, _, key = name.rpartition(".")
        if section:
            nested.setdefault(section, {})[key] = value
        else:
            nested[key] = value
    return config_from_dict(nested, base)


def preset_file_text(name: str) -> str:
    """config/<name>.yaml: the preset written out in full as a ROS 2 parameter file."""
    flat = flat_parameters(preset(name))
    lines = [f"# mf_lpr_ros parameters, preset {name!r} written out in full.",
             "# A ROS 2 parameter file for every mf_lpr_ros node:",
             f"#   ros2 run mf_lpr_ros localiser --ros-args --params-file config/{name}.yaml",
             f"# and for the offline tools: mf-lpr ... --config config/{name}.yaml",
             "# Meanings: docs/PARAMETERS.md; .inf / -.inf mean unbounded.",
             "/**:", "  ros__parameters:", f"    preset: {name}"]
    for section in ("descriptor", "search"):
        lines.append(f"    {section}:")
        lines += [f"      {key.split('.', 1)[1]}: {_yaml_scalar(value)}"
                  for key, value in flat.items() if key.startswith(section + ".")]
    lines.append(f"    spacing_m: {_yaml_scalar(flat['spacing_m'])}")
    return "\n".join(lines) + "\n"


def write_preset_files(folder: Path) -> list[Path]:
    """folder/<name>.yaml (preset_file_text) for every named preset, each written atomically."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name in sorted(PRESETS):
        path = folder / f"{name}.yaml"
        temporary = path.with_name(f".{path.name}.tmp")
        temporary.write_text(preset_file_text(name))
        os.replace(temporary, path)
        written.append(path)
    return written


def _yaml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and math.isinf(value):
        return ".inf" if value > 0 else "-.inf"
    return str(value)


def descriptor_params_from_dict(values: Mapping[str, Any]) -> DescriptorParams:
    return _merge(DescriptorParams(), values, "descriptor")


def _merge(current: Any, overrides: Mapping[str, Any], section: str) -> Any:
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"{section} must be a mapping")
    known = {f.name: f.type for f in fields(current)}
    _check_keys(overrides, set(known), section)
    coerced = {name: _coerce(name, known[name], value) for name, value in overrides.items()}
    try:
        return dataclasses.replace(current, **coerced)
    except TypeError as error:
        raise ConfigError(f"{section}: {error}") from error


def _coerce(name: str, annotation: str, value: Any) -> Any:
    """A value of the field's type; ROS parameter files and --ros-args give ints for floats,
    and +-inf stands for "unbounded" where the field is optional (YAML null is not a ROS type)."""
    optional = annotation.endswith("| None")
    kind = annotation.split("|")[0].strip()
    if value is None:
        if optional:
            return None
        raise ConfigError(f"parameter {name} must be a {kind}, got None")
    try:
        if kind == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise TypeError
            return bool(value)
        if kind == "int":
            if isinstance(value, bool) or float(value) != int(value):
                raise TypeError
            return int(value)
        if kind == "float":
            if isinstance(value, bool):
                raise TypeError
            number = float(value)
            if optional and math.isinf(number):
                return None
            if not math.isfinite(number):
                raise TypeError
            return number
        if kind == "str":
            if not isinstance(value, str):
                raise TypeError
            return value
    except (TypeError, ValueError):
        raise ConfigError(f"parameter {name} must be a {'finite ' if kind == 'float' else ''}"
                          f"{kind}, got {value!r}") from None
    raise AssertionError(f"unhandled field type {annotation}")


def _check_keys(values: Mapping[str, Any], allowed: set[str], section: str) -> None:
    unknown = sorted(set(values) - allowed)
    if unknown:
        raise ConfigError(f"unknown {section} parameter(s) {unknown}; known: {sorted(allowed)}")
