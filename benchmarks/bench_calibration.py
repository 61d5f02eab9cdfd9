"""Accuracy (and speed) of the calibration pipeline on synthetic OpenGL renders with known ground truth.

Run: ``.venv/bin/python benchmarks/bench_calibration.py [--seeds 5] [--tag-views 20]``.

Prints, against the issue's targets:
  intrinsics        max relative error of fx, fy, cx, cy (% of f)              target <= 1 %
  tag position      40 mm tag at 0.5 m, tilts 0/25/45 deg (mm)                 target <= 3 mm
  tag orientation   frontal 60 mm and 40 mm tags at 0.5 m (deg)               target <= 1 deg
  oblique           70 deg views: detected / flagged / position error
  hand-eye          noisy 15- and 25-sample sets (mm, deg), Tsai vs Park       target <= 2 mm, 0.5 deg
                    and from 12 rendered board images per set

Camera: 640x480, 70 deg horizontal FOV. Images: OpenGL render, Gaussian blur 0.6-0.7 px, noise
sigma 2 grey levels; intrinsics images also carry k1 = -0.08 radial distortion. Hand-eye noise:
arm 0.1 mm / 0.02 deg, board 0.5 mm / 0.1 deg per axis.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5, help="intrinsics and hand-eye repetitions")
    ap.add_argument("--tag-views", type=int, default=20, help="renders per tag configuration")
    args = ap.parse_args()

    from calibration.selfcheck import handeye_check, handeye_images_check, intrinsics_check, tag_check

    t0 = time.perf_counter()
    intr = [intrinsics_check(n_images=12, seed=s) for s in range(args.seeds)]
    t_intr = (time.perf_counter() - t0) / args.seeds
    mx = [r["max_pct"] for r in intr]
    print(
        f"intrinsics (12 images, {args.seeds} seeds): max error median {np.median(mx):.3f} %, worst {max(mx):.3f} %; "
        f"fx worst {max(r['fx_pct'] for r in intr):.3f} %; RMS reprojection median "
        f"{np.median([r['rms_px'] for r in intr]):.3f} px; "
        f"k1 {np.median([r['k1'] for r in intr]):.4f} (true -0.08); {t_intr:.1f} s per calibration incl. rendering"
    )

    for tilt in (0.0, 25.0, 45.0):
        r = tag_check(0.5, tilt, 0.04, n=args.tag_views, seed=1)
        print(
            f"tag 40 mm at 0.5 m, tilt {tilt:4.1f} deg: position median {r['position_mm_median']:.2f} mm, max "
            f"{r['position_mm_max']:.2f} mm; orientation median {r['orientation_deg_median']:.2f} deg, max "
            f"{r['orientation_deg_max']:.2f} deg; {r['detected']}/{r['n']} detected, {r['flagged']} flagged"
        )
    for size in (0.06, 0.04):
        r = tag_check(0.5, 0.0, size, n=args.tag_views, seed=2)
        print(
            f"frontal orientation, {size * 1000:.0f} mm tag at 0.5 m: median "
            f"{r['orientation_deg_median']:.2f} deg, max "
            f"{r['orientation_deg_max']:.2f} deg ({r['flagged']}/{r['detected']} flagged)"
        )
    for dist, size in ((0.5, 0.04), (0.35, 0.06)):
        r = tag_check(dist, 70.0, size, n=args.tag_views, seed=3)
        print(
            f"oblique 70 deg, {size * 1000:.0f} mm at {dist} m: {r['detected']}/{r['n']} detected, "
            f"{r['flagged']} flagged; "
            f"position max {r['position_mm_max']:.2f} mm, orientation max {r['orientation_deg_max']:.2f} deg"
        )

    he = [handeye_check(seed=s) for s in range(args.seeds * 2)]
    p = np.array([r["position_mm"] for r in he])
    d = np.array([r["rotation_deg"] for r in he])
    print(
        f"hand-eye (park+refine, {len(he)} noisy 15-sample sets): position median {np.median(p):.2f} mm, max "
        f"{p.max():.2f} mm; "
        f"rotation median {np.median(d):.3f} deg, max {d.max():.3f} deg"
    )
    cp = np.array([r["check_position_mm"] for r in he])
    cd = np.array([r["check_rotation_deg"] for r in he])
    print(
        f"hand-eye tsai alone: position median {np.median(cp):.2f} mm, max {cp.max():.2f} mm; rotation max "
        f"{cd.max():.3f} deg"
    )
    dm = np.array([r["methods_disagreement_mm"] for r in he])
    dd = np.array([r["methods_disagreement_deg"] for r in he])
    print(
        f"tsai vs park disagreement: median {np.median(dm):.2f} mm / {np.median(dd):.3f} deg, max {dm.max():.2f} "
        f"mm / {dd.max():.3f} deg"
    )
    he25 = [handeye_check(n_samples=25, seed=s) for s in range(args.seeds * 2)]
    p25 = np.array([r["position_mm"] for r in he25])
    d25 = np.array([r["rotation_deg"] for r in he25])
    print(
        f"hand-eye with 25 samples: position median {np.median(p25):.2f} mm, max {p25.max():.2f} mm; rotation max "
        f"{d25.max():.3f} deg"
    )
    hi = [handeye_images_check(seed=s) for s in range(args.seeds)]
    pi = np.array([r["position_mm"] for r in hi])
    di = np.array([r["rotation_deg"] for r in hi])
    print(
        f"hand-eye from rendered board images (12 views, {len(hi)} sets): position median {np.median(pi):.2f} mm, "
        f"max {pi.max():.2f} mm; "
        f"rotation max {di.max():.3f} deg; tsai vs park max {max(r['methods_disagreement_mm'] for r in hi):.2f} mm / "
        f"{max(r['methods_disagreement_deg'] for r in hi):.3f} deg"
    )
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
