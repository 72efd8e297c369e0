"""The layering README's "Architecture" section describes: imports only run down the layers,
the core never needs ROS, and the public API is importable from the package."""

import ast
import subprocess
import sys
from pathlib import Path

import mf_lpr_ros

PACKAGE = Path(mf_lpr_ros.__file__).parent
REPOSITORY = PACKAGE.parent
# Lowest first: a module may import from its own layer and the layers before it. The package
# itself ("mf_lpr_ros", its __init__: the public API) is the top, so no module may import it.
LAYERS = ["version", "errors", "params", "config", "optional", "progress", "core", "io",
          "datasets", "live", "pipeline", "sim", "evaluation", "ros", "cli", ""]


def _layer(module: str) -> int:
    first = module.split(".")[1] if "." in module else ""
    return LAYERS.index(first) if first in LAYERS else -1


def _imports(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {name for name in found if name.split(".")[0] == "mf_lpr_ros"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    return ".".join(("mf_lpr_ros",) + (parts[:-1] if parts[-1] == "__init__" else parts))


def _modules() -> dict[str, Path]:
    """Every module of the package, __init__ files included (a package is named as itself)."""
    return {_module_name(path): path for path in PACKAGE.rglob("*.py")}


def test_every_module_belongs_to_a_layer():
    assert all(_layer(module) >= 0 for module in _modules()), \
        [module for module in _modules() if _layer(module) < 0]


def test_imports_only_run_down_the_layers():
    upward = [f"{module} imports {imported}" for module, path in _modules().items()
              for imported in _imports(path) if _layer(imported) > _layer(module)]
    assert not upward, upward


def test_the_layer_rule_catches_an_import_of_the_package_itself():
    assert _layer("mf_lpr_ros") > max(_layer(module) for module in _modules()
                                      if module != "mf_lpr_ros")
    assert _layer("mf_lpr_ros.cli") < _layer("mf_lpr_ros")


def test_version_agrees_with_setup_and_package_xml():
    version = mf_lpr_ros.__version__
    assert f'version="{version}"' in (REPOSITORY / "setup.py").read_text()
    assert f"<version>{version}</version>" in (REPOSITORY / "package.xml").read_text()


def test_relative_imports_are_not_used():
    relative = [module for module, path in _modules().items()
                if any(isinstance(node, ast.ImportFrom) and node.level > 0
                       for node in ast.walk(ast.parse(path.read_text())))]
    assert not relative, relative


def test_nothing_outside_ros_imports_rclpy():
    script = (
        "import importlib, pkgutil, sys, mf_lpr_ros\n"
        "for info in pkgutil.walk_packages(mf_lpr_ros.__path__, 'mf_lpr_ros.'):\n"
        "    if info.name.startswith('mf_lpr_ros.ros') or info.name.endswith('torch_backend'):\n"
        "        continue\n"
        "    importlib.import_module(info.name)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'rcl_interfaces')))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True
    )
    assert result.stdout.strip() == "[]"


def test_public_api():
    for name in mf_lpr_ros.__all__:
        assert getattr(mf_lpr_ros, name) is not None
    assert {
        "Config",
        "load_config",
        "ReferenceMap",
        "MatchedFilterIndex",
        "MatchResult",
        "Localiser",
        "MapBuilder",
        "build_map",
        "open_source",
        "errors",
    } <= set(mf_lpr_ros.__all__)
