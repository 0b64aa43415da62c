"""The simulated robot population (kvark_ros.sim.population): deterministic draws, every value inside the range
the module documents, rates a real controller runs at, and bags logged at the robot's own rate."""
from __future__ import annotations

import numpy as np
import pytest

from kvark_ros.core.config import default_config_path, load_config
from kvark_ros.sim import population as pop
from kvark_ros.sim.plant import CONTROL_RATES_HZ, load_plant
from kvark_ros.sim.scenarios import simulate

SEEDS = (1000, 1001)
COUNT = 12          # four robots of each class per seed


def _inside(values, low, high) -> bool:
    values = np.atleast_1d(np.asarray(values, dtype=float))
    return bool(np.all(values >= low - 1e-9) and np.all(values <= high + 1e-9))   # rounding to 6 digits


def test_same_seed_same_robots_and_another_seed_other_robots() -> None:
    first = pop.draw_population(COUNT, SEEDS[0])
    assert first == pop.draw_population(COUNT, SEEDS[0])
    other = pop.draw_population(COUNT, SEEDS[1])
    assert all(a.plant != b.plant for a, b in zip(first, other))
    assert [r.arm for r in first] == [pop.ARM_CLASSES[i % 3] for i in range(COUNT)]
    assert pop.draw_robot(5, SEEDS[0]) == first[5]          # a robot does not depend on the population's size


@pytest.mark.parametrize("seed", SEEDS)
def test_every_drawn_value_is_inside_its_documented_range(seed: int) -> None:
    for robot in pop.draw_population(COUNT, seed):
        arm, plant = robot.arm, robot.plant
        effort = np.array(pop.effort_limits(arm))
        n = len(effort)
        spec = load_plant(robot.payload_plant(), n)         # the simulator accepts it
        assert robot.rate_hz in pop.RATES_HZ[arm] and robot.rate_hz in CONTROL_RATES_HZ
        friction = plant["friction"]
        coulomb = np.array(friction["coulomb"])
        assert _inside(coulomb / effort, *pop.COULOMB_SHARE[arm])
        assert _inside(np.array(friction["static"]) / coulomb, *pop.STATIC_RATIO)
        assert _inside(friction["stribeck_velocity"], *pop.STRIBECK_VELOCITY)
        assert _inside(np.array(friction["viscous"]) / effort, *pop.VISCOUS_SHARE[arm])
        assert _inside(plant["friction_drift"]["relative_amplitude"], *pop.FRICTION_DRIFT)
        assert _inside(plant["friction_drift"]["time_constant_s"], *pop.DRIFT_TIME_S)
        big, small = pop.ARMATURE[arm]
        assert _inside(plant["armature"][:3], *big) and _inside(plant["armature"][3:], *small)
        links = plant["link_inertia"]
        assert _inside(links["mass_rel"], *pop.LINK_MASS_REL) and _inside(links["com_m"], *pop.LINK_COM_M)
        assert _inside(links["inertia_rel"], *pop.LINK_INERTIA_REL)
        error = np.abs(np.array(plant["drive_gain"]) - 1.0)
        assert _inside(error, *pop.GAIN_ERROR[arm])           # never 1: every drive is off by its drawn share
        assert _inside(np.abs(plant["torque_offset"]) / effort, 0.0, pop.OFFSET_SHARE)
        assert _inside(np.array(plant["torque_offset_drift"]["amplitude"]) / effort, *pop.OFFSET_DRIFT_SHARE)
        assert _inside(plant["torque_offset_drift"]["period_s"], *pop.OFFSET_PERIOD_S)
        assert _inside(np.array(plant["position_ripple"]["amplitude"]) / effort, *pop.RIPPLE_SHARE)
        assert set(plant["position_ripple"]["cycles_per_rev"]) <= set(map(float, pop.RIPPLE_ORDERS))
        noise = plant["noise"]
        assert _inside([noise["torque_std"], noise["torque_std_per_rad_s"]], *pop.NOISE[arm])
        assert _inside(robot.payload_kg, *pop.PAYLOAD_MASS) and spec.payload is not None
        assert spec.payload.mass == robot.payload_kg and "payload" not in plant   # only the payload scene carries it
        lateral, com_z = np.array(spec.payload.com[:2]), spec.payload.com[2]
        assert _inside(np.abs(lateral), 0.0, pop.PAYLOAD_LATERAL)
        grasp = pop.GRASP_OFFSET_M[arm]
        assert _inside(com_z, grasp + pop.PAYLOAD_GAP[0] + pop.PAYLOAD_LENGTH[0] / 2,
                       grasp + pop.PAYLOAD_GAP[1] + pop.PAYLOAD_LENGTH[1] / 2)


def test_ur_classes_carry_a_current_gain_error_larger_than_the_pandas() -> None:
    robots = pop.draw_population(COUNT, SEEDS[0])
    worst = {arm: max(np.abs(np.array(r.plant["drive_gain"]) - 1).max() for r in robots if r.arm == arm)
             for arm in pop.ARM_CLASSES}
    least = {arm: min(np.abs(np.array(r.plant["drive_gain"]) - 1).min() for r in robots if r.arm == arm)
             for arm in pop.ARM_CLASSES}
    assert worst["panda"] <= 0.02 < 0.03 <= min(least["ur5"], least["ur10"])
    assert max(worst["ur5"], worst["ur10"]) <= 0.08


def test_rates_cover_the_four_controller_rates() -> None:
    rates = {r.rate_hz for seed in SEEDS for r in pop.draw_population(COUNT, seed)}
    assert rates == {100.0, 125.0, 500.0, 1000.0}


def test_a_100_hz_robot_writes_100_hz_bags() -> None:
    robot = next(r for r in pop.draw_population(COUNT, SEEDS[0]) if r.rate_hz == 100.0)
    run = simulate(robot.setup, "collision", seed=1000, duration=0.3, plant=robot.plant, progress=False)
    stamps = run.joint_states.stamp
    assert len(stamps) == 30                                  # 0.3 s at 100 Hz
    np.testing.assert_allclose(np.diff(stamps), 0.01, atol=1e-9)
    np.testing.assert_array_equal(run.commands.stamp, stamps)


def test_bad_index_or_seed_is_refused() -> None:
    with pytest.raises(ValueError, match="index and seed"):
        pop.draw_robot(-1, 1000)


def test_motor_current_arms_carry_a_weighed_known_load_drawn_on_its_own() -> None:
    """Every UR5- and UR10-class robot has a known load in its documented range (mass, radius, length, gap) on the
    flange axis, the Panda class none (link-side sensors); the draw is deterministic and the calibration plant is the
    robot's plant carrying it."""
    for robot in pop.draw_population(COUNT, SEEDS[0]):
        if robot.arm not in pop.MOTOR_CURRENT_ARMS:
            assert robot.known_load is None
            with pytest.raises(ValueError, match="no known-load recording"):
                robot.known_load_plant()
            continue
        load = robot.known_load
        assert _inside(load["mass"], *pop.KNOWN_LOAD_MASS) and load["com"][:2] == [0.0, 0.0]
        length = 2.0 * (load["com"][2] - pop.KNOWN_LOAD_GAP[0])
        assert _inside(load["com"][2], pop.KNOWN_LOAD_GAP[0] + pop.KNOWN_LOAD_LENGTH[0] / 2,
                       pop.KNOWN_LOAD_GAP[1] + pop.KNOWN_LOAD_LENGTH[1] / 2) and length > 0.0
        # I_zz = m r² / 2 of the drawn (unrounded) mass; the stored mass is rounded to 0.1 g: 5e-5 of 2 kg
        assert load["inertia"][2] == pytest.approx(0.5 * load["mass"] * pop.KNOWN_LOAD_RADIUS ** 2, rel=1e-4)
        spec = load_plant(robot.known_load_plant(), len(pop.effort_limits(robot.arm)))
        assert spec.payload is not None and spec.payload.mass == load["mass"]
        assert pop.draw_robot(robot.index, SEEDS[0]).known_load == load
    for arm in pop.ARM_CLASSES:          # the arms whose configs say their τ_m is a motor current
        current = load_config(default_config_path(arm)).torque_measurement == "motor_current"
        assert current == (arm in pop.MOTOR_CURRENT_ARMS), arm
