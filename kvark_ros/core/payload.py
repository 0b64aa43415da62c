"""A rigid payload or tool at the flange: the config's ``robot_model.payload`` and the simulator's load.

Its own module so that the config (which only holds it) does not import the robot model (which
needs pinocchio to use it).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pinocchio as pin


@dataclass(frozen=True)
class Payload:
    """Rigid payload or tool fixed to the flange.

    mass: kg; com: (3,) m in the flange frame; inertia: (6,) kg·m² about the CoM,
    flange axes, ordered ``[ixx, iyy, izz, ixy, ixz, iyz]``.
    """

    mass: float
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def to_pinocchio(self) -> "pin.Inertia":
        """Spatial inertia in the flange frame."""
        import pinocchio as pin   # only where the payload enters a model: loading a config needs no pinocchio
        ixx, iyy, izz, ixy, ixz, iyz = self.inertia
        rot_inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        return pin.Inertia(float(self.mass), np.asarray(self.com, dtype=float), rot_inertia)
