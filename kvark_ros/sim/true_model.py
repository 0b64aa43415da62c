"""The plant's true rigid body as a URDF: link inertia errors, tool mismatch, payload (docs/method.md §10).

``true_urdf`` edits the ``<inertial>`` elements of the robot's URDF as the plant file says and
welds the extra tool (and optionally the payload) to the flange as new links. MuJoCo compiles
exactly this URDF (``mujoco_plant.build_model``), and pinocchio loads it too
(``RobotModel(true_urdf(...), …)``), so the oracle observer can run on the plant's own rigid body.
Numbers are written with 17 significant digits, so both engines read the same inertias.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import numpy.typing as npt

from kvark_ros.core.estimation.payload import Payload
from kvark_ros.sim.plant import LinkError, LinkErrorDraw, PlantError, PlantSpec
from kvark_ros.sim.robots import RobotSetup, urdf_xml

FloatArray = npt.NDArray[np.float64]
PAYLOAD_LINK = "kvark_payload"
TOOL_LINK = "kvark_tool"
_INERTIA_KEYS = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")


def moving_links(urdf: str, joint_names: tuple[str, ...]) -> tuple[str, ...]:
    """Child links of the simulated joints, in joint order: the links ``link_inertia`` may change."""
    children = {}
    for joint in ET.fromstring(urdf).findall("joint"):
        child = joint.find("child")
        if child is not None:
            children[joint.get("name")] = str(child.get("link"))
    return tuple(children[name] for name in joint_names)


def links_after(urdf: str, flange: str) -> tuple[str, ...]:
    """Every link below ``flange`` in the URDF tree (the tool the URDF fixes after the flange)."""
    children: dict[str, list[str]] = {}
    for joint in ET.fromstring(urdf).findall("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        if parent is not None and child is not None:
            children.setdefault(str(parent.get("link")), []).append(str(child.get("link")))
    below, stack = [], list(children.get(flange, ()))
    while stack:
        link = stack.pop()
        below.append(link)
        stack.extend(children.get(link, ()))
    return tuple(below)


def _inertial(link: ET.Element) -> tuple[float, FloatArray, FloatArray] | None:
    """Mass kg, centre of mass (3,) m and inertia about it (3, 3) kg·m² of a URDF link, in the
    frame of its ``<inertial><origin>`` (position in the link frame); None without ``<inertial>``."""
    inertial = link.find("inertial")
    if inertial is None:
        return None
    mass = inertial.find("mass")
    origin = inertial.find("origin")
    tensor = inertial.find("inertia")
    values = {key: float(tensor.get(key, 0.0)) if tensor is not None else 0.0 for key in _INERTIA_KEYS}
    matrix = np.array([[values["ixx"], values["ixy"], values["ixz"]],
                       [values["ixy"], values["iyy"], values["iyz"]],
                       [values["ixz"], values["iyz"], values["izz"]]])
    com = np.array([float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()])
    return (float(mass.get("value", 0.0)) if mass is not None else 0.0), com, matrix


def _set_inertial(link: ET.Element, mass: float, com: FloatArray, matrix: FloatArray) -> None:
    """Write mass, centre of mass and inertia into the link's ``<inertial>`` (keeping its rpy)."""
    inertial = _child(link, "inertial")
    _child(inertial, "mass").set("value", _num(mass))
    _child(inertial, "origin").set("xyz", " ".join(_num(v) for v in com))
    tensor = _child(inertial, "inertia")
    for key, (i, j) in zip(_INERTIA_KEYS, ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        tensor.set(key, _num(matrix[i, j]))


def _child(element: ET.Element, tag: str) -> ET.Element:
    """The first ``tag`` child of ``element``, created when missing."""
    found = element.find(tag)
    return found if found is not None else ET.SubElement(element, tag)


def _num(value: float) -> str:
    """A float as URDF text, round-trip exact."""
    return repr(float(value))


def _triple(values: FloatArray) -> tuple[float, float, float]:
    """Three floats as a tuple."""
    return float(values[0]), float(values[1]), float(values[2])


def second_moments(principal: FloatArray) -> FloatArray:
    """Second moments of the mass distribution about the principal axes, ``∫x² dm`` …, kg·m², from
    the principal moments (3,): ``tr/2 − I_k``. All ≥ 0 ⇔ the triangle inequality holds."""
    return 0.5 * principal.sum() - principal


def _draw(draw: LinkErrorDraw, links: tuple[str, ...], inertias: dict[str, FloatArray]) -> dict[str, LinkError]:
    """Random link errors within the bounds of ``draw``, deterministic for its seed (module docstring
    of ``plant``): the second moments are scaled, so each principal moment changes by a factor within
    1 ± inertia_rel and the inertia stays physical."""
    rng = np.random.default_rng(draw.seed)
    errors = {}
    for link in links:
        mass_scale = 1.0 + rng.uniform(-draw.mass_rel, draw.mass_rel)
        direction = rng.standard_normal(3)
        shift = draw.com_m * rng.uniform() ** (1.0 / 3.0) * direction / np.linalg.norm(direction)
        moment_scale = 1.0 + rng.uniform(-draw.inertia_rel, draw.inertia_rel, 3)
        if link not in inertias:
            continue
        principal = np.linalg.eigvalsh(inertias[link])
        moments = moment_scale * second_moments(principal)
        scaled = moments.sum() - moments                      # I'_k = Σ S' − S'_k
        factor = np.divide(scaled, principal, out=np.ones(3), where=principal > 0.0)
        errors[link] = LinkError(float(mass_scale), _triple(shift), _triple(factor))
    return errors


def link_errors(setup: RobotSetup, plant: PlantSpec, urdf: str | None = None) -> dict[str, LinkError]:
    """The plant's link errors by link name (drawn now for the generated form; ``urdf``: the
    robot's URDF text, default ``setup.urdf``). PlantError names a link that is not moving."""
    urdf = urdf or urdf_xml(setup.urdf)
    links = moving_links(urdf, setup.joint_names)
    if plant.link_inertia is None:
        return {}
    if isinstance(plant.link_inertia, LinkErrorDraw):
        inertias = {}
        for element in ET.fromstring(urdf).findall("link"):
            inertial = _inertial(element)
            if element.get("name") in links and inertial is not None:
                inertias[str(element.get("name"))] = inertial[2]
        return _draw(plant.link_inertia, links, inertias)
    for link in plant.link_inertia:
        if link not in links:
            raise PlantError(f"{plant.source}: link_inertia.{link} is not a moving link of {setup.name}; "
                             f"known: {list(links)}")
    return dict(plant.link_inertia)


def perturbed_inertial(mass: float, com: FloatArray, matrix: FloatArray,
                       error: LinkError) -> tuple[float, FloatArray, FloatArray]:
    """Mass kg, centre of mass (3,) m and inertia about it (3, 3) kg·m² with ``error`` applied: the
    principal moments (ascending) scaled along the unchanged principal axes. ValueError when the
    result breaks the triangle inequality (MuJoCo refuses such a body)."""
    principal, axes = np.linalg.eigh(matrix)
    scaled = principal * np.asarray(error.inertia_scale)
    if scaled.max() > scaled.sum() - scaled.max():
        raise ValueError(f"principal moments {scaled.tolist()} break the triangle inequality")
    return mass * error.mass_scale, com + np.asarray(error.com_shift), (axes * scaled) @ axes.T


def _physical(body: Payload) -> FloatArray:
    """The body's inertia (3, 3) kg·m² with the tiny violations the plant parser tolerates removed
    (negative principal moments clipped, the largest capped by the triangle inequality)."""
    ixx, iyy, izz, ixy, ixz, iyz = body.inertia
    principal, axes = np.linalg.eigh(np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]))
    principal = np.clip(principal, 0.0, None)
    principal[2] = min(principal[2], principal[0] + principal[1])
    return (axes * principal) @ axes.T


def _weld(root: ET.Element, parent: str, name: str, body: Payload) -> None:
    """Add ``body`` as link ``name`` fixed to ``parent`` at its origin (com and inertia in parent axes)."""
    link = ET.SubElement(root, "link", name=name)
    _set_inertial(link, body.mass, np.asarray(body.com, dtype=float), _physical(body))
    joint = ET.SubElement(root, "joint", name=f"{name}_joint", type="fixed")
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=name)
    ET.SubElement(joint, "origin", xyz="0 0 0", rpy="0 0 0")


def true_urdf(setup: RobotSetup, plant: PlantSpec, *, with_payload: bool = False) -> str:
    """URDF XML of the plant's true rigid body, loadable by pinocchio and MuJoCo.

    The robot's URDF with the ``link_inertia`` errors on the moving links, the links after the
    flange massless if ``tool.urdf_tool`` is absent (their frames stay), the ``tool.extra`` body
    as link ``kvark_tool`` fixed to the flange, and with ``with_payload`` the payload as link
    ``kvark_payload``. The ground truth counts the payload as external torque, so the oracle's
    model leaves it out (the default); MuJoCo simulates it (``with_payload=True``).
    Drive gain and armature are not rigid-body properties and are not in it.
    """
    urdf = urdf_xml(setup.urdf)
    root = ET.fromstring(urdf)
    links = {str(element.get("name")): element for element in root.findall("link")}
    if setup.flange_frame not in links:
        raise ValueError(f"{setup.name}: flange frame {setup.flange_frame!r} is not a URDF link")
    for name, error in link_errors(setup, plant, urdf).items():
        inertial = _inertial(links[name])
        if inertial is None:
            raise PlantError(f"{plant.source}: link_inertia.{name}: the URDF gives this link no inertial")
        try:
            _set_inertial(links[name], *perturbed_inertial(*inertial, error))
        except ValueError as exc:
            raise PlantError(f"{plant.source}: link_inertia.{name}.inertia_scale {exc}") from None
    if plant.tool_absent:
        for name in links_after(urdf, setup.flange_frame):
            if links[name].find("inertial") is not None:
                _set_inertial(links[name], 0.0, np.zeros(3), np.zeros((3, 3)))
    if plant.tool is not None:
        _weld(root, setup.flange_frame, TOOL_LINK, plant.tool)
    if with_payload and plant.payload is not None:
        _weld(root, setup.flange_frame, PAYLOAD_LINK, plant.payload)
    return ET.tostring(root, encoding="unicode")
