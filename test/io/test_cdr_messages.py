"""Single CDR messages decoded and encoded by layout (``kvark_ros.io.cdr_messages``) hold what rosbags reads.

The reference is rosbags decoding each message on its own. The node decodes its inputs this way, so a layout
taken for another (other joint names of the same length, another frame, other array lengths) would feed the
filter wrong numbers: those cases are checked here, with alignment padding that differs between messages.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from kvark_ros.io import cdr_messages
from kvark_ros.io.cdr_arrays import message_fields
from kvark_ros.io.cdr_messages import (Decoder, Template, bool_message, float64_array_template,
                                       joint_state_template, wrench_template)
from kvark_ros.io.common import BOOL, FLOAT64_ARRAY, JOINT_STATE, WRENCH_STAMPED, typestore

ROOT = Path(__file__).resolve().parents[2]
ARM = [f"panda_joint{i}" for i in range(1, 8)]
STORE = typestore()
TYPES = STORE.types


def joint_state(ns: int, names: list[str], position, velocity, effort, frame: str = ""):
    """A rosbags JointState; None: an empty field."""
    def array(values) -> np.ndarray:
        return np.empty(0) if values is None else np.asarray(values, dtype=np.float64)
    stamp = TYPES["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    return TYPES[JOINT_STATE](header=TYPES["std_msgs/msg/Header"](stamp=stamp, frame_id=frame), name=list(names),
                              position=array(position), velocity=array(velocity), effort=array(effort))


def float64_array(values, labels: list[str]):
    """A rosbags Float64MultiArray with one dimension labelled with the comma-joined ``labels``."""
    values = np.asarray(values, dtype=np.float64)
    dim = TYPES["std_msgs/msg/MultiArrayDimension"](label=",".join(labels), size=len(values), stride=len(values))
    return TYPES[FLOAT64_ARRAY](layout=TYPES["std_msgs/msg/MultiArrayLayout"](dim=[dim], data_offset=0), data=values)


def _same_numbers(numbers: dict, message, msgtype: str) -> bool:
    expected = message_fields(message, msgtype)
    return set(numbers) == set(expected) and all(
        numbers[name].dtype.isnative and np.array_equal(numbers[name], expected[name].reshape(-1))
        and numbers[name].tobytes() == expected[name].reshape(-1).astype(numbers[name].dtype).tobytes()
        for name in numbers)


@pytest.mark.parametrize("bag", sorted((ROOT / "bags").glob("panda_*")), ids=lambda path: path.name)
def test_every_message_of_the_committed_bags_decodes_as_rosbags_decodes_it(bag):
    """Joint states, commands and true torques of each bag: the same numbers bit for bit and the same names or
    labels, from one layout per topic."""
    decoders = {}
    with Reader(bag) as reader:
        for connection, _, raw in reader.messages():
            if connection.msgtype not in (JOINT_STATE, FLOAT64_ARRAY, WRENCH_STAMPED):
                continue
            decoder = decoders.setdefault(connection.topic, Decoder(connection.msgtype))
            first, numbers = decoder.decode(bytes(raw))
            expected = STORE.deserialize_cdr(raw, connection.msgtype)
            assert _same_numbers(numbers, expected, connection.msgtype), connection.topic
            if connection.msgtype == JOINT_STATE:
                assert first.name == expected.name
            elif connection.msgtype == FLOAT64_ARRAY:
                assert first.layout.dim[0].label == expected.layout.dim[0].label
    assert decoders and all(len(decoder._templates) == 1 for decoder in decoders.values())


def _padded(raw: bytes, fill: int) -> bytes:
    """``raw`` (a JointState) with its alignment padding bytes set to ``fill``, as a middleware that leaves
    its buffer's old bytes there sends it."""
    template = Template.read(raw, JOINT_STATE, STORE.deserialize_cdr(raw, JOINT_STATE))
    kept = np.zeros(len(raw), dtype=bool)
    for start, run in template.runs:
        kept[start:start + len(run)] = True
    for offset, dtype, _, count in template.fields.values():
        kept[offset:offset + dtype.itemsize * count] = True
    out = np.frombuffer(raw, np.uint8).copy()
    out[~kept] = fill
    return out.tobytes()


def test_a_message_of_another_layout_is_never_taken_for_a_known_one():
    """Same size, other names (joint 7 where joint 1 was), another order, another frame, other lengths: each
    decodes to its own names and numbers; padding bytes that differ do not make a new layout."""
    rng = np.random.default_rng(3)
    q, qd = rng.normal(size=7), rng.normal(size=7)
    variants = [ARM, ARM[::-1], ["panda_joint7"] + ARM[1:], ARM[:6], ARM + ["panda_finger_joint1"]]
    decoder = Decoder(JOINT_STATE)
    for round_ in range(2):
        for names in variants:
            for frame in ("", "base"):
                message = joint_state(10**9 + round_, names, q[:len(names)] if len(names) <= 7 else np.r_[q, 0.01],
                                      qd[:len(names)] if len(names) <= 7 else np.r_[qd, 0.0], None, frame)
                raw = bytes(STORE.serialize_cdr(message, JOINT_STATE))
                for padding in (0x00, 0xA5):
                    first, numbers = decoder.decode(_padded(raw, padding))
                    assert first.name == names and first.header.frame_id == frame
                    assert _same_numbers(numbers, message, JOINT_STATE)
                    velocity = decoder.decode(_padded(raw, padding), ("velocity",))[1]
                    assert list(velocity) == ["velocity"] and np.array_equal(velocity["velocity"], message.velocity)
    assert decoder._count == len(variants) * 2, "one layout per names and frame, whatever the padding"


def test_big_endian_messages_give_native_numbers():
    message = float64_array(np.arange(7.0) * np.pi, ARM)
    raw = bytes(STORE.serialize_cdr(message, FLOAT64_ARRAY, little_endian=False))
    assert raw[1] == 0
    for _ in range(2):                       # the first decode reads the layout, the second uses it
        first, numbers = Decoder(FLOAT64_ARRAY).decode(raw)
        assert numbers["data"].dtype == np.float64 and np.array_equal(numbers["data"], message.data)


def test_a_message_whose_layout_cannot_be_read_is_decoded_by_rosbags(monkeypatch):
    """Where ``cdr_arrays`` cannot read a layout, every message goes to rosbags and nothing is cached; a subset of
    the fields is given as asked."""
    decoder = Decoder(JOINT_STATE)
    monkeypatch.setattr(cdr_messages.Template, "read", classmethod(lambda cls, raw, msgtype, message: None))
    for k in range(3):
        message = joint_state(k, ARM, np.full(7, k), np.zeros(7), np.ones(7))
        raw = bytes(STORE.serialize_cdr(message, JOINT_STATE))
        first, numbers = decoder.decode(raw)
        assert _same_numbers(numbers, message, JOINT_STATE) and first.name == ARM
        assert set(decoder.decode(raw, ("sec", "position"))[1]) == {"sec", "position"}
    assert decoder._count == 0


@pytest.mark.parametrize("cut", [3, 40, 200])
def test_bytes_that_are_no_message_raise_a_value_error(cut):
    raw = bytes(STORE.serialize_cdr(joint_state(1, ARM, np.zeros(7), np.zeros(7), None), JOINT_STATE))
    with pytest.raises(ValueError, match="not a sensor_msgs/msg/JointState message"):
        Decoder(JOINT_STATE).decode(raw[:cut])


def test_templates_encode_what_rosbags_decodes():
    rng = np.random.default_rng(5)
    tau, w, data = rng.normal(size=7), rng.normal(size=6), rng.normal(size=36)
    torque = STORE.deserialize_cdr(joint_state_template(ARM).fill({"sec": 12, "nanosec": 345, "effort": tau}),
                                   JOINT_STATE)
    assert (torque.header.stamp.sec, torque.header.stamp.nanosec, torque.name) == (12, 345, ARM)
    assert np.array_equal(torque.effort, tau) and not len(torque.position) and not len(torque.velocity)
    wrench = STORE.deserialize_cdr(wrench_template("panda_hand_tcp").fill({"sec": 1, "nanosec": 2, "wrench": w}),
                                   WRENCH_STAMPED)
    force, moment = wrench.wrench.force, wrench.wrench.torque
    assert wrench.header.frame_id == "panda_hand_tcp"
    assert [force.x, force.y, force.z, moment.x, moment.y, moment.z] == w.tolist()
    dims = [("row", 6, 36), ("column", 6, 6)]
    array = STORE.deserialize_cdr(float64_array_template(dims, 36).fill({"data": data}), FLOAT64_ARRAY)
    assert [(d.label, d.size, d.stride) for d in array.layout.dim] == dims and np.array_equal(array.data, data)
    assert [STORE.deserialize_cdr(bool_message(flag), BOOL).data for flag in (False, True)] == [False, True]
    with pytest.raises(ValueError, match="effort: 6 values for a field of 7"):
        joint_state_template(ARM).fill({"effort": tau[:6]})


@pytest.mark.parametrize("frame", ["", "base", "panda_link0", "a_frame_id_of_some_length"])
def test_a_wrench_with_its_covariance_and_the_flags_encode_what_rosbags_decodes(frame):
    """TwistWithCovarianceStamped carrying a wrench (linear = force, angular = torque) and its 6×6 covariance, for
    frame ids whose lengths put the numbers at every 8-byte alignment, decoded back by its layout; the flags as a
    JointState's positions."""
    rng = np.random.default_rng(len(frame))
    wrench, covariance = rng.normal(size=6), rng.normal(size=36)
    raw = cdr_messages.wrench_with_covariance_template(frame).fill(
        {"sec": 7, "nanosec": 8, "wrench": wrench, "covariance": covariance})
    message = STORE.deserialize_cdr(raw, cdr_messages.TWIST_WITH_COVARIANCE_STAMPED)
    twist = message.twist.twist
    assert (message.header.stamp.sec, message.header.stamp.nanosec, message.header.frame_id) == (7, 8, frame)
    assert [twist.linear.x, twist.linear.y, twist.linear.z, twist.angular.x, twist.angular.y,
            twist.angular.z] == wrench.tolist()
    assert np.array_equal(message.twist.covariance, covariance)
    numbers = cdr_messages.Decoder(cdr_messages.TWIST_WITH_COVARIANCE_STAMPED).decode(raw)[1]   # by its layout
    assert np.array_equal(numbers["wrench"], wrench) and np.array_equal(numbers["covariance"], covariance)
    assert (int(numbers["sec"][0]), int(numbers["nanosec"][0])) == (7, 8)
    flags = STORE.deserialize_cdr(joint_state_template(["contact", "collision"], field="position").fill(
        {"sec": 1, "nanosec": 0, "position": [1.0, 0.0]}), JOINT_STATE)
    assert flags.name == ["contact", "collision"] and flags.position.tolist() == [1.0, 0.0]
    assert not len(flags.velocity) and not len(flags.effort)


def test_a_stamped_template_is_fill_with_the_stamp_and_one_field():
    """``Template.stamped`` (the node's per-sample path) writes what ``fill`` writes: the header's stamp and one
    float64 field, the rest of the template kept; a field of the wrong length is refused."""
    rng = np.random.default_rng(9)
    tau, wrench = rng.normal(size=7), rng.normal(size=6)
    torque = joint_state_template(ARM)
    assert torque.stamped(12, 345, "effort", tau) == torque.fill({"sec": 12, "nanosec": 345, "effort": tau})
    frame = wrench_template("base")
    assert frame.stamped(-3, 999_999_999, "wrench", wrench) == frame.fill(
        {"sec": -3, "nanosec": 999_999_999, "wrench": wrench})
    flags = joint_state_template(["contact", "collision"], field="position")
    decoded = STORE.deserialize_cdr(flags.stamped(7, 8), JOINT_STATE)
    assert (decoded.header.stamp.sec, decoded.header.stamp.nanosec, decoded.position.tolist()) == (7, 8, [0.0, 0.0])
    with pytest.raises(ValueError, match="effort: 6 values for a field of 7"):
        torque.stamped(1, 2, "effort", tau[:6])
