"""Dependencies imported only where a feature needs them, with one error type and install hint.

DEPENDENCIES lists each with the feature it enables and the pip requirement that installs it.
Optional ones are setup.py extras and absent from package.xml; open3d is declared required by
both (the user's design names it) but still imported lazily, because its import can fail at run
time (Debian's libusb-1.0-0 missing) and only ICP needs it. test_optional.py checks the three
agree.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType

from mf_lpr_ros.errors import MissingDependencyError


@dataclass(frozen=True)
class OptionalDependency:
    module: str
    feature: str
    requirement: str
    extra: str | None = None

    @property
    def optional(self) -> bool:
        return self.extra is not None


DEPENDENCIES = {dependency.module: dependency for dependency in (
    OptionalDependency("open3d", "ICP refinement and verification (search.verify_fitness, --icp)",
                       "open3d-cpu"),
    OptionalDependency("threadpoolctl", "a search on several threads (search.threads)",
                       "threadpoolctl"),
    OptionalDependency("torch", "the torch search backend (search.backend torch)", "torch",
                       "gpu"),
    OptionalDependency("gtsam", "the pose graph (slam-eval, the pose_graph node)", "gtsam",
                       "slam"),
    OptionalDependency("distributed", "Dask scheduling (--scheduler)", "dask[distributed]",
                       "distributed"),
    OptionalDependency("map_closures", "the MapClosures baseline (--methods map-closures)",
                       "map-closures", "baselines"),
    OptionalDependency("lzf", "reading PCD files saved as DATA binary_compressed",
                       "python-neo-lzf", "compressed_pcd"),
)}


def require(module: str) -> ModuleType:
    """Import a lazily imported dependency, or raise MissingDependencyError naming the feature that
    needs it and how to install it."""
    dependency = DEPENDENCIES[module.partition(".")[0]]
    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise MissingDependencyError(
            f"{dependency.feature} needs {dependency.module}, which failed to import ({error}); "
            f"install it with 'pip install {dependency.requirement}' (make setup does)"
        ) from error


def available(module: str) -> bool:
    """Whether a lazily imported dependency imports, without raising."""
    try:
        require(module)
    except MissingDependencyError:
        return False
    return True
