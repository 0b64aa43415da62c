"""Tare: the offset of τ̂_ext at rest, measured on request and subtracted from then on. ROS-free.

What a tare removes: at rest the estimate should be zero, but a nominal model that is slightly
wrong (an unknown tool, a cable, a URDF mass) leaves a constant τ̂_ext. ``Tare.start`` begins
averaging the estimate (before any earlier offset is removed) over ``duration`` seconds of sample
time (stamps, not wall time), while every joint stays at rest, ``max_j |q̇_j| ≤ max_speed``:

    offset = (1/N) Σ_k τ̂_k    (N samples with stamp − first stamp ≤ duration)

then ``apply`` returns ``τ̂ − offset`` for every later sample (the Estimator maps that tared τ̂ to
the wrench and runs the contact and collision tests on it). The offset holds for the pose it was
taken at; away from it the model error changes, which is why this is a tare, not a calibration.

Refusals and aborts: ``start`` refuses (``TareError``) before the first sample and while the last
sample moved; motion during the averaging, or a filter restart (``interrupt``), aborts it and says
why in ``note``; an offset active before is kept then. ``clear`` removes the offset.

Covariance: unchanged. The offset is a constant subtracted from later samples, so
Cov(τ̂ − offset) = Cov(τ̂) given the offset; the offset's own error (a fixed bias of at most the
estimate's standard deviation over √N_eff, N_eff the number of independent samples in the window)
is not per-sample noise and is not added. The states are ``IDLE`` (no offset), ``AVERAGING`` and
``ACTIVE`` (an offset is subtracted).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

IDLE, AVERAGING, ACTIVE = "idle", "averaging", "active"


class TareError(ValueError):
    """A tare cannot start now; the message says why and what to do."""


class Tare:
    """The tare of one estimator's τ̂_ext (module docstring): ``joint_names`` label the messages,
    ``duration`` s of rest are averaged, ``max_speed`` rad/s is the fastest joint speed at rest; ``offset``: the
    (n,) array to keep the offset in (written in place; default a new one)."""

    def __init__(self, joint_names: Sequence[str], duration: float, max_speed: float,
                 offset: np.ndarray | None = None) -> None:
        self.joint_names = tuple(joint_names)
        n = len(self.joint_names)
        # (n,) N·m, subtracted while ``active``; the estimator passes its compiled step's buffer, which subtracts it
        self.offset = np.zeros(n) if offset is None else offset
        self.active = False
        self.averaging = False
        self.note = "no tare taken"          # outcome of the last start, abort or clear
        self.aborted = False                 # the last averaging was aborted
        self._sum = np.zeros(n)
        self._count = 0
        self._start: float | None = None
        self._qd: np.ndarray | None = None   # q̇ of the last sample (rad/s), read when it matters
        self.configure(duration, max_speed)

    def configure(self, duration: float, max_speed: float) -> None:
        """Set the averaging time (s, > 0) and the rest speed (rad/s, > 0); an averaging under way uses them."""
        if not duration > 0.0 or not max_speed > 0.0:
            raise ValueError(f"tare duration and max_speed must be > 0, got {duration} s and {max_speed} rad/s")
        self.duration, self.max_speed = float(duration), float(max_speed)

    @property
    def state(self) -> str:
        """``averaging``, ``active`` (an offset is subtracted) or ``idle``."""
        return AVERAGING if self.averaging else ACTIVE if self.active else IDLE

    @property
    def samples(self) -> int:
        """Samples of the last averaging (under way, complete or aborted)."""
        return self._count

    def _motion(self) -> str | None:
        """What moves faster than ``max_speed`` in the last sample, or None at rest."""
        fastest = int(np.argmax(np.abs(self._qd)))
        speed = abs(float(self._qd[fastest]))
        if speed <= self.max_speed:
            return None
        return f"{self.joint_names[fastest]} moves at {speed:.3f} rad/s > tare.max_speed {self.max_speed:g} rad/s"

    def start(self) -> None:
        """Begin averaging from the next sample; ``TareError`` before the first sample or while moving."""
        if self._qd is None:
            raise TareError("no joint state received yet; call it again once the robot is at rest")
        motion = self._motion()
        if motion is not None:
            raise TareError(f"the robot is not at rest ({motion}); stop it and call it again")
        self.averaging = True
        self._sum[:] = 0.0
        self._count = 0
        self._start = None
        self.aborted = False
        self.note = f"averaging over {self.duration:g} s at rest"

    def clear(self) -> None:
        """No offset, no averaging."""
        self.offset[:] = 0.0
        self.active = self.averaging = self.aborted = False
        self.note = "cleared"

    def interrupt(self, reason: str) -> None:
        """Abort an averaging under way (motion, a filter restart); an earlier offset stays active."""
        if self.averaging:
            self.averaging, self.aborted = False, True
            self.note = f"aborted after {self._count} samples: {reason}; the "
            self.note += "previous offset stays" if self.active else "estimate stays untared"

    def track(self, qd: np.ndarray) -> None:
        """Keep the sample's q̇ (rad/s, not copied) for ``start``: all ``apply`` does while not averaging, bar the
        subtraction (the compiled step subtracts ``offset`` itself)."""
        self._qd = qd

    def apply(self, stamp: float, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Feed one estimate (stamp s, q̇ (n,) rad/s, τ̂ (n,) N·m before the tare); return τ̂ − offset.

        ``tau`` itself is returned when no offset is active (no copy); ``qd`` is kept (not copied) for ``start``.
        """
        self._qd = qd
        if self.averaging:
            motion = self._motion()
            if motion is not None:
                self.interrupt(f"motion started ({motion})")
            else:
                if self._start is None:
                    self._start = stamp
                self._sum += tau
                self._count += 1
                if stamp - self._start >= self.duration:      # offset = (1/N) Σ τ̂_k
                    np.divide(self._sum, self._count, out=self.offset)
                    self.averaging, self.active = False, True
                    self.note = f"offset of {self._count} samples over {stamp - self._start:.3f} s"
        return tau - self.offset if self.active else tau

    def continue_from(self, other: "Tare") -> None:
        """Take over ``other``'s offset, averaging and last speed (a rebuilt estimator continuing)."""
        if other.joint_names != self.joint_names:
            raise ValueError("cannot continue a tare of other joints")
        self.offset[:], self._sum[:] = other.offset, other._sum
        self.active, self.averaging, self.aborted, self.note = other.active, other.averaging, other.aborted, other.note
        self._count, self._start, self._qd = other._count, other._start, other._qd
