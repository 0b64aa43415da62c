"""MLP residual model of the NNADKF baseline (paper v2 §V-B): a per-joint MLP mean, static variance.

Like the KMP model (kvark_ros.core.estimation.residual.kmp) it maps, per joint j, the joint velocity q̇_j
(rad/s) to the residual torque τ_r,j = τ_m,j − τ_EL,j (N·m); its variance is a constant per joint,
the mean squared training residual (paper: "static covariance").
"""

from __future__ import annotations

import os
import warnings
from concurrent.futures import Executor
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import scipy.special

from kvark_ros.core.estimation.residual.common import (
    BATCH_CHUNK,
    VARIANCE_FLOOR,
    check_batch,
    check_samples,
    map_joints,
    single_threaded,
)
from kvark_ros.core.estimation.residual.files import (
    FORMAT_VERSION,
    ResidualModelError,
    check_listed_values,
    frozen_float_array,
    read_arrays,
    read_model_header,
    save_model_pair,
)

__all__ = ["MLPResidualModel"]


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0, out=x)


def _tanh(x: np.ndarray) -> np.ndarray:
    return np.tanh(x, out=x)


def _logistic(x: np.ndarray) -> np.ndarray:
    return scipy.special.expit(x, out=x)


def _identity(x: np.ndarray) -> np.ndarray:
    return x


# sklearn MLPRegressor's hidden activations, in place.
_ACTIVATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "tanh": _tanh, "relu": _relu, "logistic": _logistic, "identity": _identity}


def _fit_joint(x: np.ndarray, y: np.ndarray, settings: dict) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """One joint of ``MLPResidualModel.fit``: an MLPRegressor with ``settings`` trained on the standardised q̇ x (T, 1)
    and τ_r y (T,); its weights, biases and epochs."""
    from sklearn.exceptions import ConvergenceWarning       # fitting only: loading a model needs no sklearn
    from sklearn.neural_network import MLPRegressor
    net = MLPRegressor(**settings)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # max_epochs reached
        net.fit(x, y)
    return net.coefs_, net.intercepts_, int(net.n_iter_)


class MLPResidualModel:
    """Per-joint MLP residual mean with a static variance (NNADKF baseline, paper v2 §V-B).

    One sklearn MLPRegressor per joint: input the standardised velocity, output the
    standardised residual, hidden layers (30, 30). The paper uses ELU units; sklearn has no
    ELU, so the default is tanh (smooth and saturating on the negative side like ELU). Adam,
    learning rate 1e-3, up to 300 epochs, mini-batch 512 as in the paper. The paper's
    additive correction network (online fine-tuning) is not part of this model.

    The trained weights are exported to arrays stacked across joints, coef_k (n, in_k, out_k)
    and intercept_k (n, out_k), and predict() runs the forward pass in numpy for all joints at
    once. The variance is static per joint: the mean squared training residual
    mean_t (τ_r − μ(q̇))², the "static covariance" of the paper (the filter's covariance
    matching rescales it).

    Attributes: coefs, intercepts (lists of arrays), x_mean, x_scale, y_mean, y_scale,
    variance (n,), activation, metadata.
    """

    name = "nnadkf"
    NPZ_NAME = "mlp.npz"
    YAML_NAME = "mlp.yaml"
    _STEM = "mlp"

    def __init__(self, coefs: list[np.ndarray], intercepts: list[np.ndarray],
                 x_mean: np.ndarray, x_scale: np.ndarray, y_mean: np.ndarray,
                 y_scale: np.ndarray, variance: np.ndarray, activation: str = "tanh",
                 metadata: Mapping[str, Any] | None = None) -> None:
        if activation not in _ACTIVATIONS:
            raise ResidualModelError(
                f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        if len(coefs) < 1 or len(coefs) != len(intercepts):
            raise ResidualModelError(
                f"need as many coefs as intercepts (>= 1), got {len(coefs)} and {len(intercepts)}")
        self.coefs = [frozen_float_array(f"coef_{k}", c, ndim=3) for k, c in enumerate(coefs)]
        self.intercepts = [frozen_float_array(f"intercept_{k}", b, ndim=2)
                           for k, b in enumerate(intercepts)]
        n = self.coefs[0].shape[0]
        width = 1
        for k, (c, b) in enumerate(zip(self.coefs, self.intercepts)):
            if c.shape[:2] != (n, width) or b.shape != (n, c.shape[2]):
                raise ResidualModelError(
                    f"layer {k}: coef {c.shape} / intercept {b.shape} do not chain "
                    f"(expected ({n}, {width}, ·) and ({n}, ·))")
            width = c.shape[2]
        if width != 1:
            raise ResidualModelError(f"the last layer must have 1 output, has {width}")
        for key, value in (("x_mean", x_mean), ("x_scale", x_scale), ("y_mean", y_mean),
                           ("y_scale", y_scale), ("variance", variance)):
            array = frozen_float_array(key, value, ndim=1)
            if array.shape != (n,):
                raise ResidualModelError(f"{key} must have shape ({n},), got {array.shape}")
            if key in ("x_scale", "y_scale", "variance") and np.any(array <= 0.0):
                raise ResidualModelError(f"{key} must be strictly positive, got {array}")
            setattr(self, key, array)
        self.activation = activation
        self.metadata: dict[str, Any] = dict(metadata or {})
        self._act = _ACTIVATIONS[activation]
        # Hot-path views: first layer (n, H1) (the input is a scalar per joint), last layer
        # (n, H_last) scaled by y_scale, middle layers as they are.
        self._w_in = self.coefs[0][:, 0, :]
        self._b_in = self.intercepts[0]
        self._middle = list(zip(self.coefs[1:-1], self.intercepts[1:-1]))
        self._inv_x_scale = 1.0 / self.x_scale
        if len(self.coefs) > 1:
            self._w_out = self.coefs[-1][:, :, 0] * self.y_scale[:, None]
            self._b_out = self.intercepts[-1][:, 0] * self.y_scale + self.y_mean

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self.x_mean.shape[0]

    @property
    def hidden_layer_sizes(self) -> tuple[int, ...]:
        return tuple(c.shape[2] for c in self.coefs[:-1])

    def predict(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qd: (n,) rad/s -> (mean (n,) N·m, static variance (n,) N²·m²). Hot path."""
        if len(self.coefs) == 1:  # no hidden layer: a linear model
            return self._forward_batch(qd[None, :])[0], self.variance.copy()
        x = (qd - self.x_mean) * self._inv_x_scale
        h = x[:, None] * self._w_in
        h += self._b_in
        self._act(h)
        for w, b in self._middle:
            h = np.matmul(h[:, None, :], w)[:, 0, :]
            h += b
            self._act(h)
        mean = np.einsum("jh,jh->j", h, self._w_out)
        mean += self._b_out
        return mean, self.variance.copy()

    def _forward_batch(self, qd: np.ndarray) -> np.ndarray:
        """qd (t, n) -> mean (t, n), all layers, joints first: h (n, t, width)."""
        h = ((qd - self.x_mean) * self._inv_x_scale).T[:, :, None]  # (n, t, 1)
        last = len(self.coefs) - 1
        for k, (w, b) in enumerate(zip(self.coefs, self.intercepts)):
            h = np.matmul(h, w) + b[:, None, :]
            if k < last:
                self._act(h)
        return (h[:, :, 0] * self.y_scale[:, None] + self.y_mean[:, None]).T

    def predict_batch(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qd: (T, n) -> mean (T, n), variance (T, n) (the static variance on every row)."""
        qd = check_batch(qd, self.n_joints)
        mean = np.empty_like(qd)
        for start in range(0, qd.shape[0], BATCH_CHUNK):
            rows = slice(start, start + BATCH_CHUNK)
            mean[rows] = self._forward_batch(qd[rows])
        return mean, np.broadcast_to(self.variance, qd.shape).copy()

    @classmethod
    @single_threaded
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray,
            hidden_layer_sizes: tuple[int, ...] = (30, 30), activation: str = "tanh",
            learning_rate: float = 1e-3, max_epochs: int = 300, batch_size: int = 512,
            l2: float = 1e-4, tol: float = 0.0, seed: int = 0, executor: Executor | None = None) -> MLPResidualModel:
        """Train one MLPRegressor per joint on standardised qd (T, n) rad/s -> tau_r (T, n) N·m.

        Adam with `learning_rate`, `max_epochs` epochs (earlier only if the training loss has
        not improved by `tol` for 10 epochs; sklearn's default tol 1e-4 stopped training at
        ~120 epochs with the friction step still blurred, hence tol 0), mini-batches of
        min(batch_size, T), L2 penalty `l2` (sklearn's alpha), random_state seed + j for
        joint j. The paper's 512-sample batches need enough data: with only 3000 samples,
        300 epochs are ~1800 Adam steps and leave the step at q̇ = 0 blurred (RMSE ≈ the noise
        level in our check); batch_size 128 fixed that.
        """
        if activation not in _ACTIVATIONS:
            raise ValueError(
                f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        qd, tau_r = check_samples(qd, tau_r, 10, "an MLP")
        n_samples, n = qd.shape
        x_mean, x_scale = qd.mean(axis=0), qd.std(axis=0)
        y_mean, y_scale = tau_r.mean(axis=0), tau_r.std(axis=0)
        y_scale = np.where(y_scale > 0.0, y_scale, 1.0)
        settings = dict(hidden_layer_sizes=tuple(hidden_layer_sizes), activation=activation, solver="adam",
                        learning_rate_init=learning_rate, max_iter=max_epochs, batch_size=min(batch_size, n_samples),
                        alpha=l2, tol=tol, n_iter_no_change=10, shuffle=True)
        tasks = [(((qd[:, j] - x_mean[j]) / x_scale[j])[:, None], (tau_r[:, j] - y_mean[j]) / y_scale[j],
                  {**settings, "random_state": seed + j}) for j in range(n)]
        layers, biases, epochs = zip(*map_joints(_fit_joint, tasks, executor))
        coefs = [np.stack([layers[j][k] for j in range(n)]) for k in range(len(layers[0]))]
        intercepts = [np.stack([biases[j][k] for j in range(n)]) for k in range(len(biases[0]))]
        placeholder = np.ones(n)
        model = cls(coefs, intercepts, x_mean, x_scale, y_mean, y_scale, placeholder, activation)
        residual = tau_r - model.predict_batch(qd)[0]
        variance = np.maximum(np.mean(residual ** 2, axis=0), VARIANCE_FLOOR)
        metadata = {"fit": {"n_samples": n_samples, "epochs": list(epochs),
                            "learning_rate": learning_rate, "batch_size": batch_size, "l2": l2,
                            "seed": seed}}
        return cls(coefs, intercepts, x_mean, x_scale, y_mean, y_scale, variance, activation,
                   metadata)

    def save(self, directory: str | os.PathLike, metadata: dict | None = None) -> None:
        """Writes directory/mlp.npz (coef_k, intercept_k, scalings, variance) and mlp.yaml."""
        arrays = {f"coef_{k}": c for k, c in enumerate(self.coefs)}
        arrays.update({f"intercept_{k}": b for k, b in enumerate(self.intercepts)})
        arrays.update(x_mean=self.x_mean, x_scale=self.x_scale, y_mean=self.y_mean,
                      y_scale=self.y_scale, variance=self.variance)
        header = {
            "format_version": FORMAT_VERSION,
            "model": self.name,
            "n_joints": self.n_joints,
            "hidden_layer_sizes": list(self.hidden_layer_sizes),
            "activation": self.activation,
            "variance": "static: mean squared training residual",
            "hyperparameters": {"variance": self.variance.tolist()},
            "metadata": dict(self.metadata if metadata is None else metadata),
        }
        save_model_pair(directory, self._STEM, arrays, header)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> MLPResidualModel:
        """Load a model written by save(); np.load(..., allow_pickle=False). Any problem ->
        ResidualModelError naming the file."""
        directory = Path(directory)
        yaml_path, npz_path = directory / cls.YAML_NAME, directory / cls.NPZ_NAME
        header = read_model_header(yaml_path, (), cls.name)
        n = header["n_joints"]
        if header.get("activation") not in _ACTIVATIONS:
            raise ResidualModelError(f"{yaml_path}: activation must be one of "
                                     f"{sorted(_ACTIVATIONS)}, got {header.get('activation')!r}")
        sizes = header.get("hidden_layer_sizes")
        if not isinstance(sizes, list) or not all(
                isinstance(s, int) and not isinstance(s, bool) and s >= 1 for s in sizes):
            raise ResidualModelError(
                f"{yaml_path}: hidden_layer_sizes must be a list of positive integers, "
                f"got {sizes!r}")
        widths = [1] + sizes + [1]
        shapes: dict[str, tuple[int, ...]] = {}
        for k in range(len(widths) - 1):
            shapes[f"coef_{k}"] = (n, widths[k], widths[k + 1])
            shapes[f"intercept_{k}"] = (n, widths[k + 1])
        shapes.update({key: (n,) for key in ("x_mean", "x_scale", "y_mean", "y_scale", "variance")})
        arrays = read_arrays(npz_path, shapes)
        check_listed_values(yaml_path, npz_path, header.get("hyperparameters"), arrays, ("variance",))
        n_layers = len(widths) - 1
        try:
            return cls([arrays[f"coef_{k}"] for k in range(n_layers)],
                       [arrays[f"intercept_{k}"] for k in range(n_layers)],
                       arrays["x_mean"], arrays["x_scale"], arrays["y_mean"], arrays["y_scale"],
                       arrays["variance"], header.get("activation"), metadata=header["metadata"])
        except ResidualModelError as exc:
            raise ResidualModelError(f"{npz_path}: {exc}") from exc
