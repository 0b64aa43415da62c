"""The population's payload identification recording (tools/sim_bags.py): an excitation carrying the robot's payload,
read as a user reads a tool's mass; simulated once and reused. A population Panda for 1 s: a few seconds."""
from __future__ import annotations

import numpy as np

from kvark_ros.io import read_run
from kvark_ros.sim.population import draw_robot
from kvark_ros.sim.scenarios import simulate
from kvark_ros.tools.sim_bags import PAYLOAD_ID_LABEL, PAYLOAD_ID_SEED, BenchmarkPlan, simulate_payload_identification

PLAN = BenchmarkPlan(train_seeds=(11,), train_duration=1.0, test_duration=1.0)


def test_the_payload_identification_run_carries_the_payload_and_is_simulated_once(tmp_path):
    """Its true external torque is the payload's: the same excitation without the payload has none, and here the
    shoulder's RMS is at least 1 N·m per kg of payload (measured 6.5, its gravity at a ~0.67 m lever; 1 would still
    hold with the flange 0.1 m from the axis on average). A second call finds the bag and simulates nothing."""
    robot = draw_robot(0, 29)
    lines: list[str] = []
    path = simulate_payload_identification(robot.setup, PLAN, tmp_path, 7, lines.append, robot.payload_plant())
    assert path == tmp_path / PAYLOAD_ID_LABEL and len(lines) == 1
    carried = read_run(path).external_torque.effort
    bare = simulate(robot.setup, "excitation", 7 + PAYLOAD_ID_SEED, PLAN.train_duration, robot.plant).external_torque
    assert bare is None or not np.any(bare.effort)
    assert np.sqrt(np.mean(carried[:, 1] ** 2)) >= 1.0 * robot.payload_kg
    assert simulate_payload_identification(robot.setup, PLAN, tmp_path, 7, lines.append,
                                           robot.payload_plant()) == path and len(lines) == 1
