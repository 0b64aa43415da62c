"""The layering rules, checked on the source: who may import whom, no cycles, module sizes, one key table.

Imports are read with ``ast`` from every module of ``kvark_ros`` (module level and inside functions
alike), so a lazy import counts the same as a top-level one.
"""
from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from kvark_ros.core.config_schema import KEYS, keys_table
from kvark_ros.core.config_sources import REGENERATE, SETTINGS_PATH, regenerated_config_text, settings_source

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "kvark_ros"
LOWER_LAYERS = ("core", "io")                      # ROS-free, offline-free rules and bag I/O
UPPER_LAYERS = ("tools", "sim", "gap", "ros")
MAX_LINES = 600
MAX_NODE_LINES = 450


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
    """kvark_ros module -> the kvark_ros modules it imports (``from a import b`` counts a.b if it is a module)."""
    modules = {_module_name(path): path for path in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.add(node.module)
                found.update(f"{node.module}.{alias.name}" for alias in node.names)
        graph[name] = {target for target in found if target in modules and target != name}
    return graph


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_core_and_io_import_no_upper_layer():
    graph = _imports()
    offenders = [f"{module} imports {target}" for module, targets in graph.items()
                 if _package(module) in LOWER_LAYERS for target in targets if _package(target) in UPPER_LAYERS]
    offenders += [f"{module} imports {target}" for module, targets in graph.items()
                  if _package(module) == "core" for target in targets if _package(target) == "io"]
    assert not offenders, "\n".join(offenders)


def test_no_command_line_parsing_below_the_commands():
    """``core`` and ``io`` hold rules and bag I/O, not command lines: argparse is imported only by the layers above
    (and ``kvark_ros/cli_options.py``, the options the commands share)."""
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        if _package(_module_name(path)) not in LOWER_LAYERS:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) else [])
            offenders += [str(path.relative_to(ROOT)) for name in names if name == "argparse"]
    assert not offenders, offenders


def test_live_estimation_imports_nothing_of_learning():
    """What the node loads (``core.estimation``, and the shared modules of ``core``) never imports ``core.learning``,
    not even inside a function: learning is a layer above live estimation."""
    graph = _imports()
    live = [module for module in graph if module.startswith("kvark_ros.core") and not
            module.startswith("kvark_ros.core.learning")]
    offenders = [f"{module} imports {target}" for module in live for target in graph[module]
                 if target.startswith("kvark_ros.core.learning")]
    assert not offenders, "\n".join(offenders)


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the directed graph, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for target in sorted(graph.get(node, ())):
            if state.get(target) == 1:
                return stack[stack.index(target):] + [target]
            if target not in state and (found := visit(target)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_no_import_cycle_between_modules_or_between_packages():
    """Package imports (``from kvark_ros.io import x``) resolve to the package facade, which is a module too."""
    graph = _imports()
    cycle = _cycle({module: {t for t in targets if not module.startswith(t + ".")}
                    for module, targets in graph.items()})
    assert cycle is None, " -> ".join(cycle or [])
    packages: dict[str, set[str]] = {}
    for module, targets in graph.items():
        packages.setdefault(_package(module), set()).update(
            _package(t) for t in targets if _package(t) != _package(module) and _package(t))
    cycle = _cycle(packages)
    assert cycle is None, " -> ".join(cycle or [])


def test_module_sizes():
    sizes = {path.relative_to(ROOT).as_posix(): len(path.read_text().splitlines()) for path in PACKAGE.rglob("*.py")}
    too_big = {name: size for name, size in sizes.items() if size > MAX_LINES}
    assert not too_big, too_big
    assert sizes["kvark_ros/ros/estimator_node.py"] <= MAX_NODE_LINES


def test_the_node_loads_no_plotting_fitting_or_offline_module():
    """Imported (against the rclpy stand-in) in a fresh interpreter: no matplotlib, no sklearn, no tools/gap/sim."""
    code = "import json, sys\nimport kvark_ros.ros.estimator_node\nprint(json.dumps(sorted(sys.modules)))"
    stand_in = str(ROOT / "test" / "ros_stand_in")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (stand_in, os.environ.get("PYTHONPATH"))))}
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    loaded = json.loads(done.stdout)
    assert "rclpy" in loaded and "kvark_ros.core.estimation.residual" in loaded
    offenders = [name for name in loaded if name.split(".")[0] in ("matplotlib", "sklearn")
                 or _package(name) in ("tools", "gap", "sim") and name.startswith("kvark_ros.")
                 or name.startswith("kvark_ros.core.learning")]
    assert not offenders, offenders


def test_documented_key_table_is_the_schema():
    """docs/configuration.md's table of configuration keys is ``kvark config --keys`` verbatim."""
    assert keys_table() in (ROOT / "docs" / "configuration.md").read_text(), (
        "docs/configuration.md's table of keys is stale: run `make generated`")


def test_settings_module_is_what_the_key_table_generates():
    """The typed settings (``kvark_ros/core/settings.py``) are generated from KEYS: a new row needs the generator."""
    assert SETTINGS_PATH.read_text() == settings_source(), (f"{SETTINGS_PATH.name} is not what KEYS generates; "
                                                            f"run {REGENERATE}")


@pytest.mark.parametrize("config", sorted((ROOT / "config").glob("*.yaml")), ids=lambda p: p.name)
def test_config_file_comments_are_what_the_key_table_generates(config):
    """Every key of KEYS is in the file, with its table comment; the file's values, notes and prose are its own."""
    text = config.read_text()
    assert regenerated_config_text(text, config.name) == text, (f"{config.name} is not what KEYS generates; "
                                                                f"run {REGENERATE}")


@pytest.mark.parametrize("config", sorted((ROOT / "config").glob("*.yaml")), ids=lambda p: p.name)
def test_every_key_in_the_config_files_is_in_the_schema_and_commented(config):
    """A key line is documented by a comment line just above it (or above its group), or on the line."""
    names = {key.name for key in KEYS}
    lines = config.read_text().splitlines()
    path: list[tuple[int, str]] = []
    for number, line in enumerate(lines):
        match = re.match(r"^(\s*)([A-Za-z_]+):(.*)$", line)
        if not match or match.group(2) in ("kvark_estimator", "ros__parameters"):
            continue
        indent, key, rest = len(match.group(1)), match.group(2), match.group(3)
        path = [(i, k) for i, k in path if i < indent] + [(indent, key)]
        dotted = ".".join(k for _, k in path)
        if rest.strip() and not rest.strip().startswith("#"):
            assert dotted in names, f"{config.name}: {dotted} is not a config key"
            above = lines[number - 1].strip() if number else ""
            assert "#" in rest or above.startswith("#"), f"{config.name}:{number + 1}: {dotted} has no comment"
