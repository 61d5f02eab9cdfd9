"""Recordings written from the simulator, for the attack on recorded frames (attack.recorded).

The simulator renders a few short episodes through the existing renderer (:class:`sim.world.SimWorld`)
with the adversarial object hidden (the frames a user records hold the real scene, never the object
the attack adds), and :func:`sim.recording.write_recording` writes them: frame k at the TCP pose it
was rendered from, the wrist camera with its scene intrinsics and mount ``T_tcp_cam``, scene cameras
at their fixed ``T_table_cam`` (:func:`trials.recordings.simulated.scene_cameras`, as ``advobj record
sim`` declares them). Unlike ``advobj record sim`` (closed-loop episodes of a policy), the TCP moves
straight ahead here, so a test's frames do not depend on a policy.
"""

from __future__ import annotations

import contextlib
from unittest import mock

import numpy as np

from sim.action import next_tcp_pose
from sim.configs import sample_config
from sim.geometry import make_T
from sim.recording import RecordedStep, write_recording
from sim.spec import WRIST
from sim.world import SimWorld
from trials.recordings.simulated import scene_cameras

FORWARD = np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0])  # half a step along the TCP's approach axis


def _lit(rgb: np.ndarray, gain: float) -> np.ndarray:
    if gain == 1.0:
        return rgb
    lin = (rgb / 255.0) ** 2.2 * gain
    return np.clip(np.rint(np.clip(lin, 0.0, 1.0) ** (1 / 2.2) * 255.0), 0, 255).astype(np.uint8)


def sim_configs(spec, episodes: int, seed: int = 0) -> list:
    """The configurations episode 0, 1, ... of :func:`sim_recording` start from."""
    return [sample_config(spec, seed + e) for e in range(episodes)]


def sim_recording(
    path,
    spec,
    size: int = 32,
    episodes: int = 3,
    steps: int = 3,
    seed: int = 0,
    cameras=(WRIST,),
    T_table_base=None,
    names: dict | None = None,
    dist=(),
    light_gain: float = 1.0,
):
    """Write a recording of ``episodes`` episodes of ``steps`` steps each (the TCP moving straight
    ahead) of ``spec`` through ``cameras`` (the wrist camera at ``size`` px square, scene cameras at
    their own size) into ``path``; returns it read back. ``T_table_base`` (default identity) is what
    the manifest says, the frames are rendered as the simulator's world is; ``names`` renames
    cameras in the recording (``{scene name: recorded name}``); ``dist``: the OpenCV distortion every
    camera is declared with (the frames stay pinhole renders); ``light_gain``: each frame's linear
    light is multiplied by it (a brighter or darker cell than the scene's)."""
    names = names or {}
    adv = spec.object_index("adversarial")
    world = SimWorld(spec, image_size=size, seed=seed)
    try:
        for c in cameras:
            world.camera_renderer(c).set_object_visible(adv, False)
        eps = []
        for e, config in enumerate(sim_configs(spec, episodes, seed)):
            world.reset(config=config)
            rows = []
            for k in range(steps):
                images = {
                    names.get(c, c): _lit(world.render(camera=c, with_ids=False).rgb, light_gain) for c in cameras
                }
                rows.append(RecordedStep(0.1 * k, images, world.T_world_tcp))
                ep = spec.episode
                world.set_tcp_pose(next_tcp_pose(world.T_world_tcp, FORWARD, ep.max_step_m, ep.max_step_rad))
            eps.append((f"ep{e}", rows))
        cams = scene_cameras(spec, {c: world.camera_renderer(c) for c in cameras}, names, dist)
        base = make_T(np.eye(3), np.zeros(3)) if T_table_base is None else T_table_base
        return write_recording(path, cams, eps, T_table_base=base, sync_tolerance_s=0.01, source={"from": "sim"})
    finally:
        world.close()


@contextlib.contextmanager
def no_simulator():
    """Within it, building the simulator's env or rolling one out raises AssertionError: what an
    attack on recorded frames must never do (attack.recorded: open loop, no simulator in the loop)."""
    import attack.optimize
    import sim.env
    import sim.policies.rollout

    def refuse(*_a, **_k):
        raise AssertionError("the recordings attack built a simulator env or rolled one out")

    with (
        mock.patch.object(sim.env.ReachEnv, "__init__", refuse),
        mock.patch.object(attack.optimize, "ReachEnv", refuse),
        mock.patch.object(attack.optimize, "rollout", refuse),
        mock.patch.object(sim.policies.rollout, "rollout", refuse),
    ):
        yield
