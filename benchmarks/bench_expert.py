"""Privileged expert's success rate over a pool of initial configurations (target >= 98%).

Run: ``.venv/bin/python benchmarks/bench_expert.py [--episodes 500]``.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--episodes", type=int, default=500)
    ap.add_argument("--seed", type=int, default=100_000)
    args = ap.parse_args()
    import numpy as np

    from sim.env import ReachEnv
    from sim.spec import default_scene
    from sim.stats import wilson_interval

    spec = default_scene()
    n_envs = 10
    env = ReachEnv(spec, num_envs=n_envs, image_size=32, seed=args.seed, render_obs=False)
    succ, steps, other = 0, [], 0
    for b in range(args.episodes // n_envs):
        env.reset(seed=args.seed + b * n_envs)
        while not env.done.all():
            _, _, _, _, info = env.step(env.expert_actions())
        succ += int(info["success"].sum())
        other += int(((info["reached"] >= 0) & ~info["success"]).sum())
        steps += info["step"][info["success"]].tolist()
    n = (args.episodes // n_envs) * n_envs
    lo, hi = wilson_interval(succ, n)
    print(
        f"expert success {succ}/{n} = {100 * succ / n:.1f}% (95% Wilson {100 * lo:.1f}-{100 * hi:.1f}%); "
        f"reached another object {other}; median steps to goal {np.median(steps):.0f}"
    )
    env.close()


if __name__ == "__main__":
    main()
