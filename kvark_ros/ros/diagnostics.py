"""The node's ``/diagnostics`` statuses (model, input, filter, wrench, tare), built from plain numbers.

Kept apart from the node so that the node is the adapter only. ``filter`` shows the contact and the
collision test, ``wrench`` the Jacobian's condition number and the wrench directions the joints cannot
sense (docs/method.md §1.4.1), ``tare`` the tare's state (idle, averaging, active), its offset per joint
(N·m) and the outcome of the last request.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from kvark_ros.core.estimation.estimator import Estimate, Status
from kvark_ros.core.estimation.model_checks import model_warnings
from kvark_ros.core.estimation.pairing import Reject
from kvark_ros.core.estimation.tare import Tare

SERVICE_RESET = "reset: ~/reset service"
NOT_READY = "dropped: no estimator (model not loaded or waiting for robot_description)"
NOT_PROBLEMS = {Status.OK, Status.WARMUP, Reject.OTHER_JOINTS, Reject.EARLY_COMMAND, SERVICE_RESET}
RESETS = (Status.GAP_RESET, Status.DIVERGED_RESET, Reject.TIME_JUMP, SERVICE_RESET)
LEVELS = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)


@dataclass
class Window:
    """What happened since the previous ``/diagnostics`` message."""

    seconds: float
    received: int
    published: int
    counts: Counter[str]            # every count since start
    fresh: dict[str, int]           # the counts' growth in this window
    lost: int                       # joint states missing from the stamps' sequence in this window
    max_loss: float                 # share of lost joint states above which the input status warns


class Windows:
    """Cuts the node's running totals into ``/diagnostics`` windows: each :class:`Window` covers what changed since
    the previous one (``start``: the first window's start time, s)."""

    def __init__(self, start: float) -> None:
        self._time = start
        self._received = self._published = self._lost = 0
        self._counts: Counter[str] = Counter()

    def next(self, now: float, received: int, published: int, counts: Counter[str], lost: int,
             max_loss: float) -> Window:
        """The window ending at ``now`` (s), given the totals since start."""
        fresh = {key: total - self._counts.get(key, 0) for key, total in counts.items()
                 if total > self._counts.get(key, 0)}
        window = Window(now - self._time, received - self._received, published - self._published, counts, fresh,
                        lost - self._lost, max_loss)
        self._time, self._received, self._published, self._lost, self._counts = now, received, published, lost, counts
        return window


class StatusBuilder:
    """Makes ``DiagnosticStatus`` messages named ``<node>: <part>`` for one robot."""

    def __init__(self, node_name: str, hardware_id: str) -> None:
        self.node_name = node_name
        self.hardware_id = hardware_id

    def status(self, level: int, name: str, message: str, values: dict[str, Any]) -> DiagnosticStatus:
        return DiagnosticStatus(level=LEVELS[level], name=f"{self.node_name}: {name}", message=message,
                                hardware_id=self.hardware_id,
                                values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])

    def model(self, config: Any, urdf_in_use: str, estimator: Any, problem: str,
              reload_problem: str | None, data_rate: float = math.nan) -> DiagnosticStatus:
        """ERROR without an estimator (``problem`` says why), WARN after a failed reload or when the model does not
        fit the data (``core.estimation.model_checks``: rate ``data_rate`` Hz off by more than 20 %, another robot),
        else OK."""
        payload = config.payload
        values = {"model_dir": config.model_dir, "observer": config.observer, "urdf": urdf_in_use or config.urdf,
                  "joints": ",".join(config.joint_names), "torque_source": config.input.torque_source,
                  "payload": "none" if payload is None else f"{payload.mass:g} kg at {list(payload.com)} m"}
        if estimator is None:
            return self.status(2, "model", f"no estimator: {problem}", values)
        info = estimator.trained.info
        values.update({"trained_samples": info.get("samples", "?"), "trained_with": info.get("kvark_ros_version", "?"),
                       "residual_compensated": estimator.observer.uses_residual_model})
        values.update({"model_sample_rate_hz": f"{estimator.trained.sample_rate:.1f}",
                       "data_rate_hz": f"{data_rate:.1f}"})
        if reload_problem is not None:
            return self.status(1, "model", f"last reload failed, previous model kept: {reload_problem}", values)
        warnings = model_warnings(estimator.trained, config.robot, data_rate, simulated=None)
        if warnings:
            return self.status(1, "model", "; ".join(line.removeprefix("warning: ") for line in warnings), values)
        return self.status(0, "model", "model loaded", values)

    def input(self, window: Window, totals: dict[str, Any], missing_detail: str) -> DiagnosticStatus:
        """Input and output rates and every drop reason; WARN when output lags input or something was dropped."""
        span = window.seconds
        rate_in = window.received / span if span > 0 else math.nan
        rate_out = window.published / span if span > 0 else math.nan
        values: dict[str, Any] = {"input_rate_hz": f"{rate_in:.1f}", "output_rate_hz": f"{rate_out:.1f}",
                                  "window_s": f"{span:.3f}", **totals}
        values.update({key: f"{total} (+{window.fresh.get(key, 0)})" for key, total in sorted(window.counts.items())})
        if missing_detail:
            values["last_missing_joint"] = missing_detail
        problems = {key: number for key, number in window.fresh.items() if key not in NOT_PROBLEMS}
        summary = "; ".join(f"{number} × {key}" for key, number in sorted(problems.items(), key=lambda kv: -kv[1]))
        loss = window.lost / (window.lost + window.received) if window.lost + window.received else 0.0
        values["loss_share"] = f"{loss:.4f}"
        if window.received == 0:
            return self.status(1, "input", f"no joint_states in the last {span:.1f} s", values)
        if loss > window.max_loss:
            return self.status(1, "input", f"{window.lost} joint states lost in {span:.1f} s ({loss:.1%} of the "
                               f"input, above diagnostics.max_loss {window.max_loss:.1%})", values)
        if window.published < 0.9 * window.received:
            return self.status(1, "input", f"output {rate_out:.0f} Hz below input {rate_in:.0f} Hz"
                               + (f": {summary}" if summary else ""), values)
        if problems:
            return self.status(1, "input", f"input {rate_in:.0f} Hz, output {rate_out:.0f} Hz; {summary}", values)
        return self.status(0, "input", f"input {rate_in:.0f} Hz, output {rate_out:.0f} Hz", values)

    def filter(self, window: Window, estimator: Any, covariance: np.ndarray | None,
               covariance_note: str) -> DiagnosticStatus:
        """ERROR if P is not finite positive definite, WARN after a reset in this window, else the contact
        and collision state (``estimator``: None without one)."""
        values: dict[str, Any] = {key: window.counts.get(key, 0) for key in RESETS}
        contact = None if estimator is None else estimator.contact
        if estimator is not None:
            collision = estimator.collision
            values.update({"contact": contact.flag, "contact_statistic": f"{contact.statistic:.3g}",
                           "contact_threshold": f"{contact.threshold:.3g}", "contact_confidence": contact.confidence,
                           "contact_covariance_not_positive_definite": contact.invalid_covariances,
                           "collision": collision.flag, "collision_excess_nm": f"{collision.excess:.3g}",
                           "collision_torque_nm": f"{collision.collision_torque:g}"})
        healthy = True
        if covariance is None:
            values["P"] = covariance_note
        else:
            try:
                np.linalg.cholesky(covariance)
                healthy = bool(np.isfinite(covariance).all())
            except np.linalg.LinAlgError:
                healthy = False
            values["P"] = "finite, positive definite" if healthy else "NOT positive definite"
        if not healthy:
            return self.status(2, "filter", "covariance P is not finite positive definite", values)
        resets = {key: window.fresh[key] for key in RESETS if window.fresh.get(key)}
        if resets.get(Status.DIVERGED_RESET) or resets.get(Reject.TIME_JUMP) or resets.get(Status.GAP_RESET):
            text = "; ".join(f"{number} × {key}" for key, number in resets.items())
            return self.status(1, "filter", text, values)
        state = "contact" if contact is not None and contact.flag else "no contact"
        if estimator is not None and estimator.collision.flag:
            state = "collision"
        return self.status(0, "filter", state, values)

    def wrench(self, estimate: Estimate | None, estimator: Any) -> DiagnosticStatus:
        """The newest estimate's Jacobian condition number κ and unobservable wrench directions (σ_i < δ, in
        ``wrench_frame`` axes, [force; moment] unit vectors): WARN while there is one, else OK."""
        if estimate is None or estimator is None:
            return self.status(0, "wrench", "no estimate yet", {})
        settings = estimator.config.wrench
        weak = estimate.weak_directions
        values: dict[str, Any] = {
            "jacobian_condition": f"{estimate.jacobian_condition:.4g}", "unobservable_directions": weak.shape[1],
            "samples_with_unobservable_direction": estimator.unobservable_samples, "axes": estimate.wrench_frame,
            "damping": f"{settings.damping:g}", "prior_force_n": f"{settings.prior_force:g}",
            "prior_moment_nm": f"{settings.prior_moment:g}"}
        values.update({f"direction {i + 1}": np.array2string(np.round(direction, 3) + 0.0)    # + 0.0: no "-0."
                       for i, direction in enumerate(weak.T)})
        if weak.shape[1]:
            return self.status(1, "wrench", f"{weak.shape[1]} wrench direction(s) unobservable near a singular pose "
                               f"(condition number {estimate.jacobian_condition:.3g}): their covariance is the "
                               "wrench.prior_* scale", values)
        return self.status(0, "wrench", f"observable (condition number {estimate.jacobian_condition:.3g})", values)

    def tare(self, tare: Tare | None) -> DiagnosticStatus:
        """The tare's state and offset per joint (N·m); WARN when the last averaging was aborted."""
        if tare is None:
            return self.status(0, "tare", "idle (no estimator)", {"state": "idle"})
        values: dict[str, Any] = {"state": tare.state, "last": tare.note, "samples": tare.samples,
                                  "duration_s": f"{tare.duration:g}", "max_speed_rad_s": f"{tare.max_speed:g}"}
        values.update({f"offset_nm {name}": f"{value:.4f}" for name, value in zip(tare.joint_names, tare.offset)})
        level = 1 if tare.aborted else 0
        return self.status(level, "tare", f"{tare.state}: {tare.note}", values)
