"""The one output rule (kvark_ros/core/files.py): an existing non-empty output only with force, built beside the
target and swapped in whole, the old output untouched by a failed run."""
from __future__ import annotations

from pathlib import Path

import pytest

from kvark_ros.core.files import OutputExistsError, check_output, staged_directory

MESSAGE = "exists and is not empty; pass --force to replace it or choose another --out"


def _old_output(path: Path) -> dict[str, str]:
    """A previous output with a file and a sub-directory; its content."""
    (path / "plots").mkdir(parents=True)
    (path / "report.md").write_text("old report")
    (path / "plots" / "a.png").write_text("old plot")
    return _content(path)


def _content(path: Path) -> dict[str, str]:
    return {str(p.relative_to(path)): p.read_text() for p in sorted(path.rglob("*")) if p.is_file()}


def test_new_paths_empty_directories_and_empty_files_are_free(tmp_path):
    check_output(tmp_path / "new", force=False)
    (tmp_path / "empty").mkdir()
    check_output(tmp_path / "empty", force=False)
    (tmp_path / "empty.yaml").write_text("")
    check_output(tmp_path / "empty.yaml", force=False)


@pytest.mark.parametrize("kind", ["directory", "file", "link"])
def test_anything_else_is_refused_in_one_line_unless_force(tmp_path, kind):
    path = tmp_path / "out"
    if kind == "directory":
        path.mkdir()
        (path / "x").write_text("")
    elif kind == "file":
        path.write_text("old")
    else:
        path.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(OutputExistsError) as error:
        check_output(path, force=False)
    assert str(error.value) == f"{path}: {MESSAGE}"
    assert isinstance(error.value, ValueError)      # a user error: kvark prints it as one line
    check_output(path, force=True)


def test_a_forced_build_replaces_the_old_output_whole(tmp_path):
    target = tmp_path / "out"
    _old_output(target)
    with staged_directory(target, force=True) as staging:
        assert staging.parent == tmp_path and staging.name.startswith(".out.") and not any(staging.iterdir())
        (staging / "metrics.json").write_text("new")
    assert _content(target) == {"metrics.json": "new"}          # no stale report or plot of the old run
    assert [p.name for p in tmp_path.iterdir()] == ["out"]      # no staging, no backup


def test_a_failed_forced_build_leaves_the_old_output_untouched(tmp_path):
    target = tmp_path / "out"
    before = _old_output(target)
    with pytest.raises(RuntimeError, match="boom"), staged_directory(target, force=True) as staging:
        (staging / "metrics.json").write_text("half")
        raise RuntimeError("boom")
    assert _content(target) == before
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_an_unforced_build_is_refused_before_it_starts_and_an_empty_directory_is_used(tmp_path):
    target = tmp_path / "out"
    before = _old_output(target)
    started = []
    with pytest.raises(OutputExistsError, match=MESSAGE), staged_directory(target, force=False):
        started.append(True)
    assert not started and _content(target) == before
    empty = tmp_path / "empty"
    empty.mkdir()
    with staged_directory(empty, force=False) as staging:
        (staging / "metrics.json").write_text("new")
    assert _content(empty) == {"metrics.json": "new"}


def test_an_output_that_appears_while_building_is_not_replaced_without_force(tmp_path):
    target = tmp_path / "out"
    with pytest.raises(OutputExistsError), staged_directory(target, force=False) as staging:
        (staging / "metrics.json").write_text("new")
        _old_output(target)                                      # another run wrote it meanwhile
    assert _content(target) == {"plots/a.png": "old plot", "report.md": "old report"}
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_force_never_replaces_the_current_directory_or_a_parent_of_it(tmp_path, monkeypatch):
    work = tmp_path / "project" / "work"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    for path in (".", "..", str(tmp_path / "project")):
        with pytest.raises(OutputExistsError, match="holds the current directory"):
            check_output(path, force=True)
    check_output(str(tmp_path / "other"), force=True)


def test_force_never_replaces_an_output_that_holds_an_input(tmp_path):
    """`replay --bag OUT/estimates --out OUT --force` would delete its own bag at the swap: refused, naming it."""
    out = tmp_path / "out"
    _old_output(out)
    with pytest.raises(OutputExistsError, match=r"holds the input .*report\.md, which --force would replace"):
        check_output(out, force=True, inputs=(None, out / "report.md"))
    with pytest.raises(OutputExistsError, match="holds the input"):
        check_output(out, force=True, inputs=(out,))
    check_output(out, force=True, inputs=(tmp_path / "elsewhere", None))
