"""Cost of one attack iteration at the paper's shape, split by stage, vs a policy-only iteration.

Run: ``python benchmarks/bench_attack.py [--iters 3] [--size 128] [--arch resnet18] [--shading deferred]
[--out DIR]``.
With ``--out`` the figures, the command, commit, machine and wall/CPU time are written to
``DIR/summary.json`` (the committed measurements live in ``results/bench_attack/``).

Shape: resnet18 policy at 128x128, 4 envs x 10 steps = 40 image-action pairs, saliency + PCGrad on.
Prints ms per iteration for standard rendering (2 pyrender passes per pair, colour and ids, with
the shading computed; ``--shading passes``: 4, the shading measured), the differentiable
texture path, the policy forward (features + head + Grad-CAM graph) and the backward passes; the
ratio of a full iteration to a *policy-only* iteration (the same losses and gradients on
pre-rendered images: the floor for a white-box attack); and peak RSS.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import time
from contextlib import contextmanager

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np
import torch


class Timer:
    def __init__(self):
        self.t = {}
        self.depth = 0

    @contextmanager
    def __call__(self, key):
        t0 = time.perf_counter()
        yield
        self.t[key] = self.t.get(key, 0.0) + time.perf_counter() - t0


def _timed(timer, key, fn):
    def wrapped(*a, **k):
        if timer.depth:  # the single-frame render calls the batched one: time the outer call only
            return fn(*a, **k)
        timer.depth += 1
        try:
            with timer(key):
                return fn(*a, **k)
        finally:
            timer.depth -= 1

    return wrapped


def instrument(run, timer):
    """Wrap the run's stages with timers (no change to what they compute)."""
    import attack.optimize as opt
    import attack.render as ar

    cap = run.hybrid.capture

    def capture(*a, **k):
        with timer("standard render"):
            return cap(*a, **k)

    run.hybrid.capture = capture
    # Per frame (before) or batched; wrapped in the renderer's module and wherever the attack's
    # modules imported the name (a module-level import binds the function itself).
    import attack.sources as src

    for name in ("render_adversarial", "render_adversarial_batch"):
        if hasattr(ar, name):
            fn = getattr(ar, name)
            timed = _timed(timer, "differentiable texture", fn)
            for mod in (ar, opt, src):
                if getattr(mod, name, None) is fn:
                    setattr(mod, name, timed)
    losses = run.objective.losses

    def timed_losses(*a, **k):
        # Includes Grad-CAM's create_graph gradient: the forward graph the losses need.
        with timer("policy forward + Grad-CAM"):
            return losses(*a, **k)

    run.objective.losses = timed_losses
    grad = torch.autograd.grad

    def timed_grad(*a, **k):
        if k.get("create_graph"):  # inside the loss computation, already timed there
            return grad(*a, **k)
        with timer("backward to the texture"):
            return grad(*a, **k)

    torch.autograd.grad = timed_grad
    return opt


def _batch(run, x, caps, T, p_adv):
    """The :class:`attack.objective.FrameBatch` ``AttackRun.frame_gradients`` builds, on images ``x``."""
    from attack.objective import FrameBatch

    return FrameBatch(
        images=x,
        T_world_tcp=T,
        p_adv=p_adv,
        adv_mask=np.stack([c.adv_mask for c in caps]),
        goal_mask=np.stack([c.goal_mask for c in caps]),
        policy=run,
        clean_images=lambda: x.detach(),
    )


def policy_only_iteration(run, imgs, caps, T, p_adv):
    """The same losses and gradients w.r.t. the images, without any rendering."""
    total = 0.0
    for step in range(run.cfg.rollout_steps):
        x = imgs.clone().requires_grad_(True)
        t0 = time.perf_counter()
        losses = run.objective.losses(_batch(run, x, caps, T, p_adv), run.state.iteration, run.cfg.iterations)
        for k, (_, loss, _) in enumerate(losses):
            if loss.requires_grad:
                later = any(lo.requires_grad for _, lo, _ in losses[k + 1 :])
                torch.autograd.grad(loss, x, retain_graph=later)
        total += time.perf_counter() - t0
    return total


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--iters", type=int, default=3)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--arch", default="resnet18")
    ap.add_argument("--sampler", default="trilinear")
    ap.add_argument(
        "--shading",
        default="deferred",
        choices=("deferred", "passes"),
        help="how captures get the object's shading: computed (2 passes per frame) or measured (4)",
    )
    ap.add_argument("--out", default=None, help="write summary.json here (with command, commit, machine, times)")
    args = ap.parse_args()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    from attack.optimize import AttackRun, resolve_config
    from attack.render import render_adversarial
    from sim.policies.policy import VisuomotorPolicy
    from sim.spec import default_scene

    torch.manual_seed(0)
    policy = VisuomotorPolicy(arch=args.arch, image_size=args.size)
    cfg = resolve_config("paper", {"iterations": args.iters + 1, "pool_size": 50, "sampler": args.sampler})
    run = AttackRun(policy, default_scene(), cfg)
    run.hybrid.shading = args.shading  # the frame source shares this renderer
    run.step()  # warm-up: GL uploads, allocator
    timer = Timer()
    instrument(run, timer)
    walls = []
    for _ in range(args.iters):
        t0 = time.perf_counter()
        run.step()
        walls.append(time.perf_counter() - t0)
    n = args.iters
    stages = dict(timer.t)  # snapshot: the floor below runs through the same instrumented calls
    # Policy-only floor on frames captured from the current state.
    run.env.reset_envs(range(cfg.num_envs), configs=run.pool[: cfg.num_envs])
    caps = [run.hybrid.capture(w) for w in run.env.worlds]
    imgs = torch.stack([render_adversarial(c, run.state.texture) for c in caps]).detach()
    T = torch.from_numpy(run.env.T_world_tcp).float()
    p_adv = torch.from_numpy(run.env.object_centers[:, run.adv]).float()
    floor = statistics.median(policy_only_iteration(run, imgs, caps, T, p_adv) for _ in range(n))
    full = statistics.median(walls)
    rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    print(
        f"# {args.arch} {args.size}x{args.size}, {cfg.num_envs} envs x {cfg.rollout_steps} steps, saliency+PCGrad, "
        f"sampler={args.sampler}, shading={args.shading}; "
        f"cores={os.cpu_count()} torch={torch.__version__} threads={torch.get_num_threads()}"
    )
    print("| stage | ms / iteration |")
    print("|---|---|")
    for k, v in stages.items():
        print(f"| {k} | {1000 * v / n:.0f} |")
    print(f"| full iteration (median of {n}) | {1000 * full:.0f} |")
    print(f"| policy-only iteration | {1000 * floor:.0f} |")
    print(f"ratio full / policy-only: {full / floor:.2f} (target <= 1.05)")
    print(f"peak RSS: {rss_gb:.2f} GB (target <= 4 GB)")
    run.close()
    if args.out:
        import json
        import sys
        from pathlib import Path

        from sim.runinfo import git_commit
        from trials.experiments.tradeoff import machine_info

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        doc = {
            "command": " ".join(["python"] + sys.argv),
            "commit": git_commit(),
            "machine": machine_info(),
            "shape": {
                "arch": args.arch,
                "size": args.size,
                "num_envs": cfg.num_envs,
                "rollout_steps": cfg.rollout_steps,
                "sampler": args.sampler,
                "shading": args.shading,
                "iters": n,
            },
            "iteration_walls_s": walls,
            "stages_ms_per_iteration": {k: 1000 * v / n for k, v in stages.items()},
            "full_ms_median": 1000 * full,
            "policy_only_ms_median": 1000 * floor,
            "ratio": full / floor,
            "peak_rss_gb": rss_gb,
            "run": {"wall_s": round(time.perf_counter() - wall0, 1), "cpu_s": round(time.process_time() - cpu0, 1)},
        }
        (out / "summary.json").write_text(json.dumps(doc, indent=2))
        print(f"wrote {out / 'summary.json'}")


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
