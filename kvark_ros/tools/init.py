"""``kvark init``: a commented estimator config for a new robot, from its URDF or xacro.

The file has the format of config/panda.yaml (``kvark_estimator: ros__parameters:``, groups nested).
Its keys, defaults and comments come from ``kvark_ros.core.config_schema.KEYS``, so a generated file
always matches the schema; it is checked with ``load_config`` before it is written (atomically).
Joints are the URDF's arm: the movable joints from the base to the ee frame (``--ee-frame``), else to
where the tree first branches (a gripper's fingers stay locked), unless ``--joints`` names them. A
missing ee frame is proposed: the last link of the chain; the flange defaults to the ee frame.
Relative paths in a config are relative to its own folder: the URDF is written relative to it when it
lies in the same project (under the config folder's parent), else absolute; a xacro is expanded into
``<robot>.urdf`` next to the config; ``residual_model.model_dir`` is ``../models/<robot>`` for a
config in a ``config/`` folder (the package layout: config/ and models/ side by side), else
``models/<robot>`` next to the config. The file's key is ``/**/kvark_estimator``: it applies to the node
in any namespace (``ros2 run … --ros-args -r __ns:=/lbr --params-file FILE``) and every command reads it.
``--driver franka|ur|lbr`` sets what the driver publishes (``kvark_ros.tools.drivers``): the torque source and
its measurement, the joint-state topic, the flange and ee frames and the wrench's base frame; ``--effort-scale``
and ``--effort-offset`` the effort's conversion to N·m (a UR's motor current).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pinocchio as pin

from kvark_ros.core.config import ANY_NAMESPACE, EXAMPLE_ROBOT_DATA_PREFIX, ConfigError, load_config
from kvark_ros.core.config_sources import ConfigDocument, comment_lines, config_text
from kvark_ros.core.files import check_output, write_text_atomically
from kvark_ros.core.estimation.robot_model import RobotModel, resolve_urdf
from kvark_ros.tools.drivers import DRIVERS, Driver
from kvark_ros.tools.xacro_files import expand_xacro, parse_assignments

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers


def _joint_path(model: pin.Model, joint: int) -> list[int]:
    """Joint ids from the first joint after the base to ``joint``."""
    path = []
    while joint != 0:
        path.append(joint)
        joint = model.parents[joint]
    return path[::-1]


def _arm(model: pin.Model) -> list[int]:
    """Joints from the base while each has exactly one child joint (the arm before a gripper's fingers)."""
    children: dict[int, list[int]] = {}
    for joint in range(1, model.njoints):
        children.setdefault(model.parents[joint], []).append(joint)
    chain, joint = [], 0
    while len(children.get(joint, [])) == 1:
        joint = children[joint][0]
        chain.append(joint)
    return chain


def _last_links(model: pin.Model, joint: int) -> list[str]:
    """Links moved by ``joint`` alone (no later joint), deepest first (ties: the last in the URDF first)."""
    def depth(frame: int) -> int:
        steps = 0
        while frame != 0:
            item = model.frames[frame]
            frame = item.parentFrame if hasattr(item, "parentFrame") else item.previousFrame  # pinocchio < 3
            steps += 1
        return steps

    bodies = [(depth(k), k, f.name) for k, f in enumerate(model.frames)
              if f.type == pin.FrameType.BODY and f.parentJoint == joint]
    return [name for _, _, name in sorted(bodies, reverse=True)]


def _frame(model: pin.Model, name: str, flag: str, joint: int) -> str:
    """``name`` if the URDF has that frame, else one error listing the candidates."""
    if model.existFrame(name):
        return name
    links = ", ".join(_last_links(model, joint)) or "none"
    raise ConfigError(f"{flag} {name!r} is not a frame of the URDF; the last links of the chain are {links} "
                      f"(all links: {', '.join(f.name for f in model.frames if f.type == pin.FrameType.BODY)})")


def choose_joints_and_frames(model: pin.Model, joints: list[str] | None, ee_frame: str | None,
                             flange_frame: str | None) -> tuple[list[str], str, str, dict[str, str]]:
    """(joints, ee frame, flange frame, notes by key): the user's choices checked, the rest proposed."""
    notes: dict[str, str] = {}
    movable = list(model.names[1:])
    if joints is not None:
        unknown = [name for name in joints if name not in movable]
        if unknown:
            raise ConfigError(f"--joints: {unknown[0]!r} is not a movable joint of the URDF; it has "
                              f"{', '.join(movable)}")
        chain = [model.getJointId(name) for name in joints]
    elif ee_frame is not None:
        arm_end = (_arm(model) or [0])[-1]
        parent = model.frames[model.getFrameId(_frame(model, ee_frame, "--ee-frame", arm_end))].parentJoint
        chain = _joint_path(model, parent)
        notes["robot_model.joint_names"] = f"From the URDF: the movable joints from the base to {ee_frame}."
    else:
        chain = _arm(model)
        notes["robot_model.joint_names"] = "From the URDF: its movable joints from the base to the first branch."
    if not chain:
        raise ConfigError(f"no joint chain found (movable joints: {', '.join(movable) or 'none'}); pass --joints")
    names = [model.names[j] for j in chain]
    locked = [name for name in movable if name not in names]
    if locked:
        notes["robot_model.joint_names"] = (notes.get("robot_model.joint_names", "") +
                                            f" Locked (not estimated): {', '.join(locked)}.").strip()
    last = chain[-1]
    if ee_frame is None:
        links = _last_links(model, last)
        ee_frame = links[0] if links else model.names[last]
        notes["robot_model.ee_frame"] = (f"Proposed by kvark init: the last link of the chain (candidates: "
                                         f"{', '.join(links)}); check it.")
    ee_frame = _frame(model, ee_frame, "--ee-frame", last)
    if flange_frame is None:
        flange_frame = ee_frame
        notes["robot_model.flange_frame"] = "Proposed by kvark init: the ee_frame; set the tool flange if it differs."
    return names, ee_frame, _frame(model, flange_frame, "--flange-frame", last), notes


def driver_settings(driver: Driver, model: pin.Model, names: list[str], given: tuple[str | None, str | None],
                    frames: tuple[str, str], scale: list[float] | None,
                    notes: dict[str, str]) -> tuple[dict[str, Any], tuple[str, str]]:
    """(config values, (ee frame, flange frame)) of ``driver`` for the chain ``names``: its frames where the user
    gave none (``given``) and the URDF has them, else ``frames`` as proposed; ``notes`` get the driver's."""
    if driver.needs_effort_scale and scale is None:
        raise ConfigError(f"--driver {driver.name}: the driver's joint_states effort is a motor current (A); pass "
                          "--effort-scale with N·m/A per joint (the robot's own: actual_current_as_torque / "
                          "actual_current), or --effort-scale 1 where it reports torque (docs/ros.md, Drivers)")
    values = {**driver.values, **driver.topics(names)}
    proposed = driver.frames(names, model.existFrame)
    chosen = tuple(mine or (theirs if theirs and model.existFrame(theirs) else default)
                   for mine, theirs, default in zip(given, proposed, frames))
    for key, mine, frame in zip(("robot_model.ee_frame", "robot_model.flange_frame"), given, chosen):
        if mine is None and frame in proposed:
            notes[key] = f"Set by kvark init --driver {driver.name}."
    if driver.base_frame and model.existFrame(driver.base_frame):
        values["wrench.base_frame"] = driver.base_frame
    notes.update(driver.notes)
    return values, (chosen[0], chosen[1])


def config_relative(target: Path, folder: Path) -> str:
    """A path as the config writes it: relative to its folder when under that folder's parent, else absolute."""
    target, folder = target.resolve(), folder.resolve()
    if target.is_relative_to(folder.parent):
        return os.path.relpath(target, folder)
    return str(target)


def _urdf(args: argparse.Namespace, out: Path) -> tuple[str, str, Path | None, str]:
    """(URDF XML, the config's robot_model.urdf, the expanded file to write or None, comment)."""
    if args.xacro:
        packages = {name: Path(folder).expanduser().resolve() for name, folder in parse_assignments(
            args.package_path, "=", "--package-path", "NAME=DIR").items()}
        arguments = parse_assignments(args.xacro_arg, ":=", "--xacro-arg", "NAME:=VALUE")
        xml = expand_xacro(Path(args.xacro), packages, arguments)
        target = out.parent / f"{args.robot}.urdf"
        given = ", ".join(f"{k}:={v}" for k, v in arguments.items()) or "none"
        return xml, target.name, target, (f"Expanded by kvark init from {Path(args.xacro).resolve()} (xacro args: "
                                          f"{given}); expand it again after changing the xacro.")
    if args.urdf.startswith(EXAMPLE_ROBOT_DATA_PREFIX):
        return resolve_urdf(args.urdf), args.urdf, None, ""
    path = Path(args.urdf).expanduser()
    if not path.is_file():
        raise ConfigError(f"{path}: URDF file not found; check --urdf")
    return path.read_text(), config_relative(path, out.parent), None, "Relative to this file's folder."


def _check(text: str, out: Path) -> None:
    """``load_config`` on the text, from a temporary file next to ``out`` (so paths resolve alike)."""
    descriptor, name = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".yaml")
    try:
        with os.fdopen(descriptor, "w") as stream:
            stream.write(text)
        load_config(name)
    except ConfigError as exc:
        raise ConfigError(f"{out}: the generated config does not validate ({exc}); please report this") from exc
    finally:
        os.unlink(name)


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser("init", help="write a commented config for a new robot from its URDF or xacro",
                                   description=__doc__.split("\n\n")[1].replace("``", ""),
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--urdf", metavar="FILE",
                        help="the robot's URDF (or example-robot-data:panda / :ur5 / :ur10)")
    source.add_argument("--xacro", metavar="FILE", help="the robot's xacro, expanded into <robot>.urdf next to --out")
    parser.add_argument("--package-path", action="append", default=[], metavar="NAME=DIR",
                        help="folder of ROS package NAME for $(find NAME) and package://NAME/ (repeatable)")
    parser.add_argument("--xacro-arg", action="append", default=[], metavar="NAME:=VALUE",
                        help="xacro argument, as after `xacro FILE` (repeatable)")
    parser.add_argument("--joints", metavar="A,B,C", help="estimated joints in chain order (default: the URDF's "
                                                          "arm, see above)")
    parser.add_argument("--ee-frame", metavar="FRAME", help="wrench reference frame (default: the chain's last link)")
    parser.add_argument("--flange-frame", metavar="FRAME", help="frame a payload attaches to (default: the ee frame)")
    parser.add_argument("--driver", choices=sorted(DRIVERS),
                        help="the ROS 2 driver that publishes the arm's joint states: franka (franka_ros2), ur "
                             "(ur_robot_driver) or lbr (lbr_fri_ros2_stack); sets the torque source, its measurement, "
                             "the topic, the frames and the wrench's base frame as it publishes them")
    parser.add_argument("--effort-scale", type=_numbers, metavar="K[,K...]",
                        help="input.effort_scale: N·m per unit of the effort field, one value or one per joint (a "
                             "motor current in A: N·m/A); needed with --driver ur")
    parser.add_argument("--effort-offset", type=_numbers, metavar="B[,B...]",
                        help="input.effort_offset: N·m added after the scale, one value or one per joint")
    parser.add_argument("--robot", required=True, help="robot name (letters, digits, _ and -): in models, reports "
                                                       "and file names")
    parser.add_argument("--out", required=True, metavar="FILE", help="config to write, e.g. config/myrobot.yaml")
    parser.add_argument("--force", action="store_true", help="replace an existing --out (and expanded URDF)")
    parser.set_defaults(run=run)


def _numbers(text: str) -> list[float]:
    """``--effort-scale``/``--effort-offset``: comma-separated finite numbers (argparse type)."""
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(value) for value in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}")
    return values


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    check_output(out, args.force)
    if not re.fullmatch(r"[A-Za-z0-9_-]+", args.robot):
        raise ConfigError(f"--robot {args.robot!r}: use letters, digits, _ and - only (it names files)")
    xml, urdf_value, expanded, urdf_note = _urdf(args, out)
    if expanded is not None:
        check_output(expanded, args.force)
    try:
        model = pin.buildModelFromXML(xml)
    except RuntimeError as exc:
        raise ConfigError(f"{args.urdf or args.xacro}: the URDF could not be parsed ({exc})") from exc
    joints = [name.strip() for name in args.joints.split(",")] if args.joints else None
    names, ee_frame, flange_frame, notes = choose_joints_and_frames(model, joints, args.ee_frame, args.flange_frame)
    driver_values: dict[str, Any] = {}
    if args.driver is not None:
        driver_values, (ee_frame, flange_frame) = driver_settings(
            DRIVERS[args.driver], model, names, (args.ee_frame, args.flange_frame), (ee_frame, flange_frame),
            args.effort_scale, notes)
    driver_values.update({key: value for key, value in (("input.effort_scale", args.effort_scale),
                                                          ("input.effort_offset", args.effort_offset)) if value})
    RobotModel(xml, names, ee_frame, flange_frame)   # the estimator's own checks (chain order, 1-DoF joints)
    model_dir = f"../models/{args.robot}" if out.parent.resolve().name == "config" else f"models/{args.robot}"
    train_out = os.path.relpath(out.parent.resolve() / model_dir)
    notes["robot_model.urdf"] = urdf_note
    notes["residual_model.model_dir"] = "Relative to this file's folder; `kvark train --out` must write this directory."
    values = {"robot": args.robot, "robot_model.urdf": urdf_value, "robot_model.joint_names": names,
              "robot_model.ee_frame": ee_frame, "robot_model.flange_frame": flange_frame,
              "residual_model.model_dir": model_dir, **driver_values}
    header = [f"kvark_ros estimator configuration: {args.robot} ({len(names)} joints), written by `kvark init`.",
              "The same file is the ROS 2 node's parameter file and the config of `kvark import`, `kvark diagnose`,",
              "`kvark train` and `kvark replay`. Units are SI (rad, rad/s, N·m, N, s). Nested groups become dotted",
              "ROS parameter names, e.g. filter.ewma_time. Each key's first comment lines are its row of the key",
              "table (kvark_ros/core/config_schema.py; `kvark config --keys` prints them all);",
              "`python -m kvark_ros.tools.generate_sources --write-configs FILE` rewrites them, keeping the values",
              "and the notes after a lone '#'.",
              "Relative paths (robot_model.urdf, residual_model.model_dir, model_augmentation) are relative to",
              f"this file's folder. The key {ANY_NAMESPACE} applies to the node in any namespace."]
    if args.driver is not None:
        header.append(f"Driver: kvark init --driver {args.driver} set the torque source, the topic and the frames "
                      "(docs/ros.md, Drivers).")
    text = config_text(ConfigDocument(header=[f"# {line}" if line else "#" for line in header], values=values,
                                      notes={key: comment_lines(note, key) for key, note in notes.items() if note},
                                      node_key=ANY_NAMESPACE))
    out.parent.mkdir(parents=True, exist_ok=True)
    _check(text, out)
    if expanded is not None:
        write_text_atomically(expanded, xml)
    write_text_atomically(out, text)
    print(f"kvark init: wrote {out} (robot {args.robot})")
    if expanded is not None:
        print(f"  URDF: {expanded} (expanded from {args.xacro})")
    print(f"  joints ({len(names)}): {', '.join(names)}")
    for key in ("robot_model.joint_names", "robot_model.ee_frame", "robot_model.flange_frame"):
        shown = [] if key == "robot_model.joint_names" else [str(values[key])]
        shown += [f"({notes[key]})"] if key in notes else []
        print(f"  {key.split('.')[-1]}: {' '.join(shown)}")
    for key in ("input.torque_source", "input.joint_states_topic", "input.effort_scale", "wrench.base_frame"):
        if key in driver_values:
            print(f"  {key}: {driver_values[key]}")
    print(f"  model directory: {model_dir} (relative to {out.parent}); train it with "
          f"`kvark train --config {args.out} --bags BAG... --out {train_out}`")
    return 0
