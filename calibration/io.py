"""YAML files of the calibration package: strict schemas, errors that name the file and field.

Poses are stored as ``{translation_m: [x, y, z], rotvec_rad: [rx, ry, rz]}`` (axis-angle, the
project's rotation exchange format); :func:`pose_to_T` / :func:`T_to_pose` convert to 4x4.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, TypeVar

import numpy as np
import yaml
from pydantic import BaseModel, Field, ValidationError

from calibration.errors import CalibrationFileError
from sim.configio import StrictModel
from sim.configio import read_yaml as _read_yaml
from sim.files import FileRefusedError, check_regular, not_a_regular_file, read_regular
from sim.poses import Pose, check_T

__all__ = [
    "Strict",
    "PoseModel",
    "Vec3",
    "pose_to_T",
    "T_to_pose",
    "read_yaml",
    "load_model",
    "write_yaml",
    "check_T",
    "read_image",
    "not_a_regular_file",
    "check_file",
    "read_bytes",
    "nesting_depth",
    "MAX_YAML_BYTES",
    "MAX_IMAGE_BYTES",
    "SceneCameraPoseFile",
    "save_scene_camera_pose",
    "load_scene_camera_pose",
]

M = TypeVar("M", bound=BaseModel)


class Strict(StrictModel):
    """Base of every file schema: unknown keys are errors, values are immutable."""


Vec3 = Annotated[tuple[float, float, float], Field(description="3-vector")]


class PoseModel(Pose, Strict):
    """A rigid transform ``T_parent_child`` as translation (m) + axis-angle rotation (rad).

    The project's pose entry (:class:`sim.poses.Pose`: its bounds, ``.T`` and ``of``), each field
    defaulting to zero (an omitted one is the identity's).
    """

    translation_m: Vec3 = (0.0, 0.0, 0.0)
    rotvec_rad: Vec3 = (0.0, 0.0, 0.0)


def pose_to_T(pose: PoseModel) -> np.ndarray:
    """4x4 ``T_parent_child`` from a :class:`PoseModel`."""
    return pose.T


def T_to_pose(T: np.ndarray) -> PoseModel:
    """:class:`PoseModel` of a 4x4 rigid transform (held to :func:`check_T` first)."""
    return PoseModel.of(check_T(T, "T", single=True))


MAX_YAML_BYTES = 64 * 2**20  # a calibration YAML (samples, registry, board) is kilobytes
MAX_IMAGE_BYTES = 1024 * 2**20  # an uncompressed 16384 x 16384 RGB(A) photo fits


def check_file(path, field: str, max_bytes: int) -> None:
    """:class:`CalibrationFileError` naming ``path`` and ``field`` for a device, FIFO or socket, or a
    file over ``max_bytes``; asked before anything opens or reads it (:func:`sim.files.check_regular`).
    A missing path, a directory or one that cannot be asked about passes: its reader reports it."""
    try:
        check_regular(path, max_bytes)
    except FileRefusedError as err:
        if err.reason not in ("missing", "unreadable", "directory"):
            raise CalibrationFileError(path, field, err.problem()) from None


_READ_WORDS = {"missing": "cannot read ({strerror})"}  # a missing calibration file is one that cannot be read


def read_bytes(path, field: str, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``max_bytes``: a device, FIFO, socket,
    directory, missing or larger file raises :class:`CalibrationFileError` naming the file, without
    blocking (:func:`sim.files.read_regular`: checked before it is opened and on the open file)."""
    try:
        return read_regular(path, max_bytes)
    except FileRefusedError as err:
        raise CalibrationFileError(path, field, err.problem(_READ_WORDS)) from None


_COMPACT = re.compile(r"(?:[-?](?:[ \t]+|$))*")  # leading "- - " / "? " indicators: one block level each
# What a line's flow nesting is read from: a quoted scalar where one can start (skipped whole), a
# comment (the rest of the line), or a bracket.
_TOKEN = re.compile(
    r"""(?<![^\s\[{,:])(?:"(?:[^"\\]|\\.)*"|'(?:[^']|'')*')"""
    r"|(?<!\S)#.*"
    r"|[\[\]{}]"
)


def nesting_depth(text: str) -> int:
    """An estimate of how deeply the YAML or JSON ``text`` nests, without parsing it (linear time).

    A line's block depth is the number of indentation levels open at it plus its leading ``- `` /
    ``? `` indicators; flow depth counts the ``[`` / ``{`` open, skipping quoted strings and
    comments. Exact for JSON; for YAML at least half the real depth, except that a string the scan
    cannot see as one (spanning lines, or quoted mid-word) could hide closing brackets from it:
    callers also bound the count of brackets, which bounds flow nesting whatever the strings hold.
    """
    depth = flow = 0
    indents = [0]
    for line in text.split("\n"):
        stripped = line.lstrip(" ")
        if stripped and not stripped.startswith("#"):
            col = len(line) - len(stripped)
            while indents[-1] > col:
                indents.pop()
            if indents[-1] < col:
                indents.append(col)
            lead = _COMPACT.match(stripped).group()
            block = len(indents) - 1 + lead.count("-") + lead.count("?")
            depth = max(depth, block + flow)
            for m in _TOKEN.finditer(stripped):
                c = m.group()[0]
                if c in "[{":
                    flow += 1
                    depth = max(depth, block + flow)
                elif c in "]}":
                    flow = max(0, flow - 1)
    return depth


def read_yaml(path) -> object:
    """Parsed YAML of ``path``; missing or malformed files, devices, FIFOs and files over
    :data:`MAX_YAML_BYTES` raise :class:`CalibrationFileError`."""
    check_file(path, "<file>", MAX_YAML_BYTES)

    def error(p, problem: str) -> CalibrationFileError:
        unreadable = problem.startswith(("cannot read", "is a directory"))
        return CalibrationFileError(p, "<file>" if unreadable else "<yaml>", problem)

    return _read_yaml(path, "calibration file", mapping=False, error=error)


def load_model(path, model: type[M], data: object | None = None) -> M:
    """Validate ``data`` (default: the YAML in ``path``) against ``model``.

    The first validation error becomes a :class:`CalibrationFileError` naming the file and the
    dotted field path (``K.0``, ``samples.3.T_base_tcp.rotvec_rad``); the others are listed after it.
    """
    data = read_yaml(path) if data is None else data
    if not isinstance(data, dict):
        raise CalibrationFileError(path, "<root>", f"expected a mapping, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as err:
        errs = err.errors()
        locs = [".".join(str(p) for p in e["loc"]) or "<root>" for e in errs]
        text = [e["msg"].removeprefix("Value error, ") for e in errs]  # a validator's own ValueError text
        msg = text[0]
        if len(errs) > 1:
            msg += "; also: " + "; ".join(f"{l}: {t}" for l, t in zip(locs[1:], text[1:]))
        raise CalibrationFileError(path, locs[0], msg) from None


def write_yaml(path, data: dict, header: str | None = None) -> Path:
    """Write ``data`` as block-style YAML (lists of numbers inline), creating parent directories."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    class _Dumper(yaml.SafeDumper):
        pass

    def _list(dumper, seq):
        flow = all(isinstance(x, (int, float)) for x in seq)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", seq, flow_style=flow)

    _Dumper.add_representer(list, _list)
    _Dumper.add_representer(tuple, _list)
    text = yaml.dump(data, Dumper=_Dumper, sort_keys=False)
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + text
    path.write_text(text)
    return path


def read_image(path) -> np.ndarray:
    """An image file as (H, W) grey or (H, W, 3|4) RGB(A) array; unreadable files raise
    :class:`CalibrationFileError`."""
    import cv2  # lazy: robot_io start-up (cv2)

    check_file(path, "<image>", MAX_IMAGE_BYTES)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CalibrationFileError(path, "<image>", "cannot read as an image")
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return img


# ---------------------------------------------------------------------- scene camera pose
MAX_POSE_IMAGE_PX = 16384  # per side: calibration.intrinsics.MAX_IMAGE_PX (that module imports this one, not back)


class SceneCameraPoseFile(Strict):
    """``T_table_cam.yaml`` of a fixed scene camera, written by ``advobj calibrate scene-camera``.

    ``T_table_cam`` is the camera (OpenCV frame: +x right, +y down, +z along the optical axis) in
    the table frame; ``width`` x ``height`` the frames it was estimated from (the camera file's
    size): a session refuses frames of another size from that camera. The rest records the fit.
    """

    T_table_cam: PoseModel = Field(description="the camera's pose in the table frame")
    width: Annotated[int, Field(ge=1, le=MAX_POSE_IMAGE_PX, description="frame width the pose holds for, px")]
    height: Annotated[int, Field(ge=1, le=MAX_POSE_IMAGE_PX, description="frame height the pose holds for, px")]
    reprojection_rms_px: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = Field(
        None, description="RMS reprojection error of every table-tag corner used, px"
    )
    tag_ids: list[Annotated[int, Field(ge=0)]] = Field([], description="the table tags the pose was fit to")
    n_images: Annotated[int, Field(ge=1)] | None = Field(None, description="images that saw a table tag")

    @property
    def T(self) -> np.ndarray:
        """(4, 4) ``T_table_cam``."""
        return self.T_table_cam.T


def save_scene_camera_pose(
    path,
    T_table_cam: np.ndarray,
    width: int,
    height: int,
    reprojection_rms_px: float | None = None,
    tag_ids=(),
    n_images: int | None = None,
) -> Path:
    """Write a :class:`SceneCameraPoseFile` (validated first: nothing is written for a bad value)."""
    p = T_to_pose(T_table_cam)
    model = SceneCameraPoseFile(
        T_table_cam=p,
        width=int(width),
        height=int(height),
        reprojection_rms_px=None if reprojection_rms_px is None else round(float(reprojection_rms_px), 4),
        tag_ids=sorted(int(i) for i in tag_ids),
        n_images=None if n_images is None else int(n_images),
    )
    data = model.model_dump(mode="json")
    data["T_table_cam"] = {"translation_m": list(p.translation_m), "rotvec_rad": list(p.rotvec_rad)}
    return write_yaml(
        path,
        data,
        header="Fixed scene camera: its pose (OpenCV camera frame) in the table frame, from the table's AprilTags\n"
        "(advobj calibrate scene-camera); width x height: the frames it holds for",
    )


def load_scene_camera_pose(path) -> SceneCameraPoseFile:
    """The :class:`SceneCameraPoseFile` in ``path``; a :class:`CalibrationFileError` names the file and field."""
    return load_model(path, SceneCameraPoseFile)
