"""Written files honour the umask (0644 under 022), as ``open`` would make them, while staying atomic: a node
running as another user (or in a container with another UID) must be able to read a model and its reports."""
from __future__ import annotations

import os
import stat

import pytest

from kvark_ros.core.files import write_text_atomically
from kvark_ros.core.estimation.model_store import load_model, save_model


@pytest.fixture
def umask():
    """Set the process umask for one test and put the old one back."""
    previous = os.umask(0o022)

    def set_mask(mask: int) -> None:
        os.umask(mask)

    yield set_mask
    os.umask(previous)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask, file_mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_atomic_text_files_get_the_umask_mode(tmp_path, umask, mask, file_mode):
    umask(mask)
    path = tmp_path / "metrics.json"
    write_text_atomically(path, "{}\n")
    assert path.read_text() == "{}\n" and _mode(path) == file_mode
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"], "no temporary file left behind"


def test_a_saved_model_is_readable_by_others_under_umask_022(tmp_path, umask, panda, panda_trained):
    umask(0o022)
    save_model(tmp_path / "model", panda_trained)
    assert _mode(tmp_path / "model") == 0o755
    modes = {p.name: _mode(p) for p in (tmp_path / "model").iterdir()}
    assert modes and set(modes.values()) == {0o644}, modes
    assert load_model(tmp_path / "model", panda.joint_names).joint_names == panda.joint_names
