"""tag36h11 recall and corner accuracy: AprilTag 3 (``pupil-apriltags``, the default) vs ``cv2.aruco``.

    .venv/bin/python benchmarks/bench_tags.py [--views 600] [--out results/tags] [--photos DIR --truth FILE]

Synthetic part: OpenGL renders of one 40 mm tag36h11 tag on the docs' camera (640x480, 70 deg
horizontal FOV), at a random distance that puts the tag's side between about 6 and 60 px, tilted
0-70 deg about a random axis, rolled, offset across the image, then blurred (0.8 px) and noised
(2/255), as a cheap webcam would give. The ground truth corners are the projection of the tag's
true corners. Both backends run through :func:`calibration.apriltag.detect_tags` (so with the
same edge refinement and pose solver); per view and backend a row records whether the tag was
found, its largest corner error (px) and its position error (mm).

Photo part (``--photos``): real images whose tags are listed in ``--truth`` (a YAML mapping of
file name to the tag ids visible in it). Recall per backend against that list, false detections
(ids not listed), and the corner agreement (largest corner distance, px) where both found a tag.

Writes ``synthetic.csv`` (and ``photos.csv``) plus ``summary.json`` (with the command, commit,
machine, wall and CPU time) to ``--out`` and prints the figures. No target: it measures.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

BACKENDS = ("apriltag3", "aruco")
SIDE_BINS = ((0, 15), (15, 25), (25, 40), (40, 1000))
TAG_SIZE_M = 0.04
TAG_ID = 7


def synthetic_rows(views: int, seed: int = 0, progress=None) -> list[dict]:
    import calibration.synthetic as S
    from calibration.apriltag import TagDetectorOptions, detect_tags, tag_object_points
    from calibration.intrinsics import CameraIntrinsics

    W, H = 640, 480
    K = S.default_K(W, H)
    cam = CameraIntrinsics(K, np.zeros(5), W, H)
    rng = np.random.default_rng(seed)
    rows = []
    for v in range(views):
        side_goal = float(np.exp(rng.uniform(np.log(6.0), np.log(60.0))))  # px, log-uniform
        dist = K[0, 0] * TAG_SIZE_M / side_goal
        a = rng.uniform(0, np.pi)
        tilt = rng.uniform(0.0, 70.0)
        T = S.camera_facing(dist, np.radians(tilt), (np.cos(a), np.sin(a), 0.0), rng.uniform(-np.pi, np.pi),
                            rng.uniform(-0.25, 0.25, 2) * dist)
        img = S.degrade(S.render_planes([S.tag_plane(TAG_ID, TAG_SIZE_M, T)], K, W, H), 0.8, 2.0, seed=seed * 100003 + v)
        truth = cam.project((T[:3, :3] @ tag_object_points(TAG_SIZE_M).T).T + T[:3, 3])
        side = float(np.mean(np.linalg.norm(truth - np.roll(truth, -1, 0), axis=1)))
        for backend in BACKENDS:
            dets = [d for d in detect_tags(img, cam, TAG_SIZE_M, TagDetectorOptions(backend=backend)) if d.tag_id == TAG_ID]
            row = {"view": v, "side_px": round(side, 2), "tilt_deg": round(tilt, 2), "backend": backend, "detected": int(bool(dets)),
                   "corner_err_px": "", "position_err_mm": "", "false_ids": 0}
            if dets:
                d = dets[0]
                row["corner_err_px"] = round(float(np.linalg.norm(d.corners_px - truth, axis=1).max()), 4)
                if d.T_cam_tag is not None:
                    row["position_err_mm"] = round(1000 * float(np.linalg.norm(d.T_cam_tag[:3, 3] - T[:3, 3])), 3)
            row["false_ids"] = len({d.tag_id for d in detect_tags(img, cam, None, TagDetectorOptions(backend=backend))} - {TAG_ID})
            rows.append(row)
        if progress:
            progress(v + 1, views)
    return rows


def photo_rows(photos: Path, truth: dict) -> list[dict]:
    from calibration.apriltag import detect_tag_corners
    from calibration.intrinsics import to_gray
    from calibration.io import read_image

    rows = []
    for name, ids in sorted(truth.items()):
        gray = to_gray(read_image(photos / name))
        found = {b: dict(detect_tag_corners(gray, None, b)) for b in BACKENDS}
        for tag_id in sorted(set(ids) | set(found["apriltag3"]) | set(found["aruco"])):
            a, c = found["apriltag3"].get(tag_id), found["aruco"].get(tag_id)
            side = a if a is not None else c
            rows.append({"photo": name, "tag_id": tag_id, "listed": int(tag_id in ids),
                         "side_px": "" if side is None else round(float(np.mean(np.linalg.norm(side - np.roll(side, -1, 0), axis=1))), 2),
                         "apriltag3": int(a is not None), "aruco": int(c is not None),
                         "agreement_px": "" if a is None or c is None else round(float(np.linalg.norm(a - c, axis=1).max()), 4)})
    return rows


def summarize_synthetic(rows: list[dict]) -> dict:
    out = {}
    for b in BACKENDS:
        rb = [r for r in rows if r["backend"] == b]
        per_bin = {}
        for lo, hi in SIDE_BINS:
            rr = [r for r in rb if lo <= r["side_px"] < hi]
            errs = [r["corner_err_px"] for r in rr if r["detected"]]
            per_bin[f"{lo}-{hi}px"] = {"n": len(rr), "detected": sum(r["detected"] for r in rr),
                                       "corner_err_px_median": float(np.median(errs)) if errs else None}
        errs = [r["corner_err_px"] for r in rb if r["detected"]]
        out[b] = {"n": len(rb), "detected": sum(r["detected"] for r in rb), "false_ids": sum(r["false_ids"] for r in rb),
                  "corner_err_px_median": float(np.median(errs)) if errs else None,
                  "corner_err_px_p95": float(np.percentile(errs, 95)) if errs else None, "by_side": per_bin}
    return out


def summarize_photos(rows: list[dict]) -> dict:
    listed = [r for r in rows if r["listed"]]
    agree = [r["agreement_px"] for r in rows if r["agreement_px"] != ""]
    small = [r for r in listed if r["side_px"] != "" and r["side_px"] < 25]
    return {"listed_tags": len(listed), "photos": len({r["photo"] for r in rows}),
            **{b: {"detected": sum(r[b] for r in listed), "false": sum(r[b] for r in rows if not r["listed"]),
                   "detected_under_25px": sum(r[b] for r in small)} for b in BACKENDS},
            "listed_under_25px_seen": len(small),
            "agreement_px_median": float(np.median(agree)) if agree else None,
            "agreement_px_max": float(np.max(agree)) if agree else None, "both_detected": len(agree)}


def _machine() -> dict:
    import os
    import platform

    return {"cpus": os.cpu_count(), "machine": platform.machine(), "system": platform.system(), "python": platform.python_version(),
            "load_avg": [round(x, 2) for x in os.getloadavg()]}


def _write_csv(path: Path, rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="results/tags")
    ap.add_argument("--photos", type=Path, default=None, help="folder of real tag photos")
    ap.add_argument("--truth", type=Path, default=None, help="YAML: photo file name -> list of tag ids visible in it")
    a = ap.parse_args(argv)
    if (a.photos is None) != (a.truth is None):
        ap.error("--photos and --truth go together")
    import yaml

    from tqdm import tqdm

    from sim.runinfo import git_commit, write_run_info

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    write_run_info(out, {k: str(v) for k, v in vars(a).items()}, a.seed)
    t0, c0 = time.perf_counter(), time.process_time()
    with tqdm(total=a.views, desc="views", unit="view") as bar:  # shows the ETA
        rows = synthetic_rows(a.views, a.seed, lambda i, n: bar.update(1))
    _write_csv(out / "synthetic.csv", rows)
    summary = {"synthetic": summarize_synthetic(rows)}
    if a.photos is not None:
        prow = photo_rows(a.photos, yaml.safe_load(a.truth.read_text()))
        _write_csv(out / "photos.csv", prow)
        summary["photos"] = summarize_photos(prow)
    summary["run"] = {"commit": git_commit(), "machine": _machine(), "command": "python benchmarks/bench_tags.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                      "wall_s": round(time.perf_counter() - t0, 1), "cpu_s": round(time.process_time() - c0, 1)}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for b, s in summary["synthetic"].items():
        bins = ", ".join(f"{k} {v['detected']}/{v['n']}" for k, v in s["by_side"].items())
        print(f"synthetic {b:9s}: {s['detected']}/{s['n']} found ({bins}); corner error median {s['corner_err_px_median']:.3f} px, "
              f"p95 {s['corner_err_px_p95']:.3f} px; {s['false_ids']} false id(s)")
    if "photos" in summary:
        p = summary["photos"]
        for b in BACKENDS:
            print(f"photos    {b:9s}: {p[b]['detected']}/{p['listed_tags']} listed tags found ({p[b]['detected_under_25px']}/"
                  f"{p['listed_under_25px_seen']} under 25 px), {p[b]['false']} unlisted")
        if p["both_detected"]:
            print(f"photos agreement: median {p['agreement_px_median']:.3f} px, max {p['agreement_px_max']:.3f} px over {p['both_detected']} tags")
    print(f"wrote {out}/summary.json; {summary['run']['wall_s']} s wall, {summary['run']['cpu_s']} s CPU")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
