"""Speed and accuracy of the rendering shortcuts, and the cost of the attack's validation.

Run: ``.venv/bin/python benchmarks/bench_render_shortcuts.py [--policy DIR] [--attack DIR]
[--episodes 16] [--size 64] [--validation]``.

Per shortcut it prints ms per frame with and without, their ratio, and the accuracy effect:

* frustum culling (``SceneRenderer(frustum_cull=...)``) on wrist-camera reach trajectories: how
  often an object is culled, the max-abs pixel difference of color and id images, and the
  episode outcomes (success, reached-adversarial = T-ASR) of the same episodes with and without;
* frustum culling on a cluttered table (``--clutter N`` extra objects around the same trajectories);
* isolated shading passes (``HybridRenderer(isolate_shading=...)``: the attack's white/black
  passes draw the adversarial object alone and reuse the color pass for everything else): ms
  per capture, max-abs difference of the shading passes under the object's mask and of ``I_adv``;
* reusing the previous step's frame as the background (NOT shipped): the wrist camera moves
  every step, so the measured difference shows it is not exact;
* rendering at the policy's size vs rendering at the camera's size and downsampling;
* ``--validation``: seconds per held-out validation call and per quick-preset attack run.

Trajectories come from ``--policy`` (a checkpoint directory) or, without it, the scripted expert.
Medians over alternating blocks (the machine is shared and noisy); the load average is printed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np


def _act(policy, env, obs):
    return env.expert_actions() if policy is None else policy.act(obs)


def rollouts(spec, configs, size: int, policy, texture, cull: bool):
    """Run every config to the end; returns per-episode outcomes and every rendered state.

    ``states`` lists ``(T_world_objects, T_world_tcp, T_world_cam)`` step by step across the batch
    (env 0 step 0, env 1 step 0, ...); ``episodes[j]`` is the env index of ``states[j]``.
    """
    from sim.env import ReachEnv

    n = len(configs)
    env = ReachEnv(spec, num_envs=n, seed=0, policy_image_size=size)
    env.renderer.frustum_cull = cull
    if texture is not None:
        env.renderer.set_object_texture(env.adv_index, texture)
    states, episodes = [], []
    obs, _ = env.reset(configs=configs)
    while not env.done.all():
        for i in np.flatnonzero(~env.done):
            w = env.worlds[i]
            states.append((w.T_world_objects.copy(), w.T_world_tcp, w.camera_pose()))
            episodes.append(int(i))
        obs, *_ = env.step(_act(policy, env, obs))
    out = {"reached": env.reached.copy(), "steps": env.steps.copy(), "tcp": env.T_world_tcp, "episodes": episodes}
    env.close()
    return out, states


def time_renders(renderer, states, with_ids: bool, blocks: int = 5) -> tuple[float, list]:
    """Median ms per frame over ``blocks`` passes through ``states``; also the frames of the last."""
    ms, frames = [], []
    for b in range(blocks):
        frames = []
        t0 = time.perf_counter()
        for T_objs, T_tcp, T_cam in states:
            renderer.set_state(T_objs, T_tcp)
            frames.append(renderer.render(T_cam, with_ids=with_ids))
        ms.append(1000 * (time.perf_counter() - t0) / len(states))
    return statistics.median(ms), frames


def cull_on_off(renderer, states, with_ids: bool, rounds: int = 3) -> tuple[float, float, int, int]:
    """Median ms per frame with and without culling, max |rgb diff| and differing id pixels.

    On and off blocks alternate so that load changes hit both alike.
    """
    ms, frames = {True: [], False: []}, {}
    for _ in range(rounds):
        for cull in (True, False):
            renderer.frustum_cull = cull
            t, frames[cull] = time_renders(renderer, states, with_ids, blocks=1)
            ms[cull].append(t)
    pairs = list(zip(frames[True], frames[False]))
    d_rgb = max(int(np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max()) for a, b in pairs)
    d_ids = max(int((a.ids != b.ids).sum()) for a, b in pairs) if with_ids else 0
    return statistics.median(ms[True]), statistics.median(ms[False]), d_rgb, d_ids


def bench_frustum(spec, configs, size, policy, texture) -> None:
    from sim.render import SceneRenderer

    on, states = rollouts(spec, configs, size, policy, texture, cull=True)
    off, _ = rollouts(spec, configs, size, policy, texture, cull=False)
    adv, goal = spec.object_index("adversarial"), spec.object_index("goal")
    same = (
        np.array_equal(on["reached"], off["reached"])
        and np.array_equal(on["steps"], off["steps"])
        and np.array_equal(on["tcp"], off["tcp"])
    )
    r = SceneRenderer(spec, size, size)
    if texture is not None:
        r.set_object_texture(adv, texture)
    per_object = np.zeros(len(spec.objects))
    any_culled = 0
    for T_objs, T_tcp, T_cam in states:
        r.set_state(T_objs, T_tcp)
        r.render(T_cam, with_ids=False)
        for k in r.culled:
            per_object[k] += 1
        any_culled += bool(r.culled)
    time_renders(r, states, True, blocks=1)  # warm-up: first-use GL uploads land in neither arm
    results = {with_ids: cull_on_off(r, states, with_ids) for with_ids in (False, True)}
    r.close()
    n = len(states)
    print(
        f"[frustum cull] {len(configs)} episodes, {n} wrist-camera frames at {size}x{size} "
        f"({'policy' if policy is not None else 'expert'} trajectories)"
    )
    print(
        f"  frames with an object culled: {any_culled}/{n} = {any_culled / n:.1%}; per object: "
        + ", ".join(f"{o.name} {c / n:.1%}" for o, c in zip(spec.objects, per_object))
    )
    for with_ids, (t_on, t_off, d_rgb, d_ids) in results.items():
        print(
            f"  {'color+id' if with_ids else 'color   '} pass: {t_on:.2f} ms/frame with, {t_off:.2f} without, "
            f"ratio {t_off / t_on:.3f}x; max |rgb diff| {d_rgb}, differing id pixels {d_ids}"
        )
    print(
        f"  outcomes with/without identical: {same}; success {np.mean(on['reached'] == goal):.3f} / "
        f"{np.mean(off['reached'] == goal):.3f}; reached adversarial (T-ASR) {np.mean(on['reached'] == adv):.3f} / "
        f"{np.mean(off['reached'] == adv):.3f}"
    )
    return states, on["episodes"]


def clutter_spec(spec, n: int):
    """``spec`` plus ``n`` distractors (cubes, ducks, dogs, cylinders) on a ring 0.45-0.7 m from the
    table centre, and their fixed ``T_world_object`` poses ``(n, 4, 4)``."""
    from sim.render import object_pose

    meshes = ("cube", "duck", "dog", "cylinder")
    objs, poses = [o.model_dump() for o in spec.objects], []
    for k in range(n):
        a, rad = 2 * np.pi * k / n, 0.45 + 0.25 * (k % 2)
        x, y = rad * np.cos(a), rad * np.sin(a)
        objs.append(
            {
                "name": f"clutter_{k}",
                "mesh": meshes[k % len(meshes)],
                "role": "distractor",
                "pose": {"x_m": float(x), "y_m": float(y), "yaw_deg": float(np.degrees(a))},
            }
        )
        poses.append(object_pose(x, y, a))
    return spec.model_copy(update={"objects": [type(spec.objects[0]).model_validate(o) for o in objs]}), np.array(poses)


def bench_frustum_clutter(spec, states, size, n: int) -> None:
    """Culling where it can pay: the same wrist trajectories in a table with ``n`` extra objects."""
    from sim.render import SceneRenderer

    cspec, extra = clutter_spec(spec, n)
    r = SceneRenderer(cspec, size, size)
    cstates = [(np.concatenate([T_objs, extra]), T_tcp, T_cam) for T_objs, T_tcp, T_cam in states]
    time_renders(r, cstates[:20], True, blocks=1)  # warm-up
    culled = []
    for T_objs, T_tcp, T_cam in cstates:
        r.set_state(T_objs, T_tcp)
        r.render(T_cam, with_ids=False)
        culled.append(len(r.culled))
    t_on, t_off, d_rgb, d_ids = cull_on_off(r, cstates, True)
    r.close()
    print(
        f"[frustum cull, cluttered] the same {len(cstates)} frames with {n} extra objects "
        f"({len(cspec.objects)} in all): "
        f"{np.mean(culled):.1f} objects culled per frame on average"
    )
    print(
        f"  color+id pass: {t_on:.2f} ms/frame with, {t_off:.2f} without, ratio {t_off / t_on:.3f}x; "
        f"max |rgb diff| {d_rgb}, differing id pixels {d_ids}"
    )


def bench_isolated_shading(spec, states, size) -> None:
    import torch

    from attack.render import HybridRenderer, render_adversarial
    from sim.world import SimWorld

    torch.set_num_threads(1)
    world = SimWorld(spec, size, seed=0)
    hyb = HybridRenderer(world.renderer, shading="passes")  # the measured shortcut is the passes path's
    tex = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(0))
    # Only frames showing the adversarial object exercise the shading passes.
    frames = []
    for T_objs, T_tcp, T_cam in states:
        world.T_world_objects = T_objs
        world.set_tcp_pose(T_tcp)
        world.prepare()
        if world.renderer.render(T_cam, with_ids=True).object_mask(hyb.adv).any():
            frames.append((T_objs, T_tcp, T_cam))
    frames = frames[:: max(1, len(frames) // 150)]

    def captures():
        out = []
        for T_objs, T_tcp, T_cam in frames:
            world.T_world_objects = T_objs
            world.set_tcp_pose(T_tcp)
            out.append(hyb.capture(world, T_cam))
        return out

    ms = {True: [], False: []}
    caps = {}
    captures()  # warm-up
    for _ in range(3):
        for iso in (True, False):
            hyb.isolate_shading = iso
            t0 = time.perf_counter()
            caps[iso] = captures()
            ms[iso].append(1000 * (time.perf_counter() - t0) / len(frames))
    d_shade = max(
        float(
            max(
                np.abs(a.fragments.diffuse - b.fragments.diffuse).max(initial=0),
                np.abs(a.fragments.specular - b.fragments.specular).max(initial=0),
            )
        )
        for a, b in zip(caps[True], caps[False])
    )
    d_img = max(
        float((render_adversarial(a, tex) - render_adversarial(b, tex)).abs().max())
        for a, b in zip(caps[True], caps[False])
    )
    t_on, t_off = statistics.median(ms[True]), statistics.median(ms[False])
    world.close()
    print(f"[isolated shading passes] {len(frames)} attack captures (color + ids + white + black) at {size}x{size}")
    print(
        f"  {t_on:.2f} ms/capture with, {t_off:.2f} without, ratio {t_off / t_on:.3f}x; "
        f"max |diffuse/specular diff| {d_shade:g}, max |I_adv diff| {d_img:g}"
    )


def bench_previous_frame(spec, states, episodes, size, max_pairs: int = 300) -> None:
    """Reusing the previous step's render as the background: how far from exact it is.

    Compares step t with step t+1 *of the same episode* (``episodes[j]`` names the episode of
    ``states[j]``), outside the gripper in both frames: the part a reused background would supply.
    """
    from sim.render import GRIPPER_ID, SceneRenderer

    by_episode: dict[int, list] = {}
    for e, s in zip(episodes, states):
        by_episode.setdefault(e, []).append(s)
    r = SceneRenderer(spec, size, size)
    diffs, fracs, means = [], [], []
    for seq in by_episode.values():
        prev = None
        for T_objs, T_tcp, T_cam in seq:
            if len(diffs) >= max_pairs:
                break
            r.set_state(T_objs, T_tcp)
            out = r.render(T_cam, with_ids=True)
            if prev is not None:
                bg = (out.ids != GRIPPER_ID) & (prev.ids != GRIPPER_ID)
                d = np.abs(out.rgb.astype(int) - prev.rgb.astype(int)).max(-1)[bg]
                diffs.append(int(d.max(initial=0)))
                fracs.append(float((d > 0).mean()) if d.size else 0.0)
                means.append(float(d.mean()) if d.size else 0.0)
            prev = out
    r.close()
    print(
        f"[previous-frame background, not shipped] {len(diffs)} pairs of consecutive frames of one episode "
        f"(gripper excluded): max |rgb diff| median {statistics.median(diffs)}, max {max(diffs)}; "
        f"mean |diff| median {statistics.median(means):.2f}/255; pixels changed: median "
        f"{statistics.median(fracs):.1%}, "
        f"min {min(fracs):.1%}"
    )


def bench_resolution(spec, states, size) -> None:
    from PIL import Image

    from sim.render import SceneRenderer

    big = 2 * size
    r_small, r_big = SceneRenderer(spec, size, size), SceneRenderer(spec, big, big)
    ms_small, ms_big, diffs = [], [], []
    sub = states[:150]
    time_renders(r_small, sub[:10], False, blocks=1)
    time_renders(r_big, sub[:10], False, blocks=1)
    for _ in range(3):
        t, small = time_renders(r_small, sub, False, blocks=1)
        ms_small.append(t)
        t0 = time.perf_counter()
        down = []
        for T_objs, T_tcp, T_cam in sub:
            r_big.set_state(T_objs, T_tcp)
            img = r_big.render(T_cam, with_ids=False).rgb
            down.append(np.asarray(Image.fromarray(img).resize((size, size), Image.BOX)))
        ms_big.append(1000 * (time.perf_counter() - t0) / len(sub))
    diffs = [np.abs(a.rgb.astype(int) - b.astype(int)) for a, b in zip(small, down)]
    r_small.close()
    r_big.close()
    t_s, t_b = statistics.median(ms_small), statistics.median(ms_big)
    print(
        f"[resolution] render at the policy's {size}px: {t_s:.2f} ms/frame; render {big}px + box downsample: {t_b:.2f} "
        f"ms/frame; ratio {t_b / t_s:.3f}x; the two images differ (max |diff| {max(int(d.max()) for d in diffs)}, "
        f"mean {np.mean([d.mean() for d in diffs]):.2f}/255): the env renders at the policy's size only"
    )


def bench_validation(spec, policy_dir, size) -> None:
    import torch

    from attack.optimize import AttackRun, resolve_config
    from sim.configs import load_pool
    from sim.policies.policy import VisuomotorPolicy

    torch.set_num_threads(1)
    cfg = resolve_config("quick")
    pool = None
    if policy_dir is not None:
        from sim.policies.checkpoint import load_policy
        from sim.policies.pool import feasible_pool_path

        policy = load_policy(policy_dir)
        pool_file = feasible_pool_path(policy_dir)
        pool = load_pool(pool_file, spec) if pool_file.is_file() else None
    else:
        torch.manual_seed(0)
        policy = VisuomotorPolicy(arch="small_cnn", image_size=size)  # untrained: episodes run to max_steps
    run = AttackRun(policy, spec, cfg, pool=pool)
    val = [run.validate()["seconds"] for _ in range(3)]
    steps = []
    for _ in range(5):
        t0 = time.perf_counter()
        run.step()
        steps.append(time.perf_counter() - t0)
    run.close()
    v, s = statistics.median(val), statistics.median(steps)
    calls = 1 + cfg.iterations // cfg.validation_every + (cfg.iterations % cfg.validation_every > 0)
    print(
        f"[validation] quick preset ({cfg.validation_episodes} held-out episodes, <= {spec.episode.max_steps} steps, "
        f"{run.image_size}px): {v:.2f} s/call; attack step {s:.2f} s/iteration; per quick run {calls} calls = "
        f"{calls * v:.0f} s on top of {cfg.iterations} x {s:.2f} = {cfg.iterations * s:.0f} s "
        f"(+{calls * v / (cfg.iterations * s):.0%})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy", default=None, help="policy checkpoint directory (default: the scripted expert)")
    ap.add_argument("--attack", default=None, help="attack run directory whose texture.npy is put on the object")
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--size", type=int, default=64, help="render size without --policy (else the policy's)")
    ap.add_argument("--validation", action="store_true", help="also time the attack's held-out validation")
    ap.add_argument(
        "--clutter", type=int, default=12, help="extra objects for the cluttered-table culling row (0: skip)"
    )
    args = ap.parse_args()

    import torch

    from sim.configs import load_pool, sample_pool
    from sim.spec import default_scene

    torch.set_num_threads(1)
    spec = default_scene()
    policy, size = None, args.size
    configs = sample_pool(spec, args.episodes, seed=1000)
    if args.policy is not None:
        from sim.policies.checkpoint import load_policy
        from sim.policies.pool import feasible_pool_path

        policy = load_policy(args.policy)
        size = int(policy.image_size)
        pool_file = feasible_pool_path(args.policy)
        if pool_file.is_file():  # task-feasible starts: the episodes the evaluation runs
            configs = load_pool(pool_file, spec)[: args.episodes]
    texture = None
    if args.attack is not None:
        tex = np.load(os.path.join(args.attack, "texture.npy"))
        texture = np.clip(np.rint(tex * 255.0), 0, 255).astype(np.uint8)
    print(f"load average {os.getloadavg()[0]:.2f}, torch threads {torch.get_num_threads()}")
    states, episodes = bench_frustum(spec, configs, size, policy, texture)
    if args.clutter:
        bench_frustum_clutter(spec, states, size, args.clutter)
    bench_isolated_shading(spec, states, size)
    bench_previous_frame(spec, states, episodes, size)
    bench_resolution(spec, states, size)
    if args.validation:
        bench_validation(spec, args.policy, size)
    print(f"load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
