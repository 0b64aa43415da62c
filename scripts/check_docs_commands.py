"""Run every shell block of README.md and docs/*.md as a reader would, after the quick start: in a scratch copy
of the project (tracked files only, sharing .venv), README's quick start first (``make demo``; ``make test`` is
what CI has just run in this clone), then each document's blocks in order in one shell, so an ``activate`` or a
``cd`` carries on to the next block as it does for a reader. Exit 1 naming the first block that fails.

    python scripts/check_docs_commands.py [--keep DIR] [DOCUMENT ...]

``make docs-check`` runs it (CI too); block kinds: scripts/doc_blocks.py.
"""
from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from doc_blocks import DOCUMENTS, LONG_RUNNING_S, Block, scratch_copy, shell_blocks

QUICK_START_SKIPPED = ("make test",)


def block_script(block: Block, folder: Path, index: int) -> str:
    """Shell lines that run ``block`` inside the document's shell (``set -e`` active)."""
    path = folder / f"block_{index}.sh"
    where = f"{block.document}:{block.line}"
    if block.kind == "quick-start":
        lines = [line for line in block.text.splitlines() if not line.strip().startswith(QUICK_START_SKIPPED)]
        path.write_text("\n".join(lines) + "\n")
    else:
        path.write_text(block.text)
    if block.kind == "long-running":
        return (f"echo '== {where} (long-running: must still serve after {LONG_RUNNING_S} s)'\n"
                f"set +e; timeout --signal INT {LONG_RUNNING_S} bash -e {shlex.quote(str(path))}; rc=$?; set -e\n"
                f"if [ $rc -ne 124 ]; then echo 'docs-check: {where} stopped (exit '$rc')'; exit 1; fi\n")
    return f"echo '== {where}'\nsource {shlex.quote(str(path))}\n"


def run_document(document: str, copy: Path, folder: Path, blocks: list[Block]) -> bool:
    """Run ``blocks`` of ``document`` in one bash from the copy's root; True when every block succeeded."""
    parts = ["set -euo pipefail", f"cd {shlex.quote(str(copy))}"]
    parts += [block_script(block, folder, index) for index, block in enumerate(blocks)]
    script = folder / f"{document.replace('/', '_')}.sh"
    script.write_text("\n".join(parts) + "\n")
    started = time.monotonic()
    env = {key: value for key, value in os.environ.items() if key not in ("VIRTUAL_ENV",)}
    # The copy's package first, for `kvark` (the shared .venv's editable install points at the project) as for
    # `python -m`: every block runs the copy, with its own compiled-kernel cache, as in a user's checkout.
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(copy), os.environ.get("PYTHONPATH"))))
    result = subprocess.run(["bash", str(script)], cwd=copy, env=env)
    print(f"docs-check: {document}: {len(blocks)} blocks, {'ok' if result.returncode == 0 else 'FAILED'} "
          f"in {time.monotonic() - started:.0f} s", flush=True)
    return result.returncode == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("documents", nargs="*", default=list(DOCUMENTS), help="documents (default: README and docs/)")
    parser.add_argument("--keep", metavar="DIR", help="run in DIR and keep it (default: a temporary folder)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="kvark-docs-") as temporary:
        base = Path(args.keep or temporary)
        base.mkdir(parents=True, exist_ok=True)
        copy, scripts = scratch_copy(base), base / "scripts"
        scripts.mkdir(exist_ok=True)
        quick = [block for block in shell_blocks("README.md") if block.kind == "quick-start"]
        if len(quick) != 1:
            print("docs-check: README.md needs exactly one `bash quick-start` block", file=sys.stderr)
            return 1
        if not run_document("quick start", copy, scripts, quick):
            return 1
        failed = []
        for document in args.documents:
            every = shell_blocks(document)
            blocks = [block for block in every if block.kind in ("run", "long-running")]
            skipped = [block for block in every if block.kind == "ros-install"]
            if skipped:
                print(f"docs-check: {document}: {len(skipped)} block(s) need a ROS 2 install; not run here")
            if blocks and not run_document(document, copy, scripts, blocks):
                failed.append(document)
    if failed:
        print(f"docs-check: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
