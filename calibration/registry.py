"""The object registry: which tag sits on which object, its size, and where the object is from it.

YAML (``examples/calibration/objects.yaml``)::

    tags:
      0: {object: table, size_m: 0.04}            # table tags define the table frame
      3: {object: goal, size_m: 0.04, T_tag_object: {translation_m: [0, 0, -0.05]}}

``T_tag_object`` maps the object frame into the tag frame; the object frame's origin is the
point the reach criterion measures to (the object's centre). Several tags on one object form a
bundle whose pose is fit to all their corners at once (:func:`locate_objects`), which also
resolves the single-tag IPPE ambiguity. The object named ``table`` is the table frame: world, z
up, origin on the table top (a tag lying face-up on the table with identity ``T_tag_object``
defines it directly).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Sequence

import numpy as np
from pydantic import Field, field_validator

from calibration.apriltag import BundlePose, TagDetection, TagDetectorOptions, estimate_bundle_pose, tag_object_points
from calibration.intrinsics import CameraIntrinsics
from calibration.io import PoseModel, Strict, load_model, write_yaml
from sim.geometry import invert_T, transform_points

__all__ = [
    "TABLE",
    "TagEntry",
    "ObjectRegistry",
    "ObjectObservation",
    "load_registry",
    "save_registry",
    "locate_objects",
    "visible_tag_fraction",
]

TABLE = "table"
N_TAG36H11 = 587  # ids 0..586


class TagEntry(Strict):
    object: Annotated[str, Field(min_length=1)]
    size_m: Annotated[float, Field(gt=0.0, le=2.0, description="black-square side as printed, m")]
    T_tag_object: PoseModel = PoseModel()


class ObjectRegistry(Strict):
    """Tag id -> :class:`TagEntry`. Validated: ids in tag36h11's range, sizes positive."""

    tags: dict[int, TagEntry]

    @field_validator("tags")
    @classmethod
    def _ids(cls, tags):
        bad = [i for i in tags if not 0 <= i < N_TAG36H11]
        if bad:
            raise ValueError(f"tag ids must be in 0..{N_TAG36H11 - 1} (tag36h11); got {bad}")
        return tags

    @property
    def objects(self) -> tuple[str, ...]:
        """Object names in first-appearance order (``table`` included if registered)."""
        return tuple(dict.fromkeys(e.object for e in self.tags.values()))

    def tag_size(self, tag_id: int) -> float | None:
        e = self.tags.get(tag_id)
        return None if e is None else e.size_m

    def tag_ids(self, obj: str) -> tuple[int, ...]:
        return tuple(i for i, e in self.tags.items() if e.object == obj)

    def corners_in_object(self, tag_id: int) -> np.ndarray:
        """Corners ``(4, 3)`` m of tag ``tag_id`` in its object's frame (detector order)."""
        e = self.tags[tag_id]
        return transform_points(invert_T(e.T_tag_object.T), tag_object_points(e.size_m))


@dataclass(frozen=True)
class ObjectObservation:
    """Where one registered object is in the camera frame, from its visible tags.

    ``alternatives`` hold the other plausible poses when the fit is ambiguous (one tag seen nearly
    frontally, say); the real reach outcome checks they all lead to the same answer.
    """

    name: str
    T_cam_object: np.ndarray
    tag_ids: tuple[int, ...]
    reprojection_rms_px: float
    ambiguous: bool
    alternatives: tuple[np.ndarray, ...] = ()

    @property
    def position_cam_m(self) -> np.ndarray:
        return self.T_cam_object[:3, 3]

    def positions_cam_m(self) -> np.ndarray:
        """(1 + n_alternatives, 3): best position first."""
        return np.stack([self.T_cam_object[:3, 3]] + [a[:3, 3] for a in self.alternatives])


def locate_objects(
    detections: Sequence[TagDetection],
    registry: ObjectRegistry,
    camera: CameraIntrinsics,
    options: TagDetectorOptions | None = None,
) -> dict[str, ObjectObservation]:
    """Every registered object with at least one posed tag -> its :class:`ObjectObservation`.

    Objects whose tags were not seen are absent (the caller decides what unknown means).
    """
    out = {}
    for name in registry.objects:
        ids = registry.tag_ids(name)
        corners = {i: registry.corners_in_object(i) for i in ids}
        bp: BundlePose | None = estimate_bundle_pose(
            [d for d in detections if d.tag_id in corners], corners, camera, options
        )
        if bp is not None:
            out[name] = ObjectObservation(
                name, bp.T_cam_frame, bp.tag_ids, bp.reprojection_rms_px, bp.ambiguous, bp.alternatives
            )
    return out


EXPECTED_MIN_COS = 0.26  # view angle up to ~75 deg (the detectors' practical limit)
EXPECTED_MIN_SIDE_PX = 10.0  # shorter tag edges are not reliably decoded


def visible_tag_fraction(
    registry: ObjectRegistry, name: str, T_cam_object: np.ndarray, seen_ids, camera: CameraIntrinsics
) -> float | None:
    """How much of an object's tag area that should be visible was seen: an occlusion measure.

    From the object's pose, each of its registered tags that faces the camera (view angle under
    ~75 deg), is at least 10 px a side and lies wholly in the image is *expected*; the result is the
    projected area of the expected tags that were detected over the area of all expected ones
    (1.0 = nothing hidden; 0.4 = 60 % of the print area the camera should see is covered). None when
    no tag is expected (nothing to measure).
    """
    expected, seen = 0.0, 0.0
    seen_ids = set(int(i) for i in seen_ids)
    for i in registry.tag_ids(name):
        T_cam_tag = np.asarray(T_cam_object) @ invert_T(registry.tags[i].T_tag_object.T)
        pts = transform_points(T_cam_tag, tag_object_points(registry.tags[i].size_m))
        if np.any(pts[:, 2] <= 0):
            continue  # behind the camera
        # Facing the camera along its line of sight (not merely along the optical axis), and not
        # so grazing or small that no detector could read it: only such a tag is "expected".
        ray = T_cam_tag[:3, 3] / np.linalg.norm(T_cam_tag[:3, 3])
        if float(T_cam_tag[:3, 2] @ ray) > -EXPECTED_MIN_COS:
            continue
        px = camera.project(pts)
        if np.any(px < -0.5) or np.any(px[:, 0] > camera.width - 0.5) or np.any(px[:, 1] > camera.height - 0.5):
            continue
        if float(np.min(np.linalg.norm(px - np.roll(px, -1, 0), axis=1))) < EXPECTED_MIN_SIDE_PX:
            continue
        x, y = px[:, 0], px[:, 1]
        area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
        expected += area
        seen += area if i in seen_ids else 0.0
    return None if expected <= 0 else seen / expected


def load_registry(path) -> ObjectRegistry:
    """The registry in ``path``; a :class:`CalibrationFileError` names the file and field."""
    return load_model(path, ObjectRegistry)


def save_registry(path, registry: ObjectRegistry) -> Path:
    data = {
        "tags": {
            int(i): {
                "object": e.object,
                "size_m": e.size_m,
                "T_tag_object": {
                    "translation_m": list(e.T_tag_object.translation_m),
                    "rotvec_rad": list(e.T_tag_object.rotvec_rad),
                },
            }
            for i, e in registry.tags.items()
        }
    }
    return write_yaml(path, data, header="Object registry: tag id -> object, tag size (m), T_tag_object")
