"""``python -m kvark_ros.tools.generate_sources``: write what the key table generates (``core.config_sources``): the
typed settings module, the key comments of config files and docs/configuration.md's table of keys; ``make
generated`` runs it after a change to ``core.config_schema.KEYS``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from kvark_ros.core.config_sources import (CONFIG_DIR, SETTINGS_PATH, document_with_keys_table,
                                           regenerated_config_text, settings_source)


def write_if_changed(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` unless it holds it already; say which."""
    if (path.read_text() if path.exists() else None) != text:
        path.write_text(text)
        print(f"wrote {path}")
    else:
        print(f"{path}: up to date")


def main(argv: list[str] | None = None) -> int:
    """``python -m kvark_ros.tools.generate_sources``: write the sources generated from the key table."""
    parser = argparse.ArgumentParser(prog="python -m kvark_ros.tools.generate_sources",
                                     description="Write what the key table generates (after changing KEYS).")
    parser.add_argument("--write-settings", action="store_true", help=f"write {SETTINGS_PATH.name} (typed settings)")
    parser.add_argument("--write-configs", nargs="*", metavar="FILE",
                        help="rewrite the key comments of config files, keeping their values, notes and prose "
                             f"(default: {CONFIG_DIR}/**/*.yaml)")
    parser.add_argument("--write-keys-doc", type=Path, metavar="MARKDOWN",
                        help="replace the table of keys in this document (docs/configuration.md) by "
                             "`kvark config --keys`")
    args = parser.parse_args(argv)
    if not args.write_settings and args.write_configs is None and args.write_keys_doc is None:
        parser.error("give --write-settings, --write-configs and/or --write-keys-doc")
    if args.write_settings:
        write_if_changed(SETTINGS_PATH, settings_source())
    if args.write_configs is not None:
        for path in map(Path, args.write_configs or sorted(CONFIG_DIR.rglob("*.yaml"))):
            write_if_changed(path, regenerated_config_text(path.read_text(), str(path)))
    if args.write_keys_doc is not None:
        write_if_changed(args.write_keys_doc, document_with_keys_table(args.write_keys_doc.read_text()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
