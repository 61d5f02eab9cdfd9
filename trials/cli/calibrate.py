"""``advobj calibrate``: printables, intrinsics, tag detection, hand-eye, synthetic self-check."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer
from pydantic import ValidationError

from calibration.errors import CalibrationError, CalibrationFileError
from sim.errors import AdvobjError, format_validation_error

app = typer.Typer(no_args_is_help=True, help="Calibrate cameras, tags and hand-eye for real trials.")


def _board(
    board: Optional[Path],
    squares_x: int,
    squares_y: int,
    square_mm: float,
    marker_mm: float,
    dictionary: str,
    legacy: bool,
):
    from calibration.intrinsics import BoardSpec, load_board_yaml  # lazy: CLI start-up (+51 ms)

    if board is not None:
        return load_board_yaml(board)
    try:
        return BoardSpec(
            squares_x=squares_x,
            squares_y=squares_y,
            square_size_m=square_mm / 1000,
            marker_size_m=marker_mm / 1000,
            dictionary=dictionary,
            legacy_pattern=legacy,
        )
    except ValidationError as err:
        raise AdvobjError(
            format_validation_error(err, "board (--squares-x/--squares-y/--square-mm/--marker-mm/--dictionary)")
        ) from None


def _read_image(path: Path):
    from calibration.io import read_image  # lazy: CLI start-up (+11 ms)

    return read_image(path)


# The photos of one intrinsics calibration: tens are plenty (the coverage and tilt it reports say
# when more views help), and every photo is decoded and held at once. A folder exported from a
# recording (a ROS bag, a video) can hold thousands of frames: pick a subset.
MAX_INTRINSICS_PHOTOS = 100


def _photo_paths(images: List[Path]) -> list[Path]:
    """The photos ``calibrate intrinsics`` reads: each file as given, each folder as its image files
    (the replay camera's suffixes, any case; sorted by name; sub-folders and other files left out). At
    most :data:`MAX_INTRINSICS_PHOTOS`; every file's size is checked before any is read."""
    from calibration.io import MAX_IMAGE_BYTES, check_file  # lazy: CLI start-up (+11 ms)
    from robot_io.cameras.replay import IMAGE_SUFFIXES  # lazy: CLI start-up (numpy, PIL)

    paths: list[Path] = []
    for p in images:
        if not p.is_dir():
            paths.append(p)
            continue
        try:
            found = sorted((f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and f.is_file()), key=str)
        except OSError as err:
            raise CalibrationFileError(p, "<images>", f"cannot list the folder ({err.strerror or err})") from None
        if not found:
            raise CalibrationFileError(
                p,
                "<images>",
                f"a folder with no photos ({' '.join(IMAGE_SUFFIXES)}); give the board photos or their folder",
            )
        root = p.resolve()
        for f in found:
            if not f.resolve().is_relative_to(root):
                raise CalibrationFileError(f, "<images>", f"a link to {f.resolve()}, outside the folder {p}")
        paths += found
    if len(paths) > MAX_INTRINSICS_PHOTOS:
        raise CalibrationError(
            f"<images>: {len(paths)} photos, over the maximum of {MAX_INTRINSICS_PHOTOS} for one calibration; pick a "
            "subset that shows the board across the image and tilted (e.g. every 10th frame of a recording)"
        )
    for f in paths:
        check_file(f, "<image>", MAX_IMAGE_BYTES)
    return paths


_SQX = typer.Option(8, "--squares-x", help="board squares across")
_SQY = typer.Option(6, "--squares-y", help="board squares down")
_SQ = typer.Option(30.0, "--square-mm", help="square side, mm")
_MK = typer.Option(22.0, "--marker-mm", help="marker side, mm")
_DICT = typer.Option("5X5_100", "--dictionary", help="ArUco dictionary of the board markers (e.g. 5X5_100)")
_LEG = typer.Option(False, "--legacy", help="board printed by OpenCV < 4.6 (even row count)")


@app.command()
def board(
    out: Path = typer.Option(Path("board.pdf"), help="output PDF; the board YAML is written next to it"),
    squares_x: int = _SQX,
    squares_y: int = _SQY,
    square_mm: float = _SQ,
    marker_mm: float = _MK,
    dictionary: str = _DICT,
    legacy: bool = _LEG,
    page: str = typer.Option(
        "A4", help="paper: A4, A3, A2, letter, tabloid, or WIDTHxHEIGHT in mm; a board that does not fit is refused"
    ),
) -> None:
    """Write a true-scale printable ChArUco board (PDF) and its description (YAML)."""
    from calibration.intrinsics import save_board_yaml  # lazy: CLI start-up (+51 ms)
    from calibration.printables import board_pdf  # lazy: CLI start-up (cv2, matplotlib)

    spec = _board(None, squares_x, squares_y, square_mm, marker_mm, dictionary, legacy)
    board_pdf(out, spec, page=page)
    y = save_board_yaml(out.with_suffix(".yaml"), spec)
    typer.echo(f"wrote {out} and {y}; print at 100 % and check the 50 mm scale bar")


@app.command()
def tags(
    ids: str = typer.Option("0-7", help="tag ids, e.g. 0-7,12"),
    size_mm: float = typer.Option(40.0, "--size-mm", help="black-square side, mm"),
    out: Path = typer.Option(Path("tags.pdf"), help="output PDF"),
) -> None:
    """Write true-scale printable tag36h11 AprilTags (PDF)."""
    from calibration.printables import parse_id_ranges, tag_sheet_pdf  # lazy: CLI start-up (cv2, matplotlib)

    try:
        id_list = parse_id_ranges(ids)
    except ValueError as err:
        raise typer.BadParameter(str(err).removeprefix("ids: "), param_hint="--ids") from None
    tag_sheet_pdf(out, id_list, size_mm)
    typer.echo(f"wrote {out}: {len(id_list)} tag(s) of {size_mm:g} mm; print at 100 % and check the 50 mm scale bar")


def _inner_corners(text: Optional[str]):
    if text is None:
        return None
    try:
        cols, rows = (int(x) for x in text.lower().split("x"))
        if cols < 3 or rows < 3:
            raise ValueError
    except ValueError:
        raise typer.BadParameter(
            f"expected COLSxROWS inner corners, each >= 3 (e.g. 9x6), got {text!r}", param_hint="--inner-corners"
        ) from None
    return cols, rows


@app.command()
def intrinsics(
    images: List[Path] = typer.Argument(
        ..., help="board photos (ChArUco or plain chessboard), or folders of them (their image files, sorted by name)"
    ),
    out: Path = typer.Option(Path("cam.yaml"), help="output camera YAML"),
    board: str = typer.Option(
        "auto", help="auto (tell from the photos), charuco, chessboard, or a board YAML from 'calibrate board'"
    ),
    inner_corners: Optional[str] = typer.Option(
        None,
        "--inner-corners",
        help="plain chessboard: inner corners COLSxROWS, e.g. 9x6 (default with auto: the first common size found)",
    ),
    squares_x: int = _SQX,
    squares_y: int = _SQY,
    square_mm: float = _SQ,
    marker_mm: float = _MK,
    dictionary: str = _DICT,
    legacy: bool = _LEG,
    min_corners: int = typer.Option(12, help="reject images with fewer board corners"),
    max_blur_px: float = typer.Option(1.5, help="reject images whose board edges are blurrier than this (px)"),
    fmt: str = typer.Option("advobj", "--format", help="camera file format: advobj or ros (camera_info YAML)"),
) -> None:
    """Calibrate K and distortion from board photos; report per-image and RMS reprojection error,
    the intrinsics' standard deviations, and the views' coverage of the image and of tilt."""
    from calibration.intrinsics import (  # lazy: CLI start-up (+51 ms)
        CAMERA_FORMATS,
        CalibrationOptions,
        ChessboardSpec,
        calibrate_intrinsics,
        identify_board,
        save_camera_yaml,
        to_gray,
    )

    if fmt not in CAMERA_FORMATS:
        raise typer.BadParameter(f"expected one of {', '.join(CAMERA_FORMATS)}, got {fmt!r}", param_hint="--format")
    corners = _inner_corners(inner_corners)
    images = _photo_paths(images)
    arrays = [_read_image(p) for p in images]
    if board in ("auto", "charuco", "chessboard"):
        charuco = _board(None, squares_x, squares_y, square_mm, marker_mm, dictionary, legacy)
        if board == "charuco":
            spec, how = charuco, "ChArUco board (as given)"
        elif board == "chessboard" and corners is not None:
            spec, how = (
                ChessboardSpec(inner_cols=corners[0], inner_rows=corners[1], square_size_m=square_mm / 1000),
                f"plain chessboard, {corners[0]}x{corners[1]} inner corners (as given)",
            )
        else:  # auto, or a chessboard of unknown size
            grays = [to_gray(a) for a in arrays]
            spec, how = identify_board(grays, charuco, corners, square_mm / 1000)
            if board == "chessboard" and not isinstance(spec, ChessboardSpec):
                raise CalibrationError(
                    "board: --board chessboard, but the photos show a ChArUco board; pass --board charuco or auto"
                )
    else:
        spec = _board(Path(board), squares_x, squares_y, square_mm, marker_mm, dictionary, legacy)
        how = f"from {board}"
    typer.echo(f"board: {how}")
    res = calibrate_intrinsics(
        arrays, spec, [str(p) for p in images], CalibrationOptions(min_corners=min_corners, max_blur_px=max_blur_px)
    )
    for r in res.images:
        status = f"{r.reprojection_rms_px:.3f} px" if r.accepted else f"REJECTED: {r.reason}"
        typer.echo(f"  {r.name}: {r.n_corners} corners, blur {r.blur_px:.2f} px, {status}")
    save_camera_yaml(out, res.camera, res.images, fmt=fmt, std_px=res.std_px)
    K = res.camera.K
    sd = res.std_px
    typer.echo(
        f"RMS {res.rms_px:.3f} px over {len(res.images) - len(res.rejected)} image(s); fx={K[0, 0]:.2f} "
        f"fy={K[1, 1]:.2f} "
        f"cx={K[0, 2]:.2f} cy={K[1, 2]:.2f}; wrote {out}"
    )
    if sd:
        typer.echo(
            f"1-sigma: fx {sd['fx']:.2f} fy {sd['fy']:.2f} cx {sd['cx']:.2f} cy {sd['cy']:.2f} px; "
            f"coverage {100 * res.coverage:.0f} % of the image; tilt {res.tilt_deg[0]:.0f}-{res.tilt_deg[1]:.0f} deg"
        )
    for w in res.warnings:
        typer.echo(f"WARNING: {w}")


@app.command()
def convert(
    camera: Path = typer.Argument(
        ..., help="a camera file: ours, ROS camera_info YAML, or OpenCV FileStorage YAML/JSON"
    ),
    out: Path = typer.Option(..., help="output camera file"),
    fmt: str = typer.Option("advobj", "--format", help="advobj or ros"),
    rescale: Optional[str] = typer.Option(None, help="also rescale to WIDTHxHEIGHT (same aspect ratio)"),
) -> None:
    """Convert a camera file between formats (and optionally resolutions)."""
    from calibration.intrinsics import (  # lazy: CLI start-up (+51 ms)
        CAMERA_FORMATS,
        camera_file_format,
        load_camera_yaml,
        save_camera_yaml,
    )

    if fmt not in CAMERA_FORMATS:
        raise typer.BadParameter(f"expected one of {', '.join(CAMERA_FORMATS)}, got {fmt!r}", param_hint="--format")
    cam = load_camera_yaml(camera)
    if rescale is not None:
        cam = _rescaled(cam, rescale, "--rescale")
    save_camera_yaml(out, cam, fmt=fmt)
    typer.echo(f"read {camera} ({camera_file_format(camera)}), {cam.width}x{cam.height}; wrote {out} ({fmt})")


def _rescaled(cam, size: str, flag: str):
    try:
        w, h = (int(x) for x in size.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected WIDTHxHEIGHT, got {size!r}", param_hint=flag) from None
    try:
        return cam.scaled(w, h)  # refuses another aspect ratio and sides over MAX_IMAGE_PX
    except ValueError as err:
        raise typer.BadParameter(str(err).removeprefix("scaled: "), param_hint=flag) from None


@app.command()
def detect(
    image: Path = typer.Argument(..., help="a photo"),
    camera: Path = typer.Option(..., help="camera YAML"),
    registry: Optional[Path] = typer.Option(None, help="object registry YAML (tag id -> object)"),
    size_mm: Optional[float] = typer.Option(None, "--size-mm", help="tag size for tags not in the registry"),
    dictionary: str = typer.Option(
        "tag36h11", "--dictionary", help="tag36h11 (AprilTag 3) or an ArUco dictionary, e.g. 4X4_50"
    ),
    rescale: bool = typer.Option(
        False,
        "--rescale",
        help="if the photo's size differs from the camera file's but has its aspect "
        "ratio, rescale the intrinsics to the photo",
    ),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """Print every detected tag (both pose solutions, errors, ambiguity) and every registered object's position."""
    import numpy as np  # lazy: CLI start-up (numpy)

    from calibration.apriltag import detect_tags, resolve_dictionary  # lazy: CLI start-up (cv2, pupil_apriltags)
    from calibration.intrinsics import load_camera_yaml  # lazy: CLI start-up (+51 ms)
    from calibration.registry import TABLE, load_registry, locate_objects  # lazy: CLI start-up (cv2, pupil_apriltags)
    from sim.geometry import invert_T, transform_points  # lazy: CLI start-up (+3 ms)

    try:
        dictionary = resolve_dictionary(dictionary)
    except ValueError as err:
        raise typer.BadParameter(str(err).removeprefix("dictionary: "), param_hint="--dictionary") from None
    cam = load_camera_yaml(camera)
    photo = _read_image(image)
    h, w = photo.shape[:2]
    if (w, h) != (cam.width, cam.height) and rescale:
        try:
            scaled = cam.scaled(w, h)  # refuses another aspect ratio
        except ValueError:
            raise typer.BadParameter(
                f"{image} is {w}x{h}, the camera file {camera} is {cam.width}x{cam.height}: another aspect ratio "
                "(a crop), so the intrinsics cannot be rescaled; calibrate at this size",
                param_hint="--rescale",
            ) from None
        typer.echo(f"rescaled the intrinsics from {cam.width}x{cam.height} to {w}x{h}")
        cam = scaled
    reg = load_registry(registry) if registry else None
    default = size_mm / 1000 if size_mm else None

    def size_of(i: int):
        s = reg.tag_size(i) if reg else None
        return s if s is not None else default

    try:
        dets = detect_tags(photo, cam, size_of, dictionary=dictionary)
    except CalibrationError as err:
        raise CalibrationError(f"{image}: {err}") from None  # name the photo: the detector does not know it
    objects, missing = {}, []
    if reg is not None:
        obs = locate_objects(dets, reg, cam)
        T_table_cam = invert_T(obs[TABLE].T_cam_object) if TABLE in obs else None
        for name in reg.objects:
            if name not in obs:
                missing.append(name)
                continue
            o = obs[name]
            d = {
                "position_cam_m": np.round(o.position_cam_m, 5).tolist(),
                "tag_ids": list(o.tag_ids),
                "reprojection_rms_px": round(o.reprojection_rms_px, 4),
                "ambiguous": o.ambiguous,
                "alternative_positions_cam_m": [np.round(a[:3, 3], 5).tolist() for a in o.alternatives],
            }
            if T_table_cam is not None:
                d["position_table_m"] = np.round(transform_points(T_table_cam, o.position_cam_m[None])[0], 5).tolist()
            objects[name] = d
    report = {"image": str(image), "tags": [d.to_dict() for d in dets], "objects": objects, "not_detected": missing}
    if as_json:
        typer.echo(json.dumps(report, indent=2))
        return
    typer.echo(f"{len(dets)} tag(s) in {image}")
    for d in dets:
        sols = ", ".join(
            f"t={np.round(s.T_cam_tag[:3, 3], 4).tolist()} m err {s.reprojection_rms_px:.3f} px" for s in d.solutions
        )
        typer.echo(f"  id {d.tag_id}: {sols or 'no pose (unknown size)'} {' '.join(d.flags)}")
    for name, o in objects.items():
        where = f" table {o['position_table_m']}" if "position_table_m" in o else ""
        typer.echo(f"  object {name}: cam {o['position_cam_m']}{where}{' AMBIGUOUS' if o['ambiguous'] else ''}")
    for name in missing:
        typer.echo(f"  object {name}: not detected")


@app.command("scene-camera")
def scene_camera(
    images: List[Path] = typer.Argument(..., help="photos of the fixed camera that see the table's tags"),
    camera: Path = typer.Option(..., help="the fixed camera's intrinsics YAML (from 'calibrate intrinsics')"),
    registry: Path = typer.Option(..., help="tag registry YAML: its 'table' tags define the table frame"),
    out: Path = typer.Option(Path("T_table_cam.yaml"), help="output YAML (the hardware config's T_table_cam)"),
    min_tags: int = typer.Option(2, "--min-tags", min=1, help="refuse with fewer distinct table tags seen"),
    max_rms_px: float = typer.Option(2.0, "--max-rms-px", min=0.0, help="refuse a fit worse than this (RMS, px)"),
) -> None:
    """Locate a fixed scene camera against the table's AprilTags: T_table_cam by PnP over every table-tag corner
    of every photo; prints the reprojection RMS and refuses too few tags or a poor fit."""
    from calibration.intrinsics import load_camera_yaml  # lazy: CLI start-up (+51 ms)
    from calibration.io import save_scene_camera_pose  # lazy: CLI start-up (+11 ms)
    from calibration.registry import load_registry  # lazy: CLI start-up (cv2, pupil_apriltags)
    from calibration.scene_camera import MAX_IMAGES, locate_scene_camera  # lazy: CLI start-up (cv2)

    if out.is_dir():
        raise CalibrationError(f"--out: {out} is a directory; give the pose file's name (front_pose.yaml)")
    if len(images) > MAX_IMAGES:  # before any photo is read
        raise typer.BadParameter(f"at most {MAX_IMAGES} photos, got {len(images)}", param_hint="IMAGES")
    cam = load_camera_yaml(camera)
    reg = load_registry(registry)
    photos = [_read_image(p) for p in images]
    fit = locate_scene_camera(photos, cam, reg, min_tags, max_rms_px, names=[str(p) for p in images])
    for p, rms in zip(images, fit.per_image_rms_px):
        typer.echo(f"  {p}: " + ("no table tag" if rms is None else f"{rms:.3f} px"))
    save_scene_camera_pose(
        out, fit.T_table_cam, fit.width, fit.height, fit.reprojection_rms_px, fit.tag_ids, fit.n_images
    )
    t = fit.T_table_cam[:3, 3]
    typer.echo(
        f"RMS {fit.reprojection_rms_px:.3f} px over {fit.n_corners} corners of table tags "
        f"{', '.join(map(str, fit.tag_ids))} in {fit.n_images} image(s); camera at "
        f"[{t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}] m in the table frame; wrote {out}"
    )


@app.command()
def handeye(
    samples: Path = typer.Argument(
        ..., help="samples YAML: T_base_tcp plus an image (with board/camera files) or T_cam_board"
    ),
    out: Path = typer.Option(Path("T_tcp_cam.yaml"), help="output YAML"),
    method: str = typer.Option("park", help="tsai | park | horaud | andreff | daniilidis"),
    check: str = typer.Option("tsai", help="second method to cross-check against"),
    refine: bool = typer.Option(True, "--refine/--no-refine", help="refine jointly with the board pose (AX = YB)"),
) -> None:
    """Eye-in-hand calibration: solve T_tcp_cam, cross-check two methods, report residuals."""
    from calibration.handeye import (  # lazy: CLI start-up (cv2)
        HandEyeOptions,
        load_samples_yaml,
        save_hand_eye_yaml,
        solve_hand_eye,
    )

    try:
        opt = HandEyeOptions(method=method, check_method=check, refine=refine)
    except ValueError as err:
        raise typer.BadParameter(str(err).splitlines()[-1]) from None
    A, B, notes = load_samples_yaml(samples)
    for n in notes:
        typer.echo(f"  {n}")
    res = solve_hand_eye(A, B, opt)
    typer.echo(res.summary())
    save_hand_eye_yaml(out, res)
    typer.echo(f"wrote {out}")


@app.command()
def selfcheck(seed: int = typer.Option(0, min=0, help="random seed")) -> None:
    """Run the pipeline on synthetic OpenGL renders with known ground truth and print the errors."""
    from calibration.selfcheck import handeye_check, intrinsics_check, tag_check  # lazy: CLI start-up (pyrender, cv2)

    i = intrinsics_check(n_images=8, seed=seed)
    typer.echo(
        f"intrinsics: max error {i['max_pct']:.3f} % (fx {i['fx_pct']:.3f}, fy {i['fy_pct']:.3f}), RMS "
        f"{i['rms_px']:.3f} px"
    )
    t = tag_check(n=5, seed=seed)
    typer.echo(
        f"tag 40 mm at 0.5 m, frontal: position max {t['position_mm_max']:.2f} mm, orientation median "
        f"{t['orientation_deg_median']:.2f} deg ({t['detected']}/{t['n']} detected, {t['flagged']} flagged)"
    )
    h = handeye_check(seed=seed)
    typer.echo(
        f"hand-eye: {h['position_mm']:.2f} mm, {h['rotation_deg']:.3f} deg; park vs tsai "
        f"{h['methods_disagreement_mm']:.2f} mm, {h['methods_disagreement_deg']:.3f} deg"
    )
