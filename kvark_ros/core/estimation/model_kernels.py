"""Compiled evaluations of the trained model that ``core.estimation.compiled_step`` calls from Python once per sample,
beside ``step_kernel.estimate_step``: the KMP with a second input (``kmp_predict_pose``) and the augmentation's joint
torque τ_aug (``augmentation_torque``). Each equals its numpy reference (``KMPResidualModel.predict``,
``Augmentation.joint_torque``) to rounding (``test/core/test_compiled_step_matches_reference.py``); they cost 3-15 µs
where the references cost 30-90 µs per sample.

Like ``step_kernel`` (whose docstring says why) every number comes from the arguments, from this file's own constants
or from the layouts of ``core.estimation.kernel_layouts`` (``Pose``, ``Effect``), whose content ``LAYOUTS_DIGEST`` pins
here: numba's on-disk cache is keyed on this file alone. No kernel of ``step_kernel`` calls these.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.estimation.kernel_layouts import Effect, Pose
from kvark_ros.core.estimation.step_kernel import jit

# sha256 of core/estimation/kernel_layouts.py (its docstring): update it with the file,
# so numba recompiles these kernels.
LAYOUTS_DIGEST = "bd6c2c2bebe3a8abc39aa0d302fd5e0cc972fb0b4f532e271f1a41c16a46f28d"


@jit
def kmp_predict_pose(qd: np.ndarray, q: np.ndarray, g: np.ndarray, pose: np.ndarray, support: np.ndarray,
                     support2: np.ndarray, weights_t: np.ndarray, floor_weights_t: np.ndarray, w: np.ndarray,
                     e: np.ndarray, f: np.ndarray, floor: float, mean: np.ndarray, var: np.ndarray) -> None:
    """``KMPResidualModel.predict`` of a model with a second input (q_j or g_j) on some joints (docs/method.md
    §3.7), into ``mean``, ``var`` (n,): as ``kmp_predict`` with the second input z_j = takes_q q_j + takes_g g_j in
    the kernel, and for two-input joints the far-field floor σ_f²(1 − ‖L_K⁻¹e‖²) (``floor_weights_t`` (n, N, N),
    L_K⁻¹ transposed; zeros on the others). ``support2`` (n, N): the support points' second inputs; ``w`` (N+1,),
    ``e``, ``f`` (N,): work space the caller allocates once."""
    n, n_support = support.shape
    rows = weights_t.shape[2]
    for j in range(n):
        z = pose[Pose.TAKES_Q, j] * q[j] + pose[Pose.TAKES_G, j] * g[j]
        w[:] = 0.0
        nearest = 0.0
        for i in range(n_support):
            a, b = qd[j] - support[j, i], z - support2[j, i]
            e[i] = np.exp(a * a * pose[Pose.LS, j] + b * b * pose[Pose.LS_Z, j])  # k_*/σ_f², eq. 21
            nearest = max(nearest, e[i])
            for r in range(rows):
                w[r] += weights_t[j, i, r] * e[i]
        sigma_f2 = pose[Pose.SIGMA_F2, j]
        if pose[Pose.TWO_INPUT, j] != 0.0:                                        # the GP on every support point
            f[:] = 0.0
            for i in range(n_support):                                            # L_K⁻¹ e, column by column
                for r in range(n_support):
                    f[r] += floor_weights_t[j, i, r] * e[i]
            norm2 = 0.0
            for r in range(n_support):
                norm2 += f[r] * f[r]
            far = sigma_f2 * max(1.0 - norm2, 0.0)
        else:
            far = sigma_f2 * (1.0 - nearest * nearest)
        quad = 0.0
        for r in range(1, rows):
            quad += w[r] * w[r]
        mean[j] = w[0]                                                              # eq. 22
        var[j] = max(max(pose[Pose.VAR_SCALE, j] * (sigma_f2 - quad), far), floor)  # eq. 23, floors


@jit
def augmentation_torque(q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray, codes: np.ndarray, joints: np.ndarray,
                        params: np.ndarray, theta: np.ndarray, out: np.ndarray) -> None:
    """τ_aug(q, q̇, τ_m) (n,) N·m into ``out``: per entry m, joint ``joints[m]``, the effect ``codes[m]``'s columns
    (``augmentation.joint_columns``; ``params[m]``: tanh width ε, then v_s or cycles per revolution k) weighted by
    ``theta[m]`` (two columns, the second used by the ripple only), added in the reference's order."""
    out[:] = 0.0
    for m in range(codes.shape[0]):
        j, code, a = joints[m], codes[m], theta[m, 0]
        if code == Effect.COULOMB_FRICTION:
            out[j] += np.tanh(qd[j] / params[m, 0]) * a
        elif code == Effect.VISCOUS_FRICTION:
            out[j] += qd[j] * a
        elif code == Effect.STRIBECK_FRICTION:
            v = qd[j] / params[m, 1]
            out[j] += np.exp(-(v * v)) * np.tanh(qd[j] / params[m, 0]) * a
        elif code == Effect.DRIVE_GAIN:
            out[j] += tau_m[j] * a
        elif code == Effect.TORQUE_OFFSET:
            out[j] += -1.0 * a
        else:
            k = params[m, 1]
            out[j] += -np.sin(k * q[j]) * a
            out[j] += -np.cos(k * q[j]) * theta[m, 1]
