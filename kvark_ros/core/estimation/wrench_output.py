"""The wrench as a driver's users read it: its frame id, axes and sign (``wrench.base_frame``, ``wrench.convention``).

``Estimate.wrench`` is the environment's wrench on the robot at the ee_frame origin, in the URDF root link's axes
(``base``) or ee_frame's (``end_effector``). A driver names its base otherwise: ur_description's root link is
``world`` and UR's base frame is ``base``, turned 180° about z from ``base_link``, so relabelling ``world`` as
``base`` would flip x and y. ``wrench.base_frame`` names a frame fixed to the root link; the wrench in base axes
is turned into it, ``F_b = diag(Rᵀ, Rᵀ) F_root`` with R its rotation in root axes (``v_root = R v_b``), and its
covariance ``Σ_b = T Σ Tᵀ`` with that T. The reference point stays the ee_frame origin: only axes change.
``wrench.convention: applied_by_robot`` publishes −F (Franka's O_F_ext_hat_K sign); the covariance is unchanged.
The node applies this to what it publishes; the estimate itself keeps kvark's convention.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from kvark_ros.core.config import EstimatorConfig
    from kvark_ros.core.estimation.estimator import Estimate
    from kvark_ros.core.estimation.robot_model import RobotModel

__all__ = ["WrenchOutput"]


class WrenchOutput:
    """Frame ids, axes and sign of the published wrench for one robot model and config (module docstring).

    base_frame / ee_frame: the frame ids of the wrench in base and in ee_frame axes."""

    def __init__(self, robot: RobotModel, config: EstimatorConfig) -> None:
        root = robot.root_link
        self.base_frame = config.wrench.base_frame or root
        self.ee_frame = config.ee_frame
        self._turn: np.ndarray | None = None              # (6, 6) diag(Rᵀ, Rᵀ), None where R = I
        if self.base_frame != root:
            model = robot.model
            if not model.existFrame(self.base_frame):
                fixed = [f.name for f in model.frames if f.parentJoint == 0 and str(f.type) == "BODY"]
                raise ValueError(f"wrench.base_frame {self.base_frame!r} is not a frame of {robot.urdf_name}; the "
                                 f"frames fixed to its root link {root} are {', '.join(fixed)}")
            frame = model.frames[model.getFrameId(self.base_frame)]
            if frame.parentJoint != 0:
                raise ValueError(f"wrench.base_frame {self.base_frame!r} moves with joint "
                                 f"{model.names[frame.parentJoint]}; name a frame fixed to the root link {root}, "
                                 "or use wrench.frame end_effector")
            rotation = np.asarray(frame.placement.rotation)
            if not np.allclose(rotation, np.eye(3), rtol=0.0, atol=1e-12):
                self._turn = np.kron(np.eye(2), rotation.T)
        self.sign = 1.0
        self.configure(config)

    def configure(self, config: EstimatorConfig) -> None:
        """Take the run-time key ``wrench.convention`` of ``config``."""
        self.sign = -1.0 if config.wrench.convention == "applied_by_robot" else 1.0
        self._as_estimated = self.sign > 0.0 and self._turn is None     # the estimate's wrench as it is

    def in_axes(self, estimate: Estimate, axes: str) -> tuple[str, np.ndarray]:
        """(frame id, wrench (6,) N, N·m) of ``estimate`` in ``base`` or ``end_effector`` axes, in the published
        convention; the estimate's own array when nothing changes it."""
        wrench = estimate.wrench_in(axes)
        if axes == "base" and self._turn is not None:
            wrench = self._turn @ wrench
        if self.sign < 0.0:
            wrench = -wrench
        return (self.base_frame if axes == "base" else self.ee_frame), wrench

    def published(self, estimate: Estimate) -> tuple[str, np.ndarray]:
        """``in_axes`` of the estimate's own axes (``wrench.frame``)."""
        if self._as_estimated:                       # the node's path per sample: no copy, no call
            return (self.base_frame if estimate.wrench_frame == "base" else self.ee_frame), estimate.wrench
        return self.in_axes(estimate, estimate.wrench_frame)

    def covariance(self, estimate: Estimate) -> np.ndarray:
        """(6, 6) covariance of ``published``'s wrench (its axes; a sign flip leaves it unchanged)."""
        if estimate.wrench_frame == "base" and self._turn is not None:
            return self._turn @ estimate.wrench_cov @ self._turn.T
        return estimate.wrench_cov
