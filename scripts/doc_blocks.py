"""What the two documentation scripts share: the shell blocks of a Markdown file, a scratch copy of the
project to run them in, and the generated sections of a document.

A fenced block whose info string starts with ``bash`` is a command a reader may paste: it must run as written
after the quick start (``check_docs_commands.py``). A second word says how:

- ``bash`` runs, and must exit 0;
- ``bash long-running`` starts something that serves until stopped (the node): it must still run after
  ``LONG_RUNNING_S`` seconds;
- ``bash ros-install`` needs a ROS 2 install (colcon, rosdep, ``ros2 launch``), which has no wheels: shown,
  not run here;
- ``bash quick-start`` is the quick start itself, which the checker runs first (``make test`` aside: CI has
  just run it in the same clone).

Blocks with placeholders (``BAG``, ``DIR``) are reference syntax and use ``text``.
"""
from __future__ import annotations

import re
import shutil
import textwrap
import subprocess
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = ("README.md", *sorted(str(path.relative_to(ROOT)) for path in (ROOT / "docs").glob("*.md")))
LONG_RUNNING_S = 20
FENCE = re.compile(r"^( *)```([^\n`]*)\n(.*?)^\1```", re.MULTILINE | re.DOTALL)     # a block may be indented
SECTION = re.compile(r"(<!-- generated: (?P<name>[a-z0-9-]+) -->\n)(?P<body>.*?)(<!-- end: (?P=name) -->)", re.DOTALL)


@dataclass(frozen=True)
class Block:
    """A fenced shell block: its document, line, kind (``run``, ``long-running``, ``ros-install``,
    ``quick-start``) and text."""

    document: str
    line: int
    kind: str
    text: str


def shell_blocks(document: str, root: Path = ROOT) -> list[Block]:
    """The ``bash`` blocks of ``document`` (a path relative to ``root``), in order."""
    text = (root / document).read_text()
    blocks = []
    for match in FENCE.finditer(text):
        words = match.group(2).split()
        if not words or words[0] != "bash":
            continue
        kind = words[1] if len(words) > 1 else "run"
        if kind not in ("run", "long-running", "ros-install", "quick-start"):
            raise ValueError(f"{document}: unknown shell block kind {kind!r} (see scripts/doc_blocks.py)")
        body = textwrap.dedent(match.group(3))
        blocks.append(Block(document, text.count("\n", 0, match.start()) + 1, kind, body))
    return blocks


def scratch_copy(destination: Path, root: Path = ROOT) -> Path:
    """A copy of the project's tracked files (times kept, so make sees .venv as up to date) at
    ``destination``, sharing ``root``'s .venv and the ``../shared`` beside it; returns the copy's root."""
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=root, check=True, capture_output=True).stdout
    copy = destination / root.name
    for name in filter(None, tracked.decode().split("\0")):
        source = root / name
        if source.is_file():
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, copy / name)
    (copy / ".venv").symlink_to(root / ".venv")
    shared = root.parent / "shared"
    if shared.exists() and not (destination / "shared").exists():
        (destination / "shared").symlink_to(shared)
    return copy


def generated_sections(text: str) -> dict[str, str]:
    """The bodies of ``<!-- generated: NAME -->`` ... ``<!-- end: NAME -->`` sections, by name."""
    return {match.group("name"): match.group("body") for match in SECTION.finditer(text)}


def replace_section(text: str, name: str, body: str) -> str:
    """``text`` with section ``name``'s body replaced; an error when the document has no such section."""
    found = [match for match in SECTION.finditer(text) if match.group("name") == name]
    if not found:
        raise KeyError(f"no '<!-- generated: {name} -->' section")
    match = found[0]
    return text[:match.start("body")] + body.rstrip("\n") + "\n" + text[match.end("body"):]
