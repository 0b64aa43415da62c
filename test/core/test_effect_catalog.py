"""The catalog of diagnosis effects (``core.effect_catalog``): every list of effects is derived from it and equals the
hand-written list it replaced, and every torque effect has its numpy columns and its compiled branch."""
from __future__ import annotations

import numpy as np
import pytest

from kvark_ros.core import effect_catalog as catalog
from kvark_ros.core.estimation import augmentation
from kvark_ros.core.estimation.augmentation import Augmentation, TorqueEffect, joint_columns
from kvark_ros.core.estimation.compiled.layouts import Effect
from kvark_ros.core.estimation.compiled.residual import EFFECT_CODES, augmentation_torque, pack_augmentation
from kvark_ros.core.learning import static_band
from kvark_ros.gap import effects
from kvark_ros.gap.effects import Priors, Term, variants

# The hand-written lists the catalog replaced, verbatim (the diagnosis tries effects in EFFECT_NAMES' order, so it
# and every list derived from it keep their order).
OLD_EFFECT_NAMES = ("coulomb_friction", "viscous_friction", "stribeck_friction", "armature", "payload",
                    "link_inertia", "drive_gain", "torque_offset", "position_ripple", "joint_offset")
OLD_PER_JOINT = ("coulomb_friction", "viscous_friction", "stribeck_friction", "armature", "drive_gain",
                 "torque_offset", "position_ripple")
OLD_TORQUE_EFFECTS = ("coulomb_friction", "viscous_friction", "stribeck_friction", "drive_gain", "torque_offset",
                      "position_ripple")
# Read only as sets (``name in``): the catalog lists them in its own order
OLD_STRUCTURAL_EFFECTS = ("payload", "link_inertia", "armature", "joint_offset")
OLD_FRICTION_EFFECTS = ("coulomb_friction", "stribeck_friction", "viscous_friction")
OLD_PARAMETERS_PER_JOINT = {"coulomb_friction": 1, "viscous_friction": 1, "stribeck_friction": 1, "drive_gain": 1,
                            "torque_offset": 1, "position_ripple": 2, "armature": 1, "joint_offset": 1}
OLD_REQUIRED_VARIANT = {"stribeck_friction": ("stribeck_velocity",), "position_ripple": ("cycles_per_rev",)}
OLD_PAYLOAD_PARAMETERS = ("mass", "mx", "my", "mz", "ixx", "ixy", "iyy", "ixz", "iyz", "izz")
OLD_PER_JOINT_PARAMETERS = {
    "coulomb_friction": ("coulomb",), "viscous_friction": ("viscous",), "stribeck_friction": ("static_minus_coulomb",),
    "armature": ("armature",), "drive_gain": ("gain_error_neg",), "torque_offset": ("offset",),
    "position_ripple": ("sin_amplitude", "cos_amplitude"), "joint_offset": ("offset",),
    "payload": OLD_PAYLOAD_PARAMETERS, "link_inertia": OLD_PAYLOAD_PARAMETERS}
OLD_NONNEGATIVE = ("coulomb_friction", "viscous_friction", "stribeck_friction", "armature")
OLD_BODY_EFFECTS = ("payload", "link_inertia")                  # gap.diagnose's ("payload", "link_inertia")
# Issue 28: every effect has a physical prior (gap.priors), not only drive gain and joint offset
PRIOR_BOUNDED = OLD_EFFECT_NAMES
OLD_STRIBECK_VELOCITIES = (0.03, 0.1, 0.3)
OLD_COULOMB_WIDTHS = (0.02, 0.05, 0.1, 0.2)
OLD_RIPPLE_CYCLES = (2, 3, 4, 6, 8, 12, 16, 24, 32, 50, 64, 100)
OLD_TANH_EPSILON = 0.02


def test_the_derived_lists_are_the_old_hand_lists():
    assert catalog.EFFECT_NAMES == OLD_EFFECT_NAMES == effects.EFFECT_NAMES
    assert catalog.PER_JOINT == OLD_PER_JOINT == effects.PER_JOINT
    assert catalog.TORQUE_EFFECTS == OLD_TORQUE_EFFECTS == augmentation.TORQUE_EFFECTS
    assert set(catalog.STRUCTURAL_EFFECTS) == set(OLD_STRUCTURAL_EFFECTS) == set(augmentation.STRUCTURAL_EFFECTS)
    assert set(static_band.FRICTION_EFFECTS) == set(OLD_FRICTION_EFFECTS)
    assert catalog.PARAMETERS_PER_JOINT == OLD_PARAMETERS_PER_JOINT == augmentation.PARAMETERS_PER_JOINT
    assert catalog.REQUIRED_VARIANT == OLD_REQUIRED_VARIANT == augmentation.REQUIRED_VARIANT
    assert catalog.NONNEGATIVE == OLD_NONNEGATIVE
    assert catalog.BODY_EFFECTS == OLD_BODY_EFFECTS
    assert catalog.PRIOR_BOUNDED == PRIOR_BOUNDED
    assert catalog.TANH_EPSILON == OLD_TANH_EPSILON == augmentation.TANH_EPSILON
    assert augmentation.PAYLOAD_SIZE == len(OLD_PAYLOAD_PARAMETERS)
    assert {name: Term(name, (0,)).per_joint_parameters for name in OLD_EFFECT_NAMES} == OLD_PER_JOINT_PARAMETERS
    assert set(catalog.TORQUE_EFFECTS) | set(catalog.STRUCTURAL_EFFECTS) == set(catalog.EFFECT_NAMES)
    assert len(set(catalog.EFFECT_NAMES)) == len(catalog.EFFECT_NAMES)


def test_the_variants_are_the_old_grids():
    """``variants`` as it was written by hand, the dicts' keys in the same order (they reach the written files)."""
    expected = {name: [{}] for name in OLD_EFFECT_NAMES}
    expected["coulomb_friction"] = [{"epsilon": eps} for eps in OLD_COULOMB_WIDTHS]
    expected["stribeck_friction"] = [{"stribeck_velocity": v, "epsilon": OLD_TANH_EPSILON}
                                     for v in OLD_STRIBECK_VELOCITIES]
    expected["position_ripple"] = [{"cycles_per_rev": float(k)} for k in OLD_RIPPLE_CYCLES]
    com = Priors(payload_com=(0.01, 0.02, 0.03))
    for name in OLD_EFFECT_NAMES:
        for priors in (None, Priors(), com):
            found = variants(name, priors)
            want = ([{"com_x": 0.01, "com_y": 0.02, "com_z": 0.03}] if name == "payload" and priors is com
                    else expected[name])
            assert found == want and [list(v) for v in found] == [list(v) for v in want], name
            assert all(type(value) is float for variant in found for value in variant.values())


def test_the_bounds_are_the_old_bounds():
    """Without a robot's derived ``limits`` (``gap.priors.robot_priors``) only drive gain and joint offset are
    bounded by their priors."""
    priors = Priors(max_gain_error=0.07, max_joint_offset=0.01, flange_mass=1.5)
    for name in OLD_EFFECT_NAMES:
        term = Term(name, (0, 2, 3), variants(name)[0])
        lo, hi = term.bounds(priors)
        want_lo, want_hi = np.full(term.size, -np.inf), np.full(term.size, np.inf)
        if name in OLD_NONNEGATIVE:
            want_lo[:] = 0.0
        elif name == "payload":
            want_lo[0] = effects.MIN_MASS - priors.flange_mass
        elif name == "drive_gain":
            want_lo[:], want_hi[:] = -0.07, 0.07
        elif name == "joint_offset":
            want_lo[:], want_hi[:] = -0.01, 0.01
        np.testing.assert_array_equal(lo, want_lo, err_msg=name)
        np.testing.assert_array_equal(hi, want_hi, err_msg=name)


def test_every_catalog_line_is_well_formed():
    for entry in catalog.EFFECTS:
        assert entry.kind in (catalog.TORQUE, catalog.STRUCTURAL), entry.name
        assert entry.layout in (catalog.JOINT, catalog.COUPLED, catalog.BODY), entry.name
        assert entry.parameters and entry.help, entry.name
        assert entry.prior, entry.name                # a physical prior for every effect (gap.priors)
        assert all(values for values in entry.grid.values()), entry.name
        if entry.kind == catalog.TORQUE:           # one column per parameter, on its own joint; ≤ 1 kernel setting
            assert entry.layout == catalog.JOINT and len(entry.required) <= 1, entry.name
        if entry.friction:
            assert entry.kind == catalog.TORQUE, entry.name


def _samples(rng: np.random.Generator, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return rng.uniform(-3.0, 3.0, shape), rng.uniform(-1.0, 1.0, shape), rng.uniform(-20.0, 20.0, shape)


@pytest.mark.parametrize("name", catalog.TORQUE_EFFECTS)
def test_every_torque_effect_has_its_columns_and_its_compiled_branch(name):
    """Its ``Effect`` member and ``joint_columns`` branch exist, give one column per parameter, and the compiled
    ``augmentation_torque`` equals the numpy ``joint_torque`` on it in every variant of its grid."""
    entry = catalog.EFFECTS_BY_NAME[name]
    assert EFFECT_CODES[name] == Effect[name.upper()]
    rng = np.random.default_rng(7)
    n = 3
    joints = np.array([0, 2])
    for variant in variants(name):
        q, qd, tau_m = _samples(rng, (50,))
        columns = joint_columns(name, variant, q, qd, tau_m)
        assert len(columns) == len(entry.parameters)
        assert all(np.shape(column) == (50,) and np.all(np.isfinite(column)) for column in columns)
        theta = rng.uniform(-1.0, 1.0, (len(joints), len(entry.parameters)))
        aug = Augmentation("test", ("a", "b", "c"), (name,), None, None, np.zeros(n), np.zeros(n),
                           (TorqueEffect(name, joints, variant, theta),), "", "")
        packed = pack_augmentation(aug)
        out = np.empty(n)
        for _ in range(20):
            q, qd, tau_m = _samples(rng, (n,))
            augmentation_torque(q, qd, tau_m, packed, out)
            np.testing.assert_allclose(out, aug.joint_torque(q, qd, tau_m), rtol=0.0, atol=1e-12, err_msg=name)
            assert np.any(out[joints] != 0.0) and out[1] == 0.0


def test_the_effect_layout_is_the_catalogs_torque_effects():
    """One ``Effect`` member per torque effect, in the catalog's order (the codes numba compiled); structural effects
    have no columns."""
    assert [member.name for member in Effect] == [name.upper() for name in catalog.TORQUE_EFFECTS]
    for name in catalog.STRUCTURAL_EFFECTS:
        with pytest.raises(ValueError, match="not a torque effect"):
            joint_columns(name, {}, np.zeros(3), np.zeros(3), np.zeros(3))
