"""Issue 27: a wrong config key or value, joint or frame name is one error line naming the key and the nearest
valid value (``core.hints``), not a list of every valid one."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from kvark_ros.core.config import ConfigError, load_config
from kvark_ros.core.config_schema import KEYS
from kvark_ros.core.estimation.robot_model import RobotModel, RobotModelError

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"


def _one_line(message: str, *words: str) -> None:
    assert "\n" not in message and len(message) < 300, message
    for word in words:
        assert word in message, f"{word!r} not in: {message}"


def _config(tmp_path: Path, edit) -> Path:
    document = yaml.safe_load(CONFIG.read_text())
    edit(document["kvark_estimator"]["ros__parameters"])
    path = tmp_path / "x.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


@pytest.mark.parametrize("group, name, hint", [
    ("filter", "onset_treshold", "did you mean 'filter.onset_threshold'?"),
    ("input", "joint_state_topic", "did you mean 'input.joint_states_topic'?"),
    (None, "ee_frame", "did you mean 'robot_model.ee_frame'?"),          # a key outside its group
    (None, "zzzz", "`kvark config --keys` lists every key"),
])
def test_unknown_key_names_the_nearest_key_not_every_key(tmp_path, group, name, hint):
    def edit(parameters: dict) -> None:
        (parameters[group] if group else parameters)[name] = 1.0

    with pytest.raises(ConfigError) as raised:
        load_config(_config(tmp_path, edit))
    message = str(raised.value)
    _one_line(message, str(tmp_path / "x.yaml"), f"unknown key '{f'{group}.' if group else ''}{name}'", hint)
    assert sum(f"'{key.name}'" in message for key in KEYS) <= 1       # the nearest, not a list


def test_invalid_choice_names_the_nearest_choice(tmp_path):
    with pytest.raises(ConfigError) as raised:
        load_config(_config(tmp_path, lambda parameters: parameters.__setitem__("observer", "kvrak")))
    _one_line(str(raised.value), "key 'observer' has invalid value 'kvrak'", "did you mean 'kvark'?")


@pytest.mark.parametrize("joint, ee_frame, flange_frame, words", [
    ("panda_joint8", None, None, ("robot_model.joint_names: 'panda_joint8' is a fixed joint of the URDF",
                                  "did you mean 'panda_joint7'?")),
    ("panda_jiont7", None, None, ("robot_model.joint_names: 'panda_jiont7' is not a joint of the URDF",
                                  "did you mean 'panda_joint7'?")),
    (None, "panda_hand_tc", None, ("robot_model.ee_frame: 'panda_hand_tc' is not a frame of the URDF",
                                   "did you mean 'panda_hand_tcp'?")),
    (None, None, "panda_link9", ("robot_model.flange_frame: 'panda_link9' is not a frame of the URDF",
                                 "did you mean 'panda_link8'?")),
    (None, "nothing_like_it", None, ("robot_model.ee_frame", "its links: panda_link0", "and 3 more")),
])
def test_wrong_joint_or_frame_names_the_key_and_the_nearest_in_the_urdf(panda_config, joint, ee_frame,
                                                                         flange_frame, words):
    c = panda_config
    names = [*c.joint_names[:-1], joint or c.joint_names[-1]]
    with pytest.raises(RobotModelError) as raised:
        RobotModel(c.urdf, names, ee_frame or c.ee_frame, flange_frame or c.flange_frame)
    _one_line(str(raised.value), c.urdf, *words)
