"""``kvark excitation``: the simulator's optimised excitation trajectory, for a real arm, to record training data.

The trajectory is ``sim/excitation.py``'s (paper v1 eqs. 24-25): whole-cycle Fourier harmonics about a centre pose,
faded in and out so that it starts and ends at rest there, the log-det of its (q, q̇, q̈) cloud maximised by
differential evolution and scaled until it keeps strictly within the limits on a 500 Hz grid. Here the limits are
the config's URDF's and the user's: the position window ``--centre`` ± ``--half-range`` (cut to the URDF's position
limits × ``--position-scale``), the URDF's velocity limits × ``--velocity-scale`` and ``--acceleration``
(a URDF has no acceleration limits). No MuJoCo: only the [sim] extra's ``simulate`` needs it.

Written into ``--out`` (whole, atomically; see ``--force``):

- ``excitation.csv``: time (s from the start of the motion) and q, q̇, q̈ of every joint at ``--rate`` Hz;
- ``joint_trajectory.yaml``: the trajectory_msgs/JointTrajectory (points at ``--rate`` with positions, velocities
  and accelerations, the first ``--start-delay`` s after the message arrives), as ``ros2 topic echo`` writes a
  message;
- ``joint_trajectory/``: a rosbag2 bag of that one message on ``--topic``, for ``ros2 bag play`` to send to the
  driver's joint trajectory controller.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from kvark_ros.core.config import ConfigError, EstimatorConfig, load_config
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.files import staged_directory
from kvark_ros.io.cdr_messages import JOINT_TRAJECTORY, joint_trajectory_message
from kvark_ros.io.writer import BagWriter, Messages
from kvark_ros.sim.excitation import CHECK_RATE_HZ, ExcitationLimits, optimise_excitation, urdf_limits

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

__all__ = ["add_parser", "limits_for", "run"]


def _per_joint(text: str, flag: str, n: int, positive: bool = True) -> np.ndarray:
    """A flag's one value (every joint) or n comma-separated values, as an (n,) array."""
    try:
        values = np.array([float(part) for part in text.split(",")])
    except ValueError as exc:
        raise ConfigError(f"{flag} {text!r}: give one number or {n} comma-separated numbers") from exc
    if len(values) not in (1, n) or not np.isfinite(values).all() or (positive and (values <= 0.0).any()):
        raise ConfigError(f"{flag} {text!r}: give one {'positive ' if positive else ''}number or {n} "
                          "comma-separated ones (one per robot_model.joint_names)")
    return np.broadcast_to(values, (n,)).copy()


def limits_for(config: EstimatorConfig, centre: np.ndarray, half_range: np.ndarray, acceleration: np.ndarray,
               position_scale: float, velocity_scale: float) -> ExcitationLimits:
    """The box the trajectory keeps in (module docstring): ``centre`` ± ``half_range`` cut to the URDF's position
    limits shrunk about their middle by ``position_scale``; ``velocity_scale`` × the URDF's velocity limits;
    ``acceleration`` (n,) rad/s². ConfigError for a centre outside the shrunk limits, naming the joint."""
    lower, upper, velocity = urdf_limits(RobotModel.from_config(config).model, position_scale, velocity_scale)
    low, high = np.maximum(centre - half_range, lower), np.minimum(centre + half_range, upper)
    outside = np.flatnonzero((centre <= lower) | (centre >= upper))
    if len(outside):
        j = outside[0]
        raise ConfigError(f"--centre: {config.joint_names[j]} = {centre[j]:g} rad is not within its URDF limits × "
                          f"--position-scale [{lower[j]:.3f}, {upper[j]:.3f}] rad")
    # The window about the centre, symmetric: the nearer of the two cut edges.
    window = np.minimum(centre - low, high - centre)
    return ExcitationLimits(centre=centre.copy(), half_range=window, velocity=velocity, acceleration=acceleration)


def _trajectory_yaml(names: list[str], times: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> str:
    """The JointTrajectory as ``ros2 topic echo`` writes a message (YAML, lists in flow style)."""
    def point(k: int) -> dict:
        sec, nanosec = divmod(int(round(times[k] * 1e9)), 1_000_000_000)
        return {"positions": q[k].tolist(), "velocities": qd[k].tolist(), "accelerations": qdd[k].tolist(),
                "effort": [], "time_from_start": {"sec": sec, "nanosec": nanosec}}
    message = {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""}, "joint_names": names,
               "points": [point(k) for k in range(len(times))]}
    return yaml.safe_dump(message, sort_keys=False, default_flow_style=None, width=120)


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    names, n = list(config.joint_names), config.n_joints
    if args.duration <= 2 * args.ramp or args.rate <= 0.0 or args.start_delay < 0.0:
        raise ConfigError(f"--duration {args.duration:g} s must exceed twice --ramp ({args.ramp:g} s), --rate be "
                          "positive and --start-delay at least 0")
    limits = limits_for(config, _per_joint(args.centre, "--centre", n, positive=False),
                        _per_joint(args.half_range, "--half-range", n), _per_joint(args.acceleration,
                                                                                   "--acceleration", n),
                        args.position_scale, args.velocity_scale)
    print(f"[excitation] {config.robot}: {args.duration:g} s, {args.harmonics} harmonics, optimising "
          f"({args.population} candidates × {args.generations} generations, seed {args.seed})", flush=True)
    result = optimise_excitation(limits, args.duration, args.seed, harmonics=args.harmonics,
                                 population=args.population, generations=args.generations, ramp=args.ramp)
    trajectory = result.trajectory
    grid = np.arange(int(round(args.duration * CHECK_RATE_HZ)) + 1) / CHECK_RATE_HZ
    worst = limits.violation(*trajectory.sample(grid))                 # per joint, ≤ 1 within the limits
    times = np.arange(int(round(args.duration * args.rate)) + 1) / args.rate
    q, qd, qdd = (values + 0.0 for values in trajectory.sample(times))      # + 0.0: no "-0.0" in the files
    with staged_directory(args.out, args.force) as folder:
        with open(folder / "excitation.csv", "w", newline="") as stream:
            writer = csv.writer(stream)
            writer.writerow(["time", *[f"{kind}:{name}" for kind in ("q", "qd", "qdd") for name in names]])
            writer.writerows(np.column_stack([times, q, qd, qdd]).tolist())
        sent = times + args.start_delay
        (folder / "joint_trajectory.yaml").write_text(_trajectory_yaml(names, sent, q, qd, qdd))
        raw = joint_trajectory_message(names, sent, q, qd, qdd)
        with BagWriter(folder / "joint_trajectory") as bag:
            bag.write_block(Messages(args.topic, JOINT_TRAJECTORY, np.zeros(1, dtype=np.int64),
                                     np.frombuffer(raw, dtype=np.uint8)[None, :]))
    print(f"[excitation] wrote {args.out}: excitation.csv, joint_trajectory.yaml, joint_trajectory/ (on {args.topic}); "
          f"{len(times)} points at {args.rate:g} Hz, starting {args.start_delay:g} s after the message at the centre "
          f"pose, at rest", flush=True)
    print(f"[excitation] largest share of a limit used (position window, velocity, acceleration; 500 Hz grid): "
          + ", ".join(f"{name} {value:.2f}" for name, value in zip(names, worst)), flush=True)
    print(f"[excitation] log-det coverage {result.logdet:.1f} (best of the initial population "
          f"{result.initial_best_logdet:.1f}); move the arm to the centre pose first, then record its joint states "
          f"while `ros2 bag play {Path(args.out) / 'joint_trajectory'}` sends it (docs/ros.md, Excitation for "
          "training data)", flush=True)
    return 0


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "excitation", help="write an optimised excitation trajectory within a real arm's limits (CSV, "
                           "JointTrajectory)",
        description=__doc__.split("\n\n")[1] + " Needs no MuJoCo.")
    parser.add_argument("--config", required=True, help="estimator config: the joints and the URDF's limits")
    parser.add_argument("--centre", required=True, metavar="Q[,Q...]",
                        help="rad, one per joint (or one for all): a collision-free pose with room around it, where "
                             "the motion starts and ends at rest")
    parser.add_argument("--half-range", default="0.3", metavar="R[,R...]",
                        help="rad each joint may move either side of --centre (cut to the URDF's limits); "
                             "default %(default)s")
    parser.add_argument("--acceleration", default="1.0", metavar="A[,A...]",
                        help="rad/s², the largest joint acceleration (a URDF has none); default %(default)s")
    parser.add_argument("--velocity-scale", type=float, default=0.5,
                        help="share of the URDF's velocity limits used; default %(default)s")
    parser.add_argument("--position-scale", type=float, default=0.8,
                        help="share of the URDF's position range the window stays in; default %(default)s")
    parser.add_argument("--duration", type=float, default=60.0, help="s of motion; default %(default)s")
    parser.add_argument("--ramp", type=float, default=2.0, help="s of fade-in and fade-out; default %(default)s")
    parser.add_argument("--harmonics", type=int, default=5, help="Fourier harmonics per joint; default %(default)s")
    parser.add_argument("--seed", type=int, default=0, help="optimiser seed (same seed, same file); default 0")
    parser.add_argument("--population", type=int, default=24, help="candidates per generation; default %(default)s")
    parser.add_argument("--generations", type=int, default=60, help="optimiser generations; default %(default)s")
    parser.add_argument("--rate", type=float, default=50.0,
                        help="Hz of the CSV rows and the trajectory's points; default %(default)s")
    parser.add_argument("--start-delay", type=float, default=5.0,
                        help="s between the message and its first point (the controller moves to the centre pose "
                             "meanwhile; start from it); default %(default)s")
    parser.add_argument("--topic", default="/joint_trajectory_controller/joint_trajectory",
                        help="topic of the bag's message: the controller's joint_trajectory topic; "
                             "default %(default)s")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (new or empty; see --force)")
    parser.add_argument("--force", action="store_true", help="replace an existing --out once the new one is complete")
    parser.set_defaults(run=run)
