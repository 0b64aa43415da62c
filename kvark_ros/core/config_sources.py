"""What the key table generates (``config_schema.KEYS``): the typed settings module, the key comments of config
files and docs/configuration.md's table of keys. ``make generated`` writes them after a change to the table::

    python -m kvark_ros.tools.generate_sources --write-settings --write-configs --write-keys-doc docs/configuration.md

The tests compare each generated file with what this module makes now and name the command when one is stale.
``kvark init`` writes its configs through ``config_text`` too.
"""
from __future__ import annotations

import json
import re
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from kvark_ros.core.config import applies_to
from kvark_ros.core.config_schema import OPEN_CHOICES, GROUPS, KEYS, KEYS_BY_NAME, NODE_NAME, Key, keys_table

# Generated sources: the typed settings module and the key comments of the config files (module docstring).
SETTINGS_PATH = Path(__file__).with_name("settings.py")
CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
REGENERATE = "make generated"
COMMENT_WIDTH = 110                        # generated comment lines of a config file
_SOURCE_WIDTH = 120


def settings_class(group: str) -> str:
    """The settings dataclass of a group of keys: ``FilterSettings`` for ``filter.*``."""
    return "".join(part.title() for part in group.split("_")) + "Settings"


def describe(key: Key, default: bool = True) -> str:
    """A key's comment: its meaning, what it accepts, its default (``default``) and whether it changes at run time."""
    text = f"{key.meaning}. Allowed: {key.documented}."
    if default:
        text += " Required." if key.default is None else f" Default: {flow_value(key.default)}."
    return text + (" Can be changed while the node runs." if key.runtime else "")


def _annotation(key: Key) -> str:
    """The type of a key's value in its settings class, as source (lists become tuples)."""
    if key.kind == "choice" and key.name not in OPEN_CHOICES:
        return f"Literal[{', '.join(json.dumps(choice) for choice in key.choices)}]"
    return {"number": "float", "integer": "int", "names": "tuple[str, ...]", "per_joint": "tuple[float, ...]",
            "vector3": "tuple[float, float, float]",
            "vector6": "tuple[float, float, float, float, float, float]"}.get(key.kind, "str")


def _python(value: Any) -> str:
    """A default as Python source (lists become tuples, as the config holds them)."""
    if isinstance(value, list):
        return repr(tuple(value))
    return json.dumps(value, ensure_ascii=False) if isinstance(value, str) else repr(value)


def _field(name: str, annotation: str, default: str | None, doc: str) -> list[str]:
    """One dataclass field with its docstring, wrapped to the source width."""
    line = f"    {name}: {annotation}" + ("" if default is None else f" = {default}")
    if len(line) > _SOURCE_WIDTH and "[" in annotation:
        head, _, rest = line.partition("[")
        items = textwrap.wrap(rest, _SOURCE_WIDTH - len(head) - 1, break_on_hyphens=False, break_long_words=False)
        line = f"\n{' ' * (len(head) + 1)}".join([f"{head}[{items[0]}", *items[1:]])
    if '"""' in doc or "\\" in doc or doc.endswith('"'):
        raise ValueError(f"{name}: a meaning with a backslash or ending in a quote cannot be a docstring: {doc}")
    text = textwrap.wrap(f'"""{doc}"""', _SOURCE_WIDTH - 4, break_on_hyphens=False, break_long_words=False)
    return [line, *(f"    {part}" for part in text)]


def _fields(keys: list[Key]) -> list[str]:
    """The fields of a settings class, one a key, in the table's order."""
    lines: list[str] = []
    for position, key in enumerate(keys):
        if key.default is None and any(k.default is not None for k in keys[:position]):
            raise ValueError(f"required key {key.name} follows a key with a default in its group: move its row up")
        default = None if key.default is None else _python(key.default)
        lines += _field(key.attr, _annotation(key), default, describe(key, default=False))
    return lines


def settings_source() -> str:
    """The source of ``kvark_ros/core/settings.py``: a frozen dataclass per group of KEYS and ``EstimatorConfig``."""
    groups = [group for group in GROUPS if group != "payload"]
    lines = ['"""Typed settings of the configuration: one frozen dataclass per group of keys, and ``EstimatorConfig``.',
             "",
             "Generated from config_schema.KEYS by `python -m kvark_ros.tools.generate_sources --write-settings` (or",
             "`make generated`); do not edit: change the key table and regenerate (the tests check this file).",
             '"""', "from __future__ import annotations", "", "from dataclasses import dataclass, field",
             "from typing import Literal", "", "from kvark_ros.core.estimation.payload import Payload", ""]
    names = ", ".join(json.dumps(name) for name in [*map(settings_class, groups), "EstimatorConfig",
                                                    "SETTINGS_BY_GROUP"])
    lines += textwrap.wrap(f"__all__ = [{names}]", _SOURCE_WIDTH, subsequent_indent=" " * 11)
    for group in groups:
        lines += ["", "", "@dataclass(frozen=True)", f"class {settings_class(group)}:",
                  f'    """The ``{group}`` keys of the config (config_schema.KEYS)."""', ""]
        lines += _fields([key for key in KEYS if key.group == group])
    lines += ["", "", "@dataclass(frozen=True)", "class EstimatorConfig:",
              '    """Validated estimator settings (config_schema.KEYS). Units SI; see config/panda.yaml."""', ""]
    lines += _fields([key for key in KEYS if key.group is None])
    lines += _field("payload", "Payload | None", "None", "the robot_model.payload.* keys: the known payload at the "
                    "flange, or None when its mass is 0")
    for group in groups:
        lines += _field(group, settings_class(group), f"field(default_factory={settings_class(group)})",
                        f"the {group}.* keys")
    lines += ["", "    @property", "    def n_joints(self) -> int:",
              '        """Number of estimated joints (``robot_model.joint_names``)."""',
              "        return len(self.joint_names)", "", "",
              "# Group name -> its settings class (robot_model.payload.* becomes ``EstimatorConfig.payload`` instead).",
              "SETTINGS_BY_GROUP: dict[str, type] = {"]
    lines += [f'    "{group}": {settings_class(group)},' for group in groups] + ["}"]
    return "\n".join(lines) + "\n"


def flow_value(value: Any, column: int = 0) -> str:
    """A value in YAML flow style, strings quoted only when needed; a list longer than the comment width
    continues on lines indented to its opening bracket (``column``: the bracket's column)."""
    text = yaml.safe_dump([value], default_flow_style=True, allow_unicode=True, width=10**6).strip()[1:-1]
    if not isinstance(value, list) or column + len(text) <= COMMENT_WIDTH:
        return text
    lines = textwrap.wrap(text[1:-1], COMMENT_WIDTH - column - 2, break_on_hyphens=False, break_long_words=False)
    return "[" + f"\n{' ' * (column + 1)}".join(lines) + "]"


def comment_lines(text: str, name: str) -> list[str]:
    """``text`` as wrapped comment lines for the key or group ``name`` (without its indentation)."""
    width = COMMENT_WIDTH - 2 * (name.count(".") + 2) - 2
    return [f"# {line}" for line in textwrap.wrap(text, width, break_on_hyphens=False, break_long_words=False)]


@dataclass
class ConfigDocument:
    """What a config file holds besides the key table's text (the table gives every key's first comment lines).

    ``header``: comment lines above the node's key; ``node_key``: that key (``kvark_estimator``, or
    ``/**/kvark_estimator`` for the node in any namespace); ``values``: dotted key -> value (absent: its default);
    ``notes``: dotted key -> this file's comment lines below the table's, after a lone ``#``; ``prose``: dotted key
    or group -> comment lines above it, set apart from a key's comment by a blank line ('' = after the last key).
    Lines are stripped of their indentation.
    """

    header: list[str] = field(default_factory=list)
    values: dict[str, Any] = field(default_factory=dict)
    node_key: str = NODE_NAME
    notes: dict[str, list[str]] = field(default_factory=dict)
    prose: dict[str, list[str]] = field(default_factory=dict)


def _key_tree() -> dict[str, Any]:
    """KEYS nested as the YAML nests them (group -> ... -> Key), in the table's order."""
    tree: dict[str, Any] = {}
    for key in KEYS:
        *groups, leaf = key.name.split(".")
        node = tree
        for group in groups:
            node = node.setdefault(group, {})
        node[leaf] = key
    return tree


def config_text(document: ConfigDocument) -> str:
    """The config file: the header, then every key of KEYS in the table's order, each with the table's comment
    (``describe``) and the document's notes, prose and value. ``kvark init`` and ``--write-configs`` write this."""
    unknown = sorted(set(document.values) - set(KEYS_BY_NAME))
    if unknown:
        raise ValueError(f"unknown key '{unknown[0]}'")
    lines = [*document.header, f"{document.node_key}:", "  ros__parameters:"]

    def emit(node: dict[str, Any], path: str, depth: int) -> None:
        indent = "  " * depth
        for position, (name, item) in enumerate(node.items()):
            dotted = f"{path}{name}"
            prose = [f"{indent}{line}" if line else "" for line in document.prose.get(dotted, [])]
            lines.extend([""] * (depth == 2 and position > 0) + prose)
            if isinstance(item, dict):
                lines.append(f"{indent}{name}:")
                emit(item, f"{dotted}.", depth + 1)
                continue
            value = document.values.get(dotted, item.default)
            if value is None:
                raise ValueError(f"required key '{dotted}' has no value")
            lines.extend([""] * bool(prose) + [f"{indent}{line}" for line in comment_lines(describe(item), dotted)])
            notes = document.notes.get(dotted, [])
            lines.extend([f"{indent}#"] * bool(notes) + [f"{indent}{line}" for line in notes])
            lines.append(f"{indent}{name}: {flow_value(value, len(indent) + len(name) + 2)}")

    emit(_key_tree(), "", 2)
    tail = document.prose.get("", [])
    return "\n".join(lines + [""] * bool(tail) + tail) + "\n"


def _trim(lines: list[str]) -> list[str]:
    """Lines without leading and trailing blank ones."""
    marks = [index for index, line in enumerate(lines) if line]
    return lines[marks[0]:marks[-1] + 1] if marks else []


_ENTRY = re.compile(r"^( *)([A-Za-z_][A-Za-z0-9_]*):(.*)$")


def parse_config_text(text: str, source: str = "config") -> ConfigDocument:
    """A config file's header, values, notes and prose (``ConfigDocument``); its table comments are dropped: the
    comment lines just above a key up to a lone ``#`` (all of them without one). Inline comments are dropped too."""
    lines = text.splitlines()
    try:
        start = next(k for k, line in enumerate(lines) if line.endswith(":") and not line[:1].isspace()
                     and not line.startswith("#") and applies_to(line[:-1]))
        node_key = lines[start][:-1]
        parameters = yaml.safe_load(text)[node_key]["ros__parameters"]
    except (StopIteration, TypeError, KeyError, yaml.YAMLError) as exc:
        raise ValueError(f"{source}: not a config file ('{NODE_NAME}: ros__parameters:' expected)") from exc
    document = ConfigDocument(header=_trim(lines[:start]), values=_flatten(parameters), node_key=node_key)
    unknown = sorted(set(document.values) - set(KEYS_BY_NAME))
    if unknown:
        raise ValueError(f"{source}: unknown key '{unknown[0]}'")
    pending: list[str] = []
    path: list[tuple[int, str]] = []
    value_indent: int | None = None
    for line in lines[start + 1:]:
        stripped = line.strip()
        indent = len(line) - len(line.lstrip())
        match = _ENTRY.match(line)
        if not stripped or stripped.startswith("#"):
            pending.append(stripped)
        elif match and (value_indent is None or indent <= value_indent) and stripped != "ros__parameters:":
            path = [(depth, name) for depth, name in path if depth < indent] + [(indent, match.group(2))]
            dotted = ".".join(name for _, name in path)
            before, pending = _trim(pending), []
            if dotted not in KEYS_BY_NAME:                        # a group
                value_indent = None
                document.prose.update({dotted: before} if before else {})
                continue
            value_indent = indent
            split = len(before) - before[::-1].index("") if "" in before else 0
            prose, block = _trim(before[:split]), before[split:]
            document.prose.update({dotted: prose} if prose else {})
            if "#" in block:
                document.notes[dotted] = block[block.index("#") + 1:]
    if _trim(pending):
        document.prose[""] = _trim(pending)
    return document


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """Nested groups to dotted names (as ``config.flatten_parameters``)."""
    if not isinstance(tree, dict):
        return {}
    flat: dict[str, Any] = {}
    for name, value in tree.items():
        flat.update(_flatten(value, f"{prefix}{name}.") if isinstance(value, dict) else {f"{prefix}{name}": value})
    return flat


def regenerated_config_text(text: str, source: str = "config") -> str:
    """A config file with every key's table comment as KEYS says now; its values, notes and prose kept."""
    return config_text(parse_config_text(text, source))


def document_with_keys_table(text: str) -> str:
    """``text`` (docs/configuration.md) with its table of keys (the lines from the table's header row) made ``keys_table()``."""
    header = keys_table().splitlines()[0]
    if header not in text:
        raise ValueError(f"the document has no table of keys (a line {header!r})")
    start = text.index(header)
    end = text.find("\n\n", start)
    end = len(text.rstrip("\n")) if end < 0 else end
    return text[:start] + keys_table() + text[end:]
