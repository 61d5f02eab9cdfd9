"""Arms described by a URDF: the chain between two named links and its forward kinematics in torch.

This module owns URDF arm models: it alone reads ``.urdf`` files and the shipped arms
(``sim/data/urdf/<arm>/<arm>.urdf`` with their ``PROVENANCE.json``).

* :func:`load_arm` reads a URDF and returns the :class:`ArmModel` of the chain from ``base_link`` to
  ``tool_link``: its actuated joints in chain order (:attr:`ArmModel.joint_names`), their units
  (``rad`` for revolute, ``m`` for prismatic joints) and limits (position and velocity, each one
  finite: a NaN or infinite limit is refused), and :meth:`ArmModel.fk`, ``q: (..., n) ->
  T_base_tool: (..., 4, 4)``, batched, differentiable, on the model's device, in float64 or float32;
  :meth:`ArmModel.fk_jacobian` adds the geometric Jacobian (the IK's, :mod:`sim.ik`).
* :func:`read_chain` is the parsing half alone (numpy, float64, no device), which a scene config
  uses to check its links at load.
* :data:`SHIPPED_ARMS` lists the arms that come with advobj (:func:`shipped_urdf`,
  :func:`read_provenance`).

Frames and units follow :mod:`sim.geometry`: ``T_base_tool`` maps points in the tool link's frame
into the base link's frame, metres and radians.

What a URDF may be. The file is parsed as plain XML and nothing in it is executed or fetched: no
xacro (a file using xacro elements or ``$(...)``/``${...}`` substitutions is refused: expand it with
xacro first), no DOCTYPE or entities (refused), no ``package://`` look-ups. Meshes are not needed for
kinematics: every ``<visual>``, ``<collision>`` and ``<inertial>`` is dropped before the model is
built, so no mesh file name is ever resolved or opened. The path must be a regular file of at most
:data:`MAX_URDF_BYTES` (checked on the open file before it is read) and, when a ``root`` is given
(a scene's folder), inside it. The chain may hold ``revolute``, ``prismatic`` and ``fixed`` joints;
``continuous`` (no position limits), ``floating``, ``planar`` and mimic joints in the chain are
refused, as are a revolute or prismatic joint without ``<limit lower upper velocity>``, a zero axis
and any non-finite number in the chain. Every refusal is a :class:`KinematicsError`, one line that
names the file and the joint, link or attribute.

Why yourdfpy + our own FK, and not pytorch-kinematics (measured on the two shipped arms against
pinocchio 4.1, 10,000 random joint vectors within the limits, float64):

* pytorch-kinematics 0.10.0 builds every joint offset through a float32 tensor
  (``urdf._convert_transform``), so even after ``chain.to(dtype=torch.float64)`` its Panda pose
  differs from pinocchio's by up to 2.5e-8 m and 8.4e-8 rad; our chain, built from yourdfpy's
  float64 origins, differs by 4.4e-16 m and 5.7e-16 rad (UR5: 1.7e-8 m / 1.5e-11 rad against
  4.4e-16 m / 5.4e-16 rad). It also prints a line for every URDF tag it does not know and adds
  absl-py, arm_pytorch_utilities and pytorch_seed to the environment.
* yourdfpy (0.0.60) is a maintained URDF parser that turns origins (``xyz``, ``rpy`` as fixed-axis
  x-y-z, URDF's convention) into float64 matrices and loads nothing when its scene graph and meshes
  are off. Two things it does are worked around here: it falls back to lxml's ``recover=True`` on
  malformed XML (so the file is parsed strictly here first and only a clean tree is handed to it),
  and it requires ``trimesh[easy]`` (fourteen packages, an HTTP client among them, for mesh loading
  that never happens here), so it is installed without its dependencies (``make venv``); the ones
  it imports (lxml, six, numpy, trimesh) are the project's own.
* The FK itself is a product of one constant transform and one joint motion per actuated joint
  (Rodrigues' formula for revolute joints): a few lines of batched torch, exact in float64.
"""

from __future__ import annotations

import functools
import io
import json
import math
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import torch
import yourdfpy
from lxml import etree

from sim.errors import AdvobjError
from sim.files import FileRefusedError, read_regular

__all__ = [
    "KinematicsError",
    "MAX_URDF_BYTES",
    "SHIPPED_ARMS",
    "PROVENANCE_JSON",
    "JOINT_UNITS",
    "ArmChain",
    "JointLimits",
    "ArmModel",
    "read_chain",
    "load_arm",
    "shipped_urdf",
    "shipped_arm",
    "read_provenance",
    "urdf_source",
]

#: A URDF larger than this is refused before it is read (a 7-joint arm with every tag is ~20 KB).
MAX_URDF_BYTES = 4 * 2**20

#: The arms shipped with advobj: name -> (base link, tool link) of the chain advobj uses. The URDF
#: is ``sim/data/urdf/<name>/<name>.urdf`` beside its ``PROVENANCE.json`` and licence.
SHIPPED_ARMS: dict[str, tuple[str, str]] = {
    "panda": ("panda_link0", "panda_hand"),  # pybullet's pybullet_data/franka_panda/panda.urdf
    "ur5": ("base_link", "tool0"),  # example-robot-data's ur_description/urdf/ur5_robot.urdf
}
PROVENANCE_JSON = "PROVENANCE.json"

#: The unit of each joint type a chain may hold (position; velocities are per second).
JOINT_UNITS = {"revolute": "rad", "prismatic": "m"}

_XACRO = re.compile(r"\$[({]")  # xacro's substitution args $(...) and properties ${...}
_SHOWN = 20  # link names listed in a "not in the file" message


class KinematicsError(AdvobjError, ValueError):
    """A URDF, link name or joint vector advobj cannot use; one line naming the file and the field.

    ``field`` is the argument at fault when there is one (``"urdf"``, ``"base_link"``,
    ``"tool_link"``, ``"q"``), so a config loader can name its own field."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


# ---------------------------------------------------------------------------------------------
# Reading a URDF


@dataclass(frozen=True, eq=False)
class ArmChain:
    """The chain from ``base_link`` to ``tool_link`` as read from a URDF (numpy, float64).

    With ``n`` actuated joints, ``T_fixed: (n + 1, 4, 4)``: ``T_fixed[k]`` is the constant transform
    from the previous joint's frame (the base link for ``k = 0``) to joint ``k``'s frame (the fixed
    joints' origins in between and joint ``k``'s own origin); ``T_fixed[n]`` runs from the last
    joint's frame to the tool link. ``axes: (n, 3)`` unit joint axes in their joint frames; limits
    ``q_min``, ``q_max``, ``qd_max``: ``(n,)`` in each joint's unit (:attr:`units`) and per second.
    """

    urdf: Path
    base_link: str
    tool_link: str
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    T_fixed: np.ndarray
    axes: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    qd_max: np.ndarray

    @property
    def units(self) -> tuple[str, ...]:
        """Each joint's position unit: ``"rad"`` (revolute) or ``"m"`` (prismatic)."""
        return tuple(JOINT_UNITS[t] for t in self.joint_types)


#: How a URDF that is no file to read is refused (:class:`sim.files.FileRefusedError`'s reasons).
_FILE_WORDS = {
    "missing": "no such URDF file",
    "unreadable": "cannot read the URDF ({strerror})",
    "directory": "a directory, expected a URDF file",
    "special": "not a regular file, expected a URDF file",
    "too_large": "{size} bytes, larger than a URDF may be ({max_bytes} bytes)",
    "grew": "grew past {max_bytes} bytes while it was read",
}


def _open_checked(path: Path) -> bytes:
    """The bytes of ``path``: a regular file of at most :data:`MAX_URDF_BYTES`, checked on the open
    file (a FIFO or device is refused without blocking on it; :func:`sim.files.read_regular`)."""
    try:
        return read_regular(path, MAX_URDF_BYTES)
    except FileRefusedError as err:
        raise KinematicsError(f"{path}: {err.problem(_FILE_WORDS)}", "urdf") from None


def _strict_tree(path: Path, data: bytes) -> etree._Element:
    """The XML root of ``data``, parsed strictly (no recovery, entities, DTD or network)."""
    parser = etree.XMLParser(
        resolve_entities=False,
        no_network=True,
        load_dtd=False,
        huge_tree=False,
        remove_comments=True,
        remove_pis=True,
        remove_blank_text=True,
    )
    if b"<!DOCTYPE" in data:
        raise KinematicsError(f"{path}: a URDF with a DOCTYPE is refused (no DTDs or entities are read)", "urdf")
    try:
        tree = etree.parse(io.BytesIO(data), parser)
    except etree.XMLSyntaxError as err:
        raise KinematicsError(f"{path}: not well-formed XML ({' '.join(str(err).split())})", "urdf") from None
    if tree.docinfo.doctype or tree.docinfo.internalDTD is not None:
        raise KinematicsError(f"{path}: a URDF with a DOCTYPE is refused (no DTDs or entities are read)", "urdf")
    root = tree.getroot()
    if root.tag != "robot":
        raise KinematicsError(f"{path}: not a URDF: the top element is <{root.tag}>, expected <robot>", "urdf")
    return root


def _is_xacro(el: etree._Element) -> bool:
    tag = el.tag if isinstance(el.tag, str) else ""
    return (tag.startswith("{") and "xacro" in tag[1:].split("}")[0]) or tag.startswith("xacro:")


def _floats(path: Path, where: str, text: str, count: int) -> None:
    """Refuse ``text`` unless it is ``count`` numbers (NaN and inf parse: the chain refuses them)."""
    parts = text.split()
    try:
        [float(p) for p in parts]
    except ValueError:
        raise KinematicsError(f"{path}: {where}={text!r} is not a number", "urdf") from None
    if len(parts) != count:
        raise KinematicsError(f"{path}: {where}={text!r}: expected {count} numbers, got {len(parts)}", "urdf")


_JOINT_NUMBERS = {("origin", "xyz"): 3, ("origin", "rpy"): 3, ("axis", "xyz"): 3}
_LIMIT_ATTRS = ("lower", "upper", "velocity", "effort")
_JOINT_KEEP = {"parent", "child", "origin", "axis", "limit"}


def _kinematic_tree(path: Path, root: etree._Element) -> tuple[etree._Element, set[str]]:
    """``root`` reduced to what kinematics reads (link names; joints' parent, child, origin, axis,
    limit), every number in it checked; and the names of the mimic joints.

    Refuses xacro. Drops, explicitly, everything else: links' visual, collision and inertial
    elements (meshes are never resolved), materials, transmissions, gazebo tags, and joints'
    dynamics, calibration and safety controllers.
    """
    for el in root.iter():
        if _is_xacro(el) or any(_XACRO.search(v) for v in el.attrib.values()):
            raise KinematicsError(
                f"{path}: a xacro file (line {el.sourceline}): expand it with xacro into a plain URDF first; "
                "advobj runs no xacro",
                "urdf",
            )
    if "name" not in root.attrib:
        raise KinematicsError(f"{path}: <robot> has no name attribute", "urdf")
    kept = etree.Element("robot", name=root.get("name"))
    mimic: set[str] = set()
    joints: set[str] = set()
    for el in root:
        if el.tag == "link":
            if not el.get("name"):
                raise KinematicsError(f"{path}: a <link> without a name (line {el.sourceline})", "urdf")
            etree.SubElement(kept, "link", name=el.get("name"))
        elif el.tag == "joint":
            name = el.get("name")
            if not name:
                raise KinematicsError(f"{path}: a <joint> without a name (line {el.sourceline})", "urdf")
            if name in joints:
                raise KinematicsError(f"{path}: two joints are called {name!r}", "urdf")
            joints.add(name)
            joint = etree.SubElement(kept, "joint", name=name, type=el.get("type", ""))
            for part in ("parent", "child"):
                found = el.find(part)
                if found is None or not found.get("link"):
                    raise KinematicsError(f"{path}: joint {name!r} has no <{part} link=...>", "urdf")
            for child in el:
                if child.tag == "mimic":
                    mimic.add(name)
                if child.tag not in _JOINT_KEEP:
                    continue
                for attr, value in child.attrib.items():
                    if child.tag == "limit":
                        count = 1 if attr in _LIMIT_ATTRS else None
                    else:
                        count = _JOINT_NUMBERS.get((child.tag, attr))
                    if count is not None:
                        _floats(path, f"joint {name!r} <{child.tag} {attr}>", value, count)
                joint.append(child)
    return kept, mimic


def _list(names) -> str:
    names = sorted(names)
    more = f" ... ({len(names) - _SHOWN} more)" if len(names) > _SHOWN else ""
    return ", ".join(names[:_SHOWN]) + more


def _chain(path: Path, robot: yourdfpy.URDF, mimic: set[str], base_link: str, tool_link: str) -> ArmChain:
    """The chain of ``robot`` from ``base_link`` down to ``tool_link``, every value checked."""
    links = robot.link_map
    for field, link in (("base_link", base_link), ("tool_link", tool_link)):
        if link not in links:
            raise KinematicsError(
                f"{path}: {field} {link!r} is not a link of the URDF (its links: {_list(links)})", field
            )
    if base_link == tool_link:
        raise KinematicsError(
            f"{path}: base_link and tool_link are both {base_link!r}: an arm has joints between them", "tool_link"
        )
    into: dict[str, yourdfpy.Joint] = {}
    for j in robot.robot.joints:
        if j.child in into:
            raise KinematicsError(
                f"{path}: link {j.child!r} is the child of two joints ({into[j.child].name!r}, {j.name!r})", "urdf"
            )
        into[j.child] = j
    path_joints, link, seen = [], tool_link, {tool_link}
    while link != base_link:
        j = into.get(link)
        if j is None:
            raise KinematicsError(
                f"{path}: tool_link {tool_link!r} is not below base_link {base_link!r} in the URDF", "tool_link"
            )
        if j.parent in seen:
            raise KinematicsError(f"{path}: the joints above link {link!r} form a loop", "urdf")
        path_joints.append(j)
        seen.add(j.parent)
        link = j.parent
    path_joints.reverse()

    names, types, fixed, axes, q_min, q_max, qd_max = [], [], [], [], [], [], []
    T = np.eye(4)
    for j in path_joints:
        where = f"{path}: joint {j.name!r}"
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
        if not np.isfinite(origin).all():
            raise KinematicsError(f"{where}: its <origin> is not finite", "urdf")
        T = T @ origin
        if j.type == "fixed":
            continue
        if j.type not in JOINT_UNITS:
            why = {
                "continuous": "has no position limits; give it type revolute with <limit lower upper velocity>",
                "floating": "is not an arm joint",
                "planar": "is not an arm joint",
            }.get(j.type, f"has an unknown type {j.type!r} (revolute, prismatic, fixed, continuous, floating, planar)")
            raise KinematicsError(f"{where}: type {j.type!r} in the chain {why}", "urdf")
        if j.name in mimic:
            raise KinematicsError(
                f"{where}: a mimic joint in the chain (it moves with another joint) is refused", "urdf"
            )
        axis = np.asarray(j.axis, dtype=np.float64)
        norm = float(np.linalg.norm(axis))
        if not np.isfinite(axis).all() or norm < 1e-9:
            raise KinematicsError(
                f"{where}: its <axis xyz> must be a finite non-zero vector, got {axis.tolist()}", "urdf"
            )
        lim = j.limit
        values = {k: None if lim is None else getattr(lim, k) for k in ("lower", "upper", "velocity")}
        missing = [k for k, v in values.items() if v is None]
        if missing:
            raise KinematicsError(f"{where}: its <limit> gives no {', '.join(missing)} (each joint needs them)", "urdf")
        for k, v in values.items():
            if not math.isfinite(v):
                raise KinematicsError(f"{where}: <limit {k}> is {v}, a limit must be a finite number", "urdf")
        if values["lower"] > values["upper"]:
            raise KinematicsError(f"{where}: <limit lower> {values['lower']} exceeds upper {values['upper']}", "urdf")
        if values["velocity"] <= 0:
            raise KinematicsError(f"{where}: <limit velocity> must be > 0, got {values['velocity']}", "urdf")
        names.append(j.name)
        types.append(j.type)
        fixed.append(T)
        axes.append(axis / norm)
        q_min.append(values["lower"])
        q_max.append(values["upper"])
        qd_max.append(values["velocity"])
        T = np.eye(4)
    if not names:
        raise KinematicsError(
            f"{path}: no revolute or prismatic joint between base_link {base_link!r} and tool_link {tool_link!r}",
            "tool_link",
        )
    fixed.append(T)
    arrays = [
        np.array(a, dtype=np.float64).reshape(shape)
        for a, shape in ((fixed, (-1, 4, 4)), (axes, (-1, 3)), (q_min, (-1,)), (q_max, (-1,)), (qd_max, (-1,)))
    ]
    for a in arrays:
        a.setflags(write=False)
    return ArmChain(path, base_link, tool_link, tuple(names), tuple(types), *arrays)


def _resolve(urdf_path: str | Path, root: str | Path | None) -> Path:
    """``urdf_path`` resolved (links followed); relative to ``root`` and required inside it when given."""
    path = Path(urdf_path).expanduser()
    if root is None:
        return path.resolve()
    base = Path(root).expanduser().resolve()
    path = (base / path).resolve()
    if base not in path.parents:
        raise KinematicsError(f"{urdf_path}: the URDF lies outside {base}; put it there and name it relatively", "urdf")
    return path


@functools.lru_cache(maxsize=32)
def _read_chain_cached(path: Path, _stamp: tuple, base_link: str, tool_link: str) -> ArmChain:
    data = _open_checked(path)
    kept, mimic = _kinematic_tree(path, _strict_tree(path, data))
    try:
        robot = yourdfpy.URDF.load(
            io.BytesIO(etree.tostring(kept)),
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
            filename_handler=yourdfpy.filename_handler_null,
        )
    except (ValueError, TypeError, KeyError, AttributeError, IndexError) as err:  # numbers are checked: a safety net
        raise KinematicsError(f"{path}: not a usable URDF ({' '.join(str(err).split())})", "urdf") from None
    return _chain(path, robot, mimic, base_link, tool_link)


def read_chain(urdf_path: str | Path, base_link: str, tool_link: str, *, root: str | Path | None = None) -> ArmChain:
    """The :class:`ArmChain` from ``base_link`` to ``tool_link`` of the URDF at ``urdf_path``.

    With ``root``, a relative path is relative to that folder, and the path (after resolving links)
    must lie inside it. Everything the module docstring lists is refused with a
    :class:`KinematicsError`. Results are cached per file (path, inode, size, modification time) and
    link pair.
    """
    path = _resolve(urdf_path, root)
    try:
        st = path.stat()
        stamp = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    except OSError:
        stamp = ()  # the open reports it
    return _read_chain_cached(path, stamp, str(base_link), str(tool_link))


# ---------------------------------------------------------------------------------------------
# The model


@dataclass(frozen=True, eq=False)
class JointLimits:
    """Per joint in chain order, each in its joint's unit (rad or m) and per second: ``(n,)`` float64
    tensors on the model's device. Every value is finite."""

    q_min: torch.Tensor
    q_max: torch.Tensor
    qd_max: torch.Tensor


@dataclass(frozen=True)
class _Factors:
    """One dtype's constants of :meth:`ArmModel.fk`, on the model's device.

    For joint ``k`` with fixed transform ``(C_R, C_p)`` and axis ``a`` (``K = skew(a)``): revolute
    ``C_R R(q) = C_R + sin q (C_R K) + (1 - cos q) (C_R K^2)``, prismatic ``C_p + q (C_R a)``.
    """

    R_fixed: torch.Tensor  # (n + 1, 3, 3)
    p_fixed: torch.Tensor  # (n + 1, 3)
    R_sin: torch.Tensor  # (n, 3, 3): C_R K
    R_vers: torch.Tensor  # (n, 3, 3): C_R K^2
    p_slide: torch.Tensor  # (n, 3): C_R a


def _factors(chain: ArmChain, dtype: torch.dtype, device: torch.device) -> _Factors:
    R = chain.T_fixed[:, :3, :3]
    a = chain.axes
    K = np.zeros((len(a), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
    K -= np.swapaxes(K, -1, -2)
    Rn = R[:-1]
    t = functools.partial(torch.tensor, dtype=dtype, device=device)
    return _Factors(
        R_fixed=t(R),
        p_fixed=t(chain.T_fixed[:, :3, 3]),
        R_sin=t(Rn @ K),
        R_vers=t(Rn @ K @ K),
        p_slide=t(np.einsum("kij,kj->ki", Rn, a)),
    )


@dataclass(frozen=True, eq=False)
class ArmModel:
    """An arm's chain from ``base_link`` to ``tool_link`` on ``device``: :meth:`fk` and the joints.

    Build it with :func:`load_arm` (or :func:`shipped_arm`); :meth:`to` moves it to another device.
    """

    chain: ArmChain
    device: torch.device
    limits: JointLimits
    _by_dtype: dict

    @property
    def urdf(self) -> Path:
        return self.chain.urdf

    @property
    def base_link(self) -> str:
        return self.chain.base_link

    @property
    def tool_link(self) -> str:
        return self.chain.tool_link

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The actuated joints of the chain, base to tool: the order of ``q``'s last axis."""
        return self.chain.joint_names

    @property
    def units(self) -> tuple[str, ...]:
        """Each joint's position unit, ``"rad"`` or ``"m"`` (velocities: per second)."""
        return self.chain.units

    @property
    def n_joints(self) -> int:
        return len(self.chain.joint_names)

    def to(self, device: str | torch.device) -> "ArmModel":
        """This model on ``device``."""
        return _model(self.chain, device)

    def _checked(self, q, what: str = "q") -> torch.Tensor:
        if not isinstance(q, torch.Tensor):
            raise KinematicsError(f"{what} must be a torch tensor (..., {self.n_joints}), got {type(q).__name__}", "q")
        if q.dtype not in self._by_dtype:
            raise KinematicsError(f"{what} must be float64 or float32, got {q.dtype}", "q")
        if q.ndim == 0 or q.shape[-1] != self.n_joints:
            got = "a scalar" if q.ndim == 0 else f"a joint vector of length {q.shape[-1]} (shape {tuple(q.shape)})"
            raise KinematicsError(
                f"{what}: {got}; the chain {self.base_link} -> {self.tool_link} of {self.urdf.name} "
                f"has {self.n_joints} joints ({', '.join(self.joint_names)})",
                "q",
            )
        if q.device != self.device:
            raise KinematicsError(f"{what} is on {q.device}, the arm model on {self.device} (use ArmModel.to)", "q")
        return q

    def fk(self, q: torch.Tensor) -> torch.Tensor:
        """``T_base_tool: (..., 4, 4)`` of joint positions ``q: (..., n)`` (rad or m, :attr:`units`).

        Batched over any leading dimensions, differentiable in ``q``, computed in ``q``'s dtype
        (float64 or float32) on the model's device; ``q`` must be on that device. ``q`` is not
        checked against the limits or for finiteness here (that would synchronise a GPU on every
        call; use :meth:`check_q` on input from outside): a NaN or infinite entry gives NaN in its
        own pose and leaves every other pose of the batch as it is; a large finite angle gives a
        rigid transform. A wrong length, dtype or device raises :class:`KinematicsError`.
        """
        return self._walk(q, jacobian=False)[0]

    def fk_jacobian(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(T_base_tool (..., 4, 4), J (..., 6, n))``: :meth:`fk` and the geometric Jacobian.

        ``J``'s rows are the tool origin's linear velocity (m/s, first three) and the tool's angular
        velocity (rad/s, last three), both in the base frame, per unit joint velocity: a revolute
        joint ``k`` with axis ``z_k`` through ``o_k`` gives ``(z_k x (p_tool - o_k), z_k)``, a
        prismatic one ``(z_k, 0)``. Same inputs and checks as :meth:`fk`.
        """
        return self._walk(q, jacobian=True)

    def _walk(self, q: torch.Tensor, jacobian: bool):
        q = self._checked(q)
        f = self._by_dtype[q.dtype]
        batch = q.shape[:-1]
        R = torch.eye(3, dtype=q.dtype, device=q.device).expand(*batch, 3, 3)
        p = torch.zeros(*batch, 3, dtype=q.dtype, device=q.device)
        axes, origins = [], []
        for k, kind in enumerate(self.chain.joint_types):
            # (R, p) <- (R, p) (C_k M_k(q_k)): joint k's fixed transform, then its motion.
            qk = q[..., k, None, None]
            if jacobian:  # joint k's axis and origin in the base frame, before its own motion
                axes.append((R @ f.p_slide[k].unsqueeze(-1)).squeeze(-1))
                origins.append(p + (R @ f.p_fixed[k].unsqueeze(-1)).squeeze(-1))
            if kind == "revolute":
                half = torch.sin(qk / 2)  # 1 - cos q = 2 sin^2(q/2), exact near q = 0
                G_R = f.R_fixed[k] + torch.sin(qk) * f.R_sin[k] + 2 * half * half * f.R_vers[k]
                G_p = f.p_fixed[k]
            else:
                G_R = f.R_fixed[k]
                G_p = f.p_fixed[k] + qk[..., 0] * f.p_slide[k]
            p = p + (R @ G_p.unsqueeze(-1)).squeeze(-1)
            R = R @ G_R
        n = self.n_joints
        p = p + (R @ f.p_fixed[n].unsqueeze(-1)).squeeze(-1)
        R = R @ f.R_fixed[n]
        top = torch.cat([R, p.unsqueeze(-1)], dim=-1)
        bottom = torch.zeros(*batch, 1, 4, dtype=q.dtype, device=q.device)
        bottom[..., 0, 3] = 1
        T = torch.cat([top, bottom], dim=-2)
        if not jacobian:
            return T, None
        z = torch.stack(axes, -1)  # (..., 3, n)
        o = torch.stack(origins, -1)
        revolute = torch.tensor([t == "revolute" for t in self.chain.joint_types], device=q.device)
        lin = torch.where(revolute, torch.linalg.cross(z, p.unsqueeze(-1) - o, dim=-2), z)
        ang = torch.where(revolute, z, torch.zeros_like(z))
        return T, torch.cat([lin, ang], dim=-2)

    def check_q(self, q: torch.Tensor, *, tol: float = 0.0, what: str = "q") -> torch.Tensor:
        """``q`` itself when it is a usable joint vector: the right length, dtype and device, every
        entry finite and within ``[q_min - tol, q_max + tol]``; else a :class:`KinematicsError` naming
        the first joint at fault. For input from outside (a file, a policy, an operator); it reads
        the values, so it synchronises a GPU."""
        q = self._checked(q, what)
        bad = ~torch.isfinite(q)
        if bad.any():
            idx = tuple(int(i) for i in bad.nonzero()[0])
            raise KinematicsError(
                f"{what}{list(idx[:-1]) or ''}: joint {self.joint_names[idx[-1]]!r} is {float(q[idx])}", "q"
            )
        lo = self.limits.q_min.to(q.dtype) - tol
        hi = self.limits.q_max.to(q.dtype) + tol
        out = (q < lo) | (q > hi)
        if out.any():
            idx = tuple(int(i) for i in out.nonzero()[0])
            k = idx[-1]
            raise KinematicsError(
                f"{what}{list(idx[:-1]) or ''}: joint {self.joint_names[k]!r} at {float(q[idx]):.6g} {self.units[k]} "
                f"is outside its limits [{float(lo[k]):.6g}, {float(hi[k]):.6g}]",
                "q",
            )
        return q


def _model(chain: ArmChain, device: str | torch.device) -> ArmModel:
    try:
        dev = torch.device(device)
        torch.empty(0, device=dev)
    except (RuntimeError, TypeError, ValueError, AssertionError) as err:  # no CUDA build: AssertionError
        raise KinematicsError(f"device {device!r} is not usable here ({' '.join(str(err).split())})") from None
    t = functools.partial(torch.tensor, dtype=torch.float64, device=dev)
    limits = JointLimits(q_min=t(chain.q_min), q_max=t(chain.q_max), qd_max=t(chain.qd_max))
    by_dtype = {dt: _factors(chain, dt, dev) for dt in (torch.float64, torch.float32)}
    return ArmModel(chain=chain, device=dev, limits=limits, _by_dtype=by_dtype)


def load_arm(
    urdf_path: str | Path,
    base_link: str,
    tool_link: str,
    *,
    device: str | torch.device = "cpu",
    root: str | Path | None = None,
) -> ArmModel:
    """The :class:`ArmModel` of the chain from ``base_link`` to ``tool_link`` of a URDF, on ``device``.

    ``root``: when given, the URDF must lie inside this folder. Refusals: see :func:`read_chain`.
    """
    return _model(read_chain(urdf_path, base_link, tool_link, root=root), device)


# ---------------------------------------------------------------------------------------------
# The shipped arms


def _shipped_dir(name: str) -> Path:
    if name not in SHIPPED_ARMS:
        raise KinematicsError(f"no shipped arm {name!r}; advobj ships: {', '.join(SHIPPED_ARMS)}", "urdf")
    return Path(str(resources.files("sim").joinpath("data", "urdf", name)))


def shipped_urdf(name: str) -> Path:
    """The URDF file of the shipped arm ``name`` (one of :data:`SHIPPED_ARMS`)."""
    return _shipped_dir(name) / f"{name}.urdf"


def shipped_arm(name: str, *, device: str | torch.device = "cpu") -> ArmModel:
    """The shipped arm ``name`` with its chain's links from :data:`SHIPPED_ARMS`, on ``device``."""
    path = shipped_urdf(name)
    return load_arm(path, *SHIPPED_ARMS[name], device=device)


def read_provenance(name: str) -> dict:
    """The shipped arm's provenance record: package, version, path in the package, licence, sha256."""
    return json.loads((_shipped_dir(name) / PROVENANCE_JSON).read_text(encoding="utf-8"))


def urdf_source(value: str, *, root: str | Path | None = None) -> Path:
    """The URDF file a config names: a shipped arm's name (:data:`SHIPPED_ARMS`) or a file path;
    a relative path is relative to ``root`` (when given), and the file must lie inside ``root``."""
    return shipped_urdf(value) if value in SHIPPED_ARMS else _resolve(value, root)
