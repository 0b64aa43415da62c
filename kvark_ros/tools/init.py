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
``models/<robot>`` next to the config.
"""

from __future__ import annotations

import argparse
import os
import re
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import pinocchio as pin

from kvark_ros.core.config import EXAMPLE_ROBOT_DATA_PREFIX, ConfigError, load_config
from kvark_ros.core.config_sources import ConfigDocument, comment_lines, config_text
from kvark_ros.core.files import check_output, write_text_atomically
from kvark_ros.core.estimation.robot_model import RobotModel, resolve_urdf
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
    source.add_argument("--urdf", metavar="FILE", help="the robot's URDF (or example-robot-data:panda / :ur5)")
    source.add_argument("--xacro", metavar="FILE", help="the robot's xacro, expanded into <robot>.urdf next to --out")
    parser.add_argument("--package-path", action="append", default=[], metavar="NAME=DIR",
                        help="folder of ROS package NAME for $(find NAME) and package://NAME/ (repeatable)")
    parser.add_argument("--xacro-arg", action="append", default=[], metavar="NAME:=VALUE",
                        help="xacro argument, as after `xacro FILE` (repeatable)")
    parser.add_argument("--joints", metavar="A,B,C", help="estimated joints in chain order (default: the URDF's "
                                                          "arm, see above)")
    parser.add_argument("--ee-frame", metavar="FRAME", help="wrench reference frame (default: the chain's last link)")
    parser.add_argument("--flange-frame", metavar="FRAME", help="frame a payload attaches to (default: the ee frame)")
    parser.add_argument("--robot", required=True, help="robot name (letters, digits, _ and -): in models, reports "
                                                       "and file names")
    parser.add_argument("--out", required=True, metavar="FILE", help="config to write, e.g. config/myrobot.yaml")
    parser.add_argument("--force", action="store_true", help="replace an existing --out (and expanded URDF)")
    parser.set_defaults(run=run)


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
    RobotModel(xml, names, ee_frame, flange_frame)   # the estimator's own checks (chain order, 1-DoF joints)
    model_dir = f"../models/{args.robot}" if out.parent.resolve().name == "config" else f"models/{args.robot}"
    train_out = os.path.relpath(out.parent.resolve() / model_dir)
    notes["robot_model.urdf"] = urdf_note
    notes["residual_model.model_dir"] = "Relative to this file's folder; `kvark train --out` must write this directory."
    values = {"robot": args.robot, "robot_model.urdf": urdf_value, "robot_model.joint_names": names,
              "robot_model.ee_frame": ee_frame, "robot_model.flange_frame": flange_frame,
              "residual_model.model_dir": model_dir}
    header = [f"kvark_ros estimator configuration: {args.robot} ({len(names)} joints), written by `kvark init`.",
              "The same file is the ROS 2 node's parameter file and the config of `kvark import`, `kvark diagnose`,",
              "`kvark train` and `kvark replay`. Units are SI (rad, rad/s, N·m, N, s). Nested groups become dotted",
              "ROS parameter names, e.g. filter.ewma_time. Each key's first comment lines are its row of the key",
              "table (kvark_ros/core/config_schema.py; `kvark config --keys` prints them all);",
              "`python -m kvark_ros.core.config_sources --write-configs FILE` rewrites them, keeping the values",
              "and the notes after a lone '#'.",
              "Relative paths (robot_model.urdf, residual_model.model_dir, model_augmentation) are relative to",
              "this file's folder."]
    text = config_text(ConfigDocument(header=[f"# {line}" if line else "#" for line in header], values=values,
                                      notes={key: comment_lines(note, key) for key, note in notes.items() if note}))
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
    print(f"  model directory: {model_dir} (relative to {out.parent}); train it with "
          f"`kvark train --config {args.out} --bags BAG... --out {train_out}`")
    return 0
