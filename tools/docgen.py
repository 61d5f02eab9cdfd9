"""Render ``docs/configuration.md`` from the pydantic models, so the reference cannot drift.

Every table row comes from the model itself: the field's type, default, constraints
(``ge``/``gt``/``le``/``lt``/lengths/pattern) and description. A field without a ``description``
borrows the ``#`` comment written on or right above it in the model's source.

Regenerate with::

    python -m tools.docgen --write            # rewrites docs/configuration.md
    python -m tools.docgen --check            # exit 1 if docs/configuration.md is stale
    python -m tools.docgen > some/file.md     # print to stdout

``tests/tools/test_docgen.py`` fails when the committed file differs from the output.
"""

from __future__ import annotations

import argparse
import ast
import inspect
import io
import json
import re
import sys
import textwrap
import tokenize
import types
import typing
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Callable, Iterable

import annotated_types as at
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from attack.optimize import PRESETS as ATTACK_PRESETS
from attack.optimize import AttackConfig
from calibration.handeye import HandEyeSamplesFile, _HandEyeFile
from calibration.intrinsics import BoardSpec, _CameraFile
from calibration.registry import ObjectRegistry
from robot_io.config import HardwareConfig
from sim.policies.card import PolicyCard
from sim.policies.presets import PRESETS as POLICY_PRESETS
from sim.policies.presets import TrainConfig
from sim.spec import SceneSpec
from trials.eval.evaluate import EvalConfig
from trials.real.plan import TrialPlan

__all__ = ["Section", "sections", "render", "model_rows", "DEFAULT_PATH", "main"]

DEFAULT_PATH = Path("docs/configuration.md")
REGENERATE = "python -m tools.docgen --write"


# ---------------------------------------------------------------------------------------------
# Types, defaults, constraints


def _constraint_text(meta: Iterable[Any]) -> list[str]:
    out = []
    for m in meta:
        if isinstance(m, at.Gt):
            out.append(f"> {m.gt}")
        elif isinstance(m, at.Ge):
            out.append(f">= {m.ge}")
        elif isinstance(m, at.Lt):
            out.append(f"< {m.lt}")
        elif isinstance(m, at.Le):
            out.append(f"<= {m.le}")
        elif isinstance(m, at.MinLen):
            out.append(f"len >= {m.min_length}")
        elif isinstance(m, at.MaxLen):
            out.append(f"len <= {m.max_length}")
        elif isinstance(m, at.MultipleOf):
            out.append(f"multiple of {m.multiple_of}")
        elif isinstance(m, FieldInfo):
            out.extend(_constraint_text(m.metadata))
        else:
            pattern = getattr(m, "pattern", None)
            if isinstance(pattern, str):
                out.append(f"matches `{pattern}`")
            if getattr(m, "allow_inf_nan", None) is False:
                out.append("finite")
    return out


def type_name(tp: Any) -> str:
    """A short, YAML-user-facing spelling of annotation ``tp`` (inner constraints inline)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Annotated:
        inner, *meta = args
        cons = _constraint_text(meta)
        base = type_name(inner)
        return f"{base} ({', '.join(cons)})" if cons else base
    if origin is typing.Literal:
        return " | ".join(json.dumps(a.value if isinstance(a, Enum) else a) for a in args)
    if origin in (typing.Union, types.UnionType):
        parts = [type_name(a) for a in args if a is not type(None)]
        if type(None) in args:
            parts.append("null")
        return " | ".join(parts)
    if origin in (list, tuple, set, frozenset, dict):
        name = {list: "list", tuple: "tuple", set: "set", frozenset: "set", dict: "dict"}[origin]
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return f"list[{type_name(args[0])}]"
        return f"{name}[{', '.join(type_name(a) for a in args)}]"
    if tp is type(None):
        return "null"
    if inspect.isclass(tp) and issubclass(tp, BaseModel):
        return f"[{_display(tp)}](#{_anchor(tp)})"
    if inspect.isclass(tp) and issubclass(tp, Path):
        return "path"
    if isinstance(tp, type):
        return {"str": "str", "int": "int", "float": "float", "bool": "bool"}.get(tp.__name__, tp.__name__)
    return str(tp).replace("typing.", "")


def _plain(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def default_text(info: FieldInfo) -> str:
    if info.default_factory is not None:
        value = info.default_factory()
    elif info.default is PydanticUndefined:
        return "**required**"
    else:
        value = info.default
    if isinstance(value, BaseModel):
        return "(its defaults)"
    text = json.dumps(_plain(value))
    if isinstance(value, float) and not isinstance(value, bool):
        text = repr(value)
    return f"`{text}`"


# ---------------------------------------------------------------------------------------------
# Comments in the model source stand in for missing descriptions


def _source_comments(cls: type) -> dict[str, str]:
    """``{field: comment}`` from ``# ...`` lines right above a field or at the end of its line."""
    try:
        src = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    comments: dict[int, tuple[str, bool]] = {}  # line -> (text, whole-line comment)
    lines = src.splitlines()
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            row, col = tok.start
            whole = not lines[row - 1][:col].strip()
            comments[row] = (tok.string.lstrip("#").strip(), whole)
    tree = ast.parse(src)
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    out = {}
    for node in body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        parts = []
        row = node.lineno - 1
        above = []
        while row in comments and comments[row][1]:
            above.insert(0, comments[row][0])
            row -= 1
        parts.extend(above)
        for r in range(node.lineno, (node.end_lineno or node.lineno) + 1):
            if r in comments and not comments[r][1]:
                parts.append(comments[r][0])
        text = " ".join(p for p in parts if p and not p.startswith("type:") and not p.startswith("noqa"))
        if text:
            out[node.target.id] = text
    return out


def _comments(model: type[BaseModel]) -> dict[str, str]:
    out: dict[str, str] = {}
    for cls in reversed(model.__mro__):
        if inspect.isclass(cls) and issubclass(cls, BaseModel) and cls is not BaseModel:
            out.update(_source_comments(cls))
    return out


# ---------------------------------------------------------------------------------------------
# Models -> tables


def _display(model: type) -> str:
    return model.__name__.lstrip("_")


def _anchor(model: type) -> str:
    return _display(model).lower()


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _nested_models(tp: Any) -> list[type[BaseModel]]:
    if inspect.isclass(tp) and issubclass(tp, BaseModel):
        return [tp]
    found = []
    for a in typing.get_args(tp):
        for m in _nested_models(a):
            if m not in found:
                found.append(m)
    return found


def model_rows(model: type[BaseModel]) -> list[tuple[str, str, str, str, str]]:
    """``(field, type, default, constraint, description)`` per field of ``model``."""
    comments = _comments(model)
    rows = []
    for name, info in model.model_fields.items():
        key = info.alias or name
        cons = ", ".join(_constraint_text(info.metadata))
        desc = info.description or comments.get(name, "") or FIELD_NOTES.get(model.__name__, {}).get(name, "")
        rows.append((f"`{key}`", type_name(info.annotation), default_text(info), cons, desc))
    return rows


# Intros for models whose class has no docstring (file schemas kept private in their modules).
MODEL_NOTES = {
    "_CameraFile": "`cam.yaml`: intrinsics written by `advobj calibrate intrinsics` (OpenCV pinhole; `dist` = k1 "
    "k2 p1 p2 k3).",
    "_HandEyeFile": "`T_tcp_cam.yaml`: written by `advobj calibrate handeye`; the hardware config's "
    "`T_tcp_cam` reads it "
    "(a bare `{translation_m, rotvec_rad}` mapping is accepted too).",
    "TagEntry": "One registered tag: the object it sits on, its printed size and its pose relative to the object.",
    "HardwareConfig": "The hardware YAML (`--config` of `advobj hw check`).",
}


# Descriptions for fields whose model gives none (a note for a field that does not exist fails the test).
FIELD_NOTES = {
    "AttackConfig": {
        "iterations": "optimisation steps (one EOT batch each)",
        "rollout_steps": "policy steps per rollout; each step's view is one image-action pair",
        "lambda_dist": "weight of the distance term in L_pose = L_ori + lambda_dist * L_dist",
        "lambda_sal": "weight of the saliency term (Grad-CAM attention on the goal)",
        "loss": "targeted: pull the policy toward the adversarial object; untargeted: push its action away from "
        "the clean one",
        "use_pose": "include the pose loss (ablation switch)",
        "use_saliency": "include the saliency loss (ablation switch)",
        "pcgrad": "combine the pose and saliency gradients with PCGrad",
        "schedule": "camera-distance curriculum: c2f (coarse to fine), f2c, ns (no schedule), or a single stage",
        "sampler": "texture sampler of the differentiable renderer (trilinear = mip-mapped)",
        "texture_size": "side of the optimised texture, px",
        "init_texture": "starting texture: the object's own look, flat grey, or noise",
        "light_randomization": "randomise the lights during optimisation (EOT over lighting)",
        "print_aware": "EOT over print colour shifts: a random per-channel gain (0.85-1.15) and bias (+-0.05) "
        "each iteration",
        "checkpoint_every": "iterations between resumable checkpoints",
        "seed": "seeds the configuration draws and every RNG of the run",
        "device": "torch device (cpu, cuda)",
    },
    "SafetyLimits": {
        "workspace_min_m": "lower corner of the box (base frame) the TCP must stay in",
        "workspace_max_m": "upper corner of that box; policy steps are clipped into it, positioning moves outside "
        "it refused",
        "max_step_m": "translation per control step, cap",
        "max_step_rad": "rotation per control step, cap",
        "max_speed_mps": "translation speed cap; step cap = min(max_step_m, max_speed_mps * control_period_s)",
        "max_speed_radps": "rotation speed cap",
        "max_accel_mps2": "soft cap on the change of the step between consecutive steps",
        "control_period_s": "the control-loop period actually achieved; the speed caps assume it",
        "max_frame_age_ms": "a step computed from an older camera frame is refused and the arm stops",
        "max_trial_s": "a trial running longer stops the arm",
        "positioning_speed_mps": "default speed of positioning moves (homing, hw check --jog); <= max_speed_mps",
        "joints": "the joint path's limits (joint commands to an arm a URDF describes)",
    },
}


def _doc(model: type) -> str:
    doc = model.__dict__.get("__doc__")
    if not doc:
        return MODEL_NOTES.get(model.__name__, "")
    return re.sub(r":\w+:`([^`]+)`", r"`\1`", inspect.cleandoc(doc))


def render_model(model: type[BaseModel]) -> str:
    out = [f"### {_display(model)}", ""]
    doc = _doc(model)
    if doc:
        out += [" ".join(doc.split("\n\n")[0].split()).replace("``", "`"), ""]
    extra = model.model_config.get("extra")
    if extra == "forbid":
        out += ["Unknown keys are errors.", ""]
    out += ["| field | type | default | constraint | description |", "|---|---|---|---|---|"]
    for row in model_rows(model):
        out.append("| " + " | ".join(_cell(c) for c in row) + " |")
    return "\n".join(out) + "\n"


def walk_models(roots: Iterable[type[BaseModel]]) -> list[type[BaseModel]]:
    """``roots`` and every model reachable through their fields, depth first, each once."""
    seen: list[type[BaseModel]] = []

    def visit(m):
        if m in seen:
            return
        seen.append(m)
        for info in m.model_fields.values():
            for sub in _nested_models(info.annotation):
                visit(sub)

    for r in roots:
        visit(r)
    return seen


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def presets_table(presets: dict[str, dict]) -> str:
    """One row per field any preset sets, one column per preset (blank: the model default)."""
    flat = {name: _flatten(p) for name, p in presets.items()}
    keys: list[str] = []
    for f in flat.values():
        keys += [k for k in f if k not in keys]
    head = "| field | " + " | ".join(f"`{n}`" for n in flat) + " |"
    out = [head, "|---|" + "---|" * len(flat)]
    for k in keys:
        cells = [f"`{json.dumps(_plain(f[k]))}`" if k in f else "" for f in flat.values()]
        out.append(f"| `{k}` | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------------
# The document


@dataclass
class Section:
    title: str
    intro: str
    roots: Callable[[], list[type[BaseModel]]]
    extra: Callable[[], str] = field(default=lambda: "")


def _scene():
    return [SceneSpec]


def _attack():
    return [AttackConfig]


def _attack_presets():
    return "Presets (`--preset`); a `--config` YAML overrides single fields on top:\n\n" + presets_table(ATTACK_PRESETS)


def _eval():
    return [EvalConfig]


def _policy():
    return [PolicyCard, TrainConfig]


def _policy_presets():
    return "Training presets (`advobj policy train --preset`); blank: the model default:\n\n" + presets_table(
        POLICY_PRESETS
    )


def _hardware():
    return [HardwareConfig]


def _calibration():
    return [BoardSpec, _CameraFile, ObjectRegistry, HandEyeSamplesFile, _HandEyeFile]


def _plan():
    return [TrialPlan]


SECTIONS: list[Section] = [
    Section(
        "Scene (`--scene scene.yaml`)",
        "The reach scene: table, lights, objects (goal, adversarial object, distractors), wrist camera, "
        "gripper, episode and initial-configuration sampling. Every command that takes `--scene` reads this; "
        "the built-in scene is `sim/data/default_scene.yaml`. `mesh` is a built-in name (`tomato_soup_can`, "
        "`mustard_bottle`, `cube`, `cylinder`, `duck`, `dog`, `patch`) or a mesh file path, relative to the "
        "scene file. Loaded by `sim.spec.load_scene`.",
        _scene,
    ),
    Section(
        "Attack (`advobj attack run --preset P --config attack.yaml`)",
        "All knobs of one attack run. The YAML holds only the fields you change; they override the preset's. "
        "The resolved config is stored in the run's `run.json`.",
        _attack,
        _attack_presets,
    ),
    Section(
        "Evaluation (`advobj eval`, stored as `manifest.json`)",
        "Set from `advobj eval`'s options and stored in the evaluation directory's `manifest.json`; "
        "`--resume` refuses a directory whose manifest differs.",
        _eval,
    ),
    Section(
        "Policy checkpoint (`policy.json`) and training",
        "A checkpoint is a directory with `weights.safetensors` and the card `policy.json` "
        "(see [workflow.md](workflow.md#2-attack-your-own-policy)). `training` holds the resolved `TrainConfig` "
        "of `advobj policy train`.",
        _policy,
        _policy_presets,
    ),
    Section(
        "Hardware (`advobj hw check --config hw.yaml`)",
        "Wrist camera, arm, safety limits and, for `sim` devices, the simulated world. `camera` and `arm` pick "
        "their variant by `type`. Relative paths are relative to the YAML. Examples: `examples/hardware/`. "
        "What the safety limits do: [safety.md](safety.md). An arm's `kinematics` (its URDF) gives it joint "
        "commands; the servo-bus arms (`feetech`: SO-100/SO-101, `dynamixel`: Koch) need it: where their URDFs "
        "come from and how to fill `joints` from LeRobot's calibration is in "
        "[real-trials.md](real-trials.md#lerobot-arms-so-100so-101-koch).",
        _hardware,
    ),
    Section(
        "Calibration files",
        "`board.yaml` (from `advobj calibrate board`, read by `intrinsics --board` and hand-eye samples), "
        "the camera file `cam.yaml` (from `calibrate intrinsics`), the object registry `objects.yaml` "
        "(`calibrate detect --registry`), hand-eye samples (`calibrate handeye SAMPLES`) and the hand-eye "
        "result `T_tcp_cam.yaml` (the hardware config's `T_tcp_cam`). Examples: `examples/calibration/`; "
        "method: [calibration.md](calibration.md).",
        _calibration,
    ),
    Section(
        "Real-trial plan (`advobj trial plan --out plan.yaml`)",
        "Written by `advobj trial plan` and read by the other `advobj trial` commands: the randomized design "
        "(every TCP pose x object layout per environment, shape and condition), the poses in the table frame, "
        "the attack textures with their SHA-256, and the trial order. Generated, not hand-written; how to run "
        "it: [real-trials.md](real-trials.md).",
        _plan,
    ),
]


def sections() -> list[Section]:
    return list(SECTIONS)


HEADER = """\
<!-- Generated by `python -m tools.docgen --write` from the pydantic models; do not edit by hand.
     tests/tools/test_docgen.py fails when this file is stale. -->
# Configuration reference

Every YAML/JSON file advobj reads is validated by a pydantic model: unknown keys are errors, and
an error names the file and the dotted field (`objects.1.pose.yaw_deg: ...`). This page is
generated from those models, so it lists exactly what the code accepts. Units are in the field
names (`_m` metres, `_rad` radians, `_deg` degrees, `_s` seconds, `_px` pixels). In the tables, `null`
means the YAML `null` (or leaving the field out where that is the default).
"""


def render() -> str:
    out = [HEADER]
    out.append("## Contents\n")
    for s in SECTIONS:
        anchor = "".join(c for c in s.title.lower().replace(" ", "-") if c.isalnum() or c in "-_")
        out.append(f"- [{s.title}](#{anchor})")
    out.append("")
    rendered: set = set()
    for s in SECTIONS:
        out.append(f"## {s.title}\n")
        out.append(" ".join(s.intro.split()) + "\n")
        for m in walk_models(s.roots()):
            if m in rendered:
                continue
            rendered.add(m)
            out.append(render_model(m))
        extra = s.extra()
        if extra:
            out.append(extra)
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tools.docgen", description="Render docs/configuration.md from the pydantic models."
    )
    group = ap.add_mutually_exclusive_group()
    group.add_argument("--write", action="store_true", help="write PATH")
    group.add_argument("--check", action="store_true", help="exit 1 if PATH differs from the generated text")
    ap.add_argument("path", nargs="?", type=Path, default=DEFAULT_PATH, help="default: docs/configuration.md")
    args = ap.parse_args(argv)
    text = render()
    if args.write:
        args.path.write_text(text)
        print(f"wrote {args.path}", file=sys.stderr)
        return 0
    if args.check:
        current = args.path.read_text() if args.path.is_file() else ""
        if current != text:
            print(f"{args.path} is stale; regenerate with: {REGENERATE}", file=sys.stderr)
            return 1
        return 0
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
