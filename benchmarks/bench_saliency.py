"""How large the saliency term's texture gradient is beside the pose term's, per lambda_sal.

    .venv/bin/python benchmarks/bench_saliency.py --policy runs/evidence/policy-quick [--configs 32]

For each of the first ``--configs`` attack-part configurations of the policy's pool, renders the
first frame under the benign texture (hybrid render) and takes both objectives' texture gradients
(:meth:`attack.optimize.AttackRun.frame_gradients` at lambda_sal = 1). The ratio
``||g_sal|| / ||g_pose||`` then scales linearly with lambda_sal; the script prints its median and
quartiles, and the cosine between the two gradients (PCGrad only acts when it is negative).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    import numpy as np
    import torch

    from attack.optimize import AttackRun, resolve_config
    from attack.sources import Frames
    from sim.configs import in_part, load_pool
    from sim.policies.checkpoint import load_policy
    from sim.policies.pool import feasible_pool_path
    from sim.spec import default_scene

    ap = argparse.ArgumentParser()
    ap.add_argument("--policy", required=True)
    ap.add_argument("--configs", type=int, default=32)
    a = ap.parse_args()
    torch.set_num_threads(1)
    spec = default_scene()
    pool = load_pool(feasible_pool_path(Path(a.policy)), spec)
    configs = in_part(pool, "attack")[: a.configs]
    cfg = resolve_config("quick", {"lambda_sal": 1.0, "num_envs": 1, "validation_every": 0})
    run = AttackRun(load_policy(a.policy), spec, cfg, pool=pool)
    ratios, cosines = [], []
    t0 = time.perf_counter()
    try:
        for c in configs:
            run.env.reset_envs([0], configs=[c])
            cap = run.hybrid.capture(run.env.worlds[0])
            T = torch.from_numpy(run.env.T_world_tcp[:1]).float()
            p = torch.from_numpy(run.env.object_centers[:1, run.adv]).float()
            g = run.frame_gradients(run.state, Frames([cap], T, p))["grads"]
            n_pose, n_sal = float(g["pose"].norm()), float(g["saliency"].norm())
            if n_pose > 0 and n_sal > 0:
                ratios.append(n_sal / n_pose)
                cosines.append(float((g["pose"] * g["saliency"]).sum()) / (n_pose * n_sal))
    finally:
        run.close()
    q = np.quantile(ratios, [0.25, 0.5, 0.75]) if ratios else [float("nan")] * 3
    print(
        f"# {a.policy}: {len(ratios)} of {len(configs)} first frames show the object; {time.perf_counter() - t0:.1f} s"
    )
    print("| lambda_sal | median ||g_sal|| / ||g_pose|| | quartiles |")
    print("|---|---|---|")
    for lam in (0.01, 0.1, 1.0):
        print(f"| {lam} | {lam * q[1]:.4f} | [{lam * q[0]:.4f}, {lam * q[2]:.4f}] |")
    if cosines:
        print(
            f"cosine(g_pose, g_sal): median {statistics.median(cosines):+.3f}, negative in "
            f"{sum(c < 0 for c in cosines)} "
            f"of {len(cosines)}"
        )


if __name__ == "__main__":
    main()
