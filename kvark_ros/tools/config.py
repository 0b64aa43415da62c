"""``kvark config``: print a config file's validated settings, or the table of every key.

``kvark config --keys`` prints the Markdown table of ``kvark_ros.core.config_schema`` (the README's
key table is exactly this output); ``kvark config FILE`` prints every key of FILE after validation
and path resolution, defaults filled in: what the node, train and replay will run with.
"""
from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from kvark_ros.core.config import load_config
from kvark_ros.core.config_schema import KEYS, Key, keys_table

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser("config", help="print a config's validated settings, or every key (--keys)",
                                   description=__doc__.split("\n\n")[1])
    parser.add_argument("file", nargs="?", help="config YAML (the node's parameter file)")
    parser.add_argument("--keys", action="store_true", help="print the table of every key (Markdown)")
    parser.set_defaults(run=run)


def _value(config: object, key: Key) -> object:
    """The config value of one key (``config.<group>.<attr>`` or ``config.<attr>``)."""
    if key.group == "payload":
        payload = getattr(config, "payload")
        return getattr(payload, key.attr) if payload is not None else key.default
    owner = getattr(config, key.group) if key.group else config
    return getattr(owner, key.attr)


def run(args: argparse.Namespace) -> int:
    if args.keys:
        print(keys_table())
        return 0
    if not args.file:
        raise SystemExit("kvark: error: give a config FILE or --keys")
    config = load_config(args.file)
    width = max(len(key.name) for key in KEYS)
    for key in KEYS:
        print(f"{key.name:<{width}}  {_value(config, key)!r}")
    return 0
