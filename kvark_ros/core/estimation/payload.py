"""A rigid payload or tool at the flange: the config's ``robot_model.payload`` and the simulator's load.

Its own module so that the config (which only holds it) does not import the robot model (which
needs pinocchio to use it).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from kvark_ros.core.config_schema import INERTIA_ORDER

if TYPE_CHECKING:
    import pinocchio as pin


Inertia6 = tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class Payload:
    """Rigid payload or tool fixed to the flange.

    mass: kg; com: (3,) m in the flange frame; inertia: (6,) kg·m² about the CoM, flange axes, held as
    ``[ixx, iyy, izz, ixy, ixz, iyz]`` (diagonal first, as the plant files write it); the config takes
    ``INERTIA_ORDER`` (``from_message_order``).
    """

    mass: float
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    @classmethod
    def from_message_order(cls, mass: float, com: tuple[float, float, float],
                           inertia: tuple[float, ...]) -> Payload:
        """The payload of an inertia given in ``INERTIA_ORDER`` (ixx ixy ixz iyy iyz izz)."""
        ixx, ixy, ixz, iyy, iyz, izz = (float(v) for v in inertia)
        return cls(float(mass), com, (ixx, iyy, izz, ixy, ixz, iyz))

    def rotational_inertia(self) -> np.ndarray:
        """(3, 3) inertia about the centre of mass, flange axes, kg·m²."""
        ixx, iyy, izz, ixy, ixz, iyz = self.inertia
        return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])

    def to_pinocchio(self) -> "pin.Inertia":
        """Spatial inertia in the flange frame."""
        import pinocchio as pin   # only where the payload enters a model: loading a config needs no pinocchio
        return pin.Inertia(float(self.mass), np.asarray(self.com, dtype=float), self.rotational_inertia())


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
    return rotational_inertia_problem(origin - m * (float(com @ com) * np.eye(3) - np.outer(com, com)), tolerance)


def rotational_inertia_problem(matrix: np.ndarray, tolerance: float) -> str | None:
    """Why (3, 3) ``matrix`` is not an inertia about a centre of mass, or None: it must be positive semi-definite,
    its principal moments obeying the triangle inequality, to ``tolerance`` kg·m²."""
    principal = np.linalg.eigvalsh(matrix)
    if principal[0] < -tolerance:
        return f"inertia about the centre of mass is not positive (principal moments {np.round(principal, 5).tolist()})"
    if principal[2] > principal[0] + principal[1] + tolerance:
        return f"principal moments {np.round(principal, 5).tolist()} violate the triangle inequality"
    return None


def old_order_problem(inertia: tuple[float, ...]) -> str | None:
    """Why six inertia values look written in the order this key had before (ixx iyy izz ixy ixz iyz): they are an
    inertia in that order and not in ``INERTIA_ORDER``; the same values in ``INERTIA_ORDER`` to write instead.
    None when the values are an inertia in ``INERTIA_ORDER`` or in neither order (the physical check names that)."""
    in_order = Payload.from_message_order(1.0, (0.0, 0.0, 0.0), inertia).rotational_inertia()
    ixx, iyy, izz, ixy, ixz, iyz = (float(v) for v in inertia)
    as_before = Payload(1.0, inertia=(ixx, iyy, izz, ixy, ixz, iyz)).rotational_inertia()
    # Config values are finite (the key's check), so each reading is an inertia or has a problem.
    if rotational_inertia_problem(in_order, 1e-9) is None or rotational_inertia_problem(as_before, 1e-9) is not None:
        return None
    rewritten = ", ".join(f"{v:g}" for v in (ixx, ixy, ixz, iyy, iyz, izz))
    return (f"is ordered {' '.join(INERTIA_ORDER)} (geometry_msgs/Inertia, URDF); {list(inertia)} is an inertia "
            f"only in the former order ixx iyy izz ixy ixz iyz: write [{rewritten}]")
