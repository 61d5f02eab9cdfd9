"""Evaluation speed: episodes per minute, and eval-step cost relative to the policy forward.

Usage:
    python benchmarks/bench_eval.py [--arch resnet18] [--size 128] [--num-envs 8] [--episodes 8]
                                    [--max-steps 20] [--condition attack] [--threads 0]

Runs real ``trials.eval.evaluate.rollout_condition`` episodes (pyrender, the attack texture as a
renderer variant plus the clean view of the same state) with an untrained policy (speed does not
depend on the weights, and an untrained policy never reaches anything, so every episode runs its
full length). The policy's ``act`` is timed inside the run, so

    ratio = wall time of the whole rollout / time spent in the policy forward

is measured on the same steps: 1.0 would mean rendering, env stepping and bookkeeping are free.
Episodes per minute are given for the paper's 60-step episodes (measured step time x 60).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402


class TimedPolicy:
    def __init__(self, policy):
        self.policy = policy
        self.image_size = policy.image_size
        self.seconds = 0.0
        self.calls = 0
        self.images = 0

    def act(self, images):
        t0 = time.perf_counter()
        out = self.policy.act(images)
        self.seconds += time.perf_counter() - t0
        self.calls += 1
        self.images += len(images)
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", default="resnet18")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--num-envs", type=int, default=8)
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--max-steps", type=int, default=20)
    ap.add_argument(
        "--condition", default="attack", help="clean or attack (attack renders and acts on two views per step)"
    )
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    from sim.configs import sample_pool
    from sim.policies.policy import VisuomotorPolicy
    from sim.spec import default_scene
    from trials.eval.conditions import Sources, build_conditions
    from trials.eval.evaluate import rollout_condition

    torch.manual_seed(0)
    policy = TimedPolicy(VisuomotorPolicy(arch=args.arch, image_size=args.size).eval())
    spec = default_scene()
    spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": args.max_steps})
    configs = sample_pool(spec, args.episodes, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        np.save(d / "texture.npy", np.random.default_rng(0).random((256, 256, 3)).astype(np.float32))
        (d / "run.json").write_text(json.dumps({"config": {"attack": {"adversarial_mesh": None}}}))
        cond = {c.name: c for c in build_conditions([args.condition], Sources(attack=str(d)))}[args.condition]
        policy.act(np.zeros((2 * args.num_envs, args.size, args.size, 3), np.uint8))  # warm-up
        policy.seconds, policy.calls, policy.images = 0.0, 0, 0
        steps = []
        t0 = time.perf_counter()
        rollout_condition(policy, spec, cond, configs, args.num_envs, lambda j, r: steps.append(r["steps"]))
        wall = time.perf_counter() - t0
    env_steps = sum(steps)
    step_s = wall / env_steps
    print(
        f"arch={args.arch} size={args.size} condition={args.condition} num_envs={args.num_envs} "
        f"torch_threads={torch.get_num_threads()}"
    )
    print(
        f"  {len(steps)} episodes, {env_steps} env-steps in {wall:.1f} s (incl. env/GL setup); "
        f"{policy.calls} policy calls on {policy.images} images"
    )
    print(f"  policy forward: {policy.seconds:.1f} s ({1000 * policy.seconds / policy.images:.1f} ms/image)")
    print(f"  eval wall / policy forward = {wall / policy.seconds:.2f}  (target <= 1.3)")
    print(f"  episodes per minute (60-step episodes): {60.0 / (60 * step_s):.2f}")


if __name__ == "__main__":
    main()
