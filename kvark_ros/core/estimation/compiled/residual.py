"""The compiled evaluations of the trained model at one sample: the KMP residual (``kmp_predict``) and the
augmentation's joint torque τ_aug (``augmentation_torque``).

Each model is packed once into one float array (``pack_kmp``, ``pack_augmentation``; one array to unbox per call,
``layouts``) and evaluated by ``post.estimate_step`` inside the compiled step, or from Python (``CompiledKMP``:
``KMPResidualModel.predict``). Each equals its batch numpy form (``KMPResidualModel.predict_batch``,
``Augmentation.joint_torque``, what training computes with) to rounding
(``test/core/test_compiled_step_matches_reference.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

import numpy as np

from kvark_ros.core.effect_catalog import TORQUE_EFFECTS
from kvark_ros.core.estimation.compiled.jit import jit
from kvark_ros.core.estimation.compiled.layouts import KMP_HEADER, KMP_ROWS, Effect, Kmp, KmpHeader, pack

if TYPE_CHECKING:
    from kvark_ros.core.estimation.augmentation import Augmentation

PINS = {"layouts.py": "b567b01b443f6eb37b6883fed944593a9449df4a179e52a7f83d6a575b5beb9f"}

# ``augmentation_torque``'s code of every torque effect of the catalog: the ``Effect`` member of its name in upper case
EFFECT_CODES = {name: int(Effect[name.upper()]) for name in TORQUE_EFFECTS}


@dataclass(frozen=True)
class KMPKernelArrays:
    """A KMP's precomputed factors (``KMPResidualModel.kernel_arrays``), what ``pack_kmp`` packs for ``kmp_predict``:
    read-only views; n joints, N support points. With the unit kernel e_i = exp(neg_half_inv_ls2 (q̇ − s_i)² +
    neg_half_inv_ls2_z (z − s2_i)²) = k_*/σ_f² (eq. 21) and w = W e: mean w_0 (eq. 22), variance
    var_scale (sigma_f2 − ‖w_1..N‖²) (eq. 23), then the far-field floor and VARIANCE_FLOOR (``predict``).
    """

    support: np.ndarray  # s (n, N), rad/s
    support2: np.ndarray  # s2 (n, N), the support points' second inputs, rad or N·m (0: q̇ only)
    neg_half_inv_ls2: np.ndarray  # −1/(2ℓ²) (n,), s²/rad²
    neg_half_inv_ls2_z: np.ndarray  # −1/(2ℓ_z²) (n,) of the second input, 1/rad² or 1/(N·m)² (0: q̇ only)
    sigma_f2: np.ndarray  # σ_f² (n,), N²·m²
    var_scale: np.ndarray  # N/λ₂ (n,) of eq. 23
    takes_q: np.ndarray  # (n,) 1.0 where z_j = q_j, else 0.0
    takes_g: np.ndarray  # (n,) 1.0 where z_j = g_j, else 0.0
    two_input: np.ndarray  # (n,) bool: a second input, whose far-field floor is σ_f²(1 − ‖L_K⁻¹e‖²)
    weights: np.ndarray  # W (n, N+1, N), N·m: row 0 σ_f²(K + λ₁Σ)⁻¹μ, rows 1..N σ_f² L⁻¹
    floor_weights: np.ndarray | None  # L_K⁻¹ (n, N, N), zeros on q̇-only joints; None without a second input

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if value is not None:
                view = value.view()
                view.setflags(write=False)
                object.__setattr__(self, field.name, view)


def pack_kmp(arrays: KMPKernelArrays, floor: float) -> np.ndarray:
    """A KMP's factors as one array (``split_kmp``): [N, floor], the rows ``Kmp`` (KMP_ROWS, n), s, s₂ (n, N), Wᵀ
    (n, N, N+1), L_K⁻ᵀ (n, N, N; zeros without two-input joints) and work space for w (N+1), e and f (N)."""
    n, n_support = arrays.support.shape
    rows = pack(Kmp, {Kmp.LS: arrays.neg_half_inv_ls2, Kmp.LS_Z: arrays.neg_half_inv_ls2_z,
                      Kmp.SIGMA_F2: arrays.sigma_f2, Kmp.VAR_SCALE: arrays.var_scale, Kmp.TAKES_Q: arrays.takes_q,
                      Kmp.TAKES_G: arrays.takes_g, Kmp.TWO_INPUT: arrays.two_input})
    floor_weights = (np.zeros((n, n_support, n_support)) if arrays.floor_weights is None
                     else np.swapaxes(arrays.floor_weights, 1, 2))
    header = pack(KmpHeader, {KmpHeader.SUPPORT: n_support, KmpHeader.FLOOR: floor})
    return np.concatenate([np.asarray(header, dtype=float), np.ravel(rows), arrays.support.ravel(),
                           arrays.support2.ravel(), np.swapaxes(arrays.weights, 1, 2).ravel(), floor_weights.ravel(),
                           np.zeros(3 * n_support + 1)])


@jit
def split_kmp(packed: np.ndarray, n: int) -> tuple:
    """Views of a packed KMP of n joints (``pack_kmp``): (Kmp rows, s, s₂, Wᵀ, L_K⁻ᵀ, w, e, f, floor)."""
    size = int(packed[KmpHeader.SUPPORT])
    start = KMP_HEADER
    rows = packed[start:start + KMP_ROWS * n].reshape((KMP_ROWS, n))
    start += KMP_ROWS * n
    support = packed[start:start + n * size].reshape((n, size))
    start += n * size
    support2 = packed[start:start + n * size].reshape((n, size))
    start += n * size
    weights_t = packed[start:start + n * size * (size + 1)].reshape((n, size, size + 1))
    start += n * size * (size + 1)
    floor_t = packed[start:start + n * size * size].reshape((n, size, size))
    start += n * size * size
    return (rows, support, support2, weights_t, floor_t, packed[start:start + size + 1],
            packed[start + size + 1:start + 2 * size + 1], packed[start + 2 * size + 1:start + 3 * size + 1],
            packed[KmpHeader.FLOOR])


@jit
def kmp_predict(qd: np.ndarray, q: np.ndarray, g: np.ndarray, packed: np.ndarray, mean: np.ndarray,
                var: np.ndarray) -> None:
    """``KMPResidualModel.predict`` at one sample (docs/method.md §3), into ``mean`` (n,) N·m and ``var`` (n,) N²·m².

    ``qd`` (n,) rad/s; ``q`` (n,) rad and ``g`` (n,) N·m give a joint's second input z_j = takes_q q_j + takes_g g_j
    (§3.7; 0 on a q̇-only joint, whatever q and g hold, as long as they are finite); ``packed``: ``pack_kmp``. Rows of
    Wᵀ: column 0 σ_f² (𝒦 + λ₁Σ)⁻¹μ, columns 1..N σ_f² L⁻ᵀ with L Lᵀ = 𝒦 + λ₂Σ. The far-field floor is σ_f²(1 − c²),
    c the nearest support point's unit kernel, or for a two-input joint σ_f²(1 − ‖L_K⁻¹e‖²) (§3.6-3.7).
    """
    n = qd.shape[0]
    rows, support, support2, weights_t, floor_t, w, e, f, floor = split_kmp(packed, n)
    n_support, width = support.shape[1], weights_t.shape[2]
    for j in range(n):
        z = rows[Kmp.TAKES_Q, j] * q[j] + rows[Kmp.TAKES_G, j] * g[j]
        w[:] = 0.0
        nearest = 0.0
        for i in range(n_support):
            a, b = qd[j] - support[j, i], z - support2[j, i]
            e[i] = np.exp(a * a * rows[Kmp.LS, j] + b * b * rows[Kmp.LS_Z, j])       # k_*/σ_f², eq. 21
            nearest = max(nearest, e[i])
            for r in range(width):                                                # W e, one row per r
                w[r] += weights_t[j, i, r] * e[i]
        sigma_f2 = rows[Kmp.SIGMA_F2, j]
        if rows[Kmp.TWO_INPUT, j] != 0.0:                                         # the GP on every support point
            f[:] = 0.0
            for i in range(n_support):                                            # L_K⁻¹ e, column by column
                for r in range(n_support):
                    f[r] += floor_t[j, i, r] * e[i]
            norm2 = 0.0
            for r in range(n_support):
                norm2 += f[r] * f[r]
            far = sigma_f2 * max(1.0 - norm2, 0.0)
        else:
            far = sigma_f2 * (1.0 - nearest * nearest)
        quad = 0.0
        for r in range(1, width):
            quad += w[r] * w[r]
        mean[j] = w[0]                                                              # eq. 22
        var[j] = max(max(rows[Kmp.VAR_SCALE, j] * (sigma_f2 - quad), far), floor)  # eq. 23, floors


class CompiledKMP:
    """A KMP evaluated by ``kmp_predict`` from Python: ``predict(qd, q, g)`` (each (n,)) gives new (mean, var) arrays
    (``KMPResidualModel.predict``); ``packed`` is what the compiled step passes on."""

    def __init__(self, arrays: KMPKernelArrays, floor: float) -> None:
        self.n = arrays.support.shape[0]
        self.packed = pack_kmp(arrays, floor)
        self._zeros = np.zeros(self.n)

    def predict(self, qd: np.ndarray, q: np.ndarray | None = None,
                g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        mean, var = np.empty(self.n), np.empty(self.n)
        kmp_predict(qd, self._zeros if q is None else q, self._zeros if g is None else g, self.packed, mean, var)
        return mean, var


def pack_augmentation(augmentation: Augmentation) -> np.ndarray:
    """``augmentation.torque_terms()`` as one array (``augmentation_torque``): [m], then per entry, in the order
    ``Augmentation.joint_torque`` adds them, its code (``Effect``), joint, params [ε, v_s or k] and θ (two columns)."""
    terms = augmentation.torque_terms()
    return np.concatenate([[float(len(terms))], [EFFECT_CODES[term.name] for term in terms],
                           [term.joint for term in terms],
                           np.ravel([(term.epsilon, term.second) for term in terms]),
                           np.ravel([term.theta for term in terms])]).astype(float)


NO_AUGMENTATION = np.zeros(1)       # a packed augmentation of no entry


@jit
def augmentation_torque(q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray, packed: np.ndarray,
                        out: np.ndarray) -> None:
    """τ_aug(q, q̇, τ_m) (n,) N·m into ``out``: per entry m, joint ``joints[m]``, the effect ``codes[m]``'s columns
    (``augmentation.joint_columns``; ``params[m]``: tanh width ε, then v_s or cycles per revolution k) weighted by
    ``theta[m]`` (two columns, the second used by the ripple only), added in the reference's order."""
    count = int(packed[0])
    codes, joints = packed[1:1 + count], packed[1 + count:1 + 2 * count]
    params = packed[1 + 2 * count:1 + 4 * count].reshape((count, 2))
    theta = packed[1 + 4 * count:1 + 6 * count].reshape((count, 2))
    out[:] = 0.0
    for m in range(count):
        j, code, a = int(joints[m]), int(codes[m]), theta[m, 0]
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
