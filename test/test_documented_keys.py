"""Every configuration key the project names in prose exists: README, docs/, the config files, and the package's
comments and docstrings. A renamed or removed key is named only where its refusal is explained."""
from __future__ import annotations

import io
import re
import tokenize
from pathlib import Path

from kvark_ros.core.config_schema import GROUPS, KEYS_BY_NAME, REMOVED_KEYS, RENAMED_KEYS

ROOT = Path(__file__).resolve().parents[1]
# A dotted name in a key group (`filter.ewma_time`), not a file (`contact.py`) or an attribute chain of code
# (`config.filter.ewma_time` is matched from `filter.`).
DOTTED = re.compile(r"(?<![\w./])(" + "|".join(map(re.escape, GROUPS)) + r")\.([a-z_]+(?:\.[a-z_]+)*)\b")
FILE_SUFFIXES = ("py", "png", "yaml", "json", "md", "launch", "pyc")
# Where an old name may stand: the tables that refuse it, and prose that says it is refused.
OLD_NAME_CONTEXT = re.compile(r"refus|removed|renamed|still (names|sets)|was |old name", re.IGNORECASE)
OLD_NAME_FILES = ("kvark_ros/core/config_schema.py",)
# Dotted names that are not keys: metrics.json fields of replay (`wrench.unobservable_share`).
NOT_KEYS = {"wrench.unobservable_share", "wrench.condition_median", "wrench.condition_max"}


def prose_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "config").glob("*.yaml"))]
    files += sorted(path for path in (ROOT / "kvark_ros").rglob("*.py"))
    return files


def named_keys(text: str) -> list[tuple[int, str, str]]:
    """(line, dotted name, the line's text) of every key-like name in ``text``."""
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        for match in DOTTED.finditer(line):
            name = match.group(0)
            if name.rsplit(".", 1)[-1] in FILE_SUFFIXES or name in NOT_KEYS:
                continue
            found.append((number, name, line))
    return found


def prose(path: Path) -> str:
    """The text a reader reads: a Markdown or YAML file whole, of Python source its comments and strings (code
    has variables called ``wrench`` or ``contact``), each on its own line number."""
    text = path.read_text()
    if path.suffix != ".py":
        return text
    lines = [""] * (text.count("\n") + 1)
    for token in tokenize.generate_tokens(io.StringIO(text).readline):
        if token.type in (tokenize.COMMENT, tokenize.STRING):
            string = re.sub(r"\{[^{}]*\}", "", token.string)      # an f-string's fields are code
            for offset, part in enumerate(string.splitlines()):
                lines[token.start[0] - 1 + offset] += " " + part
    return "\n".join(lines)


def key_exists(name: str) -> bool:
    """``name`` is a key, a group prefix of keys (`robot_model.payload`) or a stem of keys (`wrench.prior_*`)."""
    stem = name + ("" if name.endswith("_") else ".")
    return name in KEYS_BY_NAME or any(key.startswith(stem) for key in KEYS_BY_NAME)


def test_every_key_named_in_docs_configs_and_code_exists():
    problems = []
    for path in prose_files():
        relative = str(path.relative_to(ROOT))
        for number, name, line in named_keys(prose(path)):
            if key_exists(name):
                continue
            old = name in RENAMED_KEYS or name in REMOVED_KEYS
            if old and (relative in OLD_NAME_FILES or OLD_NAME_CONTEXT.search(line)):
                continue
            problems.append(f"{relative}:{number}: {name}")
    assert not problems, "names that are not configuration keys:\n" + "\n".join(problems)


def test_the_scan_finds_a_stale_name_and_passes_a_file_name():
    """The scan is not blind: a misspelt key is found, a module file name is not taken for a key."""
    names = [name for _, name, _ in named_keys("set `filter.ewma_rate: 0.01` (see contact.py, wrench.png)")]
    assert names == ["filter.ewma_rate"] and not key_exists("filter.ewma_rate")
    assert key_exists("filter.ewma_time") and key_exists("robot_model.payload")
