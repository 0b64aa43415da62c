"""Every physical effect of the model-gap diagnosis by name: the one table behind ``kvark diagnose``'s library
(``gap.effects``), ``augmentation.yaml`` (``core.estimation.augmentation``) and the static friction band
(``core.learning.static_band``).

One entry an effect: its name, its kind, its parameters and bounds, the grid of fixed (non-linear) settings the
diagnosis tries it with, the settings a file's entry must give, and what it is. The table is data only (it imports
nothing of the package); every list of effects the package uses is derived from it below, in the table's order,
which is the order the diagnosis tries them in (and so the order of its outputs). An effect's formulas live with
the code that evaluates them:

* a ``torque`` effect (a joint torque τ_aug the estimator adds, ``M q̈ + C q̇ + g + τ_aug = τ_m + τ_ext``): its
  regressor columns in ``core.estimation.augmentation.joint_columns`` and, compiled, a member of
  ``core.estimation.compiled.layouts.Effect`` (its name in upper case) with its branch in
  ``core.estimation.compiled.residual.augmentation_torque``;
* a ``structural`` effect (a change of M, C, g or of q): how ``core.estimation.augmentation.parse_augmentation``
  keeps it, how ``core.estimation.robot_model`` applies it, and its regressor in ``gap.effects`` (``signals``,
  ``Term.design``).

``test/core/test_effect_catalog.py`` checks that every torque effect has its columns and its compiled branch.
"""
from __future__ import annotations

from types import MappingProxyType
from typing import Mapping, NamedTuple

TORQUE, STRUCTURAL = "torque", "structural"
JOINT, COUPLED, BODY = "joint", "coupled", "body"
TANH_EPSILON = 0.02   # rad/s, default width ε of the smoothed sign(q̇) of dry friction
# A rigid body's 10 inertial parameters [m, m c, I_origin] (pinocchio's dynamic parameters)
BODY_PARAMETERS = ("mass", "mx", "my", "mz", "ixx", "ixy", "iyy", "ixz", "iyz", "izz")


class EffectEntry(NamedTuple):
    """A physical effect of the model gap.

    kind: ``TORQUE`` (a joint torque the estimator adds) or ``STRUCTURAL`` (changes M, C, g or q);
    parameters: the names of the parameters each joint carries (a ``BODY`` effect: the body's 10);
    layout: ``JOINT`` (its own parameters per joint, screened joint by joint), ``COUPLED`` (one parameter per joint
        acting on other joints' gaps, screened jointly) or ``BODY`` (rigid bodies' 10 parameters, on every joint);
    nonnegative: θ ≥ 0 (a physical lower bound);
    friction: the static friction band (``core.learning.static_band``) reads it as friction;
    grid: the fixed settings the diagnosis tries, every combination (keys in this order);
    required: the settings an ``augmentation.yaml`` entry must give (a torque effect: at most one, the compiled
        kernel's second parameter);
    prior: what bounds |θ| ('' for none), derived per robot by ``gap.priors`` and scaled by how τ_m is measured:
        at that bound the effect stands for another one and the diagnosis drops it (and warns when the data want it
        beyond);
    between_runs: why it changes between runs of one calibrated robot ('' for none: the robot's construction,
        calibrated once); ``kvark diagnose --against`` names only these unless told otherwise;
    help: what it is (θ's sign and units).
    """

    name: str
    kind: str
    parameters: tuple[str, ...]
    layout: str = JOINT
    nonnegative: bool = False
    friction: bool = False
    grid: Mapping[str, tuple[float, ...]] = MappingProxyType({})
    required: tuple[str, ...] = ()
    prior: str = ""
    between_runs: str = ""
    help: str = ""


EFFECTS = (
    EffectEntry("coulomb_friction", TORQUE, ("coulomb",), nonnegative=True, friction=True,
                grid={"epsilon": (0.02, 0.05, 0.1, 0.2)}, prior="share of the effort limit",
                between_runs="gear temperature and wear", help="F_c tanh(q̇/ε), F_c ≥ 0 N·m; ε rad/s"),
    EffectEntry("viscous_friction", TORQUE, ("viscous",), nonnegative=True, friction=True,
                prior="share of the effort limit at the velocity limit",
                between_runs="lubricant temperature", help="F_v q̇, F_v ≥ 0 N·m·s/rad"),
    EffectEntry("stribeck_friction", TORQUE, ("static_minus_coulomb",), nonnegative=True, friction=True,
                grid={"stribeck_velocity": (0.03, 0.1, 0.3), "epsilon": (TANH_EPSILON,)},
                required=("stribeck_velocity",), prior="share of the effort limit",
                between_runs="gear temperature and wear",
                help="(F_s − F_c) exp(−(q̇/v_s)²) tanh(q̇/ε) ≥ 0 N·m; v_s rad/s"),
    EffectEntry("armature", STRUCTURAL, ("armature",), nonnegative=True,
                prior="effort limit × rotor acceleration time / velocity limit",
                help="I_a q̈, I_a ≥ 0 kg·m²: rotor inertia on M's diagonal"),
    EffectEntry("payload", STRUCTURAL, BODY_PARAMETERS, BODY, prior="mass the effort limits hold at the flange",
                between_runs="a tool or load mounted",
                help="change of the flange link's inertial parameters (flange frame): a tool (m > 0) or a mismatch"),
    EffectEntry("link_inertia", STRUCTURAL, BODY_PARAMETERS, BODY, prior="share of each link's mass and moment",
                help="changes of the other links' inertial parameters (joint frames): CAD errors"),
    EffectEntry("drive_gain", TORQUE, ("gain_error_neg",), prior="share per torque measurement (--max-gain-error)",
                help="the drive applies g τ_m: gap (1 − g) τ_m, θ = 1 − g"),
    EffectEntry("torque_offset", TORQUE, ("offset",), prior="share of the effort limit",
                between_runs="sensor and current-offset drift", help="the drive applies τ_m + o: gap −o, θ = o N·m"),
    EffectEntry("position_ripple", TORQUE, ("sin_amplitude", "cos_amplitude"),
                grid={"cycles_per_rev": (2, 3, 4, 6, 8, 12, 16, 24, 32, 50, 64, 100)}, required=("cycles_per_rev",),
                prior="share of the effort limit",
                help="the drive applies a sin(k q) + b cos(k q): gap −(a sin + b cos), N·m; k cycles per "
                     "revolution"),
    EffectEntry("joint_offset", STRUCTURAL, ("offset",), COUPLED, prior="1° (--max-joint-offset)",
                help="the encoder reads q + δ: gap −∂τ_EL/∂q δ (first order), δ rad"),
)
# How wide the priors are for each way τ_m is measured (``robot_model.torque_measurement``; reasons in ``gap.priors``):
# gain |1 − g|; offset, ripple and friction as shares of the joint's effort limit; armature: the factor c.
MEASUREMENT_WIDTHS: Mapping[str, Mapping[str, float]] = MappingProxyType({
    "link_torque_sensor": {"gain": 0.02, "offset": 0.02, "ripple": 0.01, "friction": 0.10, "armature": 0.25},
    "motor_current": {"gain": 0.10, "offset": 0.03, "ripple": 0.02, "friction": 0.20, "armature": 1.0},
    "commanded_effort": {"gain": 0.20, "offset": 0.05, "ripple": 0.05, "friction": 0.30, "armature": 2.0},
})
EFFECTS_BY_NAME = {entry.name: entry for entry in EFFECTS}
EFFECT_NAMES = tuple(entry.name for entry in EFFECTS)
TORQUE_EFFECTS = tuple(entry.name for entry in EFFECTS if entry.kind == TORQUE)
STRUCTURAL_EFFECTS = tuple(entry.name for entry in EFFECTS if entry.kind == STRUCTURAL)
PER_JOINT = tuple(entry.name for entry in EFFECTS if entry.layout == JOINT)
BODY_EFFECTS = tuple(entry.name for entry in EFFECTS if entry.layout == BODY)
FRICTION_EFFECTS = tuple(entry.name for entry in EFFECTS if entry.friction)
NONNEGATIVE = tuple(entry.name for entry in EFFECTS if entry.nonnegative)
# What can change between runs of one calibrated robot: the default library of ``kvark diagnose --against``
CHANGES_BETWEEN_RUNS = tuple(entry.name for entry in EFFECTS if entry.between_runs)
PRIOR_BOUNDED = tuple(entry.name for entry in EFFECTS if entry.prior)
# θ values per joint of the effects that have them per joint (not the bodies')
PARAMETERS_PER_JOINT = {entry.name: len(entry.parameters) for entry in EFFECTS if entry.layout != BODY}
REQUIRED_VARIANT = {entry.name: entry.required for entry in EFFECTS if entry.required}
