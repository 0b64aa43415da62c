"""Round trips through real rosbag2 files (MCAP and sqlite3) written with rosbags."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kvark_ros.core.files import OutputExistsError
from kvark_ros.io import (
    BagError,
    BagWriter,
    CommandSeries,
    JointStateSeries,
    RecordedRun,
    TopicNames,
    WrenchSeries,
    bag_info,
    read_run,
    write_run,
)

ARM = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGERS = ("panda_finger_joint1", "panda_finger_joint2")


def make_run(names: tuple[str, ...] = ARM, steps: int = 40, seed: int = 0) -> RecordedRun:
    """A small run with every topic; stamps are whole nanoseconds (exact round trip)."""
    rng = np.random.default_rng(seed)
    n = len(names)
    ns = 1_700_000_000 + np.arange(steps) * 2_000_000  # 1.7 s + 2 ms steps
    stamp = ns / 1e9
    cmd_stamp = (ns + 500_000) / 1e9  # commands 0.5 ms after the state
    return RecordedRun(
        joint_states=JointStateSeries(
            stamp,
            names,
            rng.normal(size=(steps, n)),
            rng.normal(size=(steps, n)),
            rng.normal(size=(steps, n)),
        ),
        commands=CommandSeries(cmd_stamp, rng.normal(size=(steps, n))),
        wrench=WrenchSeries(
            stamp, "panda_hand_tcp", rng.normal(size=(steps, 3)), rng.normal(size=(steps, 3))
        ),
        external_torque=JointStateSeries(
            stamp,
            names,
            np.zeros((steps, n)),
            np.zeros((steps, n)),
            rng.normal(size=(steps, n)),
        ),
    )


def assert_joint_series_equal(a: JointStateSeries, b: JointStateSeries) -> None:
    assert a.names == b.names
    for key in ("stamp", "position", "velocity", "effort"):
        got, want = getattr(a, key), getattr(b, key)
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got, want, err_msg=key)


def mcap_file(bag: Path) -> Path:
    (found,) = bag.glob("*.mcap")
    return found


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_round_trip_is_exact(tmp_path: Path, storage: str) -> None:
    run = make_run()
    path = tmp_path / "run"
    write_run(path, run, storage=storage)
    got = read_run(path)

    assert got.joint_names == ARM
    assert_joint_series_equal(got.joint_states, run.joint_states)
    assert got.external_torque is not None and run.external_torque is not None
    assert_joint_series_equal(got.external_torque, run.external_torque)
    assert got.commands is not None and run.commands is not None
    np.testing.assert_array_equal(got.commands.stamp, run.commands.stamp)
    np.testing.assert_array_equal(got.commands.effort, run.commands.effort)
    assert got.wrench is not None and run.wrench is not None
    assert got.wrench.frame_id == "panda_hand_tcp"
    np.testing.assert_array_equal(got.wrench.stamp, run.wrench.stamp)
    np.testing.assert_array_equal(got.wrench.force, run.wrench.force)
    np.testing.assert_array_equal(got.wrench.torque, run.wrench.torque)

    info = bag_info(path)
    assert info["storage"] == storage
    assert info["topics"]["/joint_states"] == {"type": "sensor_msgs/msg/JointState", "count": 40}
    assert info["topics"]["/effort_commands"]["type"] == "std_msgs/msg/Float64MultiArray"
    assert info["message_count"] == 160


def test_optional_topics_absent_read_as_none(tmp_path: Path) -> None:
    run = make_run()
    bare = RecordedRun(run.joint_states, None)
    write_run(tmp_path / "bare", bare)
    got = read_run(tmp_path / "bare")
    assert got.commands is None and got.wrench is None and got.external_torque is None
    assert_joint_series_equal(got.joint_states, run.joint_states)


def test_custom_topic_names_and_bare_mcap_file(tmp_path: Path) -> None:
    topics = TopicNames(joint_states="/franka/joint_states", effort_commands="/cmd")
    run = make_run()
    write_run(tmp_path / "run", run, topics=topics)
    got = read_run(mcap_file(tmp_path / "run"), topics=topics)  # the storage file itself
    assert_joint_series_equal(got.joint_states, run.joint_states)
    assert got.commands is not None
    with pytest.raises(BagError, match="/joint_states"):
        read_run(tmp_path / "run")


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_reorders_columns_by_name_and_drops_extra_joints(tmp_path: Path, storage: str) -> None:
    # The bag's messages carry 9 joints (arm + fingers) in a scrambled order.
    scrambled = (ARM[3], FINGERS[0], ARM[6], ARM[0], ARM[5], FINGERS[1], ARM[2], ARM[1], ARM[4])
    run = make_run(scrambled)
    write_run(tmp_path / "run", run, storage=storage)
    wanted = ARM[::-1]
    got = read_run(tmp_path / "run", joint_names=wanted)

    cols = [scrambled.index(name) for name in wanted]
    assert got.joint_names == wanted
    for key in ("position", "velocity", "effort"):
        np.testing.assert_array_equal(
            getattr(got.joint_states, key), getattr(run.joint_states, key)[:, cols]
        )
    assert got.commands is not None and run.commands is not None
    np.testing.assert_array_equal(got.commands.effort, run.commands.effort[:, cols])
    assert got.external_torque is not None and run.external_torque is not None
    np.testing.assert_array_equal(got.external_torque.effort, run.external_torque.effort[:, cols])


def test_unlabelled_commands_are_in_joint_names_order(tmp_path: Path) -> None:
    path = tmp_path / "run"
    with BagWriter(path) as bag:
        for k in range(3):
            t = 1.0 + 0.002 * k
            bag.joint_state(
                "/joint_states", t, ARM[::-1] + FINGERS, np.arange(9.0), np.zeros(9), np.zeros(9)
            )
            bag.float64_array("/effort_commands", t, np.arange(7.0) + k)
    got = read_run(path, joint_names=ARM)
    np.testing.assert_array_equal(got.joint_states.position[0], np.arange(7.0)[::-1])
    assert got.commands is not None
    np.testing.assert_array_equal(got.commands.effort[2], np.arange(7.0) + 2)
    # Without joint_names the run would have 9 joints but the commands only 7 values.
    with pytest.raises(BagError, match="joint_names"):
        read_run(path)


def test_joint_state_on_effort_commands_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "run"
    with BagWriter(path, storage="sqlite3") as bag:
        for k in range(4):
            t = 2.0 + 0.001 * k
            bag.joint_state("/joint_states", t, ARM, np.full(7, k), np.zeros(7), np.zeros(7))
            # Commands as JointState (effort field), other order, extra finger joints.
            bag.joint_state(
                "/effort_commands",
                t + 0.0002,
                FINGERS + ARM[::-1],
                effort=np.r_[-1.0, -1.0, np.arange(7.0)[::-1]] * (k + 1),
            )
    got = read_run(path)
    assert got.commands is not None
    assert got.commands.effort.shape == (4, 7)
    np.testing.assert_array_equal(got.commands.effort[1], 2 * np.arange(7.0))
    # Bag log time, stored as integer nanoseconds.
    np.testing.assert_array_equal(
        got.commands.stamp, (2_000_200_000 + 1_000_000 * np.arange(4)) / 1e9
    )


def test_messages_from_another_publisher_are_skipped(tmp_path: Path) -> None:
    path = tmp_path / "run"
    with BagWriter(path) as bag:
        for k in range(5):
            t = 1.0 + 0.002 * k
            bag.joint_state("/joint_states", t, ARM, np.full(7, k), np.zeros(7), np.zeros(7))
            bag.joint_state("/joint_states", t + 0.001, FINGERS, np.zeros(2), np.zeros(2))
    got = read_run(path, joint_names=ARM)
    assert got.joint_states.stamp.shape == (5,)
    np.testing.assert_array_equal(got.joint_states.position[:, 0], np.arange(5.0))
    # Velocity present, effort left empty by the publisher -> NaN, not zeros.
    with BagWriter(tmp_path / "noeffort") as bag:
        bag.joint_state("/joint_states", 1.0, ARM, np.zeros(7), np.zeros(7))
    assert np.isnan(read_run(tmp_path / "noeffort").joint_states.effort).all()


def test_output_sorted_by_stamp(tmp_path: Path) -> None:
    path = tmp_path / "run"
    with BagWriter(path) as bag:
        for t in (3.0, 1.0, 2.0):
            bag.joint_state("/joint_states", t, ARM, np.full(7, t), np.zeros(7), np.zeros(7))
    got = read_run(path)
    np.testing.assert_array_equal(got.joint_states.stamp, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(got.joint_states.position[:, 0], [1.0, 2.0, 3.0])


# --------------------------------------------------------------------------- failures


def test_missing_joint_names_it(tmp_path: Path) -> None:
    path = tmp_path / "run"
    write_run(path, make_run())
    with pytest.raises(BagError) as err:
        read_run(path, joint_names=(*ARM[:6], "panda_joint8"))
    message = str(err.value)
    assert str(path) in message and "panda_joint8" in message and "\n" not in message


def test_all_joints_missing_and_foreign_commands(tmp_path: Path) -> None:
    path = tmp_path / "run"
    write_run(path, make_run())
    with pytest.raises(BagError, match="fr3_joint1") as err:
        read_run(path, joint_names=("fr3_joint1", "fr3_joint2"))
    assert str(path) in str(err.value) and "panda_joint1" in str(err.value)
    # Labelled commands for other joints only: named, not silently dropped.
    other = tmp_path / "other"
    with BagWriter(other) as bag:
        bag.joint_state("/joint_states", 1.0, ARM, np.zeros(7), np.zeros(7), np.zeros(7))
        bag.float64_array("/effort_commands", 1.0, np.zeros(2), names=FINGERS)
    with pytest.raises(BagError, match="/effort_commands"):
        read_run(other)


def test_bag_from_another_writer_with_zero_header_stamps(tmp_path: Path) -> None:
    """A driver that never fills header stamps: fall back to the bag log time."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=""
    )
    path = tmp_path / "recorded"
    with Writer(path, version=8) as writer:  # sqlite3, version 8 (Humble-style)
        conn = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        for k in range(3):
            msg = types["sensor_msgs/msg/JointState"](
                header=header,
                name=list(ARM),
                position=np.full(7, float(k)),
                velocity=np.zeros(7),
                effort=np.zeros(7),
            )
            writer.write(
                conn,
                5_000_000_000 + k * 1_000_000,
                store.serialize_cdr(msg, "sensor_msgs/msg/JointState"),
            )
    got = read_run(path)
    np.testing.assert_array_equal(
        got.joint_states.stamp, (5_000_000_000 + np.arange(3) * 1_000_000) / 1e9
    )
    assert got.commands is None


def test_missing_joint_states_topic_lists_topics(tmp_path: Path) -> None:
    path = tmp_path / "run"
    with BagWriter(path) as bag:
        bag.float64_array("/effort_commands", 1.0, np.zeros(7))
        bag.boolean("/contact", 1.0, True)
    with pytest.raises(BagError) as err:
        read_run(path)
    message = str(err.value)
    assert str(path) in message and "/joint_states" in message
    assert "/effort_commands" in message and "/contact" in message and "\n" not in message


def test_wrong_message_type_on_topic(tmp_path: Path) -> None:
    path = tmp_path / "run"
    with BagWriter(path) as bag:
        bag.float64_array("/joint_states", 1.0, np.zeros(7))
    with pytest.raises(BagError, match="Float64MultiArray") as err:
        read_run(path)
    assert str(path) in str(err.value)


def test_not_a_bag_and_missing_path(tmp_path: Path) -> None:
    folder = tmp_path / "notes"
    folder.mkdir()
    (folder / "readme.txt").write_text("not a bag")
    for path in (folder, tmp_path / "nowhere", folder / "readme.txt"):
        with pytest.raises(BagError) as err:
            read_run(path)
        assert str(path) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(BagError, match="nowhere"):
        bag_info(tmp_path / "nowhere")


def test_truncated_mcap_raises_bag_error(tmp_path: Path) -> None:
    path = tmp_path / "run"
    write_run(path, make_run())
    data = mcap_file(path).read_bytes()
    mcap_file(path).write_bytes(data[: len(data) // 2])
    for target in (path, mcap_file(path)):
        with pytest.raises(BagError) as err:
            read_run(target)
        assert str(target) in str(err.value) and "\n" not in str(err.value)


def test_corrupt_sqlite_raises_bag_error(tmp_path: Path) -> None:
    path = tmp_path / "run"
    write_run(path, make_run(), storage="sqlite3")
    (db,) = path.glob("*.db3")
    db.write_bytes(b"garbage" * 100)
    with pytest.raises(BagError) as err:
        read_run(path)
    assert str(path) in str(err.value)


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "run"
    path.mkdir()                    # an empty directory is no output: written without force
    write_run(path, make_run(seed=1))
    with pytest.raises(OutputExistsError, match="exists and is not empty; pass --force") as err:
        write_run(path, make_run(seed=2))
    assert str(path) in str(err.value)
    with pytest.raises(OutputExistsError):
        BagWriter(path)
    np.testing.assert_array_equal(  # the old bag is intact
        read_run(path).joint_states.position, make_run(seed=1).joint_states.position
    )
    write_run(path, make_run(seed=2), storage="sqlite3", force=True)
    np.testing.assert_array_equal(
        read_run(path).joint_states.position, make_run(seed=2).joint_states.position
    )
    assert bag_info(path)["storage"] == "sqlite3"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no temp leftovers


@pytest.mark.parametrize("force", [False, True])
def test_failed_write_leaves_no_partial_output(tmp_path: Path, force: bool) -> None:
    path = tmp_path / "out"
    if force:
        write_run(path, make_run(seed=3))
    with pytest.raises(RuntimeError, match="boom"), BagWriter(path, force=force) as bag:
        bag.joint_state("/joint_states", 1.0, ARM, np.zeros(7), np.zeros(7), np.zeros(7))
        raise RuntimeError("boom")
    if force:  # the previous bag survives untouched
        np.testing.assert_array_equal(
            read_run(path).joint_states.effort, make_run(seed=3).joint_states.effort
        )
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    else:
        assert not path.exists()
        assert list(tmp_path.iterdir()) == []
    # A write that fails on bad data inside write_run is just as clean.
    bad = make_run()
    bad_stamp = bad.joint_states.stamp.copy()
    bad_stamp[5] = np.nan
    broken = RecordedRun(
        JointStateSeries(
            bad_stamp,
            ARM,
            bad.joint_states.position,
            bad.joint_states.velocity,
            bad.joint_states.effort,
        ),
        None,
    )
    with pytest.raises(ValueError):
        write_run(tmp_path / "broken", broken)
    assert not (tmp_path / "broken").exists()
    assert all(not p.name.startswith(".") for p in tmp_path.iterdir())


def test_bag_writer_outputs_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "replay"
    with BagWriter(path) as bag:
        bag.joint_state("/kvark_estimator/external_joint_torque", 1.5, ARM, effort=np.arange(7.0))
        bag.wrench("/kvark_estimator/external_wrench", 1.5, "base", [1, 2, 3], [4, 5, 6])
        bag.float64_array(
            "/kvark_estimator/external_joint_torque_stddev", 1.5, np.ones(7), names=ARM
        )
        bag.boolean("/kvark_estimator/contact", 1.5, True)
        with pytest.raises(ValueError):
            bag.wrench("/kvark_estimator/external_wrench", 1.6, "base", [1, 2], [4, 5, 6])
    info = bag_info(path)
    assert info["message_count"] == 4
    assert info["topics"]["/kvark_estimator/contact"]["type"] == "std_msgs/msg/Bool"
    run = read_run(
        path,
        topics=TopicNames(
            joint_states="/kvark_estimator/external_joint_torque",
            wrench="/kvark_estimator/external_wrench",
        ),
    )
    np.testing.assert_array_equal(run.joint_states.effort[0], np.arange(7.0))
    assert np.isnan(run.joint_states.position).all()
    assert run.wrench is not None and run.wrench.frame_id == "base"
    np.testing.assert_array_equal(run.wrench.torque[0], [4.0, 5.0, 6.0])
