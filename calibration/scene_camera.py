"""Where a fixed scene camera stands: its pose ``T_table_cam`` from the table's AprilTags.

A fixed camera (a lab's front or top view, read by a policy beside the wrist camera) is located
against the tags lying on the table: the registry's object ``table``
(:data:`calibration.registry.TABLE`), whose tag poses define the table frame. Every corner of
every table tag detected in every image is one correspondence between a pixel and a point of the
table frame, and one pose fits them all, since the camera does not move between the images
(Perspective-n-Point over all tag corners):

1. each image's table tags are fit as one bundle (:func:`calibration.apriltag.estimate_bundle_pose`,
   which resolves a single tag's two-fold ambiguity once several tags are seen); every bundle fit
   and its ambiguous alternatives are a seed;
2. each seed is refined by Levenberg-Marquardt on the corners of all images at once; the fit of
   the lowest RMS reprojection error wins.

Refused (:class:`~calibration.errors.CalibrationError`, one line): fewer than ``min_tags``
distinct table tags seen (one tag leaves the reflection ambiguity and a baseline of a few
centimetres), an RMS reprojection error over ``max_rms_px`` (the camera moved between the images,
a tag does not lie where the registry says, a wrong camera file), or two clearly different poses
that fit about equally well.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from calibration.apriltag import TagDetection, TagDetectorOptions, detect_tags, estimate_bundle_pose, reprojection_rms
from calibration.errors import CalibrationError
from calibration.intrinsics import CameraIntrinsics
from calibration.registry import TABLE, ObjectRegistry
from sim.geometry import invert_T, make_T, rotation_angle, so3_exp, so3_log

__all__ = [
    "MIN_TAGS",
    "MAX_RMS_PX",
    "MAX_IMAGES",
    "SceneCameraFit",
    "table_tag_corners",
    "fit_scene_camera",
    "locate_scene_camera",
]

MIN_TAGS = 2  # distinct table tags: one tag alone is the IPPE reflection ambiguity
MAX_RMS_PX = 2.0  # corners of a sharp, well calibrated view fit within a fraction of a pixel
MAX_IMAGES = 100  # images of one fixed camera: a handful is plenty (they differ by sensor noise only)


@dataclass(frozen=True)
class SceneCameraFit:
    """The pose of a fixed camera in the table frame and how well it fits.

    ``per_image_rms_px[i]``: the RMS reprojection error of image ``i``'s table-tag corners under
    the common pose (None: no table tag in that image). ``width`` x ``height``: the images' size.
    """

    T_table_cam: np.ndarray  # (4, 4)
    reprojection_rms_px: float
    per_image_rms_px: tuple[float | None, ...]
    tag_ids: tuple[int, ...]
    n_images: int  # images with at least one table tag
    n_corners: int
    width: int
    height: int


def table_tag_corners(registry: ObjectRegistry) -> dict[int, np.ndarray]:
    """Tag id -> its corners ``(4, 3)`` m in the table frame (detector order), for every table tag."""
    return {i: registry.corners_in_object(i) for i in registry.tag_ids(TABLE)}


def _names(names, n: int) -> list[str]:
    return list(names) if names is not None else [f"image {i}" for i in range(n)]


def fit_scene_camera(
    detections: Sequence[Sequence[TagDetection]],
    registry: ObjectRegistry,
    camera: CameraIntrinsics,
    min_tags: int = MIN_TAGS,
    max_rms_px: float = MAX_RMS_PX,
    options: TagDetectorOptions | None = None,
    names: Sequence[str] | None = None,
) -> SceneCameraFit:
    """``T_table_cam`` from the tags detected in each image of one fixed camera (module docstring).

    ``detections[i]``: the tags of image ``i`` (posed: their sizes known); tags that are not the
    table's are ignored. ``names`` name the images in messages.
    """
    opt = options or TagDetectorOptions()
    corners = table_tag_corners(registry)
    if not corners:
        raise CalibrationError(
            f"registry: no tag of object {TABLE!r}; a scene camera is located against the table's tags"
        )
    names = _names(names, len(detections))
    per_image = [[d for d in dets if d.tag_id in corners and d.solutions] for dets in detections]
    seen = sorted({d.tag_id for dets in per_image for d in dets})
    if len(seen) < min_tags:
        what = f"table tag{'s' if len(seen) != 1 else ''} {', '.join(map(str, seen))}" if seen else "no table tag"
        raise CalibrationError(
            f"{what} seen in {len(detections)} image(s); at least {min_tags} distinct table tags are needed "
            f"(the registry's table tags: {', '.join(map(str, sorted(corners)))}): put more of them in the "
            "camera's view, spread over the table"
        )
    obj = np.concatenate([corners[d.tag_id] for dets in per_image for d in dets])
    img = np.concatenate([d.corners_px for dets in per_image for d in dets]).astype(np.float64)
    seeds = []
    for dets in per_image:
        bp = estimate_bundle_pose(dets, corners, camera, opt)
        if bp is not None:
            seeds += [bp.T_cam_frame, *bp.alternatives]
    fits = []
    for T0 in seeds:
        rvec, tvec = so3_log(T0[:3, :3]).reshape(3, 1), T0[:3, 3].reshape(3, 1).copy()
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec)
        except cv2.error:
            continue
        T = make_T(so3_exp(rvec.reshape(3)), tvec.reshape(3))
        in_front = (obj @ T[:3, :3].T + T[:3, 3])[:, 2] > 0
        if np.all(np.isfinite(T)) and in_front.all():
            fits.append((reprojection_rms(T, obj, img, camera), T))
    if not fits:
        raise CalibrationError("no pose of the camera puts the table tags in front of it; check the camera file")
    fits.sort(key=lambda f: f[0])
    rms, T_cam_table = fits[0]
    for err, T in fits[1:]:
        angle = np.degrees(rotation_angle(T[:3, :3], T_cam_table[:3, :3]))
        if angle > opt.ambiguity_min_angle_deg and (rms / err if err > 0 else 1.0) > opt.ambiguity_ratio:
            raise CalibrationError(
                f"two poses {angle:.1f} deg apart fit the table tags about equally well ({rms:.2f} vs {err:.2f} px): "
                "the view is ambiguous; put table tags farther apart in the camera's view"
            )
    per_rms: list[float | None] = []
    for dets in per_image:
        if not dets:
            per_rms.append(None)
            continue
        o = np.concatenate([corners[d.tag_id] for d in dets])
        p = np.concatenate([d.corners_px for d in dets])
        per_rms.append(reprojection_rms(T_cam_table, o, p, camera))
    if rms > max_rms_px:
        worst = int(np.argmax([-1.0 if r is None else r for r in per_rms]))
        raise CalibrationError(
            f"the table tags' corners fit the camera's pose with an RMS reprojection error of {rms:.2f} px, over the "
            f"limit of {max_rms_px:g} px (worst: {names[worst]}, {per_rms[worst]:.2f} px); did the camera move "
            "between the images, a table tag move from where the registry puts it, or is the camera file another "
            "camera's?"
        )
    return SceneCameraFit(
        T_table_cam=invert_T(T_cam_table),
        reprojection_rms_px=float(rms),
        per_image_rms_px=tuple(per_rms),
        tag_ids=tuple(seen),
        n_images=sum(1 for dets in per_image if dets),
        n_corners=int(len(obj)),
        width=int(camera.width),
        height=int(camera.height),
    )


def locate_scene_camera(
    images: Sequence[np.ndarray],
    camera: CameraIntrinsics,
    registry: ObjectRegistry,
    min_tags: int = MIN_TAGS,
    max_rms_px: float = MAX_RMS_PX,
    options: TagDetectorOptions | None = None,
    names: Sequence[str] | None = None,
) -> SceneCameraFit:
    """Detect the tags in each image of the fixed camera (its intrinsics ``camera``; every image at
    the camera file's size) and fit ``T_table_cam`` (:func:`fit_scene_camera`)."""
    if not 1 <= len(images) <= MAX_IMAGES:
        raise CalibrationError(f"images: give 1 to {MAX_IMAGES} images of the scene camera, got {len(images)}")
    names = _names(names, len(images))
    detections = []
    for name, image in zip(names, images):
        try:
            detections.append(detect_tags(image, camera, registry.tag_size, options))
        except CalibrationError as err:
            raise CalibrationError(f"{name}: {err}") from None  # name the image: the detector does not know it
    return fit_scene_camera(detections, registry, camera, min_tags, max_rms_px, options, names)
