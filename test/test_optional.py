"""Lazily imported dependencies: one error naming the install, and setup.py / package.xml agree."""

import ast
import re
import sys
from pathlib import Path

import pytest

from mf_lpr_ros.errors import MissingDependencyError
from mf_lpr_ros.optional import DEPENDENCIES, available, require

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("module", sorted(DEPENDENCIES))
def test_a_missing_dependency_names_its_feature_and_install(monkeypatch, module):
    monkeypatch.setitem(sys.modules, module, None)  # makes the import fail
    dependency = DEPENDENCIES[module]
    with pytest.raises(MissingDependencyError) as raised:
        require(module)
    assert f"pip install {dependency.requirement}" in str(raised.value)
    assert dependency.feature in str(raised.value)
    assert not available(module)


def _setup_requirements() -> tuple[set[str], dict[str, list[str]]]:
    call = next(node for node in ast.walk(ast.parse((REPO / "setup.py").read_text()))
                if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "setup")
    keywords = {keyword.arg: ast.literal_eval(keyword.value) for keyword in call.keywords
                if keyword.arg in ("install_requires", "extras_require")}
    return set(keywords["install_requires"]), keywords["extras_require"]


def test_setup_and_package_xml_agree_on_what_is_optional():
    required, extras = _setup_requirements()
    package_xml = (REPO / "package.xml").read_text()
    declared = set(re.findall(r"<exec_depend>python3-([\w-]+?)(?:-pip)?</exec_depend>",
                              package_xml))
    for dependency in DEPENDENCIES.values():
        stem = dependency.module.replace("_", "-")
        if dependency.optional:
            assert extras[dependency.extra] == [dependency.requirement]
            assert dependency.requirement not in required
            assert stem not in declared and dependency.requirement not in declared
        else:
            assert dependency.requirement in required
            assert stem in declared
    # Every pip-installed run-time dependency of package.xml is one of setup.py's.
    pip_names = {"pil": "pillow", "yaml": "pyyaml", "open3d": "open3d-cpu"}
    assert {pip_names.get(name, name) for name in declared} <= required
