"""The interface every external-torque observer implements, and the static filter tuning."""
from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields
from typing import Any, Mapping, Protocol

import numpy as np

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.config_schema import KEYS_BY_NAME


# t_s of models written before they recorded their sample rate: they were trained on 500 Hz data.
DEFAULT_SAMPLE_PERIOD = 0.002


class ObserverError(ValueError):
    """An observer cannot be built from what was given (model, oracle); the message says what to do."""


@dataclass(frozen=True)
class PerSample:
    """The ``filter.*`` times of the config at one sample period t_s (docs/method.md §4.9).

    The config gives windows and rates in seconds so that one file means the same at 100 Hz and 1 kHz;
    the filters count samples. vb_forgetting ρ = 1 − t_s/T (memory 1/(1 − ρ) = T/t_s samples, at least 2);
    vb_window L and onset_window in samples (at least 5 and 2); ewma_rate, nis_rate = t_s/T (at most 1).
    """

    vb_forgetting: float
    vb_window: int
    onset_window: int
    ewma_rate: float
    nis_rate: float

    @classmethod
    def of(cls, settings: FilterSettings, sample_period: float) -> "PerSample":
        """Convert ``settings`` (seconds) at t_s = ``sample_period`` s."""
        if not np.isfinite(sample_period) or sample_period <= 0.0:
            raise ValueError(f"sample period must be a positive number of seconds, got {sample_period!r}")
        return cls(vb_forgetting=1.0 - min(sample_period / settings.vb_memory, 0.5),
                   vb_window=max(5, round(settings.vb_window_time / sample_period)),
                   onset_window=max(2, round(settings.onset_window_time / sample_period)),
                   ewma_rate=min(1.0, sample_period / settings.ewma_time),
                   nis_rate=min(1.0, sample_period / settings.nis_time))


class ResidualPredictor(Protocol):
    """A residual-torque model: per-joint mean (n,) N·m and variance (n,) N²·m² at velocity q̇ (n,).

    A model whose joints also take the pose (the KMP with ``qd_q``/``qd_g`` inputs) has a non-empty
    ``needs`` ({"q"}, {"g"} or both) and is called ``predict(qd, q, g)``, g the model's gravity torque.
    """

    @property
    def n_joints(self) -> int: ...

    def predict(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def _shape(value: Any) -> Any:
    """The shape signature of a state value: an array's shape, a tuple's shapes, ``()`` for a scalar."""
    if isinstance(value, np.ndarray):
        return value.shape
    if isinstance(value, (tuple, list)):
        return tuple(None if item is None else _shape(item) for item in value)
    return ()


class Stateful:
    """Something whose filter state can be copied out and loaded into another instance.

    ``STATE`` names the attributes that hold the state (what ``reset`` assigns and what ``step``
    creates lazily); everything else (model, tuning, settings) belongs to the instance. A
    ``Stateful`` attribute (a component such as the windowed VB) contributes its own ``state()``.
    Used to continue a rebuilt estimator from the old one without a restart.
    """

    STATE: tuple[str, ...] = ()

    def state(self) -> dict[str, Any]:
        """Deep copies of the ``STATE`` attributes (components as their own state dicts)."""
        return {name: _capture(getattr(self, name)) for name in self.STATE}

    def load_state(self, state: Mapping[str, Any]) -> None:
        """Set the ``STATE`` attributes to deep copies of ``state``'s (from ``state()`` of a like instance).

        Raises ``ValueError``, changing nothing, if the keys or the array shapes differ. A value that
        is ``None`` on either side (not yet set by a first step) matches any shape.
        """
        self._check_state(state)
        for name in self.STATE:
            current = getattr(self, name)
            if isinstance(current, Stateful):
                current.load_state(state[name])
            else:
                setattr(self, name, copy.deepcopy(state[name]))

    def _check_state(self, state: Mapping[str, Any]) -> None:
        """Raise ``ValueError`` unless ``state`` fits this instance (``load_state``)."""
        owner = type(self).__name__
        if not isinstance(state, Mapping) or set(state) != set(self.STATE):
            keys = sorted(state) if isinstance(state, Mapping) else type(state).__name__
            raise ValueError(f"{owner} state must have the keys {sorted(self.STATE)}, got {keys}")
        for name in self.STATE:
            current, value = getattr(self, name), state[name]
            if isinstance(current, Stateful):
                if not isinstance(value, Mapping):
                    raise ValueError(f"{owner} state '{name}': expected the component's state, got {value!r}")
                current._check_state(value)
            elif isinstance(value, Mapping):
                raise ValueError(f"{owner} state '{name}': this {owner} has no such component")
            elif current is not None and value is not None and _shape(current) != _shape(value):
                raise ValueError(f"{owner} state '{name}' has shape {_shape(value)}, expected {_shape(current)}")


def _capture(value: Any) -> Any:
    """A state value to hand out: a component's state dict, else a deep copy."""
    return value.state() if isinstance(value, Stateful) else copy.deepcopy(value)


class Observer(Stateful, ABC):
    """Estimates τ_ext (n,) N·m and its covariance P (n, n) N²·m² from momentum samples.

    The ``Estimator`` computes the generalized momentum ``p = M q̇`` and its input
    ``u = Cᵀq̇ − g + τ_m`` (paper v1 eqs. 5-7) once per sample and hands them to the observer,
    so every observer sees the same inputs.

    ``settings`` are the ``filter.*`` keys the observer was built with (``None`` for an observer
    built from explicit gains only); they are read at construction and changed only through
    ``configure``.

    ``STATE`` (see ``Stateful``): every concrete observer lists the attributes ``reset`` assigns,
    those ``step`` creates lazily and ``prediction`` if it sets it, extending its parent's tuple;
    ``state()`` and ``load_state()`` move them to a rebuilt observer of the same class.
    """

    STATE: tuple[str, ...] = ()
    name: str = ""
    uses_residual_model: bool = False
    reports_covariance: bool = True     # False: step returns P = None (e.g. the momentum observer)
    diagonal_covariance: bool = True    # P is diagonal (joints filtered apart); False: a full (n, n) P
    # The residual model's (mean (n,) N·m, variance (n,) N²·m²) at the last step's q̇, for the contact
    # test: observers with a residual model set it in ``step`` so the model is evaluated once per sample.
    prediction: tuple[np.ndarray, np.ndarray] | None = None
    # The pose inputs ("q", "g") the residual model needs in ``step``; the Estimator computes g only then.
    needs: frozenset[str] = frozenset()

    def __init__(self, n: int, settings: FilterSettings | None = None) -> None:
        self.n = n
        self.settings = settings

    def configure(self, settings: FilterSettings) -> None:
        """Apply new filter settings at run time (the ROS node's parameter changes).

        Keys marked run-time in ``config_schema.KEYS`` (``filter.ewma_time``, ``filter.nis_time``)
        take effect from the next step; any other key that differs from the observer's raises
        ``ValueError`` naming it: it shapes the filter, so the observer must be rebuilt.
        """
        if self.settings is None:
            raise ValueError(f"observer '{self.name}' was built without filter settings; rebuild it to change them")
        fixed = [f"filter.{field.name}" for field in fields(settings)
                 if not KEYS_BY_NAME[f"filter.{field.name}"].runtime
                 and getattr(settings, field.name) != getattr(self.settings, field.name)]
        if fixed:
            raise ValueError(f"{', '.join(fixed)} cannot change at run time; rebuild the observer")
        self.settings = settings
        self._apply_runtime(settings)

    def _apply_runtime(self, settings: FilterSettings) -> None:
        """Copy the run-time keys the step reads into attributes; observers reading none keep this."""

    @abstractmethod
    def reset(self) -> None:
        """Forget all state, as at start-up."""

    @abstractmethod
    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Advance one sample.

        Args:
            dt: time since the previous sample, s (the actual step, not a nominal one).
            qd: joint velocity at this sample (n,), rad/s.
            p, p_prev: generalized momentum now and at the previous sample (n,), N·m·s.
            u_prev: momentum input at the previous sample (n,), N·m.
            q, g: joint position (n,) rad and the model's gravity torque g(q) (n,) N·m at this sample,
                for a residual model that takes them (``needs``); otherwise may be None.
        Returns:
            ``(tau_ext, P)``: estimate (n,) N·m and covariance (n, n) N²·m², or ``None`` for
            observers that report no uncertainty. The arrays are not modified afterwards by the
            observer.
        """


@dataclass(frozen=True)
class FilterTuning:
    """Static covariances identified from training data (paper v2 §V-D), torque units, shape (n,).

    process_noise_density: q in ``Σ_d = diag(q)·t_s`` for the random walk of eq. 32, N²·m²/s.
    measurement_variance: the fixed R of the non-heteroscedastic filter (A1), N²·m².
    empirical_variance: ``Σ_emp / t_s²`` at start and its upper bound (v2 Remark 2), N²·m².
    residual_variance: mean squared error of the residual model on held-out training samples,
        N²·m²; the static stand-in for the KMP variance in the momentum-state filter's A1.
    """

    process_noise_density: np.ndarray
    measurement_variance: np.ndarray
    empirical_variance: np.ndarray
    residual_variance: np.ndarray | None = None

    def __post_init__(self) -> None:
        names = ("process_noise_density", "measurement_variance", "empirical_variance", "residual_variance")
        for name in names:
            if getattr(self, name) is None:
                continue
            value = np.asarray(getattr(self, name), dtype=float)
            if value.ndim != 1 or not np.all(np.isfinite(value)) or np.any(value <= 0.0):
                raise ValueError(f"filter tuning '{name}' must be a vector of positive finite numbers, got {value}")
            object.__setattr__(self, name, value)
        if len({len(getattr(self, name)) for name in names if getattr(self, name) is not None}) != 1:
            raise ValueError("filter tuning vectors must all have one entry per joint")

    def to_dict(self) -> dict[str, list[float]]:
        """Plain lists, for the model's YAML file."""
        return {name: value.tolist() for name, value in vars(self).items() if value is not None}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "FilterTuning":
        return cls(**{key: np.asarray(value, dtype=float) for key, value in values.items()})
