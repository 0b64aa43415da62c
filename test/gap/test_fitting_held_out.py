"""``Fitter.held_out``, the screens' fit, is ``Fitter.fit``'s held-out residual in the same bits (``gap.fitting``)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.robot_model import RobotModel, flange_link_parameters
from kvark_ros.gap.diagnose import body_fitter, prepare
from kvark_ros.gap.effects import Priors, Term, variants
from kvark_ros.gap.priors import robot_priors
from kvark_ros.io.recorded_inputs import read_inputs

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def fitter():
    """The diagnosis's fitter on the committed excitation bag (the Panda, link-side torque sensors)."""
    config = load_config(ROOT / "config" / "panda.yaml")
    robot = RobotModel.from_config(config)
    inputs = read_inputs(ROOT / "bags" / "panda_excitation_1", config)[1]
    flange = flange_link_parameters(robot.model, robot.flange_frame_id)
    priors = robot_priors(robot, replace(Priors(torque_measurement=config.torque_measurement),
                                         flange_mass=float(flange[0])))
    train, held = prepare(robot, [inputs], 0.3, None)
    return body_fitter(robot, train, held, priors)


def _terms(n: int) -> dict[str, list[Term]]:
    coulomb = Term("coulomb_friction", (0, 3, 5), variants("coulomb_friction")[0])
    return {"none": [], "one per-joint effect": [coulomb],
            "a body and two per-joint effects": [Term("payload", tuple(range(n)), {}), coulomb,
                                                 Term("viscous_friction", tuple(range(n)), {})],
            "link inertia": [Term("link_inertia", tuple(range(n)), {})]}


@pytest.mark.parametrize("case", list(_terms(7)))
@pytest.mark.parametrize("nuisance", [False, True], ids=["alone", "with a nuisance term"])
def test_held_out_is_the_fits_held_out_residual_bit_for_bit(fitter, case, nuisance):
    """Equal, not close: the screens of the selection compare these residuals against the thresholds of
    ``gap.selection``, and a diagnosis must not depend on which of the two computed them. With a nuisance term (a
    known load's unknown moments are fitted that way) and with none (no parameter at all: the gap itself)."""
    terms = _terms(fitter.n)[case]
    fitter.nuisance = (Term("torque_offset", tuple(range(fitter.n)), {}),) if nuisance else ()
    try:
        held = fitter.held_out(terms)
        np.testing.assert_array_equal(held, fitter.fit(terms)[3])
    finally:
        fitter.nuisance = ()
    assert held.shape == fitter.held.gap.shape
    # a parameter moves the residual off the gap (on held-out samples not always down: what the screens measure)
    assert np.array_equal(held, fitter.held.gap) == (not terms and not nuisance)
