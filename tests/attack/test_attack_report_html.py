"""The attack's report.html (attack.outputs through sim.htmlreport): the texture over iterations
from the trail the loop keeps, Grad-CAM before and after with its colour bar, and the page in a
real Chromium."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from attack.artifact import texture_to_uint8
from attack.optimize import AttackConfig, AttackRun, resolve_config, run_attack
from attack.outputs import (
    CAM_HEAT_WEIGHT,
    CAM_IMAGE_WEIGHT,
    TRAIL_MARKS,
    gradcam_colour_bar,
    texture_trail,
    trail_iterations,
    write_outputs,
)
from sim.configs import sample_pool
from sim.htmlreport import REPORT_HTML
from sim.policies.policy import VisuomotorPolicy
from sim.spec import default_scene
from tests.sim.browser_helpers import assert_renders_cleanly, needs_chromium, outline, render_in_chromium

ITERATIONS = 6


@pytest.fixture(scope="module")
def attack_out(tmp_path_factory):
    """A real 6-iteration attack (validated every 2) with the loop's texture trail, and its outputs."""
    spec = default_scene()
    cfg = resolve_config(
        "ci",
        {
            "iterations": ITERATIONS,
            "num_envs": 1,
            "validation_every": 2,
            "validation_episodes": 2,
            "adversarial_mesh": "cube",
        },
    )
    pool = sample_pool(spec, 3, seed=0, part="attack") + sample_pool(spec, 2, seed=0, part="validation")
    torch.manual_seed(0)
    out = tmp_path_factory.mktemp("attack") / "run"
    out.mkdir()
    run = AttackRun(VisuomotorPolicy(arch="small_cnn", image_size=32), spec, cfg, pool=pool, out_dir=out)
    textures = {}
    trail = texture_trail(out, cfg)

    def on_iteration(r, info):
        textures[r.state.iteration] = texture_to_uint8(r.state.texture.detach().cpu())
        trail(r, info)

    try:
        before = run.state.texture.clone()
        run_attack(run, progress=False, on_iteration=on_iteration)
        metrics = write_outputs(run, out, before)
    finally:
        run.close()
    return out, cfg, textures, texture_to_uint8(before), metrics


@given(st.integers(1, 20_000), st.integers(0, 500))
def test_the_trail_marks_the_validated_iterations_at_most_ten_and_always_the_last(iterations, every):
    cfg = AttackConfig(iterations=iterations, validation_every=every)
    marks = trail_iterations(cfg)
    assert marks == sorted(set(marks)) and marks[-1] == iterations and 0 < marks[0]
    assert len(marks) <= TRAIL_MARKS
    if every:
        assert all(k % every == 0 for k in marks[:-1])


def test_the_trail_holds_the_texture_at_each_validated_iteration(attack_out):
    out, cfg, textures, _, _ = attack_out
    files = sorted(p.name for p in (out / "texture_trail").iterdir())
    assert (
        files
        == [f"iteration_{k:06d}.png" for k in (2, 4, 6)]
        == [f"iteration_{k:06d}.png" for k in trail_iterations(cfg)]
    )
    for k in (2, 4, 6):  # a 16 px texture is kept as it is
        assert np.array_equal(iio.imread(out / "texture_trail" / f"iteration_{k:06d}.png"), textures[k])


def test_the_texture_over_iterations_shows_start_marks_and_end(attack_out):
    out, _, textures, start, _ = attack_out
    fig = iio.imread(out / "texture_over_iterations.png")[..., :3]
    # four labelled tiles (iterations 0, 2, 4, 6) side by side: 16 px textures upscaled x11 to 176 px
    assert fig.shape == (18 + 176, 4 * 176 + 3 * 4, 3)
    for i, tex in enumerate([start, textures[2], textures[4], textures[6]]):
        tile = fig[18:, i * 180 : i * 180 + 176]
        assert np.array_equal(tile[::11, ::11], tex)


def test_the_colour_bar_is_the_overlays_blend_from_zero_to_the_maximum():
    bar = gradcam_colour_bar(274)
    assert bar.shape == (274, 96, 3) and bar.dtype == np.uint8
    strip = bar[18:, 16].astype(int)  # the strip's centre column, below the title bar
    grey = round(255 * CAM_IMAGE_WEIGHT * 0.5)
    assert abs(strip[-9, 0] - grey) <= 1 and abs(strip[8, 0] - (grey + round(255 * CAM_HEAT_WEIGHT))) <= 1
    assert np.all(np.diff(strip[8:-8, 0]) <= 0)  # red falls from the top (max) to the bottom (0)
    assert np.all(strip[:, 1] == grey) and np.all(strip[:, 2] == grey)  # only red is added
    with pytest.raises(ValueError, match="colour bar"):
        gradcam_colour_bar(20)


def test_the_grad_cam_figure_carries_its_colour_bar(attack_out):
    out = attack_out[0]
    fig = iio.imread(out / "gradcam_before_after.png")[..., :3]
    bar = gradcam_colour_bar(fig.shape[0])
    assert np.array_equal(fig[:, -bar.shape[1] :], bar)


def test_the_attack_page_has_its_sections_and_embeds_every_figure(attack_out):
    out, _, _, _, metrics = attack_out
    o = outline((out / REPORT_HTML).read_text())
    assert o.headings["h1"] == [f"Attack report: cube (c2f, {ITERATIONS} iterations)"]
    assert o.headings["h2"] == [
        "Summary",
        "Held-out validation",
        "The texture over iterations",
        "Losses",
        "Grad-CAM before and after",
        "Rollout under the final texture",
        "Files",
    ]
    assert len(o.images) == 4 and all(i["src"].startswith("data:image/png;base64,") for i in o.images)
    assert "held-out validation T-ASR (n = 2)" in o.text and "light_randomization is off" in o.text
    assert o.tables == 1 and len(metrics["validation"]["iteration"]) == 4  # 0, 2, 4, 6


@needs_chromium
def test_chromium_renders_the_attack_page_without_console_messages(tmp_path, attack_out):
    r = render_in_chromium(attack_out[0] / REPORT_HTML, tmp_path, 1280, 2600)
    assert_renders_cleanly(r)
    assert r.outline.headings["h2"][0] == "Summary" and len(r.outline.images) == 4
