"""The errors the package raises on wrong input, one type per kind of input.

Each message names the offending parameter, file, cloud or pose and what is wrong with it, so
callers (the CLI, the nodes) can report it as it is. All but MissingDependencyError and
UnitFailure are ValueErrors or MapFileError's RuntimeError, as before the move here.
"""

from __future__ import annotations


class ConfigError(ValueError):
    """A parameter value is invalid; the message names the parameter."""


class ParameterFault(ConfigError):
    """A node parameter, or a combination of them, is refused at start-up; the message names it."""


class DatasetError(ValueError):
    """A dataset folder or file is not in a layout we can read; the message says what is wrong."""


class MapFileError(RuntimeError):
    """A map file cannot be used; the message names the file and the problem."""


class MapParameterMismatch(MapFileError):
    """The map was built with descriptor parameters other than the ones requested."""


class InvalidCloudError(ValueError):
    """A point cloud cannot be turned into a descriptor; the message says why."""


class InvalidPoseError(ValueError):
    """A pose sample cannot be used; the message says why."""


class MissingDependencyError(RuntimeError):
    """An optional package this feature needs is not installed; the message says how to."""


class UnitFailure(RuntimeError):
    """Work units of a distributed job failed; the message names each one and its error."""
