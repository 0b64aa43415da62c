"""Issue 7, scope 3: bad files and user errors through the real `kvark` CLI.

Every case runs ``kvark_ros.cli.main([...])`` in-process and asserts what a user sees: a non-zero
exit code and exactly one stderr line ``kvark: error: <file>: <problem>; <fix>``, never a traceback
(an exception escaping ``main`` is what the console script would print as a traceback). A training
run that fails or is interrupted leaves the previous model directory byte-identical.

One 2 s simulated Panda excitation bag and one model (``kvark train --no-baselines``) are made once
per module; every corrupted input is derived from them.
"""
from __future__ import annotations

import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from kvark_ros.cli import main
from kvark_ros.core.estimation.model_store import MODEL_FILE
from kvark_ros.io import BagWriter, write_run

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
UR5_CONFIG = ROOT / "config" / "ur5.yaml"
N = 7




# --------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A good bag, every broken bag, and a trained model (a copy of the committed models/panda)."""
    from kvark_ros.sim.scenarios import simulate
    root = tmp_path_factory.mktemp("user_errors")
    run = simulate("panda", "excitation", seed=1, duration=2.0, progress=False)
    good = root / "good"
    write_run(good, run)

    truncated = root / "truncated"                      # (1) MCAP cut in half
    write_run(truncated, run)
    (mcap,) = truncated.glob("*.mcap")
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])

    corrupt_sqlite = root / "corrupt_sqlite"            # (2) .db3 full of random bytes
    write_run(corrupt_sqlite, run, storage="sqlite3")
    (db3,) = corrupt_sqlite.glob("*.db3")
    db3.write_bytes(np.random.default_rng(0).bytes(db3.stat().st_size))

    no_joint_states = root / "no_joint_states"          # (3) commands only
    with BagWriter(no_joint_states) as bag:
        for k in range(20):
            bag.float64_array("/effort_commands", k / 500.0, np.zeros(N))

    wrong_type = root / "wrong_type"                    # (4) std_msgs/String on /joint_states
    store = get_typestore(Stores.ROS2_JAZZY)
    string = "std_msgs/msg/String"
    with Writer(wrong_type, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/joint_states", string, typestore=store)
        for k in range(20):
            writer.write(conn, 1_000_000_000 + 2_000_000 * k,
                         store.serialize_cdr(store.types[string](data="panda_joint1"), string))

    model = root / "models" / "panda"             # the committed trained model: these tests need one, not training
    shutil.copytree(ROOT / "models" / "panda", model)
    return SimpleNamespace(root=root, good=good, truncated=truncated, corrupt_sqlite=corrupt_sqlite,
                           no_joint_states=no_joint_states, wrong_type=wrong_type, model=model)


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def _copy_model(files, tmp_path: Path, name: str = "panda") -> Path:
    target = tmp_path / "models" / name
    shutil.copytree(files.model, target)
    return target


def _cli(capsys, argv: list[str]) -> tuple[int, str]:
    """Run `kvark ARGV`; an exception leaving main() is the traceback a user would see."""
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:                 # argparse / SystemExit("kvark: error: ...")
        code = exc.code if isinstance(exc.code, int) else 1
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
    except Exception as exc:                  # noqa: BLE001 - that is the point of the test
        pytest.fail(f"traceback instead of a one-line error: {type(exc).__name__}: {exc}")
    return code, capsys.readouterr().err


def _assert_user_error(code: int, err: str, path: Path | str, *words: str) -> str:
    """Non-zero exit, one line 'kvark: error: ...' naming ``path`` and every one of ``words``."""
    assert code != 0, "a user error must exit non-zero"
    assert "Traceback" not in err
    lines = err.rstrip("\n").split("\n")
    assert len(lines) == 1, f"expected one stderr line, got {len(lines)}:\n{err}"
    line = lines[0]
    assert line.startswith("kvark: error: "), line
    assert str(path) in line, f"{path} not named in: {line}"
    for word in words:
        assert word.lower() in line.lower(), f"{word!r} not in: {line}"
    return line


def _replay(files, tmp_path: Path, *, config=CONFIG, model=None, bag=None, extra=()) -> list[str]:
    return ["replay", "--config", str(config), "--model", str(model or files.model),
            "--bag", str(bag or files.good), "--out", str(tmp_path / "out"), "--no-bag", *extra]


def _train(files, tmp_path: Path, out: Path, *, config=CONFIG, bags=None) -> list[str]:
    """``kvark train`` into ``out``, with --force: a previous model there must survive the error. Every joint takes q̇
    alone: an interrupted fit is then the first fit, not the end of the input selection's (4 s)."""
    return ["train", "--config", str(config), "--bags", *map(str, bags or [files.good]),
            "--out", str(out), "--no-baselines", "--no-plots", "--force", "--residual-inputs", "qd"]


def _edit_model_yaml(model: Path, edit) -> None:
    document = yaml.safe_load((model / MODEL_FILE).read_text())
    edit(document)
    (model / MODEL_FILE).write_text(yaml.safe_dump(document, sort_keys=False))


# --------------------------------------------------------------------------- (1)-(4) bags

BAG_CASES = {
    # name: (problem words, fix word)
    "truncated": (("corrupt or truncated",), "re-record"),
    "corrupt_sqlite": (("corrupt or truncated",), "re-record"),
    "no_joint_states": (("/joint_states", "absent"), "record"),
    "wrong_type": (("/joint_states", "std_msgs/msg/String", "sensor_msgs/msg/JointState"), "record"),
}


@pytest.mark.parametrize("case", sorted(BAG_CASES))
def test_replay_of_a_bad_bag_is_one_line(files, tmp_path, capsys, case):
    bag = getattr(files, case)
    problem, fix = BAG_CASES[case]
    code, err = _cli(capsys, _replay(files, tmp_path, bag=bag))
    _assert_user_error(code, err, bag, *problem, fix)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("case", sorted(BAG_CASES))
def test_train_on_a_bad_bag_is_one_line_and_keeps_the_previous_model(files, tmp_path, capsys, case):
    bag = getattr(files, case)
    problem, fix = BAG_CASES[case]
    target = _copy_model(files, tmp_path)
    before = _snapshot(target)
    code, err = _cli(capsys, _train(files, tmp_path, target, bags=[files.good, bag]))
    _assert_user_error(code, err, bag, *problem, fix)
    assert _snapshot(target) == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["panda"]


@pytest.mark.parametrize("case", ["no_joint_states", "wrong_type"])
def test_topic_errors_name_a_fix_the_cli_user_can_apply(files, tmp_path, capsys, case):
    code, err = _cli(capsys, _replay(files, tmp_path, bag=getattr(files, case)))
    line = _assert_user_error(code, err, getattr(files, case))
    assert "TopicNames" not in line


# --------------------------------------------------------------------------- (5)-(8) models

def test_replay_with_a_missing_model_directory(files, tmp_path, capsys):
    missing = tmp_path / "no_such_model"
    code, err = _cli(capsys, _replay(files, tmp_path, model=missing))
    _assert_user_error(code, err, missing, "not found", "kvark train")


def test_replay_with_a_truncated_model_yaml(files, tmp_path, capsys):
    model = _copy_model(files, tmp_path)
    text = (model / MODEL_FILE).read_text()
    (model / MODEL_FILE).write_text(text[: len(text) // 2])
    code, err = _cli(capsys, _replay(files, tmp_path, model=model))
    _assert_user_error(code, err, model / MODEL_FILE, "retrain")


def test_replay_with_model_yaml_missing_keys(files, tmp_path, capsys):
    model = _copy_model(files, tmp_path)
    _edit_model_yaml(model, lambda d: d.pop("filter_tuning"))
    code, err = _cli(capsys, _replay(files, tmp_path, model=model))
    _assert_user_error(code, err, model / MODEL_FILE, "filter_tuning", "retrain")


def test_replay_with_a_binary_garbage_model_yaml(files, tmp_path, capsys):
    model = _copy_model(files, tmp_path)
    (model / MODEL_FILE).write_bytes(np.random.default_rng(1).bytes(300))
    code, err = _cli(capsys, _replay(files, tmp_path, model=model))
    _assert_user_error(code, err, model / MODEL_FILE, "retrain")


def test_replay_with_a_model_path_that_is_a_file(files, tmp_path, capsys):
    code, err = _cli(capsys, _replay(files, tmp_path, model=files.model / MODEL_FILE))
    _assert_user_error(code, err, files.model / MODEL_FILE, "directory")


def test_replay_with_a_garbage_kmp_npz(files, tmp_path, capsys):
    model = _copy_model(files, tmp_path)
    (model / "kmp.npz").write_bytes(np.random.default_rng(2).bytes(500))
    code, err = _cli(capsys, _replay(files, tmp_path, model=model))
    line = _assert_user_error(code, err, model / "kmp.npz", "retrain")
    assert "unsafely" not in line and "pickle" not in line


def test_replay_with_a_truncated_kmp_npz_is_one_line(files, tmp_path, capsys):
    model = _copy_model(files, tmp_path)
    data = (model / "kmp.npz").read_bytes()
    (model / "kmp.npz").write_bytes(data[: len(data) // 2])
    code, err = _cli(capsys, _replay(files, tmp_path, model=model))
    _assert_user_error(code, err, model / "kmp.npz")


def test_replay_with_a_binary_garbage_kmp_yaml(files, tmp_path, capsys):
    model = _copy_model(files, tmp_path)
    (model / "kmp.yaml").write_bytes(np.random.default_rng(3).bytes(300))
    code, err = _cli(capsys, _replay(files, tmp_path, model=model))
    _assert_user_error(code, err, model / "kmp.yaml", "retrain")


def test_replay_of_a_panda_model_with_the_ur5_config(files, tmp_path, capsys):
    code, err = _cli(capsys, _replay(files, tmp_path, config=UR5_CONFIG))
    _assert_user_error(code, err, files.model / MODEL_FILE, "panda_joint1", "shoulder_pan_joint",
                       "train a model for these joints")


def test_replay_of_a_model_with_reordered_joints(files, tmp_path, capsys):
    model = _copy_model(files, tmp_path)
    _edit_model_yaml(model, lambda d: d.__setitem__("joint_names", d["joint_names"][::-1]))
    code, err = _cli(capsys, _replay(files, tmp_path, model=model))
    _assert_user_error(code, err, model / MODEL_FILE, "differ", "train a model for these joints")


def test_replay_of_a_model_trained_on_another_urdf(files, tmp_path, capsys):
    model = _copy_model(files, tmp_path)
    recorded = yaml.safe_load((model / MODEL_FILE).read_text())["info"]["urdf_sha256"]
    assert len(recorded) == 64
    _edit_model_yaml(model, lambda d: d["info"].__setitem__("urdf_sha256", "0" * 64))
    code, err = _cli(capsys, _replay(files, tmp_path, model=model))
    _assert_user_error(code, err, model / MODEL_FILE, "urdf", "sha256", "retrain")


# --------------------------------------------------------------------------- (9) configs

def _config_text() -> str:
    return CONFIG.read_text()


def _bad_yaml(directory: Path) -> Path:
    path = directory / "config" / "bad_yaml.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(_config_text().replace("observer: kvark", "observer: [kvark", 1))
    return path


def _with_parameters(directory: Path, name: str, edit) -> Path:
    document = yaml.safe_load(_config_text())
    edit(document["kvark_estimator"]["ros__parameters"])
    path = directory / "config" / f"{name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


CONFIG_CASES = {
    # name: (writer, problem words, fix word)
    "bad_yaml": (_bad_yaml, ("invalid YAML", "line"), "fix the syntax"),
    "unknown_key": (lambda d: _with_parameters(d, "unknown_key", lambda p: p.__setitem__("obsrever", "kf")),
                    ("unknown key 'obsrever'",), "did you mean 'observer'?"),
    "out_of_range": (lambda d: _with_parameters(d, "out_of_range",
                                                lambda p: p["filter"].__setitem__("ewma_time", -2.0)),
                     ("filter.ewma_time", "-2.0"), "allowed"),
    "missing_key": (lambda d: _with_parameters(d, "missing_key", lambda p: p.pop("robot")),
                    ("missing required key 'robot'",), "non-empty string"),
}


@pytest.mark.parametrize("command", ["replay", "train"])
@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_invalid_config_is_one_line(files, tmp_path, capsys, command, case):
    make, problem, fix = CONFIG_CASES[case]
    config = make(tmp_path)
    target = _copy_model(files, tmp_path)
    before = _snapshot(target)
    argv = (_replay(files, tmp_path, config=config, model=target) if command == "replay"
            else _train(files, tmp_path, target, config=config))
    code, err = _cli(capsys, argv)
    _assert_user_error(code, err, config, *problem, fix)
    assert _snapshot(target) == before


@pytest.mark.parametrize("command", ["replay", "train"])
def test_config_that_is_a_directory(files, tmp_path, capsys, command):
    config = ROOT / "config"
    argv = (_replay(files, tmp_path, config=config) if command == "replay"
            else _train(files, tmp_path, tmp_path / "model", config=config))
    code, err = _cli(capsys, argv)
    _assert_user_error(code, err, config, "config")


@pytest.mark.parametrize("command", ["replay", "train"])
def test_config_that_is_a_binary_file(files, tmp_path, capsys, command):
    (config,) = files.good.glob("*.mcap")
    argv = (_replay(files, tmp_path, config=config) if command == "replay"
            else _train(files, tmp_path, tmp_path / "model", config=config))
    code, err = _cli(capsys, argv)
    _assert_user_error(code, err, config, "config")


# --------------------------------------------------------------------------- (10) plant files

PLANT_CASES = {
    "bad_yaml": ("friction: [1, 2\n", "YAML"),
    "unknown_key": ("nonsense_key: 3\n", "nonsense_key"),
    "bad_value": ("control_rate_hz: -5\n", "control_rate_hz"),
}


def _plant(tmp_path: Path, case: str) -> Path:
    path = tmp_path / f"plant_{case}.yaml"
    path.write_text(PLANT_CASES[case][0])
    return path


@pytest.mark.parametrize("case", [*sorted(PLANT_CASES), "missing"])
def test_simulate_with_a_bad_plant_file(tmp_path, capsys, case):
    plant = tmp_path / "no_such_plant.yaml" if case == "missing" else _plant(tmp_path, case)
    word = "plant file not found" if case == "missing" else PLANT_CASES[case][1]
    out = tmp_path / "sim_bag"
    code, err = _cli(capsys, ["simulate", "--scenario", "excitation", "--duration", "0.1",
                              "--plant", str(plant), "--out", str(out)])
    _assert_user_error(code, err, plant, word)
    assert not out.exists()


@pytest.mark.parametrize("case", sorted(PLANT_CASES))
def test_replay_with_a_bad_plant_file(files, tmp_path, capsys, case):
    plant = _plant(tmp_path, case)
    code, err = _cli(capsys, _replay(files, tmp_path, extra=("--plant", str(plant), "--observers", "oracle")))
    _assert_user_error(code, err, plant, PLANT_CASES[case][1])


# --------------------------------------------------------------------------- (11) interrupted training

def _assert_interrupted_training_keeps_the_model(files, tmp_path, capsys) -> None:
    """`kvark train` over a copy of the model: exit 130, one line, the old model byte-identical, nothing beside it."""
    target = _copy_model(files, tmp_path)
    before = _snapshot(target)
    code, err = _cli(capsys, _train(files, tmp_path, target))
    assert code == 130
    assert err.strip() == "kvark: interrupted" and "Traceback" not in err
    assert _snapshot(target) == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["panda"]


def test_train_interrupted_during_the_fit_exits_130_and_keeps_the_previous_model(
        files, tmp_path, capsys, monkeypatch):
    import kvark_ros.core.learning.training as baselines

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(baselines, "fit_kmp", interrupted)
    _assert_interrupted_training_keeps_the_model(files, tmp_path, capsys)


def test_train_interrupted_while_saving_exits_130_and_keeps_the_previous_model(
        files, tmp_path, capsys, monkeypatch):
    """The interrupt lands after kmp.npz is half written into the staging directory."""
    import kvark_ros.tools.train as train
    from kvark_ros.core.estimation.model_store import load_model
    from kvark_ros.core.estimation.residual import KMPResidualModel

    trained = load_model(files.model)
    monkeypatch.setattr(train, "train_model", lambda *args, **kwargs: trained)

    def interrupted_save(self, directory, metadata=None):
        (Path(directory) / "kmp.npz").write_bytes(b"half")
        raise KeyboardInterrupt

    monkeypatch.setattr(KMPResidualModel, "save", interrupted_save)
    _assert_interrupted_training_keeps_the_model(files, tmp_path, capsys)


def test_train_interrupted_with_no_previous_model_leaves_nothing(files, tmp_path, capsys, monkeypatch):
    import kvark_ros.core.learning.training as baselines

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(baselines, "fit_kmp", interrupted)
    target = tmp_path / "models" / "panda"
    code, err = _cli(capsys, _train(files, tmp_path, target))
    assert code == 130 and err.strip() == "kvark: interrupted"
    assert not target.exists()
    assert not target.parent.exists() or list(target.parent.iterdir()) == []
