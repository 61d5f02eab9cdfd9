"""Evaluation conditions: one CLI name each, built from an explicit name -> builder table.

A :class:`Condition` says how the adversarial object looks (benign, or an attack texture on a
given mesh), how the scene is observed (appearance randomisation, stereo) and, for a policy
reading several cameras, which of them show the texture (``attack``: all; ``attack_wrist_only``,
``attack_<camera>_only``: one, the others seeing the benign look). Every condition is
evaluated on the same task-feasible initial configurations (paired design), with the standard
pyrender renderer; the differentiable composite is never used.

Textures come from attack run directories (``advobj attack run``): ``texture.npy`` (H, W, 3)
float32 in [0, 1] and ``run.json`` whose ``config.attack.adversarial_mesh`` names the mesh the
texture was optimised on (``None`` = the scene's own adversarial mesh). Every arm built from
``--attack`` shows that mesh; only ``clean`` shows the scene's own object.

The controls: ``clean`` is the scene as it is; ``benign`` is the attacked mesh with the attack's
own unoptimised start texture (:func:`attack.optimize.initial_texture`, what the attack showed at
iteration 0), so ``attack`` vs ``benign`` isolates what the optimisation added, and ``attack`` vs
``clean`` also holds any change of shape.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from pydantic import ValidationError

from attack.artifact import RUN_JSON, AttackArtifact, texture_to_uint8
from sim.assets import build_mesh
from sim.errors import AdvobjError, format_validation_error
from sim.spec import default_scene
from sim.variations import Randomization

__all__ = [
    "ConditionError",
    "Condition",
    "AttackSource",
    "Sources",
    "CONDITIONS",
    "CAMERA_ONLY",
    "SHAPES",
    "NOISE_STD",
    "STEREO_BASELINE_M",
    "load_attack_source",
    "start_source",
    "with_benign",
    "build_conditions",
    "condition_spec",
]

# "Add Noise": Gaussian sensor noise, std as a fraction of full scale (0.03 = 7.7/255).
NOISE_STD = 0.03
# Stereo baseline used when the scene spec has none (m): a typical wrist stereo module.
STEREO_BASELINE_M = 0.06
SHAPES = ("dog", "duck", "cube", "cylinder")


class ConditionError(AdvobjError, ValueError):
    """An unknown condition, or a condition whose texture source is missing or malformed."""


@dataclass(frozen=True)
class AttackSource:
    """A texture from an attack run directory and the mesh it was optimised on."""

    path: str
    texture: np.ndarray = field(repr=False, compare=False)  # (H, W, 3) uint8
    mesh: str | None  # None = the scene's adversarial mesh
    sha256: str  # of texture.npy: guards resuming with a changed texture
    # Ids of the configurations the texture was optimised or selected on (attack/outputs.py's
    # configs.json); None when the directory has no record (then no overlap can be proven 0).
    trained_on: frozenset | None = field(default=None, repr=False, compare=False)
    # Set for the run's unoptimised start texture (the benign arm): the init_texture it was made
    # with. Dumped only when set, so every other source dumps (and hashes) as before.
    start: str | None = None

    def to_dict(self) -> dict:
        return {
            "path": self.path,
            "mesh": self.mesh,
            "sha256": self.sha256,
            "configs_recorded": self.trained_on is not None,
            **({} if self.start is None else {"start_texture": self.start}),
        }


@dataclass(frozen=True)
class Condition:
    """How one evaluation arm renders the adversarial object and observes the scene.

    ``texture=None`` is the benign look (the clean control). ``stereo``: the policy sees the
    left and right cameras and the two actions are averaged (see ``docs/evaluation.md``).
    """

    name: str
    source: AttackSource | None = None
    randomization: Randomization = Randomization()
    stereo: bool = False
    # Which cameras show the attack texture (None: every camera the policy reads); the others show
    # the benign look. "attack_wrist_only" and "attack_<camera>_only" say which camera carries it.
    attacked_cameras: tuple[str, ...] | None = None

    @property
    def texture(self) -> np.ndarray | None:
        return None if self.source is None else self.source.texture

    @property
    def mesh(self) -> str | None:
        return None if self.source is None else self.source.mesh

    def to_dict(self) -> dict:
        r = self.randomization
        return {
            "name": self.name,
            "source": None if self.source is None else self.source.to_dict(),
            "randomization": {"light": r.light, "background": r.background, "noise_std": r.noise_std},
            "stereo": self.stereo,
            # only when set: the conditions before it dump (and hash) as they did
            **({} if self.attacked_cameras is None else {"attacked_cameras": list(self.attacked_cameras)}),
        }


def load_attack_source(path: str | Path) -> AttackSource:
    """An attack run directory's texture and mesh (:class:`attack.artifact.AttackArtifact`; clear errors if not)."""
    art = AttackArtifact.load(path, error=ConditionError)
    return AttackSource(str(art.path), art.texture_u8, art.mesh, art.sha256, art.trained_on)


def start_source(path: str | Path, spec) -> AttackSource:
    """The unoptimised start texture of the attack run in ``path``, on the mesh it was optimised on.

    The texture is :func:`attack.optimize.initial_texture` of the run's recorded ``init_texture``,
    ``texture_size`` and ``seed`` (run.json's ``config.attack``; a field it lacks takes the
    AttackConfig default) on the run's mesh in ``spec`` (the scene's adversarial object, its mesh
    swapped for the run's ``adversarial_mesh`` as :func:`condition_spec` does), rounded to 8 bits
    as every texture is shown: the look the attack started from and validated at iteration 0. No
    configuration goes into it, so its overlap with any evaluation is 0.
    """
    # Imported here: advobj trial plan and fabricate import this module and need no torch.
    from attack.optimize import AttackConfig, initial_texture  # lazy: CLI start-up (torch)

    art = AttackArtifact.load(path, error=ConditionError)
    fields = {k: art.attack_config[k] for k in ("init_texture", "texture_size", "seed") if k in art.attack_config}
    try:
        cfg = AttackConfig(**fields)
    except ValidationError as err:
        raise ConditionError(format_validation_error(err, "attack config", str(art.path / RUN_JSON))) from None
    src = AttackSource(str(art.path), art.texture_u8, art.mesh, art.sha256)
    spec_c = condition_spec(spec, Condition("benign", src))
    obj = spec_c.objects[spec_c.object_index("adversarial")]
    texture = texture_to_uint8(initial_texture(cfg, build_mesh(obj.mesh, obj.scale, **obj.mesh_kwargs())))
    sha = hashlib.sha256(texture.tobytes()).hexdigest()
    return AttackSource(str(art.path), texture, art.mesh, sha, frozenset(), start=cfg.init_texture)


@dataclass(frozen=True)
class Sources:
    """Attack run directories available to the builders (CLI: --attack, --patch, --shape NAME=DIR),
    and the scene evaluated (None: the built-in scene), on which the benign arm's start texture is
    made."""

    attack: str | None = None
    patch: str | None = None
    shapes: dict = field(default_factory=dict)
    scene: object = None


def _given(path: str | None, option: str, cond: str) -> str:
    if path is None:
        raise ConditionError(f"condition {cond!r} needs an attack run directory: pass {option}")
    return path


def _need(path: str | None, option: str, cond: str) -> AttackSource:
    return load_attack_source(_given(path, option, cond))


def _clean(s: Sources) -> Condition:
    return Condition("clean")


def _attack(s: Sources) -> Condition:
    return Condition("attack", _need(s.attack, "--attack DIR", "attack"))


def _benign(s: Sources) -> Condition:
    path = _given(s.attack, "--attack DIR", "benign")
    return Condition("benign", start_source(path, s.scene if s.scene is not None else default_scene()))


def _patch(s: Sources) -> Condition:
    src = _need(s.patch, "--patch DIR", "patch")
    if src.mesh != "patch":
        raise ConditionError(
            f"{src.path}: condition 'patch' needs a run with adversarial_mesh 'patch', this one used {src.mesh!r}"
        )
    return Condition("patch", src)


def _variation(name: str, **kw) -> Callable[[Sources], Condition]:
    def build(s: Sources) -> Condition:
        return Condition(name, _need(s.attack, "--attack DIR", name), Randomization(**kw))

    return build


def _stereo(s: Sources) -> Condition:
    return Condition("stereo", _need(s.attack, "--attack DIR", "stereo"), stereo=True)


def _camera_only(camera: str) -> Callable[[Sources], Condition]:
    """The attack texture in camera ``camera``'s view only (the other cameras see the benign look)."""
    name = f"attack_{camera}_only"

    def build(s: Sources) -> Condition:
        return Condition(name, _need(s.attack, "--attack DIR", name), attacked_cameras=(camera,))

    return build


CAMERA_ONLY = re.compile(r"^attack_([A-Za-z0-9][A-Za-z0-9_-]*)_only$")


def _shape(shape: str) -> Callable[[Sources], Condition]:
    def build(s: Sources) -> Condition:
        src = _need(s.shapes.get(shape), f"--shape {shape}=DIR", f"shape_{shape}")
        if src.mesh != shape:
            raise ConditionError(
                f"{src.path}: condition 'shape_{shape}' needs a run with adversarial_mesh {shape!r}, this one used "
                f"{src.mesh!r}"
            )
        return Condition(f"shape_{shape}", src)

    return build


CONDITIONS: dict[str, Callable[[Sources], Condition]] = {
    "clean": _clean,
    # The attacked mesh with the attack's unoptimised start texture: the control of "attack".
    "benign": _benign,
    "attack": _attack,
    "patch": _patch,
    "light_bright": _variation("light_bright", light="bright"),
    "light_dim": _variation("light_dim", light="dim"),
    # Held-out light levels: a random light per episode (intensity, direction, ambient, tint), drawn
    # from the configuration's seed, so never one the attack's lighting randomisation trained on.
    "light_random": _variation("light_random", light="random"),
    "noise": _variation("noise", noise_std=NOISE_STD),
    "bkg_varied": _variation("bkg_varied", background="varied"),
    "stereo": _stereo,
    **{f"shape_{s}": _shape(s) for s in SHAPES},
    # Which camera carries the attack (policies reading several cameras): "attack" shows the texture
    # to every camera; these to the wrist camera only, and attack_<camera>_only to one scene camera.
    "attack_wrist_only": _camera_only("wrist"),
}


def with_benign(names) -> list[str]:
    """``names`` with ``benign`` put before ``attack`` when ``attack`` is asked for without it:
    ``advobj eval`` always runs the control its headline compares the attack with."""
    names = list(names)
    if "attack" in names and "benign" not in names:
        names.insert(names.index("attack"), "benign")
    return names


def build_conditions(names, sources: Sources) -> list[Condition]:
    """Conditions for ``names`` (``clean`` always first, duplicates dropped)."""
    ordered = ["clean"] + [n for n in names if n != "clean"]
    seen, out = set(), []
    for n in ordered:
        if n in seen:
            continue
        m = CAMERA_ONLY.match(n)
        if n not in CONDITIONS and m is None:
            raise ConditionError(
                f"conditions: unknown condition {n!r}; choose from {', '.join(CONDITIONS)}, attack_<camera>_only"
            )
        seen.add(n)
        out.append(CONDITIONS[n](sources) if n in CONDITIONS else _camera_only(m.group(1))(sources))
    return out


def condition_spec(spec, cond: Condition):
    """The scene a condition is rendered in: its mesh swapped in, a stereo baseline if needed.

    The mesh swap is the one :class:`attack.optimize.AttackRun` makes (same object, same pose,
    other mesh, its own default look), so the texture lands on the UVs it was optimised for.
    """
    updates = {}
    if cond.mesh is not None:
        updates["objects"] = [
            o.with_mesh(cond.mesh) if o.role == "adversarial" else o.model_dump() for o in spec.objects
        ]
    if cond.stereo and spec.camera.stereo_baseline_m <= 0:
        updates["camera"] = {**spec.camera.model_dump(), "stereo_baseline_m": STEREO_BASELINE_M}
    return spec.with_updates(**updates) if updates else spec
