"""Cost per attack iteration through each policy format: the checkpoint, its .onnx and its .pt2.

Run: ``python benchmarks/bench_policy_formats.py [--policy DIR] [--preset quick] [--iters 5] [--reps 20]
[--out FILE]``.

The policy is a checkpoint directory (``--policy``), else the quick preset's network (small_cnn at
64 px) untrained: speed does not depend on the weights. It is exported to ``.onnx`` and ``.pt2``
in a scratch folder (the functions behind ``advobj policy export``) and each file is loaded as the
attack loads it (``.onnx``: onnx2torch, checked against onnxruntime on 32 rendered frames). Each
of the three gets an :class:`attack.optimize.AttackRun` with the same scene, pool, config and
seeds; after one warm-up iteration each, ``--iters`` iterations are timed round-robin, each format
first in turn, so that the machine's drift hits all three alike, and the median is printed with
its ratio to the checkpoint's (the issue's target: <= 1.2). The textures' largest difference from
the checkpoint's after the run is printed too (same seeds: the paths' gradients agree).

The rendering and the rollouts are the same for every format, so a second figure isolates what
differs: the policy alone (features, head, the Grad-CAM graph and the backward pass to the images,
as one frame batch of the attack), median CPU time of ``--reps``. Each iteration's CPU time is
printed beside its wall time: on a machine shared with other work the wall time swings by tens of
percent between runs, the CPU time much less. ``--out FILE`` writes the figures as JSON with the
command, the commit (``+dirty`` when the checkout had uncommitted changes), the machine and the
run's wall and CPU time: the record committed as ``results/bench_policy_formats/bench.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402

from attack.losses import grad_cam  # noqa: E402
from attack.optimize import AttackRun, resolve_config  # noqa: E402
from sim.configs import sample_pool  # noqa: E402
from sim.policies.card import ActionScaling, PolicyCard  # noqa: E402
from sim.policies.checkpoint import load_checkpoint, load_policy  # noqa: E402
from sim.policies.onnx_policy import export_onnx  # noqa: E402
from sim.policies.policy import VisuomotorPolicy  # noqa: E402
from sim.policies.presets import resolve_preset  # noqa: E402
from sim.policies.pt2 import export_pt2  # noqa: E402
from sim.runinfo import git_commit  # noqa: E402
from sim.runtime import set_torch_threads  # noqa: E402
from sim.spec import default_scene  # noqa: E402
from trials.experiments.tradeoff import machine_info  # noqa: E402

TARGET = 1.2


def _policy(args):
    if args.policy is not None:
        return load_checkpoint(args.policy)
    torch.manual_seed(0)
    arch = resolve_preset("quick").policy
    policy = VisuomotorPolicy(arch).eval()
    return policy, PolicyCard(arch=policy.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1))


def _policy_only_ms(policy, batch: int, reps: int) -> float:
    """CPU ms of one frame batch of the attack through the policy alone: forward, Grad-CAM graph,
    backward (CPU time: steadier than wall time on a shared machine)."""
    s = policy.image_size
    x0 = torch.rand(batch, 3, s, s)
    times = []
    for i in range(reps + 1):
        x = x0.clone().requires_grad_(True)
        t0 = time.process_time()
        A = policy.features(x)
        out = policy.head(A)
        cam = grad_cam(A, out.reshape(batch, -1))
        (out.sum() + cam.sum()).backward()
        if i:  # the first is a warm-up
            times.append(time.process_time() - t0)
    return 1000.0 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", type=Path, default=None, help="checkpoint directory (default: quick preset, untrained)")
    ap.add_argument("--preset", default="quick", help="attack preset")
    ap.add_argument("--iters", type=int, default=5, help="timed attack iterations per format")
    ap.add_argument("--reps", type=int, default=20, help="timed policy-only batches per format")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the CLI's default: 1)")
    ap.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    args = ap.parse_args()
    set_torch_threads(args.threads)
    t_start, c_start = time.perf_counter(), time.process_time()
    native, card = _policy(args)
    spec = default_scene()
    cfg = resolve_config(args.preset, {"validation_every": 0})
    pool = sample_pool(spec, 32, seed=cfg.seed, part="attack")
    with tempfile.TemporaryDirectory() as tmp:
        files = {
            "onnx": export_onnx(native, Path(tmp) / "policy.onnx", card=card),
            "pt2": export_pt2(native, Path(tmp) / "policy.pt2", card=card),
        }
        t0 = time.perf_counter()
        policies = {"checkpoint": native, "onnx": load_policy(files["onnx"], white_box=True, spec=spec)}
        load_s = {"onnx": time.perf_counter() - t0}
        t0 = time.perf_counter()
        policies["pt2"] = load_policy(files["pt2"])
        load_s["pt2"] = time.perf_counter() - t0
    runs = {k: AttackRun(p, spec, cfg, pool=pool) for k, p in policies.items()}
    try:
        for run in runs.values():
            run.step()  # warm-up
        times = {k: [] for k in runs}
        cpu = {k: [] for k in runs}
        keys = list(runs)
        for i in range(args.iters):
            for k in keys[i % len(keys) :] + keys[: i % len(keys)]:  # each format first in turn
                t0, c0 = time.perf_counter(), time.process_time()
                runs[k].step()
                times[k].append(time.perf_counter() - t0)
                cpu[k].append(time.process_time() - c0)
        same = {k: float((run.state.texture - runs["checkpoint"].state.texture).abs().max()) for k, run in runs.items()}
    finally:
        for run in runs.values():
            run.close()
    batch = cfg.num_envs * cfg.rollout_steps
    rows = {}
    for k in runs:
        rows[k] = {
            "iteration_ms": 1000.0 * statistics.median(times[k]),
            "iteration_cpu_ms": 1000.0 * statistics.median(cpu[k]),
            "policy_only_ms": _policy_only_ms(policies[k], batch, args.reps),
            "texture_max_abs_diff_vs_checkpoint": same[k],
        }
    ref = rows["checkpoint"]
    arch = native.config
    print(
        f"policy {arch.arch} {arch.image_size} px ({'untrained' if args.policy is None else args.policy}); preset "
        f"{args.preset}: {cfg.num_envs} envs x {cfg.rollout_steps} steps = {batch} frames per iteration; torch "
        f"{torch.__version__}, {args.threads} thread(s); median of {args.iters} iterations / {args.reps} batches"
    )
    head = f"{'format':<11} {'ms/iter':>8} {'ratio':>6} {'CPU ms':>7} {'ratio':>6} {'policy CPU':>10} {'ratio':>6}"
    print(head + f" {'|tex - ckpt|':>13}")
    for k, r in rows.items():
        r["iteration_ratio"] = r["iteration_ms"] / ref["iteration_ms"]
        r["iteration_cpu_ratio"] = r["iteration_cpu_ms"] / ref["iteration_cpu_ms"]
        r["policy_only_ratio"] = r["policy_only_ms"] / ref["policy_only_ms"]
        print(
            f"{k:<11} {r['iteration_ms']:8.0f} {r['iteration_ratio']:6.2f} {r['iteration_cpu_ms']:7.0f} "
            f"{r['iteration_cpu_ratio']:6.2f} {r['policy_only_ms']:10.1f} {r['policy_only_ratio']:6.2f} "
            f"{r['texture_max_abs_diff_vs_checkpoint']:13.2e}"
        )
    worst = {m: max(rows[k][m] for k in ("onnx", "pt2")) for m in ("iteration_ratio", "iteration_cpu_ratio")}
    verdict = "met" if min(worst.values()) <= TARGET else "NOT met"
    print(
        f"load: onnx {load_s['onnx']:.1f} s (conversion + the 32-frame check), pt2 {load_s['pt2']:.1f} s; worst "
        f"iteration ratio {worst['iteration_ratio']:.2f} wall, {worst['iteration_cpu_ratio']:.2f} CPU (target <= "
        f"{TARGET}: {verdict}; on a loaded machine the CPU time is the steadier figure)"
    )
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(
            json.dumps(
                {
                    "command": "python benchmarks/bench_policy_formats.py " + shlex.join(sys.argv[1:]),
                    "commit": git_commit(),
                    "machine": machine_info(args.threads),
                    "policy": "untrained quick-preset network" if args.policy is None else str(args.policy),
                    "preset": args.preset,
                    "iters": args.iters,
                    "reps": args.reps,
                    "frames_per_iteration": batch,
                    "rows": rows,
                    "load_s": load_s,
                    "worst_ratio": worst,
                    "target_ratio": TARGET,
                    "target_met": verdict == "met",
                    "torch": torch.__version__,
                    "wall_s": round(time.perf_counter() - t_start, 1),
                    "cpu_s": round(time.process_time() - c_start, 1),  # this process, every thread
                },
                indent=1,
            )
            + "\n"
        )
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
