"""The kvark command line."""
from __future__ import annotations

import importlib
import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from kvark_ros import __version__
from kvark_ros.cli import COMMANDS, USER_ERRORS, available_commands, build_parser, main

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("pinocchio", "sklearn", "matplotlib", "rosbags", "mujoco")


def _loaded_after(argv: list[str]) -> list[str]:
    """The modules loaded by ``kvark_ros.cli.main(argv)`` in a fresh interpreter (its output discarded)."""
    code = ("import contextlib, io, json, sys\n"
            "from kvark_ros.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
            f"    code = main({argv!r})\n"
            "    assert code in (None, 0), code\n"
            "print(json.dumps(sorted(sys.modules)))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    return json.loads(done.stdout)


def test_version(capsys):
    with pytest.raises(SystemExit):
        main(["--version"])
    assert __version__ in capsys.readouterr().out


def test_bench_prints_one_json_line_last(capsys):
    assert main(["bench", "--robot", "panda", "--observer", "kvark,kf", "--duration", "1"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    summary = json.loads(last)
    assert summary["robot"] == "panda" and summary["observer"] == "kvark"
    assert summary["steps"] == 500 and 0 < summary["p50_us"] <= summary["p99_us"]
    assert set(summary["observers"]) == {"kvark", "kf"}


def test_bench_times_a_given_model_directory(capsys):
    """--model: the trained model is timed as it is (no synthetic training), compiled by default."""
    model = Path(__file__).resolve().parents[2] / "models" / "panda"
    assert main(["bench", "--model", str(model), "--duration", "1"]) == 0
    out = capsys.readouterr().out
    assert f"timing the model {model}" in out and "training a residual model" not in out
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["observers"]["kvark"]["kernel"] == "numba" and summary["steps"] == 500


def test_user_errors_give_one_line_and_exit_code(capsys, tmp_path):
    assert main(["bench", "--config", str(tmp_path / "missing.yaml")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("kvark: error:") and "missing.yaml" in err and "\n" not in err


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    listed = re.findall(r"^ {4}(\S+)", capsys.readouterr().out, re.MULTILINE)
    assert listed == [command.name for command in available_commands()]
    assert ("simulate" in listed) == (importlib.util.find_spec("mujoco") is not None)


def test_the_table_is_each_commands_own_help_line():
    """``kvark --help`` from the table is the listing each command's ``add_parser`` registers."""
    listing = build_parser().format_help()
    for command in available_commands():
        assert build_parser(command.name).format_help() == listing, command.name


@pytest.mark.parametrize("command", [command.name for command in available_commands()])
def test_every_commands_help_prints_and_exits_0(command, capsys):
    """``kvark COMMAND --help`` formats every option's help: a ``%`` in a help string not written ``%%`` made
    argparse raise a TypeError instead of printing it."""
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: kvark {command}")


def test_help_imports_no_command_module_and_no_heavy_package():
    loaded = _loaded_after(["--help"])
    assert not [name for name in loaded if name.split(".")[0] in HEAVY]
    assert not [name for name in loaded if name in {command.module for command in COMMANDS}]


def test_command_help_imports_that_command_alone():
    loaded = set(_loaded_after(["replay", "--help"]))
    assert "kvark_ros.tools.replay" in loaded
    assert not loaded & {command.module for command in COMMANDS if command.name != "replay"}
    assert not loaded & {"matplotlib", "sklearn", "mujoco"}


def test_user_errors_name_the_classes_where_they_are_defined():
    for module, name in USER_ERRORS:
        error = getattr(importlib.import_module(module), name)
        assert issubclass(error, ValueError) and error.__module__ == module, (module, name)


def test_replay_without_plots_writes_metrics_only_and_never_loads_matplotlib(tmp_path):
    out = tmp_path / "replay"
    loaded = _loaded_after(["replay", "--config", "config/panda.yaml", "--model", "models/panda", "--bag",
                            "bags/panda_payload", "--observers", "kvark", "--no-bag", "--no-plots", "--out", str(out)])
    assert "matplotlib" not in loaded
    assert sorted(path.name for path in out.iterdir()) == ["metrics.json"]
    assert "kvark" in json.loads((out / "metrics.json").read_text())["observers"]
