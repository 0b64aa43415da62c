"""Issue 27: ``kvark config FILE`` checks FILE against the URDF it names (and the model it names, once trained):
a joint or frame the URDF lacks is one error line naming FILE, the key and the nearest valid name, exit 1."""
from __future__ import annotations

from pathlib import Path

import pytest

from kvark_ros.cli import main

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"


def test_a_valid_config_says_what_it_was_checked_against(capsys):
    assert main(["config", str(CONFIG)]) == 0
    out = capsys.readouterr().out
    assert "checked against the URDF example-robot-data:panda: 7 joints in chain order, ee_frame panda_hand_tcp, " \
           "flange_frame panda_link8" in out
    assert "checked against the model" in out and "trained for these joints and this URDF" in out


@pytest.mark.parametrize("old, new, words", [
    ("panda_joint7]", "panda_joint8]", ("robot_model.joint_names: 'panda_joint8'", "did you mean 'panda_joint7'?")),
    ("ee_frame: panda_hand_tcp", "ee_frame: panda_hand_tc",
     ("robot_model.ee_frame: 'panda_hand_tc' is not a frame of the URDF", "did you mean 'panda_hand_tcp'?")),
])
def test_a_name_not_in_the_urdf_is_one_line_naming_file_key_and_nearest(tmp_path, capsys, old, new, words):
    text = CONFIG.read_text()
    assert text.count(old) == 1
    path = tmp_path / "x.yaml"
    path.write_text(text.replace(old, new))
    assert main(["config", str(path)]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""                                  # nothing printed as if it were valid
    assert captured.err.count("\n") == 1 and captured.err.startswith(f"kvark: error: {path}: "), captured.err
    for word in words:
        assert word in captured.err, captured.err


def test_a_model_not_trained_yet_is_said_not_an_error(tmp_path, capsys):
    path = tmp_path / "config" / "x.yaml"                     # its model_dir ../models/panda does not exist here
    path.parent.mkdir()
    path.write_text(CONFIG.read_text())
    assert main(["config", str(path)]) == 0
    assert f"model: {tmp_path / 'models' / 'panda'} not trained yet" in capsys.readouterr().out
