"""The layouts of the compiled step's packed arrays (``core.estimation.step_kernel``), each entry declared once.

Every array numba receives from Python costs ~1 k instructions to unbox, so the compiled step takes its state and
constants packed in a few arrays (``step_kernel`` module docstring). Their entries are declared here, one commented
line each, as a ``Layout`` (an ``IntEnum`` numbered 0, 1, … in the order declared: ``Const``, ``Param``, ``Option``,
``Vec``, ``Counter``, ``Row``, ``EstimatorParam``), and the bits of an integer as ``Bits`` (1, 2, 4, …: ``Flag``,
``Outcome``). Python code writes the arrays by member (``pack``). In Python 3.11 reading a member costs ~800
instructions (``EnumType.__getattr__``): per-sample Python code reads plain ints or views bound once
(``core.estimation.compiled_step``, ``observers.kvark_kernel``).

The layouts of ``core.estimation.model_kernels`` (``Pose``, ``Effect``) are here too.

numba freezes these numbers into the kernels' machine code, and its on-disk cache is keyed on each kernel's own
file alone: ``LAYOUTS_DIGEST`` in ``step_kernel.py`` and ``model_kernels.py`` pins this file's sha256, so changing a
layout means updating the digest there, which recompiles the kernels
(``test/core/test_compiled_step_matches_reference.py`` fails until it is done).
"""
from __future__ import annotations

import enum
from typing import Mapping


class Layout(enum.IntEnum):
    """The entries of a packed array, numbered 0, 1, … in the order declared (``vec[Vec.TAU]``); numba compiles a
    member as its integer constant. ``len`` of a layout does not compile: the kernels read the sizes from the module
    constants beside them (``VEC_ROWS = len(Vec)``)."""

    @staticmethod
    def _generate_next_value_(name: str, start: int, count: int, last_values: list) -> int:
        return count


class Bits(enum.IntEnum):
    """Bits of an integer, 1, 2, 4, … in the order declared; ``|`` of two members is a plain int."""

    @staticmethod
    def _generate_next_value_(name: str, start: int, count: int, last_values: list) -> int:
        return 1 << count


def pack(layout: type[enum.IntEnum], values: Mapping[enum.IntEnum, object]) -> list:
    """The values of ``layout``'s members in its order, from ``values`` keyed by member (a KeyError names a member
    without one): a packed array's entries written by name."""
    return [values[member] for member in layout]


class Const(Layout):
    """Rows of the per-joint constants (consts, (CONST_ROWS, n))."""

    R = enum.auto()                     # R, the measurement noise variance of p, (N·m·s)²
    R_MIN = enum.auto()                 # the EWMA R_k's floor, R_FLOOR · R, (N·m·s)²
    Q_P = enum.auto()                   # q_p, the process noise density of p (eq. 30), N²·m²·s
    Q_TAU = enum.auto()                 # q_τ, the random-walk density of τ from training (eq. 32), N²·m²/s
    Q_CONTACT = enum.auto()             # q_c, the least q_τ after an accepted onset (§4.7), N²·m²/s
    RESIDUAL_VAR = enum.auto()          # the static residual variance σ²_r (without heteroscedastic noise), N²·m²
    NEG_HALF_INV_LS2 = enum.auto()      # the q̇-only KMP's −1/(2ℓ²) (eq. 21), s²/rad²
    SIGMA_F2 = enum.auto()              # the KMP's σ_f², N²·m²
    VAR_SCALE = enum.auto()             # the KMP's N/λ₂ (eq. 23)


CONST_ROWS = len(Const)


class Param(Layout):
    """Entries of the float parameters (params, (PARAMS,)): the filter's settings per sample and the numbers of
    other modules (WINDOW_MAX_RATIO, NIS_SCALE_BOUNDS, VARIANCE_FLOOR), which reach the kernels as arguments (module
    docstring). ``KVARKKernelFilter`` writes each from the filter's attribute of its lower-case name (``ewma_rate``) or
    from its ``declared_params``."""

    EWMA_RATE = enum.auto()             # the EWMA R_k's rate per sample (eq. 31)
    NIS_RATE = enum.auto()              # the NIS mean's rate per sample (A4)
    FORGET = enum.auto()                # the window's forgetting between two closing snapshots (eq. 37)
    PRIOR_DOF = enum.auto()             # the window's prior dof (eq. 39)
    THRESHOLD = enum.auto()             # the onset detector's threshold on ℓ_θ = d²/C (§4.7)
    VB_FORGETTING = enum.auto()         # ρ of the per-sample VB's IW prediction (§4.4)
    MAX_RATIO = enum.auto()             # the window's bound q̂ ≤ ratio · q_τ (eq. 39)
    NIS_LOW = enum.auto()               # the A4 scale's lower limit
    NIS_HIGH = enum.auto()              # and its upper limit
    VARIANCE_FLOOR = enum.auto()        # the floor of the KMP's σ²_*, N²·m²


PARAMS = len(Param)


class Option(Layout):
    """Entries of the integer options (options, int64): what ``kvark_step`` runs and the sizes of the packed arrays."""

    HETEROSCEDASTIC = enum.auto()       # w_p from the residual model's σ²_* (else Const.RESIDUAL_VAR)
    EWMA = enum.auto()                  # adapt R_k (eq. 31)
    NIS = enum.auto()                   # scale Σ_d by the NIS mean (A4)
    WINDOW = enum.auto()                # the window VB estimates Σ_d (§4.6)
    ONSET = enum.auto()                 # the onset detector runs (§4.7)
    KMP = enum.auto()                   # the q̇-only KMP is evaluated inside the kernel (kmp_predict)
    STRIDE = enum.auto()                # samples from one closing snapshot of the window to the next
    SUPPORT = enum.auto()               # the KMP's support points N (split_constants)
    ONSETS = enum.auto()                # the onset detector's hypotheses M (split_state)
    VB_IW = enum.auto()                 # the per-sample VB (readings paper and smoothed, §4.4)
    SMOOTHED = enum.auto()              # its smoothed reading (lag-one RTS, §4.5)
    ITERATIONS = enum.auto()            # its VB passes per sample
    SNAPSHOTS = enum.auto()             # the window's snapshots S (split_state)
    TWIN = enum.auto()                  # the window reads the twin filter held at q_τ (vb_window_source: prior, §4.6)


class Vec(Layout):
    """Rows of the per-joint float state (vec, (VEC_ROWS, n)), the first part of the packed state (split_state)."""

    P_HAT = enum.auto()                 # momentum estimate p̂, N·m·s
    TAU = enum.auto()                   # external torque estimate τ̂, N·m
    A = enum.auto()                     # P = [[a, b], [b, c]]: a = Var p̂, (N·m·s)²
    B = enum.auto()                     # b = Cov(p̂, τ̂), N²·m²·s
    C = enum.auto()                     # c = Var τ̂, N²·m²
    R = enum.auto()                     # the EWMA's R_k (eq. 31), (N·m·s)²
    R_WEIGHT = enum.auto()              # the EWMA's mean weight w̄_k (eq. 31 weighted by (R/S)², §4.3)
    NIS = enum.auto()                   # the NIS mean, the A4 scale of Σ_d
    SIGMA_D = enum.auto()               # Σ_d of the last sample, N²·m²
    VB_DOF = enum.auto()                # the per-sample VB's IW dof λ (eq. 37)
    VB_SCALE = enum.auto()              # and its scale Υ (eq. 38), N²·m²
    Q = enum.auto()                     # the window's q̂ (Σ_d = q̂ h, §4.6), N²·m²/s
    SCALE = enum.auto()                 # the window's Υ (eq. 38), N²·m²/s
    MEAN = enum.auto()                  # the residual's μ_* (eq. 22), N·m
    VAR = enum.auto()                   # the residual's σ²_* (eq. 23), N²·m²
    TWIN_P = enum.auto()                # the window's twin filter at Σ_d0 = q_τ h (§4.6): p̂, N·m·s
    TWIN_TAU = enum.auto()              # its τ̂, N·m
    TWIN_A = enum.auto()                # its P = [[a, b], [b, c]]: a, (N·m·s)²
    TWIN_B = enum.auto()                # b, N²·m²·s
    TWIN_C = enum.auto()                # c, N²·m²


VEC_ROWS = len(Vec)


class Counter(Layout):
    """Entries of the integer state (ints, (INTS,) int64)."""

    COUNT = enum.auto()                 # the window's sample count
    SLOT = enum.auto()                  # the onset detector's ring slot of the newest hypothesis
    ALARMS = enum.auto()                # the onset detector's accepted jumps


INTS = len(Counter)


class Flag(Bits):
    """Bits of ``estimate_step``'s ``flags``: what to run this call, and the estimator's settings."""

    MOMENTUM = enum.auto()              # p, u of this sample (kept for the next)
    FILTER = enum.auto()                # the filter step, kvark_step
    POST = enum.auto()                  # τ̂, Cov τ̂, F, Σ_F and the tests' statistics
    TARED = enum.auto()                 # subtract the tare offset (§4.10)
    STICTION = enum.auto()              # widen Cov τ̂ by the static friction band (§4.11)
    SCALED = enum.auto()                # report P scaled by the interval factors (§4.13)
    END_EFFECTOR = enum.auto()          # the wrench in the ee axes
    AUGMENTED = enum.auto()             # subtract τ_aug from u (§2.2)
    TEST_REPORTED = enum.auto()         # the contact test's S: the reported covariance, not P + σ²_r (§7.2)


class Outcome(Bits):
    """Bits of the code ``estimate_step`` returns."""

    WEAK = enum.auto()                  # a direction with σ_i < δ: weak_wrench follows (§1.4.1)
    DIVERGED = enum.auto()              # a non-finite estimate
    SINGULAR = enum.auto()              # J Jᵀ + δ² I not positive definite (δ = 0 at a singular pose: refused)


class Row(Layout):
    """Rows of the estimator's per-joint buffer (rows, (ROWS, n))."""

    P_PREV = enum.auto()                # p_{k−1}, N·m·s
    U_PREV = enum.auto()                # u_{k−1}, N·m
    P = enum.auto()                     # p_k, N·m·s
    U = enum.auto()                     # u_k, N·m
    AUG = enum.auto()                   # τ_aug of this sample, N·m
    BAND = enum.auto()                  # the static friction band F_s, N·m
    SCALE = enum.auto()                 # the interval factors c (docs/method.md §4.13)
    FLOOR = enum.auto()                 # the reported variance's floor P_b, N²·m² (docs/method.md §4.13)


ROWS = len(Row)


class EstimatorParam(Layout):
    """Entries of the estimator's float parameters (params, (ESTIMATOR_PARAMS,))."""

    DAMPING = enum.auto()               # wrench.damping δ of J⁺ = (J Jᵀ + δ² I)⁻¹ J (v2 eq. 39)
    PRIOR_FORCE = enum.auto()           # wrench.prior_force, N
    PRIOR_MOMENT = enum.auto()          # wrench.prior_moment, N·m
    STICTION_VELOCITY = enum.auto()     # filter.stiction_velocity v_s, rad/s
    Z = enum.auto()                     # the collision test's z


ESTIMATOR_PARAMS = len(EstimatorParam)


class Pose(Layout):
    """Rows of ``kmp_predict_pose``'s ``pose`` (len(Pose), n), per joint (``KMPResidualModel.kernel_arrays``)."""

    LS = enum.auto()                    # −1/(2ℓ²) of q̇ (eq. 21), s²/rad²
    LS_Z = enum.auto()                  # −1/(2ℓ_z²) of the second input z (§3.7); 0 for a q̇-only joint
    SIGMA_F2 = enum.auto()              # σ_f², N²·m²
    VAR_SCALE = enum.auto()             # N/λ₂ (eq. 23)
    TAKES_Q = enum.auto()               # 1 if z = q_j, else 0
    TAKES_G = enum.auto()               # 1 if z = g_j, else 0
    TWO_INPUT = enum.auto()             # 1 if the joint has a second input (its far-field floor is the GP's), else 0


class Effect(Layout):
    """Codes of ``augmentation_torque``'s entries: one per torque effect of ``core.effect_catalog``, its name in upper
    case, in the catalog's order (``core.estimation.compiled_step.EFFECT_CODES`` maps them by name;
    ``test/core/test_effect_catalog.py`` checks that every torque effect has one)."""

    COULOMB_FRICTION = enum.auto()      # tanh(q̇/ε) θ
    VISCOUS_FRICTION = enum.auto()      # q̇ θ
    STRIBECK_FRICTION = enum.auto()     # exp(−(q̇/v_s)²) tanh(q̇/ε) θ
    DRIVE_GAIN = enum.auto()            # τ_m θ
    TORQUE_OFFSET = enum.auto()         # −θ
    POSITION_RIPPLE = enum.auto()       # −sin(k q) θ₁ − cos(k q) θ₂
