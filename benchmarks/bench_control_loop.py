"""Latency from camera frame to arm command: SimCamera -> ONNX resnet18 policy (128x128) -> safety -> SimArm.

Run: ``.venv/bin/python benchmarks/bench_control_loop.py [--onnx policy.onnx] [--stem small|standard] [--threads 1]``.

Without ``--onnx`` a randomly initialised resnet18 policy from ``sim.policies`` is exported to a
temporary ONNX file (weights do not change the cost). ``--stem small`` is the project's policy
default (no max-pool after conv1: total stride 16, ~4x the FLOPs); ``--stem standard`` is the
ImageNet ResNet-18 stem (stride 32). Prints median and p95 (ms) of each stage of
one loop iteration and of the whole iteration, where the whole starts when the frame is captured
and ends when the arm accepted the command. Target: <= 30 ms median on 2 cores (>= 30 Hz).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np

HERE = Path(__file__).resolve().parent
SIM_YAML = HERE.parent / "examples" / "hardware" / "sim.yaml"


def export_resnet18(path: Path, size: int, small_stem: bool) -> Path:
    import torch

    from sim.policies.onnx_policy import export_onnx
    from sim.policies.policy import VisuomotorPolicy

    torch.manual_seed(0)
    return export_onnx(VisuomotorPolicy(arch="resnet18", image_size=size, small_stem=small_stem), path)


def stats(xs_s: list[float], cpu_s: list[float] | None = None) -> str:
    a = np.asarray(xs_s) * 1000.0
    text = f"median {np.median(a):6.2f} ms   p95 {np.percentile(a, 95):6.2f} ms"
    if cpu_s is not None:
        text += f"   (process CPU {np.median(np.asarray(cpu_s) * 1000.0):6.2f} ms median)"
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--onnx", type=Path, help="policy ONNX file (input (B, 3, S, S)); default: export resnet18")
    ap.add_argument("--size", type=int, default=128, help="image size when exporting the default policy")
    ap.add_argument(
        "--stem",
        choices=["small", "standard"],
        default="small",
        help="resnet18 stem of the default policy (small = the project's policy default)",
    )
    ap.add_argument("--config", type=Path, default=SIM_YAML, help="hardware YAML with sim camera + sim arm")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--warmup", type=int, default=20)
    # 1 thread by default: on 2 shared cores a second (spin-waiting) onnxruntime thread slowed the
    # sim render more than it sped up the policy (measured, see the module docstring).
    ap.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads")
    ap.add_argument("--spin", action="store_true", help="let idle onnxruntime threads spin-wait (off by default)")
    args = ap.parse_args()

    from robot_io.config import build_arm, build_camera, build_world, load_hardware_config
    from sim.policies.onnx_policy import OnnxPolicy

    with tempfile.TemporaryDirectory() as tmp:
        onnx_path = args.onnx or export_resnet18(
            Path(tmp) / f"resnet18_{args.stem}_stem.onnx", args.size, args.stem == "small"
        )
        policy = OnnxPolicy(onnx_path, threads=args.threads, spin=args.spin)
        S = policy.image_size
        cfg = load_hardware_config(args.config)
        cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"image_size": (S, S)})})
        world = build_world(cfg)
        camera, arm = build_camera(cfg, world), build_arm(cfg, world)
        ep = world.spec.episode
        scale = np.array([ep.max_step_m] * 3 + [ep.max_step_rad] * 3)
        t_cam, t_pol, t_arm, t_total = [], [], [], []
        # Process CPU time per stage (all threads): on a shared machine wall time includes waiting
        # for other processes, CPU time does not, so the two bracket the unloaded latency.
        c_cam, c_pol, c_arm = [], [], []
        clipped = refused = 0
        with camera, arm:
            arm.start_trial()
            for i in range(args.warmup + args.steps):
                if i and i % 100 == 0:
                    world.reset()  # keep the random policy from parking the TCP at a wall
                    camera.read()  # the first render after a reset uploads the new look: not timed
                    arm.start_trial()
                c0, t0 = time.process_time(), time.monotonic()
                frame = camera.read()
                c1, t1 = time.process_time(), time.monotonic()
                action = policy.act(frame.rgb[None])[0]
                c2, t2 = time.process_time(), time.monotonic()
                res = arm.step_delta(action.astype(np.float64) * scale, frame)
                c3, t3 = time.process_time(), time.monotonic()
                if i >= args.warmup:
                    t_cam.append(t1 - t0)
                    t_pol.append(t2 - t1)
                    t_arm.append(t3 - t2)
                    c_cam.append(c1 - c0)
                    c_pol.append(c2 - c1)
                    c_arm.append(c3 - c2)
                    t_total.append(t3 - frame.timestamp_s)
                    clipped += res.status == "clipped"
                    refused += res.status == "refused"
        world.close()
    total_med = float(np.median(t_total)) * 1000.0
    print(
        f"control loop, {args.steps} steps, {S}x{S} px, policy {onnx_path.name}, onnxruntime threads={args.threads} "
        f"spin={args.spin}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}"
    )
    print(f"  camera read (sim render)   {stats(t_cam, c_cam)}")
    print(f"  policy (onnxruntime)       {stats(t_pol, c_pol)}")
    print(f"  safety + arm command       {stats(t_arm, c_arm)}")
    print(f"  frame -> arm command       {stats(t_total)}   (= {1000.0 / total_med:.1f} Hz at the median)")
    print(f"  commands clipped {clipped}, refused {refused}")
    print(f"  target <= 30 ms median: {'met' if total_med <= 30.0 else 'NOT met'}")


if __name__ == "__main__":
    main()
