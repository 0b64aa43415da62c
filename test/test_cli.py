"""The kvark command line."""
from __future__ import annotations

import json

import pytest

from kvark_ros import __version__
from kvark_ros.cli import main


def test_help_lists_the_subcommands(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    assert "bench" in capsys.readouterr().out


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


def test_user_errors_give_one_line_and_exit_code(capsys, tmp_path):
    assert main(["bench", "--config", str(tmp_path / "missing.yaml")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("kvark: error:") and "missing.yaml" in err and "\n" not in err
