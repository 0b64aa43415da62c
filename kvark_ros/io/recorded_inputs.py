"""Turn a recorded run into Estimator inputs: one (stamp, q, q̇, τ_m) per paired joint-state sample.

The pairing is the live node's (``kvark_ros.core.estimation.pairing.StreamPairer``) for the run's messages in
time order: joint states at their header stamps, commands at their log time, a command after the
state it shares a time with. A command therefore answers the newest joint state stamped at or
before it, and a state without one takes the newest earlier command no older than
``max_command_age``; the others are dropped and counted. ``input.torque_source: joint_states_effort``
takes the joint states' effort instead, and a bag without commands falls back to it.

A bag holds every message at once, so the rule decides every state together
(``core.estimation.pairing.paired_rows``, the pairer's bulk form); test/io/test_bulk_pairing.py checks the two agree.

What the commands read from a bag (``read_checked``) has τ_m through the config's ``input.effort_scale`` and
``input.effort_offset`` (``core.estimation.inputs.EffortCalibration``: the rule the node applies to every message,
so a UR's motor current in A becomes N·m alike live and offline), and is then checked against the physics of the
config's URDF as ``kvark import`` checks a log's rows (``core.estimation.sample_limits``: finite, within the limits
and their margins, no isolated stamp, no position jump): a sample beyond them is skipped and counted, with one line
per reason naming the bag, the topic, the time and the joint; a bag where most samples fail is refused with one line
(its joints, units or torque source do not match the config).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.contact_events import touching
from kvark_ros.core.estimation.inputs import EffortCalibration, EstimatorInputs, select_samples
from kvark_ros.core.estimation.pairing import paired_rows
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.sample_limits import Drop, RowCheck, SampleLimits, check_rows, counted
from kvark_ros.io import BagError, RecordedRun, TopicNames, read_run
from kvark_ros.io.common import FLOAT64_ARRAY, JOINT_STATE
from kvark_ros.io.info import topic_types
from kvark_ros.io.topic_hints import missing_topic

MIN_KEPT_SHARE = 0.5     # a bag with fewer samples within the physics is refused (kvark import's rule)
# What to check when a reason skips most of a bag's samples.
FIXES = {"position": "check that the config's robot_model (URDF, joint_names) is this robot's and q is in rad",
         "velocity": "check that the config's joint_names are this robot's and q̇ is in rad/s",
         "torque": "check input.torque_source and that the torque is in N·m (a motor current needs its torque "
                   "constant: input.effort_scale, or kvark import's effort scale)",
         "jump": "check that the config's joint_names are this robot's, in the bag's order",
         "far": "check the bag's header stamps", "non-finite": "re-record or re-import the bag"}


def estimator_inputs(run: RecordedRun, max_command_age: float = 0.01, path: str = "bag",
                     torque_source: str = "effort_commands", topics: TopicNames | None = None) -> EstimatorInputs:
    """Pair joint states with commands (module docstring); ``torque_source`` is ``input.torque_source``.

    ``joint_states_effort`` takes the joint states' effort even when the bag records commands. The two
    command sources take the command topic (Float64MultiArray or JointState alike); a bag without one
    falls back to the joint states' effort, and ``torque_source`` of the result says so. ``topics``: the
    ones ``run`` was read with from the bag ``path``, for an error that names the bag's command topics.
    """
    states = run.joint_states
    commands = run.commands
    if torque_source != "joint_states_effort" and commands is not None and len(commands.stamp) > 0:
        rows, paired = paired_rows(states.stamp, commands.stamp, max_command_age)
        stamp, q, qd, tau_m = states.stamp[rows], states.position[rows], states.velocity[rows], commands.effort[paired]
        return EstimatorInputs(stamp, q, qd, tau_m, "effort_commands", len(states.stamp) - len(stamp),
                               run.simulated)
    fresh = np.isfinite(states.effort).all(axis=1)
    if not fresh.any():
        problem = "no usable τ_m: no effort commands and no measured effort in joint_states"
        if torque_source == "joint_states_effort":
            raise BagError(f"{path}: {problem}; set input.torque_source to effort_commands and record the commanded "
                           "torque")
        if topics is None:
            raise BagError(f"{path}: {problem}; record the commanded torque on the topic input.effort_commands_topic "
                           "names")
        raise missing_topic(path, f"no usable τ_m: no effort commands on {topics.effort_commands} "
                                  "(input.effort_commands_topic) and no measured effort in joint_states",
                            topics.effort_commands, "input.effort_commands_topic", topic_types(path),
                            {FLOAT64_ARRAY, JOINT_STATE}, exclude=(topics.joint_states, topics.external_torque))
    label = ("joint_states effort" if torque_source == "joint_states_effort"
             else "joint_states effort (the bag has no effort commands)")
    return EstimatorInputs(states.stamp[fresh], states.position[fresh], states.velocity[fresh],
                           states.effort[fresh], label, int((~fresh).sum()), run.simulated)


def _topic(reason: str, detail: str, topics: TopicNames, torque_source: str) -> str:
    """The topic a skipped sample's reason points to: the torque's for τ, else the joint states'."""
    torque = reason == "torque" or (reason == "non-finite" and " τ = " in detail)
    return topics.effort_commands if torque and torque_source == "effort_commands" else topics.joint_states


def _skipped(drop: Drop, stamp: np.ndarray, topics: TopicNames, torque_source: str) -> str:
    """What ``drop`` skipped: count, topic, times (s from the first of ``stamp``) and what the first one shows."""
    first, last = stamp[drop.rows[0]] - stamp[0], stamp[drop.rows[-1]] - stamp[0]
    topic = _topic(drop.reason, drop.detail, topics, torque_source)
    return (f"skipped {counted(len(drop.rows), 'sample')} of {topic}, "
            f"{drop.text}, at {first:.3f}{'' if len(drop.rows) == 1 else f'-{last:.3f}'} s (first: {drop.detail})")


def skipped_lines(bag: str | Path, check: RowCheck, stamp: np.ndarray, topics: TopicNames,
                  torque_source: str) -> list[str]:
    """One line per reason samples of ``bag`` were skipped (``_skipped``; ``stamp``: the samples checked)."""
    return [f"{bag}: {_skipped(drop, stamp, topics, torque_source)}" for drop in check.drops]


def read_checked(bag: str | Path, config: EstimatorConfig, limits: SampleLimits | None = None
                 ) -> tuple[RecordedRun, EstimatorInputs, RowCheck, list[str]]:
    """``read_inputs``' run and inputs, the inputs within ``limits`` (default: the config's URDF, module
    docstring), the check and its ``skipped_lines``; a BagError if fewer than two samples or under
    ``MIN_KEPT_SHARE`` of them are within."""
    topics = TopicNames.from_config(config.input)
    run = read_run(bag, config.joint_names, topics)
    inputs = EffortCalibration.from_config(config).to_inputs(
        estimator_inputs(run, config.input.command_max_age, str(bag), config.input.torque_source, topics))
    if limits is None:
        limits = SampleLimits.from_robot(RobotModel(config.urdf, config.joint_names, config.ee_frame))
    check = check_rows(inputs.stamp, inputs.q, inputs.qd, inputs.tau_m, limits)
    source = "effort_commands" if inputs.torque_source == "effort_commands" else "joint_states"
    lines = skipped_lines(bag, check, inputs.stamp, topics, source)
    kept = int(check.kept.sum())
    if not check.drops and kept < 2:
        raise BagError(f"{bag}: {kept} usable samples of {len(run.joint_states.stamp)} joint states; check that "
                       f"{topics.joint_states} and {topics.effort_commands} overlap (input.command_max_age) and that "
                       "their stamps increase")
    if check.drops and (kept < 2 or kept < MIN_KEPT_SHARE * len(inputs)):
        main = max(check.drops, key=lambda drop: len(drop.rows))
        raise BagError(f"{bag}: {kept} of {len(inputs)} samples within the physics of {limits.source}, "
                       f"{_skipped(main, inputs.stamp, topics, source)}; {FIXES.get(main.reason, 're-record it')}")
    return run, inputs.take(check.kept) if check.drops else inputs, check, lines


def read_inputs(bag: str | Path, config: EstimatorConfig,
                log: Callable[[str], None] | None = print) -> tuple[RecordedRun, EstimatorInputs]:
    """The run of ``bag`` read with the config's topics and joints, and its estimator inputs from the config's
    ``input.torque_source`` within the physics of its URDF (``read_checked``; what ``kvark train``, ``replay``,
    ``diagnose`` and ``benchmark`` read); ``log`` gets the lines of skipped samples (None: not shown)."""
    run, inputs, _, lines = read_checked(bag, config)
    for line in lines if log is not None else ():
        log(f"warning: {line}")
    return run, inputs


def contact_warning(bag: str, run: RecordedRun, kept: EstimatorInputs, start: float) -> str | None:
    """One line when the bag's ground-truth external torque (``/ground_truth/external_joint_torque``: simulated or
    imported bags) shows contact within the ``kept`` samples (``core.contact_events.touching``): the bag is not
    contact-free. Times are s from ``start`` (the bag's first sample, as --trim counts them). Without ground truth
    nothing is checked."""
    truth = run.external_torque
    if truth is None or not len(kept):
        return None
    within = (truth.stamp >= kept.stamp[0]) & (truth.stamp <= kept.stamp[-1])
    effort = truth.effort[within]
    over = np.flatnonzero(touching(effort))
    if not len(over):
        return None
    size = np.nan_to_num(np.abs(effort), nan=0.0)
    row, joint = np.unravel_index(np.argmax(size), size.shape)
    elapsed = truth.stamp[within][over] - start
    return (f"{bag}: ground truth shows external torque up to {size[row, joint]:.1f} N·m on {run.joint_names[joint]} "
            f"at {elapsed[0]:.1f}-{elapsed[-1]:.1f} s (of {kept.stamp[-1] - start:.1f} s); use contact-free bags or "
            "--trim it out")


def load_recordings(bags: Sequence[str], config: EstimatorConfig, tag: str, trim: tuple[float, float] = (0.0, 0.0),
                    rate: float = 0.0) -> list[EstimatorInputs]:
    """Estimator inputs of every bag within the physics of the config's URDF (``read_checked``), trimmed and
    decimated (``select_samples``), with one status line each, a warning line per reason samples were skipped for
    and one for a bag whose ground truth shows contact (``contact_warning``); train and diagnose read bags this
    way."""
    segments = []
    for bag in bags:
        run, inputs, _, skipped = read_checked(bag, config)
        kept = select_samples(inputs, trim, rate) if len(inputs) > 1 else inputs
        count = f"{len(kept)}" if len(kept) == len(inputs) else f"{len(kept)} of {len(inputs)}"
        print(f"[{tag}] {bag}: {count} samples (τ_m from {kept.torque_source}, "
              f"{kept.dropped} dropped{', simulated' if kept.simulated else ''})", flush=True)
        for line in skipped:
            print(f"[{tag}] warning: {line}", flush=True)
        warning = contact_warning(bag, run, kept, float(inputs.stamp[0])) if len(inputs) else None
        if warning is not None:
            print(f"[{tag}] warning: {warning}", flush=True)
        segments.append(kept)
    return segments
