"""Docs that cannot drift: the generated reference pages equal what the code generates, every
parameter has a meaning, and every repository path and parameter name the docs, docstrings and
comments mention exists."""

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

import mf_lpr_ros
from mf_lpr_ros.cli.reference_docs import PAGES
from mf_lpr_ros.config import flat_parameters, parameter_descriptions, preset
from mf_lpr_ros.live.node_settings import NODE_SETTINGS, PRESET

REPOSITORY = Path(mf_lpr_ros.__file__).parent.parent
PACKAGE_FOLDERS = ("core", "io", "datasets", "live", "pipeline", "evaluation", "sim", "ros", "cli")
TOP_FOLDERS = ("mf_lpr_ros", "test", "docs", "config", "benchmarks", "launch", "scripts",
               "resource", ".ci")
_PATH = re.compile(r"(?<![\w./-])((?:"
                   + "|".join(re.escape(folder) for folder in TOP_FOLDERS + PACKAGE_FOLDERS)
                   + r")/[\w./-]*\w)")
_FILE = re.compile(r"(?<![\w./-])(\w+\.py)\b")
_METHOD_PARAMETER = re.compile(r"(?<![\w.])((?:descriptor|search)\.(?!py\b)[a-z_]+)\b(?!\()")
_ROS_ARGUMENT = re.compile(r"-p\s+([\w.]+):=")


def _documents() -> list[Path]:
    return [REPOSITORY / "README.md", *sorted((REPOSITORY / "docs").glob("*.md"))]


def _sources() -> list[Path]:
    return sorted(path for folder in ("mf_lpr_ros", "benchmarks", "launch", "test", "scripts")
                  for path in (REPOSITORY / folder).rglob("*.py"))


def _prose(path: Path) -> str:
    """What a reader is told: a document whole; of a source file, its docstrings and comments."""
    text = path.read_text()
    if path.suffix != ".py":
        return text
    parts = [token.string for token in tokenize.generate_tokens(io.StringIO(text).readline)
             if token.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            docstring = ast.get_docstring(node)
            if docstring:
                parts.append(docstring)
    return "\n".join(parts)


def _known_files() -> set[str]:
    return {path.name for path in REPOSITORY.rglob("*")
            if ".venv" not in path.parts and ".git" not in path.parts}


def _missing_path(reference: str) -> bool:
    reference = reference.rstrip(".")
    if "<" in reference or "*" in reference:
        return False
    candidates = [REPOSITORY / reference]
    if reference.split("/")[0] in PACKAGE_FOLDERS:
        candidates.append(REPOSITORY / "mf_lpr_ros" / reference)
    return not any(candidate.exists() for candidate in candidates)


def _node_parameter_names() -> set[str]:
    return {PRESET.name} | {parameter.name for settings_class, _ in NODE_SETTINGS.values()
                            for parameter in settings_class.PARAMETERS}


@pytest.mark.parametrize("name", sorted(PAGES))
def test_generated_pages_equal_the_code(name):
    path = REPOSITORY / "docs" / name
    assert path.read_text() == PAGES[name](), \
        f"docs/{name} is stale: run `mf-lpr docs --write docs`"


def test_every_parameter_has_a_meaning():
    descriptions = parameter_descriptions()
    assert set(descriptions) == set(flat_parameters(preset("default")))
    assert all(len(text) > 10 for text in descriptions.values())
    for settings_class, _ in NODE_SETTINGS.values():
        assert all(len(p.description) > 10 for p in settings_class.PARAMETERS), settings_class


def test_every_repository_path_mentioned_exists():
    known_files = _known_files()
    missing = []
    for path in _documents() + _sources():
        prose = _prose(path)
        where = path.relative_to(REPOSITORY)
        missing += [f"{where}: {reference}" for reference in _PATH.findall(prose)
                    if _missing_path(reference)]
        missing += [f"{where}: {name}" for name in _FILE.findall(prose)
                    if name not in known_files]
    assert not missing, missing


def test_every_parameter_name_mentioned_exists():
    method = set(flat_parameters(preset("default")))
    node = _node_parameter_names()
    unknown = []
    for path in _documents() + _sources() + sorted((REPOSITORY / "launch").glob("*.py")):
        prose = _prose(path)
        where = path.relative_to(REPOSITORY)
        unknown += [f"{where}: {name}" for name in _METHOD_PARAMETER.findall(prose)
                    if name not in method]
        unknown += [f"{where}: -p {name}" for name in _ROS_ARGUMENT.findall(prose)
                    if name not in method | node]
    assert not unknown, unknown


def test_the_checks_catch_a_renamed_file_and_parameter(tmp_path):
    assert _missing_path("mf_lpr_ros/verification.py")
    assert not _missing_path("core/verification.py")
    assert _METHOD_PARAMETER.findall("set search.top_k to 3") == ["search.top_k"]
    assert "search.top_k" not in set(flat_parameters(preset("default")))
    assert _ROS_ARGUMENT.findall("--ros-args -p map_file:=x") == ["map_file"]
    assert "map_file" not in _node_parameter_names()


LAUNCH_NODES = {"localiser.launch.py": "localiser",
                "localiser_managed.launch.py": "managed_localiser",
                "map_builder.launch.py": "map_builder"}


@pytest.mark.parametrize("launch_file, node", sorted(LAUNCH_NODES.items()))
def test_launch_arguments_default_to_the_node_parameters(launch_file, node):
    """A launch argument named as a node parameter starts from that parameter's default, so a
    changed default cannot drift between the node and its launch file."""
    tree = ast.parse((REPOSITORY / "launch" / launch_file).read_text())
    arguments = next(ast.literal_eval(statement.value) for statement in tree.body
                     if isinstance(statement, ast.Assign)
                     and getattr(statement.targets[0], "id", "") == "ARGUMENTS")
    settings_class, _ = NODE_SETTINGS[node]
    defaults = {p.name: p.default for p in settings_class.PARAMETERS}
    defaults[PRESET.name] = PRESET.default
    shared = set(arguments) & set(defaults)
    assert {"preset", "map_path", "pose_source"} <= shared
    assert {name: arguments[name][0] for name in shared} == \
        {name: str(defaults[name]) for name in shared}
