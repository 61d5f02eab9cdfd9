"""Every command in the docs exists, takes the options shown, and runs on tiny settings.

Commands are read from README.md and docs/*.md: ``$ ...`` lines of ``console`` blocks, and lines
starting with ``advobj`` or ``make`` in ``bash``/``sh``/``shell`` and untagged blocks (comments
stripped, ``\\`` continuations joined). For each one:

* the parse test (default suite, cheap): the command path exists and ``--help`` exits 0, every
  option is one of the command's parameters (read from the click command typer builds, not from
  help text), and click parses the documented argument list; ``make`` targets dry-run
  (``make -n``) and their ``advobj`` recipe lines pass the same checks;
* the run test: ``TINY`` maps the documented line to a real invocation on tiny settings (same
  command, every documented option kept unless the entry says why not, values swapped for tiny
  budgets and temporary paths) that must exit 0 and write the documented outputs. Commands that
  need more than ~30 s even then are marked ``slow``.

A documented command without a ``TINY`` entry fails ``test_every_documented_command_has_a_tiny_run``.
Shared artifacts (a tiny policy, tiny attack runs, synthetic calibration photos) are built once per
module; identical invocations run once.
"""

from __future__ import annotations

import re
import shlex
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest

ROOT = Path(__file__).resolve().parents[3]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MAX_STEPS = 3
TINY_ATTACK = (
    "iterations: 2\nnum_envs: 1\nrollout_steps: 2\ntexture_size: 16\npool_size: 4\ncheckpoint_every: "
    "1\nvalidation_every: 0\n"
)


# ============================================================================ reading the docs
@dataclass(frozen=True)
class DocCommand:
    file: str
    line: int
    text: str  # normalised: tokens joined by one space, comment stripped

    @property
    def argv(self) -> list[str]:
        return shlex.split(self.text)

    @property
    def id(self) -> str:
        return f"{self.file}:{self.line}:{self.text[:60]}"


_FENCE = re.compile(r"^\s*```\s*([\w+-]*)")


def parse_commands(path: Path, root: Path = ROOT) -> list[DocCommand]:
    rel = path.relative_to(root).as_posix()
    out: list[DocCommand] = []
    lang, pending, start = None, "", 0
    for no, raw in enumerate(path.read_text().splitlines(), 1):
        m = _FENCE.match(raw)
        if m:
            lang = None if lang is not None else (m.group(1) or "").lower()
            continue
        if lang is None or lang not in ("console", "bash", "sh", "shell", ""):
            continue
        line = raw.strip()
        if pending:
            line = pending + " " + line
        elif lang == "console":
            if not line.startswith("$ "):
                continue
            line, start = line[2:], no
        elif line.startswith("$ "):
            line, start = line[2:], no
        elif line.startswith(("advobj ", "make ")):
            start = no
        else:
            continue
        if line.endswith("\\"):
            pending = line[:-1].strip()
            continue
        pending = ""
        tokens = shlex.split(line, comments=True)
        if tokens and tokens[0] in ("advobj", "make"):
            out.append(DocCommand(rel, start, " ".join(t if "*" in t else shlex.quote(t) for t in tokens)))
    return out


DOC_COMMANDS = [c for f in DOC_FILES for c in parse_commands(f)]


# ============================================================================ the CLI as click sees it
def _root_command():
    import typer.main

    from trials.cli.main import app

    return typer.main.get_command(app)


def resolve(argv: list[str]):
    """``(command, path, rest)`` for ``argv`` without the leading ``advobj``."""
    cmd, path, rest = _root_command(), [], list(argv)
    while rest and hasattr(cmd, "commands") and rest[0] in cmd.commands:
        cmd = cmd.commands[rest[0]]
        path.append(rest.pop(0))
    return cmd, path, rest


def option_params(cmd) -> dict[str, str]:
    """Every option string of ``cmd`` -> its parameter name."""
    out = {}
    for p in cmd.params:
        for o in [*getattr(p, "opts", []), *getattr(p, "secondary_opts", [])]:
            if o.startswith("-"):
                out[o] = p.name
    return out


def used_options(cmd, rest: list[str]) -> set[str]:
    """Parameter names of the options in ``rest`` (unknown options keep their spelling)."""
    known = option_params(cmd)
    names = set()
    for tok in rest:
        if tok.startswith("-") and len(tok) > 1 and not re.match(r"^-\d", tok):
            opt = tok.split("=", 1)[0]
            names.add(known.get(opt, opt))
    return names


def check_advobj_line(argv: list[str], where: str) -> None:
    from typer.testing import CliRunner

    from trials.cli.main import app

    assert argv and argv[0].endswith("advobj"), where
    cmd, path, rest = resolve(argv[1:])
    assert path and not hasattr(cmd, "commands"), f"{where}: 'advobj {' '.join(argv[1:])}' does not name a command"
    res = CliRunner().invoke(app, [*path, "--help"])
    assert res.exit_code == 0, f"{where}: 'advobj {' '.join(path)} --help' exited {res.exit_code}: {res.output}"
    known = option_params(cmd)
    for tok in rest:
        if tok.startswith("-") and not re.match(r"^-\d", tok):
            assert tok.split("=", 1)[0] in known, (
                f"{where}: option {tok.split('=', 1)[0]} is not accepted by 'advobj {' '.join(path)}' (it takes "
                f"{sorted(known)})"
            )
    ctx = cmd.make_context("advobj " + " ".join(path), list(rest))  # types, counts, choices
    ctx.close()


# ============================================================================ tiny invocations
@dataclass
class Tiny:
    """A real run standing in for a documented command (``argv`` after ``advobj``, a template)."""

    argv: str | None
    outputs: tuple[str, ...] = ()
    slow: bool = False
    dropped: dict[str, str] = field(default_factory=dict)  # documented option -> why the tiny run leaves it out
    setup: Callable | None = None  # (monkeypatch, artifacts) -> None, before the run
    expect: str = ""  # text the command prints
    reason: str = ""  # why there is no run (argv None)


class Artifacts:
    """Lazily built inputs for the tiny runs; ``{name}`` in a template is ``self.<name>``."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.root = ROOT
        self.runs: dict[tuple, object] = {}

    def __getitem__(self, key):  # for str.format_map
        value = getattr(self, key)
        return " ".join(str(v) for v in value) if isinstance(value, list) else str(value)

    def fmt(self, template: str) -> list[str]:
        return shlex.split(template.format_map(self))

    def invoke(self, argv: list[str]):
        """Run ``advobj argv`` in-process once; a repeated identical invocation reuses the result."""
        from typer.testing import CliRunner

        from trials.cli.main import app

        key = tuple(argv)
        if key not in self.runs:
            res = CliRunner().invoke(app, argv)
            if res.exit_code != 0:
                import traceback

                tb = "".join(traceback.format_exception(res.exception)) if res.exception else ""
                raise AssertionError(f"'advobj {' '.join(argv)}' exited {res.exit_code}:\n{res.output[-3000:]}\n{tb}")
            self.runs[key] = res
        return self.runs[key]

    def _once(self, name, build):
        cache = self.__dict__.setdefault("_cache", {})
        if name not in cache:
            cache[name] = build()
        return cache[name]

    # ---- policies and attacks
    @property
    def policy(self) -> Path:
        def build():
            import torch

            from sim.policies.card import ActionScaling, PolicyCard
            from sim.policies.checkpoint import save_checkpoint
            from sim.policies.policy import VisuomotorPolicy

            torch.manual_seed(0)
            p = VisuomotorPolicy(arch="small_cnn", image_size=32)
            d = self.tmp / "policy"
            save_checkpoint(d, p, PolicyCard(arch=p.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1)))
            return d

        return self._once("policy", build)

    @property
    def policy_copy(self) -> Path:
        """A copy of the tiny policy for 'policy eval', whose pool (empty for an untrained policy) lands beside it."""
        import shutil

        dst = self.tmp / "policy-copy"
        if not dst.exists():
            shutil.copytree(self.policy, dst)
        return dst

    @property
    def pool(self) -> Path:
        """Initial configurations of the built-in scene with MAX_STEPS-step episodes (eval --pool)."""

        def build():
            from sim.configs import sample_pool, save_pool
            from sim.spec import default_scene

            spec = default_scene()
            spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": MAX_STEPS})
            path = self.tmp / "pool.json"
            save_pool(path, spec, sample_pool(spec, 8, seed=0))
            return path

        return self._once("pool", build)

    @property
    def tiny_attack(self) -> Path:
        path = self.tmp / "tiny_attack.yaml"
        path.write_text(TINY_ATTACK)
        return path

    @property
    def tiny_patch(self) -> Path:
        path = self.tmp / "patch.yaml"
        path.write_text(TINY_ATTACK + "adversarial_mesh: patch\n")
        return path

    @property
    def tiny_cube(self) -> Path:
        path = self.tmp / "cube.yaml"
        path.write_text(TINY_ATTACK + "adversarial_mesh: cube\n")
        return path

    @property
    def attack(self) -> Path:
        self.invoke(self.fmt(TINY[ATTACK_LINE].argv))
        return self.tmp / "attack"

    @property
    def patch(self) -> Path:
        self.invoke(self.fmt(TINY[PATCH_LINE].argv))
        return self.tmp / "patch"

    @property
    def attack_cube(self) -> Path:
        self.invoke(self.fmt("attack run --policy {policy} --config {tiny_cube} --out {tmp}/attack-cube"))
        return self.tmp / "attack-cube"

    @property
    def eval(self) -> Path:
        self.invoke(self.fmt(EVAL_MAIN.argv))
        return self.tmp / "eval"

    @property
    def plan(self) -> Path:
        self.invoke(self.fmt(TINY[PLAN_LINE].argv))
        return self.tmp / "trials" / "plan.yaml"

    @property
    def trial_db(self) -> Path:
        self.invoke(self.fmt(TINY[RUN_LINE].argv))
        return self.tmp / "trials" / "trials.sqlite"

    @property
    def onnx(self) -> Path:
        self.invoke(self.fmt("policy export {policy} --onnx {tmp}/policy.onnx"))
        return self.tmp / "policy.onnx"

    @property
    def onnx_copy(self) -> Path:
        """A second ONNX file (the workflow's 'my_policy.onnx')."""
        import shutil

        dst = self.tmp / "my_policy.onnx"
        if not dst.exists():
            shutil.copy(self.onnx, dst)
        return dst

    @property
    def pt2_copy(self) -> Path:
        """The tiny policy as a .pt2 file (the workflow's 'my_policy.pt2')."""
        self.invoke(self.fmt("policy export {policy} --pt2 {tmp}/my_policy.pt2"))
        return self.tmp / "my_policy.pt2"

    # ---- your own mesh
    @property
    def my_scene(self) -> Path:
        def build():
            import trimesh

            d = self.tmp / "my_scene"
            (d / "meshes").mkdir(parents=True)
            box = trimesh.creation.box(extents=(0.06, 0.06, 0.1))
            box.apply_translation((0, 0, 0.05))  # origin at the base centre
            box.export(d / "meshes" / "my_object.obj")  # no UVs: exercises the automatic atlas
            (d / "my_scene.yaml").write_text(
                "name: my-reach\n"
                "camera: {width: 32, height: 32}\n"
                "objects:\n"
                "  - {name: tomato_soup_can, mesh: tomato_soup_can, role: goal, pose: {x_m: 0.12, y_m: 0.0}}\n"
                "  - {name: my_object, mesh: meshes/my_object.obj, role: adversarial, pose: {x_m: -0.12, y_m: 0.0}}\n"
            )
            return d / "my_scene.yaml"

        return self._once("my_scene", build)

    # ---- calibration inputs (synthetic renders with the example camera)
    @property
    def calib(self) -> Path:
        d = self.tmp / "calib"
        d.mkdir(exist_ok=True)
        return d

    @property
    def board_yaml(self) -> Path:
        self.invoke(self.fmt("calibrate board --out {calib}/board.pdf"))
        return self.calib / "board.yaml"

    @property
    def shots(self) -> list[Path]:
        def build():
            import imageio.v3 as iio

            from calibration import synthetic as S
            from calibration.intrinsics import BoardSpec
            from calibration.selfcheck import _board_views

            board = BoardSpec()
            K = S.default_K(640, 480)
            cb = board.cv_board()
            (self.calib / "shots").mkdir(exist_ok=True)
            paths = []
            for i, T in enumerate(_board_views(board, 8, seed=1)):
                img = S.degrade(S.render_planes([S.board_plane(cb, T)], K, 640, 480), 0.5, 1.0, seed=i)
                paths.append(self.calib / "shots" / f"shot_{i:02d}.png")
                iio.imwrite(paths[-1], img)
            return paths

        return self._once("shots", build)

    @property
    def chess(self) -> list[Path]:
        """OpenCV's own chessboard photos (tests/data/photos/PROVENANCE.md): the docs' left*.jpg."""
        return sorted((ROOT / "tests" / "data" / "photos" / "opencv-chessboard").glob("left*.jpg"))

    @property
    def ros_cam(self) -> Path:
        def build():
            from calibration.intrinsics import load_camera_yaml, save_camera_yaml

            cam = load_camera_yaml(ROOT / "examples" / "calibration" / "cam.yaml")
            return save_camera_yaml(self.calib / "ost.yaml", cam, fmt="ros")

        return self._once("ros_cam", build)

    @property
    def photo(self) -> Path:
        def build():
            import imageio.v3 as iio

            from calibration import synthetic as S

            K = S.default_K(640, 480)  # the camera of examples/calibration/cam.yaml
            planes = [
                S.tag_plane(0, 0.04, S.camera_facing(0.4, offset_m=(-0.05, 0.0))),
                S.tag_plane(2, 0.04, S.camera_facing(0.4, offset_m=(0.05, 0.0))),
            ]
            path = self.calib / "photo.png"
            iio.imwrite(path, S.render_planes(planes, K, 640, 480))
            return path

        return self._once("photo", build)

    @property
    def front_photos(self) -> list[Path]:
        """Two photos of the table's tags (examples/calibration/objects.yaml: tags 0 and 1) from a fixed
        camera, the example camera 0.5 m from them: the docs' front_*.png."""

        def build():
            import imageio.v3 as iio
            import numpy as np

            from calibration import synthetic as S
            from calibration.registry import load_registry
            from sim.geometry import invert_T, look_at

            reg = load_registry(ROOT / "examples" / "calibration" / "objects.yaml")
            T_table_cam = look_at(np.array([0.1, -0.35, 0.35]), np.array([0.1, 0.0, 0.0]))
            K = S.default_K(640, 480)  # the camera of examples/calibration/cam.yaml
            img = S.render_planes(S.object_tag_planes(reg, invert_T(T_table_cam)), K, 640, 480)
            paths = [self.calib / f"front_{i}.png" for i in range(2)]
            for i, path in enumerate(paths):
                iio.imwrite(path, S.degrade(img, 0.5, 1.0, seed=i))
            return paths

        return self._once("front_photos", build)


def _tiny_demo(monkeypatch, art: Artifacts):
    import trials.experiments.demo as demo
    import trials.experiments.recipes as ex

    monkeypatch.setattr(
        demo,
        "DEMO_BUDGET",
        dict(
            attack_overrides={
                "iterations": 1,
                "num_envs": 1,
                "rollout_steps": 1,
                "texture_size": 8,
                "validation_every": 0,
            },
            episodes=2,
            max_steps=MAX_STEPS,
            num_envs=2,
            gifs=1,
            pool=str(art.pool),
        ),
    )
    for mod in (ex, demo):  # demo binds ensure_policy at import
        monkeypatch.setattr(mod, "ensure_policy", lambda ctx, name="reference", **kw: art.policy)


def _tiny_lerobot(monkeypatch, art: Artifacts):
    """A tiny LeRobot v2.1 dataset and the calibration files of its two cameras (tests/trials/recordings)."""
    from tests.trials.recordings.lerobot_datasets import build_v21, calibration_files

    if not (art.tmp / "lerobot").exists():
        build_v21(art.tmp / "lerobot")
        calibration_files(art.tmp / "lerobot-cal")


def _tiny_experiments(monkeypatch, art: Artifacts):
    import trials.experiments.recipes as ex

    tiny = dict(
        policy_preset="ci",
        target_policy_preset="ci",
        attack_preset="quick",
        attack_overrides={
            "iterations": 1,
            "num_envs": 1,
            "rollout_steps": 1,
            "texture_size": 8,
            "pool_size": 4,
            "validation_every": 0,
        },
        episodes=2,
        max_steps=MAX_STEPS,
        num_envs=2,
        gifs=0,
        pool=str(art.pool),
        shapes=("dog",),
    )
    for preset in ("quick", "paper"):
        monkeypatch.setitem(ex.PRESETS, preset, tiny)


TRANSFER_TARGETS = "--target resnet34={policy} --target vgg16={policy} --target inception_v3={onnx}"
EVAL_TINY = "--episodes 2 --max-steps 3 --num-envs 2 --gifs 1 --pool {pool}"
CALIB = {
    "advobj calibrate board --out board.pdf": Tiny(
        "calibrate board --out {calib}/board.pdf", ("{calib}/board.pdf", "{calib}/board.yaml")
    ),
    "advobj calibrate intrinsics shots/*.png --board board.yaml --out cam.yaml": Tiny(
        "calibrate intrinsics {shots} --board {board_yaml} --out {calib}/cam.yaml", ("{calib}/cam.yaml",), expect="RMS"
    ),
    "advobj calibrate tags --ids 0-7 --size-mm 40 --out tags.pdf": Tiny(
        "calibrate tags --ids 0-7 --size-mm 40 --out {calib}/tags.pdf", ("{calib}/tags.pdf",)
    ),
    "advobj calibrate detect photo.png --camera cam.yaml --registry objects.yaml --json": Tiny(
        "calibrate detect {photo} --camera {root}/examples/calibration/cam.yaml --registry "
        "{root}/examples/calibration/objects.yaml --json",
        expect="goal",
    ),
    "advobj calibrate handeye samples.yaml --out T_tcp_cam.yaml": Tiny(
        "calibrate handeye {root}/examples/calibration/handeye_samples.yaml --out {calib}/T_tcp_cam.yaml",
        ("{calib}/T_tcp_cam.yaml",),
    ),
    "advobj calibrate selfcheck": Tiny("calibrate selfcheck", expect="hand-eye"),
    "advobj calibrate scene-camera front_*.png --camera front_cam.yaml --registry objects.yaml --out "
    "front_pose.yaml": Tiny(
        "calibrate scene-camera {front_photos} --camera {root}/examples/calibration/cam.yaml --registry "
        "{root}/examples/calibration/objects.yaml --out {calib}/front_pose.yaml",
        ("{calib}/front_pose.yaml",),
        expect="table tags 0, 1 in 2 image(s)",
    ),
    "advobj calibrate intrinsics left*.jpg --out cam.yaml": Tiny(
        "calibrate intrinsics {chess} --out {calib}/cam_chess.yaml",
        ("{calib}/cam_chess.yaml",),
        expect="board: plain chessboard, 9x6 inner corners (found automatically)",
    ),
    "advobj calibrate intrinsics left*.jpg --board chessboard --inner-corners 9x6 --square-mm 25 --format "
    "ros --out ost.yaml": Tiny(
        "calibrate intrinsics {chess} --board chessboard --inner-corners 9x6 --square-mm 25 --format ros --out "
        "{calib}/ost_chess.yaml",
        ("{calib}/ost_chess.yaml",),
        expect="(as given)",
    ),
    "advobj calibrate convert ost.yaml --out cam.yaml": Tiny(
        "calibrate convert {ros_cam} --out {calib}/cam_from_ros.yaml", ("{calib}/cam_from_ros.yaml",), expect="(ros)"
    ),
}

PLAN_LINE = (
    "advobj trial plan --shape cube --texture cube/adv3d=runs/attack-cube --texture cube/patch=runs/patch --out "
    "runs/plan.yaml "
    "--sheet runs/plan.pdf"
)
RUN_LINE = (
    "advobj trial run --hardware my_cell.yaml --policy runs/policy-quick.onnx --plan runs/plan.yaml --session day1 "
    "--registry objects.yaml --db runs/trials.sqlite"
)
ATTACK_LINE = "advobj attack run --policy runs/policy-quick --preset quick --out runs/attack"
PATCH_LINE = "advobj attack run --policy runs/policy-quick --config patch.yaml --out runs/patch"
ATTACK_OUT = (
    "{tmp}/attack/texture.png",
    "{tmp}/attack/texture.npy",
    "{tmp}/attack/adversarial.glb",
    "{tmp}/attack/metrics.json",
    "{tmp}/attack/loss_curves.png",
    "{tmp}/attack/run.json",
)
EVAL_MAIN = Tiny(
    "eval --policy {policy} --attack {attack} --patch {patch} -c attack -c patch -c light_dim "
    + EVAL_TINY
    + " --out {tmp}/eval",
    ("{tmp}/eval/episodes.csv", "{tmp}/eval/summary.json", "{tmp}/eval/report.md", "{tmp}/eval/manifest.json"),
)

# documented line (as normalised by parse_commands) -> tiny run
TINY: dict[str, Tiny] = {
    # ---- README / workflow step 0
    "make demo": Tiny("demo --out {tmp}/demo", ("{tmp}/demo/report.md",), slow=True, setup=_tiny_demo),
    "make test": Tiny(None, reason="runs this very suite; the parse test dry-runs the target"),
    # ---- README: reference policies
    "advobj policy train --preset quick --out runs/policy-quick": Tiny(
        "policy train --preset ci --out {tmp}/train-ci --episodes 2",
        ("{tmp}/train-ci/policy.json", "{tmp}/train-ci/feasible_pool.json"),
        slow=True,
    ),
    "advobj policy train --preset paper --out runs/policy-paper --threads 2": Tiny(
        "policy train --preset ci --out {tmp}/train-threads --episodes 2 --threads 2",
        ("{tmp}/train-threads/policy.json",),
        slow=True,
    ),
    "advobj policy eval runs/policy-quick --episodes 200": Tiny(
        "policy eval {policy_copy} --episodes 2 --num-envs 2",
        ("{policy_copy}/eval/feasible_pool.json",),
        expect="clean success",
    ),
    "advobj policy export runs/policy-quick --onnx policy.onnx --pt2 policy.pt2": Tiny(
        "policy export {policy} --onnx {tmp}/policy.onnx --pt2 {tmp}/policy.pt2",
        ("{tmp}/policy.onnx", "{tmp}/policy.pt2"),
    ),
    "advobj policy export runs/policy-quick --onnx runs/policy-quick.onnx --pt2 runs/policy-quick.pt2": Tiny(
        "policy export {policy} --onnx {tmp}/policy.onnx --pt2 {tmp}/policy.pt2",
        ("{tmp}/policy.onnx", "{tmp}/policy.pt2"),
    ),
    # ---- workflow: your mesh
    "advobj scene render my_scene.yaml --seed 0 --size 256 --out runs/scene/my_scene.png": Tiny(
        "scene render {my_scene} --seed 0 --size 32 --out {tmp}/scene/my_scene.png", ("{tmp}/scene/my_scene.png",)
    ),
    "advobj scene rollout my_scene.yaml --seed 0 --out runs/scene/my_scene_rollout.gif": Tiny(
        "scene rollout {my_scene} --seed 0 --size 32 --out {tmp}/scene/rollout.gif",
        ("{tmp}/scene/rollout.gif",),
        expect="reached",
    ),
    "advobj scene pool my_scene.yaml --n 100 --seed 0 --out runs/scene/pool.json": Tiny(
        "scene pool {my_scene} --n 4 --seed 0 --out {tmp}/scene/pool.json", ("{tmp}/scene/pool.json",)
    ),
    # ---- workflow: policies
    "advobj policy eval my_policy.onnx --episodes 200 --out runs/my_policy-eval": Tiny(
        "policy eval {onnx_copy} --episodes 2 --num-envs 2 --out {tmp}/my_policy-eval",
        ("{tmp}/my_policy-eval/feasible_pool.json",),
    ),
    "advobj attack run --policy my_policy.onnx --pool runs/my_policy-eval/feasible_pool.json --out "
    "runs/attack-onnx": Tiny(
        "attack run --policy {onnx_copy} --config {tiny_attack} --out {tmp}/attack-onnx",
        ("{tmp}/attack-onnx/texture.npy", "{tmp}/attack-onnx/metrics.json"),
        dropped={"--pool": "the untrained tiny policy solves no configuration: its pool is empty"},
    ),
    "advobj attack run --policy my_policy.pt2 --pool runs/my_policy-eval/feasible_pool.json --out "
    "runs/attack-pt2": Tiny(
        "attack run --policy {pt2_copy} --config {tiny_attack} --out {tmp}/attack-pt2",
        ("{tmp}/attack-pt2/texture.npy", "{tmp}/attack-pt2/metrics.json"),
        dropped={"--pool": "the untrained tiny policy solves no configuration: its pool is empty"},
    ),
    # ---- workflow: attack
    ATTACK_LINE: Tiny(
        "attack run --policy {policy} --preset quick --config {tiny_attack} --out {tmp}/attack", ATTACK_OUT
    ),
    PATCH_LINE: Tiny(
        "attack run --policy {policy} --config {tiny_patch} --out {tmp}/patch",
        ("{tmp}/patch/texture.npy", "{tmp}/patch/run.json"),
    ),
    # ---- evaluation
    "advobj eval --policy runs/policy-quick --attack runs/attack --patch runs/patch -c attack -c patch "
    "-c light_dim --episodes 500 --max-steps 60 --out runs/eval": EVAL_MAIN,
    "advobj eval --policy runs/policy --attack runs/attack --patch runs/patch -c attack -c patch -c "
    "light_dim --episodes 500 --max-steps 60 --out runs/eval": EVAL_MAIN,
    "advobj eval --policy runs/policy-quick.onnx --attack runs/attack --episodes 200 --out runs/eval-transfer": Tiny(
        "eval --policy {onnx} --attack {attack} " + EVAL_TINY + " --out {tmp}/eval-transfer",
        ("{tmp}/eval-transfer/summary.json",),
    ),
    "advobj experiment table1 --preset quick --out runs/table1-quick": Tiny(
        "experiment table1 --preset quick --policy {policy} --out {tmp}/table1",
        ("{tmp}/table1/table.md",),
        slow=True,
        setup=_tiny_experiments,
    ),
    "advobj experiment table1 --preset quick --policy runs/policy-quick --out runs/table1-quick": Tiny(
        "experiment table1 --preset quick --policy {policy} --out {tmp}/table1",
        ("{tmp}/table1/table.md",),
        slow=True,
        setup=_tiny_experiments,
    ),
    "advobj experiment table2 --preset paper --address HEAD_HOST:6379 --device cuda --out runs/table2-paper": Tiny(
        None,
        reason="needs a Ray cluster with GPU nodes; the job layer on a real local cluster is "
        "tests/trials/jobs/test_jobs_ray.py",
    ),
    "advobj experiment table2 --preset quick": Tiny(
        "experiment table2 --preset quick --policy {policy} --out {tmp}/table2",
        ("{tmp}/table2/table.md",),
        slow=True,
        setup=_tiny_experiments,
    ),
    "advobj experiment table3 --preset paper": Tiny(
        "experiment table3 --preset paper --policy {policy} --out {tmp}/table3",
        ("{tmp}/table3/table.md",),
        slow=True,
        setup=_tiny_experiments,
    ),
    "advobj experiment transfer --preset quick --target resnet34=runs/policy-r34 --archs resnet34": Tiny(
        "experiment transfer --preset quick --policy {policy} --target resnet34={policy} --archs resnet34 --out "
        "{tmp}/transfer",
        ("{tmp}/transfer/table.md",),
        slow=True,
        setup=_tiny_experiments,
    ),
    "advobj experiment lighting --preset quick": Tiny(
        "experiment lighting --preset quick --policy {policy} --out {tmp}/lighting",
        ("{tmp}/lighting/table.md",),
        slow=True,
        setup=_tiny_experiments,
    ),
    # ---- fabrication (a cube run: it has a flat net and a tag card footprint)
    "advobj fabricate runs/attack-cube --out runs/fab-cube --tag-id 3": Tiny(
        "fabricate {attack_cube} --out {tmp}/fab-cube --tag-id 3 --dpi 60",
        (
            "{tmp}/fab-cube/sheet.pdf",
            "{tmp}/fab-cube/layout.json",
            "{tmp}/fab-cube/adversarial.glb",
            "{tmp}/fab-cube/print_check.json",
            "{tmp}/fab-cube/objects.yaml",
        ),
        expect="PASSED",
    ),
    "advobj fabricate RUN --out fab": Tiny(
        "fabricate {attack_cube} --out {tmp}/fab --dpi 60 --no-check", ("{tmp}/fab/sheet.pdf",)
    ),
    "advobj fabricate RUN --out fab --page letter --dpi 300": Tiny(
        "fabricate {attack_cube} --out {tmp}/fab-letter --page letter --dpi 300",
        ("{tmp}/fab-letter/sheet.pdf", "{tmp}/fab-letter/print_check.png"),
        slow=True,
    ),
    "advobj fabricate RUN --out fab --tag-id 3 --tag-size-mm 30": Tiny(
        "fabricate {attack_cube} --out {tmp}/fab-tag --tag-id 3 --tag-size-mm 30 --dpi 60 --no-check",
        ("{tmp}/fab-tag/objects.yaml",),
    ),
    "advobj bench tradeoff --policy runs/policy-quick --out runs/tradeoff": Tiny(
        "bench tradeoff --policy {policy} --out {tmp}/tradeoff --quick-check --pool {pool} --max-steps 3 "
        "--rows eot_envs",
        ("{tmp}/tradeoff/report.md", "{tmp}/tradeoff/rows.jsonl"),
        slow=True,
    ),
    "advobj bench tradeoff --policy runs/policy-quick --out runs/tradeoff --train-missing --plot "
    "docs/img/tradeoff_pareto.png": Tiny(
        "bench tradeoff --policy {policy} --out {tmp}/tradeoff-doc --quick-check --pool {pool} --max-steps 3 --rows "
        "deployment=onnx-fp32 "
        "--plot {tmp}/tradeoff-doc/pareto.png",
        ("{tmp}/tradeoff-doc/report.md", "{tmp}/tradeoff-doc/pareto.png"),
        slow=True,
        dropped={"--train-missing": "trains two quick-preset policies at 96 and 128 px (minutes each)"},
    ),
    # ---- calibration (workflow step 7 and calibration.md)
    **CALIB,
    # ---- real trials (the sim hardware config stands in for the cell)
    "advobj trial plan --shape cube --texture cube/adv3d=runs/attack-cube --texture cube/patch=runs/patch "
    "--out runs/plan.yaml --sheet runs/plan.pdf": Tiny(
        "trial plan --shape cube --texture cube/adv3d={attack_cube} --texture cube/patch={patch} --tcp-poses 1 "
        "--object-poses 1 "
        "--out {tmp}/trials/plan.yaml --sheet {tmp}/trials/plan.pdf",
        ("{tmp}/trials/plan.yaml", "{tmp}/trials/plan.pdf"),
    ),
    "advobj trial run --hardware my_cell.yaml --policy runs/policy-quick.onnx --plan runs/plan.yaml --session "
    "day1 --registry objects.yaml --db runs/trials.sqlite": Tiny(
        "trial run --hardware {root}/examples/hardware/sim.yaml --policy {onnx} --plan {plan} --session day1 "
        "--registry {root}/examples/calibration/objects.yaml --db {tmp}/trials/trials.sqlite --auto-confirm",
        ("{tmp}/trials/trials.sqlite",),
        expect="trials done",
    ),
    "advobj trial run --hardware my_cell.yaml --policy runs/policy-quick.onnx --plan runs/plan.yaml --session "
    "day1 --registry objects.yaml --view": Tiny(
        "trial run --hardware {root}/examples/hardware/sim.yaml --policy {onnx} --plan {plan} --session day1 "
        "--registry {root}/examples/calibration/objects.yaml --db {tmp}/trials/view.sqlite --auto-confirm --view "
        "--view-port 0",
        ("{tmp}/trials/view.sqlite",),
        expect="live view: http://127.0.0.1:",
    ),
    "advobj trial report --db runs/trials.sqlite --sim cube=runs/eval-cube --out runs/trial-report": Tiny(
        "trial report --db {trial_db} --sim cube={eval} --out {tmp}/trials/report",
        ("{tmp}/trials/report/report.md", "{tmp}/trials/report/report.json"),
    ),
    "advobj trial export --db runs/trials.sqlite --out runs/trial-tables --format csv": Tiny(
        "trial export --db {trial_db} --out {tmp}/trials/tables --format csv",
        ("{tmp}/trials/tables/trials.csv", "{tmp}/trials/tables/steps.csv"),
    ),
    # ---- recordings as input (workflow: "attack it on your recordings")
    "advobj record import --from session runs/trials.sqlite --session day1 --out runs/rec-day1": Tiny(
        "record import --from session {trial_db} --session day1 --out {tmp}/rec-day1",
        ("{tmp}/rec-day1/recording.json",),
        expect="recording:",
    ),
    "advobj record import --from lerobot datasets/my_so100 --pose-key observation.state --pose-layout xyz_rotvec "
    "--intrinsics wrist=wrist_cam.yaml --extrinsics wrist=T_tcp_cam.yaml --intrinsics front=front_cam.yaml "
    "--extrinsics front=T_table_cam.yaml --table-frame T_base_table.yaml --out runs/rec-so100": Tiny(
        "record import --from lerobot {tmp}/lerobot --pose-key observation.state --pose-layout xyz_rotvec "
        "--intrinsics wrist={tmp}/lerobot-cal/wrist_cam.yaml --extrinsics wrist={tmp}/lerobot-cal/T_tcp_cam.yaml "
        "--intrinsics front={tmp}/lerobot-cal/front_cam.yaml --extrinsics front={tmp}/lerobot-cal/T_table_cam.yaml "
        "--table-frame {tmp}/lerobot-cal/T_base_table.yaml --out {tmp}/rec-so100",
        ("{tmp}/rec-so100/recording.json",),
        expect="recording:",
        setup=_tiny_lerobot,
    ),
    "advobj record sim --policy runs/policy-quick --episodes 80 --out runs/rec-sim": Tiny(
        "record sim --policy {policy} --episodes 2 --max-steps 3 --out {tmp}/rec-sim",
        ("{tmp}/rec-sim/recording.json",),
        expect="recording: 2 episodes",
    ),
    # ---- hardware
    "advobj hw check --config examples/hardware/sim.yaml": Tiny(
        "hw check --config {root}/examples/hardware/sim.yaml --frames 2", expect="nothing moved"
    ),
    "advobj hw check --config examples/hardware/sim.yaml --jog --jog-mm 10": Tiny(
        "hw check --config {root}/examples/hardware/sim.yaml --frames 2 --jog --jog-mm 10", expect="back to"
    ),
}


def _tiny_params():
    seen, params = set(), []
    for c in DOC_COMMANDS:
        t = TINY.get(c.text)
        if c.text in seen or t is None or t.argv is None:
            continue
        seen.add(c.text)
        params.append(pytest.param(c, t, id=c.id, marks=[pytest.mark.slow] if t.slow else []))
    return params


@pytest.fixture(scope="module")
def art(tmp_path_factory):
    return Artifacts(tmp_path_factory.mktemp("docs"))


# ============================================================================ tests
def test_the_docs_have_commands_to_check():
    files = {c.file for c in DOC_COMMANDS}
    assert {"README.md", "docs/workflow.md", "docs/calibration.md", "docs/evaluation.md"} <= files
    assert any(c.text == "make demo" for c in DOC_COMMANDS) and any(
        c.text.startswith("advobj attack run") for c in DOC_COMMANDS
    )


def test_parser_reads_console_bash_and_plain_blocks(tmp_path):
    md = tmp_path / "x.md"
    md.write_text(
        "text\n```console\n$ advobj eval --policy p \\\n    --episodes 2   # note\nout line\n```\n"
        "```bash\nmake demo  # c\necho hi\n```\n```python\nadvobj = 1\n```\n```\nadvobj scene pool --n 3\n```\n"
    )
    cmds = parse_commands(md, root=tmp_path)
    assert [(c.line, c.text) for c in cmds] == [
        (3, "advobj eval --policy p --episodes 2"),
        (8, "make demo"),
        (15, "advobj scene pool --n 3"),
    ]


def test_every_documented_command_has_a_tiny_run():
    missing = sorted({f"{c.file}:{c.line}: {c.text}" for c in DOC_COMMANDS if c.text not in TINY})
    assert not missing, (
        "documented commands without an entry in TINY (tests/trials/cli/test_docs_commands.py); add a tiny-settings "
        "invocation for each:\n" + "\n".join(missing)
    )
    stale = sorted(set(TINY) - {c.text for c in DOC_COMMANDS})
    assert not stale, "TINY entries for commands no longer in the docs (remove them):\n" + "\n".join(stale)


@pytest.mark.parametrize("doc", [pytest.param(c, id=c.id) for c in DOC_COMMANDS])
def test_documented_command_exists_and_takes_its_options(doc):
    where = f"{doc.file}:{doc.line}"
    argv = doc.argv
    if argv[0] == "make":
        res = subprocess.run(["make", "-n", *argv[1:]], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert res.returncode == 0, f"{where}: 'make -n {' '.join(argv[1:])}' failed: {res.stderr}"
        for line in res.stdout.splitlines():
            toks = shlex.split(line)
            if toks and toks[0].endswith("/advobj"):
                check_advobj_line(toks, f"{where} (make recipe)")
        return
    check_advobj_line(argv, where)


@pytest.mark.parametrize("doc,tiny", _tiny_params())
def test_documented_command_runs_on_tiny_settings(doc, tiny, art, monkeypatch):
    cmd, path, rest = resolve(doc.argv[1:]) if doc.argv[0] == "advobj" else (None, None, None)
    argv = art.fmt(tiny.argv)
    tcmd, tpath, trest = resolve(argv)
    if cmd is not None:
        assert tpath == path, f"TINY entry for '{doc.text}' runs 'advobj {' '.join(tpath)}'"
        missing = (
            used_options(cmd, rest) - used_options(tcmd, trest) - {option_params(cmd).get(o, o) for o in tiny.dropped}
        )
        assert not missing, (
            f"TINY entry for '{doc.text}' leaves out documented options {sorted(missing)} (keep them or say why "
            "in dropped)"
        )
    if tiny.setup is not None:
        tiny.setup(monkeypatch, art)
    res = art.invoke(argv)
    for out in tiny.outputs:
        p = Path(out.format_map(art))
        assert p.exists(), f"'advobj {' '.join(argv)}' did not write {p}"
    assert tiny.expect in res.output, f"'advobj {' '.join(argv)}' printed no {tiny.expect!r}:\n{res.output[-2000:]}"


def test_workflow_python_block_attacks_a_wrapped_torch_model(art):
    """The 'bring your own torch model' snippet of docs/workflow.md, with a tiny network and budget."""
    import torch
    from torch import nn

    code = _workflow_block("class WhiteBox")
    out = art.tmp / "attack-mine"
    subs = {
        "image_size=128": "image_size=32",
        'resolve_config("quick", {"iterations": 300})': 'resolve_config("quick", TINY_OVERRIDES)',
        'load_scene("my_scene.yaml")': "load_scene(MY_SCENE)",
        '"runs/attack-mine"': repr(str(out)),
    }
    for old, new in subs.items():
        assert old in code, f"docs/workflow.md python block changed: {old!r} not found; update this test"
        code = code.replace(old, new)
    torch.manual_seed(0)
    import yaml

    ns = {
        "my_encoder": nn.Sequential(nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU()),
        "my_decoder": nn.Sequential(nn.Flatten(), nn.Linear(8 * 16 * 16, 6)),
        "TINY_OVERRIDES": yaml.safe_load(TINY_ATTACK),
        "MY_SCENE": str(art.my_scene),
        "__name__": "workflow_snippet",
    }
    exec(compile(code, "docs/workflow.md", "exec"), ns)
    for name in ("texture.png", "texture.npy", "adversarial.glb", "metrics.json", "run.json", "configs.json"):
        assert (out / name).is_file(), f"the workflow snippet did not write {name}"
    from trials.eval.conditions import load_attack_source

    assert load_attack_source(out).trained_on  # an 'advobj eval --attack' source with its configuration record


def _workflow_block(marker: str) -> str:
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "workflow.md").read_text(), re.S)
    found = [b for b in blocks if marker in b]
    assert len(found) == 1, f"docs/workflow.md should hold one python block with {marker!r}"
    return found[0]


def test_every_python_block_of_the_workflow_doc_is_run_by_a_test():
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "workflow.md").read_text(), re.S)
    run_here = ("class WhiteBox", 'load_scene("scenes/two-cameras.yaml")', "class LabPolicy")  # the tests' markers
    tested = [b for b in blocks if any(m in b for m in run_here)]
    assert len(tested) == len(blocks), "a python block of docs/workflow.md is run by no test"


def test_workflow_scene_cameras_snippet_runs(monkeypatch):
    code = _workflow_block('load_scene("scenes/two-cameras.yaml")')
    monkeypatch.chdir(ROOT)
    ns = {"__name__": "workflow_snippet"}
    exec(compile(code, "docs/workflow.md", "exec"), ns)
    env = ns["env"]
    try:
        assert set(env.images()) == {"wrist", "front"}
    finally:
        env.close()


def test_workflow_export_script_writes_a_two_input_chunked_onnx_policy_that_rolls_out(tmp_path):
    """The 'attack your own policy' export script of docs/workflow.md, at a smaller input size: the
    ONNX file rolls out on onnxruntime, and it and the .pt2 load white-box."""
    import numpy as np

    from sim.policies.contract import policy_contract
    from sim.policies.onnx_policy import OnnxPolicy
    from sim.policies.rollout import EnvConfig, make_env, run_episodes
    from sim.spec import default_scene

    code = _workflow_block("class LabPolicy")
    path, pt2 = tmp_path / "lab_policy.onnx", tmp_path / "lab_policy.pt2"
    for old, new in {
        "S, K = 96, 8": "S, K = 32, 8",
        '"lab_policy.onnx"': repr(str(path)),
        '"lab_policy.pt2"': repr(str(pt2)),
    }.items():
        assert old in code, f"docs/workflow.md export script changed: {old!r} not found; update this test"
        code = code.replace(old, new)
    exec(compile(code, "docs/workflow.md", "exec"), {"__name__": "workflow_export"})
    policy = OnnxPolicy(path)
    c = policy_contract(policy)
    assert (c.state, c.action.kind, c.action.chunk, c.action.execute) == (("tcp_pose", "gripper"), "absolute_tcp", 8, 4)
    spec = default_scene()
    spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": 5})
    env = make_env(spec, EnvConfig(image_size=32), num_envs=2)
    try:
        res = run_episodes(env, policy, [0, 1])
    finally:
        env.close()
    assert (res.steps >= 1).all() and np.isfinite(res.min_goal_dist).all()
    # both files load white-box with the card's contract, and compute the same policy
    from sim.policies.checkpoint import load_policy

    images = np.random.default_rng(0).integers(0, 256, (2, 32, 32, 3), dtype=np.uint8)
    state = np.zeros((2, 7), np.float32)
    ref = policy.act(images, state)
    for f in (path, pt2):
        white = load_policy(f, white_box=True)
        assert white.white_box and policy_contract(white) == c
        np.testing.assert_allclose(white.act(images, state), ref, atol=1e-4)


def _anchors(path: Path) -> set[str]:
    """GitHub's heading anchors of a markdown file (lower case, punctuation dropped, spaces -> '-')."""
    out, fenced = set(), False
    for line in path.read_text().splitlines():
        if line.strip().startswith("```"):
            fenced = not fenced
            continue
        m = None if fenced else re.match(r"^#{1,6}\s+(.*)", line)
        if m:
            out.add("".join(c for c in m.group(1).strip().lower().replace(" ", "-") if c.isalnum() or c in "-_"))
    return out


def test_local_links_and_anchors_resolve():
    broken = []
    for f in DOC_FILES:
        for m in re.finditer(r"\]\(([^)\s]+)\)", f.read_text()):
            link = m.group(1)
            if re.match(r"^[a-z]+:", link):
                continue
            path, _, frag = link.partition("#")
            target = (f.parent / path).resolve() if path else f
            if not target.exists():
                broken.append(f"{f.relative_to(ROOT)}: {link} (no such file)")
            elif frag and target.suffix == ".md" and frag not in _anchors(target):
                broken.append(f"{f.relative_to(ROOT)}: {link} (no heading with that anchor)")
    assert not broken, "broken links in the docs:\n" + "\n".join(broken)


# ============================================================================ benchmark scripts named in the docs
_VAR = re.compile(r'^([A-Z_]+)="(.*)"$')


def benchmark_lines(path: Path) -> list[tuple[int, list[str]]]:
    """``(line, argv)`` of every ``python benchmarks/...`` line in a shell block of ``path``.

    ``NAME="python benchmarks/x.py ..."`` assignments are expanded where a later line of the same
    block starts with ``$NAME``.
    """
    out, lang, env, pending, start = [], None, {}, "", 0
    for no, raw in enumerate(path.read_text().splitlines(), 1):
        if _FENCE.match(raw):
            lang, env = (None, {}) if lang is not None else ((_FENCE.match(raw).group(1) or "").lower(), {})
            continue
        if lang not in ("bash", "sh", "shell", "console", ""):
            continue
        line = raw.strip().removeprefix("$ ")
        if not pending:
            start = no
        line = (pending + " " + line).strip()
        if line.endswith("\\"):
            pending = line[:-1]
            continue
        pending = ""
        if not line.startswith(("python", "$")) and not _VAR.match(line):
            continue
        m = _VAR.match(line)
        if m:
            env[m.group(1)] = m.group(2)
            continue
        head = line.split(" ", 1)[0]
        if head.startswith("$") and head[1:] in env:
            line = env[head[1:]] + line[len(head) :]
        tokens = shlex.split(line, comments=True)
        if len(tokens) >= 2 and tokens[0] in ("python", "python3") and tokens[1].startswith("benchmarks/"):
            out.append((start, tokens[1:]))
    return out


BENCH_LINES = [(f.relative_to(ROOT).as_posix(), no, argv) for f in DOC_FILES for no, argv in benchmark_lines(f)]


def test_the_docs_name_benchmark_commands_to_check():
    assert any(argv[0] == "benchmarks/bench_tradeoff.py" for _, _, argv in BENCH_LINES)


@pytest.mark.parametrize(
    "where,argv", [(f"{f}:{no}", argv) for f, no, argv in BENCH_LINES], ids=[f"{f}:{no}" for f, no, _ in BENCH_LINES]
)
def test_documented_benchmark_command_exists_and_takes_its_options(where, argv, _bench_help={}):
    import sys

    script = ROOT / argv[0]
    assert script.is_file(), f"{where}: {argv[0]} does not exist"
    if argv[0] not in _bench_help:  # one --help per script
        r = subprocess.run(
            [sys.executable, str(script), "--help"], capture_output=True, text=True, cwd=ROOT, timeout=120
        )
        assert r.returncode == 0, f"{where}: {argv[0]} --help failed: {r.stderr[-500:]}"
        _bench_help[argv[0]] = set(re.findall(r"(--[\w-]+)", r.stdout))
    unknown = {t.split("=", 1)[0] for t in argv[1:] if t.startswith("--")} - _bench_help[argv[0]]
    assert not unknown, f"{where}: {argv[0]} has no option(s) {sorted(unknown)}"
