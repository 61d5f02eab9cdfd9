"""Intrinsics from a real plain-chessboard set against its published reference.

    .venv/bin/python benchmarks/bench_chessboard.py [--out results/chessboard] [--write-docs]

The set is OpenCV's ``left01``-``left14`` (13 photos, 640x480, 9x6 inner corners, 25 mm squares;
``tests/data/photos/opencv-chessboard``, from Debian's ``opencv-doc``), and the reference is the
``left_intrinsics.yml`` beside it: OpenCV's ``samples/cpp/calibration.cpp`` on the same photos.
Three runs of ``calibrate_intrinsics`` (each with its board found by ``identify_board``):

* ``default``: the project's defaults (adaptive sub-pixel window, k3 fixed);
* ``k3``: the same with k3 free, as the reference has it;
* ``sample-window``: k3 free and the sample's 11 px sub-pixel half-window;
* ``sample-window, no outlier pass``: the same keeping every photo, as the sample does.

Writes ``images.csv`` (per run and photo: accepted, reason, reprojection RMS, smallest corner
spacing in px) and
``summary.json`` (per run: fx, fy, cx, cy, their 1-sigma, RMS, and the differences from the
reference in % of its f; with command, commit, machine, wall and CPU time), and prints them.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
PHOTOS = ROOT / "tests" / "data" / "photos" / "opencv-chessboard"
RUNS = {
    "default": {},
    "k3": {"fix_k3": False},
    "sample-window": {"fix_k3": False, "subpix_half_window_px": 11},
    "sample-window, no outlier pass": {"fix_k3": False, "subpix_half_window_px": 11, "outlier_factor": 1000.0},
}


def run_all() -> tuple[list[dict], dict]:
    from calibration.intrinsics import (
        BoardSpec,
        CalibrationOptions,
        calibrate_intrinsics,
        identify_board,
        load_camera_yaml,
        to_gray,
    )
    from calibration.io import read_image

    paths = sorted(PHOTOS.glob("left*.jpg"))
    imgs = [read_image(p) for p in paths]
    ref = load_camera_yaml(PHOTOS / "left_intrinsics.yml")
    grays = [to_gray(i) for i in imgs]
    board, how = identify_board(grays, BoardSpec())
    from calibration.intrinsics import detect_chessboard

    spacing = {}  # smallest distance between neighbouring corners per photo (px): what bounds a sub-pixel window
    for p, g in zip(paths, grays):
        c, _ = detect_chessboard(g, board)
        grid = c.reshape(board.inner_rows, board.inner_cols, 2)
        spacing[p.name] = round(
            float(
                min(
                    np.linalg.norm(np.diff(grid, axis=1), axis=-1).min(),
                    np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
                )
            ),
            2,
        )
    rows, runs = [], {}
    f_ref = ref.K[0, 0]
    for name, opts in RUNS.items():
        res = calibrate_intrinsics(imgs, board, [p.name for p in paths], CalibrationOptions(**opts))
        K = res.camera.K
        got = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
        want = {"fx": ref.K[0, 0], "fy": ref.K[1, 1], "cx": ref.K[0, 2], "cy": ref.K[1, 2]}
        runs[name] = {
            "options": opts,
            "n_accepted": sum(r.accepted for r in res.images),
            "rms_px": res.rms_px,
            **{k: float(v) for k, v in got.items()},
            "std_px": res.std_px,
            "diff_pct_of_f": {k: float(100 * (got[k] - want[k]) / f_ref) for k in got},
        }
        for r in res.images:
            rows.append(
                {
                    "run": name,
                    "photo": r.name,
                    "accepted": int(r.accepted),
                    "reason": r.reason,
                    "corners": r.n_corners,
                    "reprojection_rms_px": round(float(r.reprojection_rms_px), 4),
                    "corner_spacing_px": spacing[r.name],
                }
            )
    reference = {
        "fx": float(ref.K[0, 0]),
        "fy": float(ref.K[1, 1]),
        "cx": float(ref.K[0, 2]),
        "cy": float(ref.K[1, 2]),
        "rms_px": ref.rms_px,
        "source": "tests/data/photos/opencv-chessboard/left_intrinsics.yml",
    }
    return rows, {"board": how, "reference": reference, "runs": runs}


DOCS = ROOT / "docs" / "calibration.md"
START, END = "<!-- bench-chessboard:start", "<!-- bench-chessboard:end -->"


def docs_block(summary: dict) -> str:
    ref, run = summary["reference"], summary["run"]
    lines = [
        f"Measured by `{run['command']}` at commit `{run['commit'][:12]}` (`results/chessboard/`; board: "
        f"{summary['board']}):",
        "",
        "| run | photos used | fx | fy | cx | cy | RMS px | fx, fy, cx, cy minus the reference, % of f |",
        "|---|---|---|---|---|---|---|---|",
        f"| reference (OpenCV's sample) | 13 | {ref['fx']:.2f} | {ref['fy']:.2f} | {ref['cx']:.2f} | {ref['cy']:.2f} "
        f"| {ref['rms_px']:.3f} | - |",
    ]
    for name, r in summary["runs"].items():
        d = r["diff_pct_of_f"]
        lines.append(
            f"| {name} | {r['n_accepted']} | {r['fx']:.2f} | {r['fy']:.2f} | {r['cx']:.2f} | {r['cy']:.2f} | "
            f"{r['rms_px']:.3f} | "
            f"{d['fx']:+.2f}, {d['fy']:+.2f}, {d['cx']:+.2f}, {d['cy']:+.2f} |"
        )
    return "\n".join(lines)


def write_docs(summary: dict) -> None:
    text = DOCS.read_text()
    i, j = text.index(START), text.index(END)
    DOCS.write_text(text[: text.index("\n", i) + 1] + docs_block(summary) + "\n" + text[j:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="results/chessboard")
    ap.add_argument("--write-docs", action="store_true", help="also rewrite the figures block of docs/calibration.md")
    a = ap.parse_args(argv)
    from sim.runinfo import git_commit
    from trials.experiments.tradeoff import machine_info

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    rows, summary = run_all()
    with (out / "images.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary["run"] = {
        "command": "python benchmarks/bench_chessboard.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "commit": git_commit(),
        "machine": machine_info(),
        "wall_s": round(time.perf_counter() - t0, 1),
        "cpu_s": round(time.process_time() - c0, 1),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(docs_block(summary))
    if a.write_docs:
        write_docs(summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
