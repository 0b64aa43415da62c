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


def inertia_problem(parameters: np.ndarray, tolerance: float = 1e-6) -> str | None:
    """Why 10 dynamic parameters ``[m, m c (3), I_origin (ixx, ixy, iyy, ixz, iyz, izz)]`` (pinocchio's order,
    kg, kg·m, kg·m²) are not a physical rigid body, or None: the mass must be positive and the rotational
    inertia about the centre of mass positive semi-definite with its principal moments obeying the
    triangle inequality (each at most the sum of the other two), to ``tolerance`` kg·m²."""
    m = float(parameters[0])
    if not m > 0.0:
        return f"mass {m:.3f} kg is not positive"
    com = np.asarray(parameters[1:4], dtype=float) / m
    ixx, ixy, iyy, ixz, iyz, izz = (float(v) for v in parameters[4:10])
    origin = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    principal = np.linalg.eigvalsh(origin - m * (float(com @ com) * np.eye(3) - np.outer(com, com)))
    if principal[0] < -tolerance:
        return f"inertia about the centre of mass is not positive (principal moments {np.round(principal, 5).tolist()})"
    if principal[2] > principal[0] + principal[1] + tolerance:
        return f"principal moments {np.round(principal, 5).tolist()} violate the triangle inequality"
    return None
