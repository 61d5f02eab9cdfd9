"""``advobj record sim``: clean episodes of a policy in the simulator, written as a recording.

The simulator stands in for a real cell: the policy runs closed loop (:func:`sim.policies.rollout.rollout`,
the one rollout loop, in a :class:`sim.env.ReachEnv`) from configurations of the split's ``attack``
part, and every frame it acts on is written with the TCP pose it was taken at, in the format a
real cell's recordings are imported into (:func:`sim.recording.write_recording`). The adversarial
object is hidden in every camera: a lab's recordings show its cell as it is, never the object the
attack will add (:mod:`attack.recorded` composites it into the frames).

* **Cameras** (:func:`scene_cameras`): the ones the policy reads, each with what the simulator
  knows of it: the intrinsics it renders with (the wrist camera's at the policy's input size, no
  lens distortion) and its mount, the wrist camera on the TCP at the scene's ``T_tcp_cam``, a
  scene camera fixed at its ``T_table_cam``. The table frame is the simulator's world frame, so
  ``T_table_base`` is the identity.
* **Steps**: step ``k`` of an episode holds the frames the policy acted on at step ``k`` and the
  TCP pose they were rendered from, at ``k`` times :data:`STEP_S`: the simulator has no clock,
  and frames and poses are simultaneous (a sync tolerance of 0).
* **Configurations** (:func:`attack_configs`): the first ``episodes`` seeds of the ``attack`` part
  (:func:`sim.configs.config_part`) from ``seed`` on, unfiltered (a lab records what the policy
  did, failures too). :func:`check_attack_part` refuses any other, so no evaluation (which uses
  the ``evaluation`` part only) ever scores a texture on a configuration it was optimised from;
  the manifest's ``source`` lists the seeds, and :func:`check_held_out` checks an evaluation's
  against them.
* **The cell** (``cell``): ``nominal``, the scene as it is, or ``shifted`` (:func:`shifted_cell`):
  the same scene under another light and on another table, a cell that differs from the scene the
  attack and the evaluation describe it with.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Literal, Optional

import numpy as np
from pydantic import Field, ValidationError
from tqdm import tqdm

from sim.configio import StrictModel
from sim.configs import PARTS, config_part, sample_pool
from sim.env import ReachEnv
from sim.errors import AdvobjError, flag_error
from sim.geometry import make_T
from sim.policies.checkpoint import load_policy
from sim.policies.contract import check_scene, policy_cameras
from sim.policies.rollout import rollout
from sim.recording import (
    MAX_EPISODES,
    RecordedStep,
    Recording,
    RecordingCamera,
    check_target,
    read_recording,
    write_recording,
)
from sim.spec import WRIST, LightingSpec, LightSpec, load_spec

__all__ = [
    "RecordSimError",
    "SimRecordJob",
    "STEP_S",
    "CELLS",
    "SHIFTED_LIGHTING",
    "SHIFTED_TABLE_RGB",
    "shifted_cell",
    "scene_cameras",
    "attack_configs",
    "check_attack_part",
    "recorded_seeds",
    "check_held_out",
    "record_episodes",
    "run_record_sim",
    "first_episodes",
]

#: Time between two recorded steps (s): the trial runner's default policy rate, 10 Hz.
STEP_S = 0.1
CELLS = ("nominal", "shifted")
#: The shifted cell's light: dimmer, warmer and from another side than the built-in scene's one light.
SHIFTED_LIGHTING = LightingSpec(
    ambient=(0.24, 0.23, 0.21),
    lights=[LightSpec(type="directional", intensity=2.0, color=(1.0, 0.9, 0.78), direction=(-0.5, 0.45, -1.0))],
)
#: The shifted cell's table: a flat grey-blue top instead of the scene's own.
SHIFTED_TABLE_RGB = (0.42, 0.46, 0.52)
#: Frames held in memory at once while episodes are rolled out (they are written an episode at a time).
MAX_BATCH_BYTES = 256 * 2**20
#: The largest recording ``record sim`` writes: its frames' raw size (the PNG files are smaller).
MAX_RAW_BYTES = 64 * 2**30


class RecordSimError(AdvobjError, ValueError):
    """An input of ``advobj record sim`` is invalid; the one-line message names the flag."""


def _flag(field: str) -> str:
    return "--" + field.replace("_", "-")


class SimRecordJob(StrictModel):
    """Every input of one ``advobj record sim``, one field per flag."""

    policy: Path = Field(description="the policy: a checkpoint directory, a .pt2 or an .onnx file")
    out: Path = Field(description="the recording's folder (new or empty); nothing is written elsewhere")
    episodes: int = Field(ge=1, le=MAX_EPISODES, description="episodes to record")
    scene: Optional[Path] = Field(None, description="scene YAML (default: the built-in scene)")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="the first configuration seed of the attack part drawn")
    max_steps: Optional[int] = Field(None, ge=1, le=100_000, description="steps per episode (default: the scene's)")
    num_envs: int = Field(8, ge=1, le=256, description="episodes rolled out at once")
    cell: Literal["nominal", "shifted"] = Field(
        "nominal", description="nominal: the scene as it is; shifted: under another light, on another table"
    )
    device: str = "cpu"

    def __init__(self, **values):
        try:
            super().__init__(**values)
        except ValidationError as err:
            raise flag_error(err, _flag, "record sim", RecordSimError) from None


def shifted_cell(spec):
    """``spec`` in another cell: lit by :data:`SHIFTED_LIGHTING`, its table :data:`SHIFTED_TABLE_RGB`."""
    table = {**spec.table.model_dump(), "texture": SHIFTED_TABLE_RGB}
    return spec.with_updates(lighting=SHIFTED_LIGHTING.model_dump(), table=table)


def scene_cameras(spec, renderers: dict, names: dict | None = None, dist=()) -> list[RecordingCamera]:
    """The recording's cameras for the scene's cameras ``renderers`` (``{camera: renderer}``, each
    with ``K``, ``width`` and ``height``: what it renders with): the wrist camera on the TCP at the
    scene's ``T_tcp_cam``, a scene camera fixed at its ``T_table_cam``. ``names`` renames cameras in
    the recording (``{scene name: recorded name}``); ``dist``: the OpenCV distortion each is declared
    with (the renders are pinhole)."""
    names = names or {}
    out = []
    for c, r in renderers.items():
        name = names.get(c, c)
        if c == WRIST:
            out.append(RecordingCamera(name, r.K, dist, r.width, r.height, "tcp", spec.camera.T_tcp_cam))
        else:
            out.append(
                RecordingCamera(name, r.K, dist, r.width, r.height, "table", None, spec.camera_spec(c).T_table_cam)
            )
    return out


def attack_configs(spec, episodes: int, seed: int) -> list:
    """The first ``episodes`` configurations of the split's ``attack`` part with seeds from ``seed`` on."""
    return sample_pool(spec, episodes, seed=seed, part="attack")


def check_attack_part(configs) -> None:
    """Refuse, in one line, any configuration that is not of the split's ``attack`` part: a recording
    an attack learns from must share no configuration with an evaluation (``evaluation`` part) or
    with the selection of a texture (``validation`` part)."""
    for c in configs:
        part = config_part(c.seed)
        if part != PARTS[0]:
            raise RecordSimError(
                f"configuration seed {c.seed} belongs to the {part} part of the split (sim.configs.config_part); "
                "a recording for an attack is made from attack-part configurations only, so that no evaluation "
                "scores a texture on a configuration it was optimised from"
            )


def recorded_seeds(recording: Recording) -> tuple[int, ...]:
    """The configuration seeds a recording made by ``record sim`` was rolled out from (its source)."""
    text = recording.source.get("config_seeds")
    if recording.source.get("from") != "sim" or text is None:
        raise RecordSimError(f"{recording.path}: not a recording made by 'advobj record sim' (no config_seeds)")
    return tuple(int(s) for s in text.split(",") if s)


def check_held_out(recording: Recording, eval_seeds) -> int:
    """The number of evaluation configurations checked against the seeds ``recording`` was made from;
    any shared one is refused in one line (the evaluation would score a texture in-sample)."""
    seen = set(recorded_seeds(recording))
    shared = sorted(seen & {int(s) for s in eval_seeds})
    if shared:
        raise RecordSimError(
            f"{recording.path}: {len(shared)} of the evaluation's configurations (seed {shared[0]} first) are ones "
            "the recording was made from; the evaluation must use held-out configurations only"
        )
    return len(list(eval_seeds))


class _RecordingEnv(ReachEnv):
    """A :class:`ReachEnv` that hands every active env's frames and TCP pose to ``on_step`` just
    before it steps: the frames the policy acted on, at the pose they were rendered from."""

    on_step: Callable | None = None

    def step(self, actions):
        if self.on_step is not None:
            self.on_step(np.flatnonzero(~self.done), self.images(), self.T_world_tcp)
        return super().step(actions)


def _frame_bytes(policy, spec) -> int:
    """Bytes of one step's frames: every camera the policy reads (the wrist camera at its input size)."""
    size = int(policy.image_size)
    sides = [
        (size, size) if c == WRIST else (spec.camera_spec(c).width, spec.camera_spec(c).height)
        for c in policy_cameras(policy)
    ]
    return sum(3 * w * h for w, h in sides)


def _batch_size(num_envs: int, max_steps: int, frame_bytes: int) -> int:
    """Episodes rolled out before they are written: a few slots' worth, within :data:`MAX_BATCH_BYTES`."""
    fits = MAX_BATCH_BYTES // max(1, max_steps * frame_bytes)
    return int(max(num_envs, min(4 * num_envs, fits)))


def record_episodes(policy, spec, configs, num_envs: int = 8, progress: Callable[[int], None] | None = None):
    """Roll ``policy`` out closed loop in ``spec`` from each of ``configs`` (attack part only,
    :func:`check_attack_part`) with the adversarial object hidden; returns ``(cameras, episodes,
    outcomes)``: the recording's cameras (:func:`scene_cameras`), a generator of ``(id, steps)``
    for :func:`sim.recording.write_recording` (rolled out a batch at a time as it is consumed; an
    episode ended before its first step, by a policy error, is left out) and ``outcomes``, filled as
    it runs: ``{id: reached object index (-1: none)}``. The env is closed when the generator ends."""
    configs = list(configs)
    check_attack_part(configs)
    check_scene(policy, spec)
    cams = policy_cameras(policy)
    n = max(1, min(int(num_envs), len(configs)))
    env = _RecordingEnv(spec, num_envs=n, image_size=int(policy.image_size), seed=0, cameras=cams)
    adv = env.adv_index
    for name in cams:
        env.renderers[name].set_object_visible(adv, False)
    cameras = scene_cameras(spec, {c: env.renderers[c] for c in cams})
    batch = _batch_size(n, spec.episode.max_steps, _frame_bytes(policy, spec))
    outcomes: dict[str, int] = {}

    def episodes():
        try:
            for start in range(0, len(configs), batch):
                part = configs[start : start + batch]
                slot_of = [-1] * n
                steps: list[list] = [[] for _ in part]

                def fill(i, j, slot_of=slot_of):
                    slot_of[i] = j

                def on_step(active, images, T, slot_of=slot_of, steps=steps):
                    for i in active:
                        j = slot_of[i]
                        if j >= 0:
                            k = len(steps[j])
                            frames = {c: images[c][i].copy() for c in cams}
                            steps[j].append(RecordedStep(k * STEP_S, frames, T[i].copy()))

                def done(j, i, res, slot_of=slot_of, part=part):
                    outcomes[_episode_id(part[j])] = int(res["reached"])
                    slot_of[i] = -1
                    if progress is not None:
                        progress(1)

                env.on_step = on_step
                rollout(env, part, policy, done, on_fill=fill)
                for j, c in enumerate(part):
                    if steps[j]:
                        yield _episode_id(c), steps[j]
        finally:
            env.close()

    return cameras, episodes(), outcomes


_EPISODE_PREFIX = "config_"


def _episode_id(config) -> str:
    return f"{_EPISODE_PREFIX}{int(config.seed):07d}"


def _seed_of(episode_id: str) -> int:
    return int(episode_id.removeprefix(_EPISODE_PREFIX))


def run_record_sim(job: SimRecordJob, log: Callable[[str], None] | None = None, progress: bool = False) -> Recording:
    """Record ``job.episodes`` clean episodes of ``job.policy`` in the simulator into ``job.out``."""
    log = log or (lambda _text: None)
    check_target(job.out)  # before anything is loaded or rolled out
    base = load_spec(job.scene)
    if job.max_steps is not None:
        base = base.with_updates(episode={**base.episode.model_dump(), "max_steps": job.max_steps})
    spec = shifted_cell(base) if job.cell == "shifted" else base
    policy = load_policy(job.policy, job.device, spec=spec)
    raw = job.episodes * spec.episode.max_steps * _frame_bytes(policy, spec)
    if raw > MAX_RAW_BYTES:
        raise RecordSimError(
            f"--episodes: {job.episodes} episodes of up to {spec.episode.max_steps} steps hold up to "
            f"{raw / 2**30:.0f} GiB of frames, over the {MAX_RAW_BYTES / 2**30:.0f} GiB a recording made here may "
            "hold; record fewer episodes (or fewer --max-steps)"
        )
    configs = attack_configs(spec, job.episodes, job.seed)
    log(
        f"record sim: {job.episodes} episodes of up to {spec.episode.max_steps} steps ({job.cell} cell), "
        f"configurations of the attack part from seed {job.seed}"
    )
    with tqdm(total=len(configs), desc="record", unit="ep", disable=not progress) as bar:
        cameras, episodes, outcomes = record_episodes(policy, spec, configs, job.num_envs, bar.update)
        source = {
            "from": "sim",
            "cell": job.cell,
            "scene": "built-in" if job.scene is None else str(job.scene),
            "policy": str(job.policy),
            "max_steps": str(spec.episode.max_steps),
            "config_part": PARTS[0],
            "config_seeds": ",".join(str(c.seed) for c in configs),
        }
        rec = write_recording(
            job.out, cameras, episodes, T_table_base=make_T(np.eye(3), np.zeros(3)), sync_tolerance_s=0.0, source=source
        )
    goal, adv = spec.object_index("goal"), spec.object_index("adversarial")
    reached = list(outcomes.values())
    log(
        f"record sim: the policy reached the goal in {sum(r == goal for r in reached)} of {len(reached)} episodes "
        f"(the hidden adversarial object's place in {sum(r == adv for r in reached)})"
    )
    return rec


def first_episodes(src, out, n: int) -> Recording:
    """A recording of the first ``n`` episodes of recording ``src`` (a folder), written into ``out``:
    the same frames, poses and cameras; the source notes which recording and how many episodes."""
    rec = src if isinstance(src, Recording) else read_recording(src)
    if not 1 <= int(n) <= len(rec.episodes):
        raise RecordSimError(f"{rec.path}: holds {len(rec.episodes)} episodes, not the first {n} asked for")
    kept = rec.episodes[: int(n)]
    source = dict(rec.source)
    if "config_seeds" in source:  # the seeds of the episodes kept (record sim names an episode by its seed)
        source["config_seeds"] = ",".join(str(_seed_of(e.id)) for e in kept)
    source["first_episodes_of"] = f"{len(rec.episodes)} episodes of {rec.path.name}"
    return write_recording(
        out,
        list(rec.cameras.values()),
        ((e.id, rec.frames(e.id)) for e in kept),
        T_table_base=rec.T_table_base,
        sync_tolerance_s=rec.sync_tolerance_s,
        gripper=rec.gripper,
        source=source,
    )
