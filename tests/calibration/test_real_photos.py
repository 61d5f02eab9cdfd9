"""Real photos from registry packages (tests/data/photos/PROVENANCE.md): a published chessboard
calibration and the AprilTag library's own detection set, and the docs' figures recomputed from them."""

import hashlib
import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
PHOTOS = ROOT / "tests" / "data" / "photos"


def _bench(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_photos_are_the_packaged_files():
    sums = re.findall(r"^([0-9a-f]{64})  (\S+)$", (PHOTOS / "PROVENANCE.md").read_text(), re.M)
    assert len(sums) == 21
    for digest, name in sums:
        assert hashlib.sha256((PHOTOS / name).read_bytes()).hexdigest() == digest, name


@pytest.fixture(scope="module")
def chessboard():
    return _bench("bench_chessboard").run_all()


def test_real_chessboard_is_found_and_calibrates_within_half_a_percent_of_the_published_intrinsics(chessboard):
    _, s = chessboard
    assert s["board"] == "plain chessboard, 9x6 inner corners (found automatically)"
    d = s["runs"]["default"]
    assert d["n_accepted"] == 13 and d["rms_px"] < 0.25
    assert max(abs(v) for v in d["diff_pct_of_f"].values()) < 0.5
    assert all(v < 1.0 for v in d["std_px"].values())


def test_with_the_samples_settings_the_published_intrinsics_are_reproduced(chessboard):
    rows, s = chessboard
    same = s["runs"]["sample-window, no outlier pass"]
    assert max(abs(v) for v in same["diff_pct_of_f"].values()) < 0.05
    # ... and our outlier pass drops the one photo whose window outgrew its squares.
    dropped = [r for r in rows if r["run"] == "sample-window" and not r["accepted"]]
    assert [r["photo"] for r in dropped] == ["left02.jpg"] and dropped[0]["reprojection_rms_px"] > 1.0


def test_the_docs_quote_the_committed_chessboard_run(chessboard):
    bench = _bench("bench_chessboard")
    committed = json.loads((ROOT / "results" / "chessboard" / "summary.json").read_text())
    _, fresh = chessboard
    for name, r in fresh["runs"].items():  # the committed figures are what the code gives now
        assert (
            committed["runs"][name]["fx"] == pytest.approx(r["fx"], abs=1e-6)
            and committed["runs"][name]["n_accepted"] == r["n_accepted"]
        )
    assert bench.docs_block(committed) in (ROOT / "docs" / "calibration.md").read_text()


def test_apriltag3_finds_the_small_tags_of_real_photos_that_cv2_aruco_misses():
    bench = _bench("bench_tags")
    p = bench.summarize_photos(bench.photo_rows(PHOTOS / "apriltag-swarmathon"))
    assert p["expected_tags"] == 47
    assert p["apriltag3"]["detected"] >= 45 and p["apriltag3"]["detected_under_25px"] >= 27
    assert p["aruco"]["detected"] <= 30 and p["apriltag3"]["unexpected"] == 0
    assert p["apriltag3"]["raw_vs_library_px_median"] < 0.01 and p["agreement_px_max"] < 0.05


def test_the_docs_quote_the_committed_tag_benchmark_recomputed_from_its_csvs():
    bench = _bench("bench_tags")
    out = ROOT / "results" / "tags"
    committed = json.loads((out / "summary.json").read_text())
    assert bench.summarize_synthetic(bench.read_csv(out / "synthetic.csv")) == committed["synthetic"]
    assert bench.summarize_photos(bench.read_csv(out / "photos.csv")) == committed["photos"]
    assert bench.docs_block(committed) in (ROOT / "docs" / "calibration.md").read_text()
    # The photo rows are what the detectors give now.
    fresh = bench.summarize_photos(bench.photo_rows(PHOTOS / "apriltag-swarmathon"))
    assert fresh == committed["photos"]


def test_the_opencv_sample_output_loads_as_a_camera_file():
    from calibration.intrinsics import load_camera_yaml

    cam = load_camera_yaml(PHOTOS / "opencv-chessboard" / "left_intrinsics.yml")
    assert (
        (cam.width, cam.height) == (640, 480)
        and cam.K[0, 0] == pytest.approx(535.9157, abs=1e-3)
        and len(cam.dist) == 5
    )
    assert np.isclose(cam.rms_px, 0.3926, atol=1e-3)


def test_the_docs_quote_the_smallest_corner_spacing_from_the_committed_rows():
    import csv

    with (ROOT / "results" / "chessboard" / "images.csv").open() as f:
        spacing = {r["photo"]: float(r["corner_spacing_px"]) for r in csv.DictReader(f) if r["run"] == "default"}
    smallest = min(spacing, key=spacing.get)
    assert smallest == "left02.jpg" and spacing[smallest] < 23  # narrower than the sample's 23 px window
    assert f"the smallest of the set ({spacing[smallest]:.1f} px" in (ROOT / "docs" / "calibration.md").read_text()
