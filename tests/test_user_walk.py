"""The measured walk of issue 30: a new user's own scanned mesh and own ONNX policy, through the
commands they type, to a simulated trial report they open in a browser.

Every ``advobj`` step runs as a subprocess of the installed console script in a fresh folder, with
Python's warnings shown as ``-W default`` shows them (``PYTHONWARNINGS=default``: every category,
DeprecationWarning included, once per place), so a warning that would reach a user's terminal
fails the walk. The steps:

1. the user's mesh, ``tests/data/meshes/scan-rabbit-mm/rabbit.stl`` (a photogrammetry scan in
   millimetres), copied into ``meshes/`` and named ``rabbit`` in the user's scene YAML;
2. the user's policy, a small torch CNN exported to ONNX with its card by docs/workflow.md's path
   (``torch.onnx.export`` with torch's deprecation notice silenced, then
   ``sim.policies.onnx_policy.attach_card``), by a script of the user's that prints no warning either;
3. ``advobj attack run``; 4. ``advobj eval``; 5. ``advobj fabricate --scene --shape rabbit
   --tag-id 7``; 6. ``advobj trial plan --scene --shape rabbit``; 7. ``advobj trial run`` on
   ``examples/hardware/sim.yaml``; 8. ``advobj trial report``; 9. its ``report.html`` in headless
   Chromium: no console message, and a screenshot.

``ADVOBJ_WALK_SCREENSHOT=docs/img/trial-report.png`` writes that screenshot there (the picture in
docs/real-trials.md); without it, the committed picture is compared with this run's by size.

The policy is untrained: its head leans straight ahead (along the camera's axis), so it reaches
the goal where the goal lies ahead and nothing elsewhere. The competence gate measures it and
refuses it (step 4 shows the refusal a user meets); the walk then evaluates it with
``--min-clean-success 0``. A policy that does the task takes minutes of training (``advobj policy
train --preset quick``): the walk checks that every command works on the user's own files, not
what an attack on a trained policy achieves. The attack itself is not gated here: without
``--pool`` it draws the scene's configurations unfiltered and builds no pool, which is when the
gate would measure.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import pytest

from calibration.registry import load_registry
from tests.sim.browser_helpers import assert_renders_cleanly, needs_chromium, render_in_chromium
from tests.trials.cli.test_docs_commands import _workflow_block
from tests.trials.real.own_mesh_helpers import RABBIT, REPO, own_scene
from tests.trials.real.trial_session_helpers import SIM_HW

ADVOBJ = Path(sys.executable).with_name("advobj")  # the console script installed beside this Python
SCREENSHOT_ENV = "ADVOBJ_WALK_SCREENSHOT"
DOC_SCREENSHOT = REPO / "docs" / "img" / "trial-report.png"
STEP_TIMEOUT_S = 900
# Python's warnings as they reach a terminal: ``file:line: SomethingWarning: message`` (and any other
# mention of a warning class). advobj's own advice lines say ``warning:`` in lower case.
_PY_WARNING = re.compile(r"\b\w*Warning\b")
EXPORT_SCRIPT = '''\
"""My policy: a small CNN, exported to ONNX with its card (docs/workflow.md)."""
import warnings

import torch
from torch import nn

from sim.policies.card import ActionScaling, PolicyCard
from sim.policies.onnx_policy import attach_card
from sim.policies.policy import PolicyArch

S = 32  # input size (px)


class MyPolicy(nn.Module):
    """images (B, 3, S, S) in [0, 1] -> a TCP motion (B, 6) in [-1, 1]."""

    def __init__(self):
        super().__init__()
        self.encoder = nn.Sequential(
            nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU(), nn.Conv2d(8, 16, 3, stride=2, padding=1), nn.ReLU()
        )
        self.decoder = nn.Sequential(nn.Flatten(), nn.Linear(16 * (S // 4) ** 2, 6))

    def forward(self, images):
        return torch.tanh(self.decoder(self.encoder(images)))


torch.manual_seed(0)
policy = MyPolicy().eval()
with torch.no_grad():  # untrained: lean straight ahead (TCP +z, the camera's axis), small weights elsewhere
    policy.decoder[1].weight.mul_(0.1)
    policy.decoder[1].bias.zero_()
    policy.decoder[1].bias[2] = 3.0
card = PolicyCard(arch=PolicyArch(image_size=S), action=ActionScaling(max_step_m=0.02, max_step_rad=0.1))
with warnings.catch_warnings():  # torch's notice that the TorchScript exporter is deprecated
    warnings.simplefilter("ignore", DeprecationWarning)
    torch.onnx.export(
        policy,
        (torch.rand(2, 3, S, S),),
        "my_policy.onnx",
        input_names=["images"],
        output_names=["actions"],
        dynamic_axes={"images": {0: "batch"}, "actions": {0: "batch"}},
        opset_version=17,
        dynamo=False,
    )
attach_card("my_policy.onnx", card)
'''


def walk_env(cache_dir: Path) -> dict:
    """The user's environment with Python's warnings as ``-W default`` shows them, and an empty
    cache (``cache_dir``: no UV atlas made by another test, as in a fresh clone)."""
    return {
        **os.environ,
        "PYTHONWARNINGS": "default",
        "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl"),
        "ADVOBJ_CACHE_DIR": str(cache_dir),
    }


def python_warnings(text: str) -> list[str]:
    """The lines of a step's terminal output that come from Python's warnings machinery."""
    return [line for line in text.splitlines() if _PY_WARNING.search(line)]


def run(cmd: list, cwd: Path) -> subprocess.CompletedProcess:
    """``cmd`` in folder ``cwd`` in the walk's environment (its cache beside ``cwd``)."""
    env = walk_env(cwd.parent / "cache")
    return subprocess.run(
        [str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=STEP_TIMEOUT_S
    )


def step(cwd: Path, *args) -> str:
    """``advobj ARGS`` as the user types it: it must work and print no Python warning; its stdout."""
    r = run([ADVOBJ, *args], cwd)
    said = r.stdout + r.stderr
    assert r.returncode == 0, f"advobj {' '.join(map(str, args))} failed ({r.returncode}):\n{said[-4000:]}"
    assert python_warnings(said) == [] and "Traceback" not in said, f"advobj {args[0]} {args[1]}:\n{said[-4000:]}"
    return r.stdout


def test_the_warning_scan_sees_what_only_w_default_shows(tmp_path):
    """The control: a library's DeprecationWarning, hidden by Python's default filters, reaches the
    terminal in the walk's environment and the scan finds it."""
    code = "import warnings; warnings.warn_explicit('old call', DeprecationWarning, 'lib.py', 3, module='lib')"
    (tmp_path / "home").mkdir()
    shown = run([sys.executable, "-c", code], tmp_path / "home")
    assert python_warnings(shown.stderr) == ["lib.py:3: DeprecationWarning: old call"]
    quiet = subprocess.run(
        [sys.executable, "-c", code],
        env={k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"},
        capture_output=True,
        text=True,
    )
    assert quiet.returncode == 0 and python_warnings(quiet.stderr) == []


def test_the_readme_says_how_to_run_the_installed_advobj_and_it_runs_without_a_warning(tmp_path):
    """After ``make test`` (or ``make demo``) a user runs the console script the walk runs: the
    README's quick start names it (``.venv/bin``, or the venv activated), and its help works."""
    readme = (REPO / "README.md").read_text()
    quick = readme[readme.index("## Quick start") :]
    quick = quick[: quick.index("\n## ", 1)]
    assert "make test" in quick and "`.venv/bin/advobj --help`" in quick and "source .venv/bin/activate" in quick
    (tmp_path / "home").mkdir()
    r = run([ADVOBJ, "--help"], tmp_path / "home")
    assert r.returncode == 0 and "attack" in r.stdout and "trial" in r.stdout, r.stderr[-4000:]
    assert python_warnings(r.stdout + r.stderr) == [], r.stderr[-4000:]


def test_the_documented_onnx_export_script_prints_no_python_warning(tmp_path):
    """docs/workflow.md's export script (at a smaller input), run as the user's own script: it
    writes both policy files and prints no Python warning, torch's exporter notice included."""
    code = _workflow_block("class LabPolicy")
    assert "S, K = 96, 8" in code, "docs/workflow.md export script changed: update this test"
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "export_lab_policy.py").write_text(code.replace("S, K = 96, 8", "S, K = 32, 8"))
    r = run([sys.executable, "export_lab_policy.py"], tmp_path / "home")
    assert r.returncode == 0, r.stderr[-4000:]
    assert all((tmp_path / "home" / f).is_file() for f in ("lab_policy.onnx", "lab_policy.pt2"))
    assert python_warnings(r.stdout + r.stderr) == [], r.stderr[-4000:]


@pytest.mark.slow
@needs_chromium
def test_a_users_own_mesh_and_onnx_policy_walk_to_a_trial_report_without_a_warning(tmp_path):
    home = tmp_path / "my-cell"
    (home / "meshes").mkdir(parents=True)
    shutil.copyfile(RABBIT, home / "meshes" / "rabbit.stl")
    # The scene: the built-in soup can as the goal, the rabbit (mm) beside it; 30-step episodes from
    # 25-50 cm, so the straight-ahead policy reaches one object or the other within an episode.
    own_scene(
        home / "my_scene.yaml",
        "meshes/rabbit.stl",
        name="rabbit",
        scene_fields={"episode": {"max_steps": 30}, "init": {"r_range_m": [0.25, 0.5]}},
    )

    # 2. the user's policy, exported by their own script
    (home / "export_policy.py").write_text(EXPORT_SCRIPT)
    r = run([sys.executable, "export_policy.py"], home)
    assert r.returncode == 0 and (home / "my_policy.onnx").is_file(), r.stderr[-4000:]
    assert python_warnings(r.stdout + r.stderr) == [], r.stderr[-4000:]

    # 3. the attack (test-sized preset; lights randomised, as for a texture to print)
    said = step(home, "attack", "run", "--policy", "my_policy.onnx", "--scene", "my_scene.yaml", "--preset", "ci",
                "--light-randomization", "--out", "runs/attack")  # fmt: skip
    assert "outputs in runs/attack/" in said
    assert all((home / "runs" / "attack" / f).is_file() for f in ("texture.npy", "configs.json", "report.html"))

    # 4. the evaluation: the competence gate refuses the untrained policy in one line, writing nothing ...
    evaluate = ["eval", "--policy", "my_policy.onnx", "--scene", "my_scene.yaml", "--attack", "runs/attack",
                "--episodes", "4", "--max-steps", "30", "--gifs", "1"]  # fmt: skip
    refused = run([ADVOBJ, *evaluate, "--out", "runs/eval-gated"], home)
    errors = [line for line in refused.stderr.splitlines() if line.startswith("error:")]
    assert refused.returncode == 2 and len(errors) == 1, refused.stderr[-4000:]
    assert "clean episodes measured on this scene" in errors[0] and "is below --min-clean-success 0.5" in errors[0]
    assert python_warnings(refused.stdout + refused.stderr) == [] and not (home / "runs" / "eval-gated").exists()
    # ... and, the check off, evaluates it (clean, benign and attack on the same configurations)
    said = step(home, *evaluate, "--min-clean-success", "0", "--out", "runs/eval")
    assert "headline: attack vs benign" in said
    summary = json.loads((home / "runs" / "eval" / "summary.json").read_text())
    assert set(summary["conditions"]) == {"clean", "benign", "attack"}
    assert (home / "runs" / "eval" / "report.html").is_file()

    # 5. the object made: the rabbit's tag card, registered under its scene name
    said = step(home, "fabricate", "runs/attack", "--scene", "my_scene.yaml", "--shape", "rabbit", "--tag-id", "7",
                "--dpi", "60", "--out", "runs/fab")  # fmt: skip
    assert "pre-print check PASSED: tag card" in said
    card = load_registry(home / "runs" / "fab" / "objects.yaml")
    assert card.objects == ("rabbit",) and set(card.tags) == {7}

    # 6. the plan (seed 3: its two start poses send this policy to both objects, so the report shows
    # both outcomes; the walk asserts no outcome)
    said = step(home, "trial", "plan", "--scene", "my_scene.yaml", "--shape", "rabbit", "--texture",
                "rabbit/adv3d=runs/attack", "--condition", "clean", "--condition", "adv3d", "--tcp-poses", "2",
                "--object-poses", "1", "--seed", "3", "--out", "runs/plan.yaml")  # fmt: skip
    assert "shape rabbit: scene object 'rabbit', mesh rabbit.stl (mm" in said

    # 7. the session on the example sim hardware
    said = step(home, "trial", "run", "--hardware", SIM_HW, "--policy", "my_policy.onnx", "--plan", "runs/plan.yaml",
                "--session", "walk", "--db", "runs/trials.sqlite", "--auto-confirm")  # fmt: skip
    assert "session walk: 4/4 trials done" in said

    # 8. the report
    said = step(home, "trial", "report", "--db", "runs/trials.sqlite", "--sim", "rabbit=runs/eval", "--out",
                "runs/trial-report")  # fmt: skip
    report = home / "runs" / "trial-report"
    assert said.strip().splitlines()[-1] == (
        "4 trials; report in runs/trial-report/report.html (open it in a browser), runs/trial-report/report.md "
        "and runs/trial-report/report.json"
    )
    doc = json.loads((report / "report.json").read_text())
    assert doc["summary"]["all"]["by_shape"]["rabbit"]["n"] == 4
    assert [row["shape"] for row in doc["table_iv"]] == ["rabbit"]

    # 9. the page a person opens
    page = render_in_chromium(report / "report.html", tmp_path / "chromium")
    assert_renders_cleanly(page)
    assert page.outline.headings["h1"] == ["Real-robot trial report"]
    assert {"Summary", "T-ASR and ASR by arm", "Paired tests between arms"} <= set(page.outline.headings["h2"])
    target = os.environ.get(SCREENSHOT_ENV)
    if target:
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(target, page.screenshot)
    else:
        assert iio.imread(DOC_SCREENSHOT)[..., :3].shape == page.screenshot.shape
