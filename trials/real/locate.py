"""Where the trial's objects are: the live tag check, the placement guidance and its sim twin.

A *locator* answers "where do the goal and the adversarial object stand, in the table frame?"
for the current camera frame and arm pose:

* :class:`TagLocator` (real cells): AprilTags detected in the wrist image
  (:func:`calibration.apriltag.detect_tags`), fitted per object with the registry
  (:func:`calibration.registry.locate_objects`, whose object names are the plan's roles ``goal``
  and ``adversarial``), then ``T_table_object = T_table_base @ T_base_tcp @ T_tcp_cam @
  T_cam_object``. The registry's object frame is the object's centre (the point the reach
  criterion measures to); its xy is compared with the plan's base-centre xy, which assumes the
  object frame's z axis is vertical above the base centre (true for the registry's upright objects).
  The runner names each trial's object (:meth:`TagLocator.for_trial`): the adversarial role is
  read from the registry object named after it (the scene object's name, e.g. ``objects.yaml`` of
  ``advobj fabricate --scene S --shape my_box``), else from ``adversarial``. For an object of the
  plan's scene the locator knows its centre in its own frame, so it gives the object's own pose:
  the tag card's registry entry is ``T_tag_object = inv(T_obj_tag) @ T_obj_centre``, hence
  ``T_table_object = T_table_tag @ inv(T_obj_tag)``: the tag's pose composed with the inverse of
  the tag's pose in the object frame.
* :class:`SimLocator` (sim hardware): the sim world's ground-truth poses, with optional Gaussian
  noise to exercise the tolerance check.

:func:`placement_issues` compares located and planned placements within the plan's tolerances
and words what the operator must do ("adversarial: move 2.3 cm toward +x, rotate -12 deg").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Protocol

import numpy as np

from calibration.apriltag import detect_tags
from calibration.frames import T_base_object
from calibration.registry import locate_objects, visible_tag_fraction
from sim.geometry import invert_T, make_T, rot_z

__all__ = [
    "LocatedObject",
    "Locator",
    "SimLocator",
    "TagLocator",
    "PlacementIssue",
    "placement_issues",
    "yaw_of",
    "wrap_angle",
]


def yaw_of(T) -> float:
    """Rotation about +z of a (4, 4) transform's x axis (rad, in (-pi, pi])."""
    T = np.asarray(T, dtype=np.float64)
    return float(math.atan2(T[1, 0], T[0, 0]))


def wrap_angle(a: float) -> float:
    return float((a + math.pi) % (2.0 * math.pi) - math.pi)


@dataclass(frozen=True)
class LocatedObject:
    """One object in the table frame: pose, the centre the criterion uses, and how it was seen.

    ``alternatives_center_m`` (A, 3): other plausible centres when the tag fit is ambiguous.
    """

    role: str
    T_table_object: np.ndarray
    center_table_m: np.ndarray
    tag_ids: tuple[int, ...] = ()
    ambiguous: bool = False
    alternatives_center_m: np.ndarray | None = None
    source: str = "tags"
    visible_fraction: float | None = (
        None  # seen / expected tag area from this view (calibration.registry.visible_tag_fraction)
    )

    @property
    def xy_m(self) -> np.ndarray:
        return self.T_table_object[:2, 3]

    @property
    def yaw_rad(self) -> float:
        return yaw_of(self.T_table_object)

    def centers_for_outcome(self) -> np.ndarray:
        """(1 + A, 3): best centre first, then the ambiguous alternatives (for measure_reach)."""
        if self.alternatives_center_m is None or len(self.alternatives_center_m) == 0:
            return self.center_table_m[None]
        return np.concatenate([self.center_table_m[None], np.asarray(self.alternatives_center_m).reshape(-1, 3)])


class Locator(Protocol):
    source: str

    def locate(self, frame, T_base_tcp: np.ndarray) -> dict[str, LocatedObject]:
        """Located objects by role; a role that was not seen is absent."""


class SimLocator:
    """Ground truth from a :class:`sim.world.SimWorld` (base frame = table frame), plus optional noise."""

    source = "sim"

    def __init__(self, world, noise_std_m: float = 0.0, noise_std_rad: float = 0.0, seed: int = 0):
        self.world = world
        self.noise_std_m = float(noise_std_m)
        self.noise_std_rad = float(noise_std_rad)
        self.rng = np.random.default_rng(seed)

    def locate(self, frame, T_base_tcp) -> dict[str, LocatedObject]:
        w = self.world
        out = {}
        centers = w.object_center_array
        for role in ("goal", "adversarial"):
            k = w.spec.object_index(role)
            T = w.T_world_objects[k].copy()
            c = centers[k].copy()
            if self.noise_std_m > 0 or self.noise_std_rad > 0:
                # Noise in place: shift on the table and turn about the object's own vertical axis.
                d = np.append(self.rng.normal(0.0, self.noise_std_m, 2), 0.0)
                T[:3, :3] = rot_z(self.rng.normal(0.0, self.noise_std_rad)) @ T[:3, :3]
                T[:3, 3] += d
                c = c + d
            out[role] = LocatedObject(role, T, c, (), False, None, "sim")
        return out


class TagLocator:
    """Objects from AprilTags in the wrist image.

    Args:
        registry: :class:`calibration.registry.ObjectRegistry` (object names = roles; ``table`` tags optional).
        intrinsics: the camera's :class:`CameraIntrinsics` at the frame resolution.
        T_tcp_cam: hand-eye result (4, 4).
        T_base_table: table frame in the robot base frame (4, 4).
    """

    source = "tags"

    def __init__(self, registry, intrinsics, T_tcp_cam: np.ndarray, T_base_table: np.ndarray):
        self.registry = registry
        self.intrinsics = intrinsics
        self.T_tcp_cam = np.asarray(T_tcp_cam, dtype=np.float64)
        self.T_base_table = np.asarray(T_base_table, dtype=np.float64)
        self.names = {role: (role,) for role in ("goal", "adversarial")}  # registry names tried, per role
        self.centers_local: dict[str, np.ndarray] = {}  # role -> its centre in its own frame, where known

    def for_trial(self, plan, trial) -> None:
        """Look for ``trial``'s adversarial object: under its name in the registry (the scene
        object's, the built-in shape's or ``patch``: :meth:`trials.real.plan.TrialPlan.object_name`),
        else under ``adversarial``; a scene object's own pose comes from its recorded centre."""
        self.names["adversarial"] = tuple(dict.fromkeys((plan.object_name(trial), "adversarial")))
        obj = plan.adversarial_for(trial)
        self.centers_local.pop("adversarial", None)
        if not isinstance(obj, str):
            self.centers_local["adversarial"] = np.asarray(obj.center_m, dtype=np.float64)

    def observe(self, frame):
        dets = detect_tags(frame.rgb, self.intrinsics, self.registry.tag_size)
        return locate_objects(dets, self.registry, self.intrinsics)

    def locate(self, frame, T_base_tcp) -> dict[str, LocatedObject]:
        return self.from_observations(self.observe(frame), T_base_tcp)

    def from_observations(self, observations: Mapping, T_base_tcp) -> dict[str, LocatedObject]:
        """Table-frame objects from :class:`calibration.registry.ObjectObservation` s seen at ``T_base_tcp``."""
        T_table_cam = invert_T(self.T_base_table) @ np.asarray(T_base_tcp, dtype=np.float64) @ self.T_tcp_cam
        out = {}
        for role in ("goal", "adversarial"):
            name = next((n for n in self.names.get(role, (role,)) if n in observations), None)
            if name is None:
                continue
            obs = observations[name]
            T_centre = T_table_cam @ obs.T_cam_object  # the registry's frame: the object's centre
            c = self.centers_local.get(role)
            T = T_centre if c is None else T_centre @ make_T(np.eye(3), -c)
            alts = [(T_table_cam @ a)[:3, 3] for a in obs.alternatives]
            vis = None
            if self.registry is not None and self.intrinsics is not None:
                vis = visible_tag_fraction(self.registry, name, obs.T_cam_object, obs.tag_ids, self.intrinsics)
            out[role] = LocatedObject(
                role,
                T,
                T_centre[:3, 3].copy(),
                tuple(obs.tag_ids),
                bool(obs.ambiguous),
                np.array(alts) if alts else None,
                "tags",
                vis,
            )
        return out

    @staticmethod
    def estimate_T_base_table(observations: Mapping, T_base_tcp, T_tcp_cam) -> np.ndarray | None:
        """``T_base_table`` from the registry's ``table`` tags seen at ``T_base_tcp`` (None if not seen)."""
        obs = observations.get("table")
        if obs is None:
            return None
        return T_base_object(
            np.asarray(T_base_tcp, dtype=np.float64),
            np.asarray(T_tcp_cam, dtype=np.float64),
            obs.T_cam_object,
            np.eye(4),
        )


@dataclass(frozen=True)
class PlacementIssue:
    """One object out of tolerance (or not seen): what to do about it."""

    role: str
    dx_m: float  # planned - located (move by this)
    dy_m: float
    dyaw_rad: float
    missing: bool = False

    @property
    def message(self) -> str:
        if self.missing:
            return f"{self.role}: not seen; check that its tags face the camera"
        d = math.hypot(self.dx_m, self.dy_m)
        parts = []
        if d > 0:
            parts.append(f"move {d * 100:.1f} cm toward {_direction(self.dx_m, self.dy_m)}")
        if self.dyaw_rad:
            parts.append(f"rotate {math.degrees(self.dyaw_rad):+.0f} deg (counter-clockwise seen from above is +)")
        return f"{self.role}: " + ", ".join(parts)


def _direction(dx: float, dy: float) -> str:
    """A readable table-frame direction: '+x', '-y', or '+x -y' with the dominant axis first."""
    parts = sorted(((abs(dx), f"{'+' if dx >= 0 else '-'}x"), (abs(dy), f"{'+' if dy >= 0 else '-'}y")), reverse=True)
    big = parts[0][0]
    return " ".join(name for mag, name in parts if mag >= 0.25 * big)


def placement_issues(
    planned: Mapping, located: Mapping[str, LocatedObject], tolerance_m: float, tolerance_rad: float
) -> list[PlacementIssue]:
    """Objects whose located pose misses the plan by more than a tolerance (empty: placed).

    ``planned``: role -> :class:`trials.real.plan.ObjectPlacement` (``xy_m``, ``yaw_rad``).
    The corrections in an issue are the full planned-minus-located offsets (both components, even
    when only one is out of tolerance), so following them lands the object on its target.
    """
    issues = []
    for role, p in planned.items():
        obj = located.get(role)
        if obj is None:
            issues.append(PlacementIssue(role, 0.0, 0.0, 0.0, missing=True))
            continue
        dx, dy = float(p.xy_m[0] - obj.xy_m[0]), float(p.xy_m[1] - obj.xy_m[1])
        dyaw = wrap_angle(float(p.yaw_rad) - obj.yaw_rad)
        if math.hypot(dx, dy) > tolerance_m or abs(dyaw) > tolerance_rad:
            issues.append(PlacementIssue(role, dx, dy, dyaw))
    return issues
