"""``kvark simulate``: record a simulated run with ground truth into a ROS 2 bag."""
from __future__ import annotations

import argparse
import sys
from typing import Any

from kvark_ros.core.files import check_output
from kvark_ros.io import write_run
from kvark_ros.sim.robots import ROBOTS
from kvark_ros.sim.scenarios import SCENARIOS, SESSION_S, run_scenario

_DESCRIPTION = """\
Simulate a robot arm in MuJoCo (the plant) and write a ROS 2 bag with what the real robot
would record -- /joint_states (quantised position, noisy velocity, noisy measured effort) and
/effort_commands (commanded torque) at 500 Hz -- plus ground truth: /ft_sensor/wrench (wrist
F/T at the flange, flange frame) and /ground_truth/external_joint_torque (effort field).

scenarios:
  excitation  optimised random-Fourier trajectory (paper eqs. 24-25), joint tracking control
  payload     another optimised trajectory carrying a payload the nominal model does not know
  contact     Cartesian impedance polishing square on a table, ~15 N normal force
  collision   joint-space motion with a 20-40 N, 0.2 s push on a link every ~5 s
"""


def add_simulate_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register the ``simulate`` sub-command on an argparse ``subparsers`` object.

    The parser's ``func`` default runs it: ``args.func(args)`` returns the exit code.
    """
    parser = subparsers.add_parser(
        "simulate", help="record a simulated run with ground truth into a bag",
        description=_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robot", choices=sorted(ROBOTS), default="panda",
                        help="simulated arm: the Franka Panda (7 joints) or the UR5 (6 joints); "
                             "default: %(default)s")
    parser.add_argument("--scenario", choices=SCENARIOS, required=True,
                        help="what the robot does (see the list above)")
    parser.add_argument("--seed", type=int, default=1,
                        help="random seed: trajectory, noise, pushes; the same seed gives the same "
                             "bag; default: %(default)s")
    parser.add_argument("--duration", type=float, default=10.0,
                        help="simulated time in seconds; default: %(default)s")
    parser.add_argument("--plant", metavar="FILE", default=None,
                        help="plant file (YAML) saying how the simulated robot differs from its URDF "
                             "(friction, armature, payload, drive gains, noise); default: the robot's "
                             "shipped kvark_ros/sim/plants/<robot>_default.yaml. Never written to the bag")
    parser.add_argument("--start-time", type=float, default=None, metavar="S",
                        help="plant clock at the first sample, s since power-on: where the plant's friction "
                             "warm-up and torque-offset drifts stand; default: drawn from the seed within the "
                             f"first {SESSION_S:g} s")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                        help="rosbag2 storage format; default: %(default)s")
    parser.add_argument("--out", metavar="BAGDIR", required=True,
                        help="output bag directory (new or empty; see --force)")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing --out (only once the new bag is complete)")
    parser.set_defaults(func=run_simulate)
    return parser


def add_parser(subparsers: Any) -> None:
    """Register ``simulate`` for the ``kvark`` command, which runs ``args.run(args)``."""
    add_simulate_parser(subparsers).set_defaults(run=run_simulate)


def run_simulate(args: argparse.Namespace) -> int:
    """Run ``kvark simulate`` for parsed arguments; prints progress and the real-time factor."""
    try:
        check_output(args.out, args.force)         # refuse before minutes of simulation
        output = run_scenario(args.robot, args.scenario, args.seed, args.duration, args.plant,
                              progress=True, start_time=args.start_time)
        write_run(args.out, output.run, storage=args.storage, force=args.force)
    except ValueError as exc:          # bad plant file (PlantError), duration, existing output (OutputExistsError)
        print(f"kvark: error: {exc}", file=sys.stderr)
        return 1
    samples = len(output.run.joint_states.stamp)
    print(f"wrote {args.out}: {args.robot} {args.scenario}, {samples} samples "
          f"({args.duration:g} s simulated in {output.wall_time:.2f} s), "
          f"real-time factor {output.real_time_factor:.1f}")
    return 0
