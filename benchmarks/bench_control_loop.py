"""Latency from camera frame to arm command: SimCamera -> ONNX resnet18 policy (128x128) -> safety -> SimArm.

Run: ``.venv/bin/python benchmarks/bench_control_loop.py [--arm tcp|joint] [--onnx policy.onnx]
[--stem small|standard] [--threads 1] [--out FILE.json]``.

Without ``--onnx`` a randomly initialised resnet18 policy from ``sim.policies`` is exported to a
temporary ONNX file (weights do not change the cost). ``--stem small`` is the project's policy
default (no max-pool after conv1: total stride 16, ~4x the FLOPs); ``--stem standard`` is the
ImageNet ResNet-18 stem (stride 32). Prints median and p95 (ms) of each stage of
one loop iteration and of the whole iteration, wall time and process CPU time, where the whole
starts when the frame is captured and ends when the arm accepted the command. Target: <= 30 ms
median on 2 cores (>= 30 Hz).

``--arm tcp`` (the default): the built-in scene's floating gripper; the policy's ``delta_tcp``
action goes through ``SafeArm.step_delta``. ``--arm joint``: a joint-space policy on the
joint-driven sim arm of a scene with an arm (``--scene``, default ``scenes/panda-joint.yaml``,
the shipped Panda): the default policy reads the arm's joint positions and commands
``joint_delta`` (the contract ``advobj policy train`` gives it on that scene), and each loop is
frame -> joint state + policy -> decode (the contract's actions, the joint target at the measured
joints) -> ``SafeArm.step_joints`` (joint position, speed and jump limits, FK of the command and
the workspace box) -> the sim arm's command (its TCP and wrist camera follow FK). A chunked
``--onnx`` policy is asked every step and only its first action sent: the worst case.

``--out FILE.json`` also writes the figures as JSON (atomically): the command, the commit (``+dirty``
when the checkout had uncommitted changes), the machine, the arm mode, the policy and its image size,
steps, warm-up and threads, each stage's wall and process CPU median and p95, the clipped and refused
commands, and the run's wall and CPU time: a record that can be committed as evidence.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np

HERE = Path(__file__).resolve().parent
SIM_YAML = HERE.parent / "examples" / "hardware" / "sim.yaml"
JOINT_SCENE = HERE.parent / "scenes" / "panda-joint.yaml"
TARGET_MS = 30.0  # frame -> arm command, median (>= 30 Hz)


def export_resnet18(path: Path, size: int, small_stem: bool) -> Path:
    import torch

    from sim.policies.onnx_policy import export_onnx
    from sim.policies.policy import VisuomotorPolicy

    torch.manual_seed(0)
    return export_onnx(VisuomotorPolicy(arch="resnet18", image_size=size, small_stem=small_stem), path)


def export_joint_resnet18(path: Path, size: int, small_stem: bool, spec) -> Path:
    """A randomly initialised joint-space resnet18 on ``spec``'s arm, exported with its card: it reads
    the joint positions and commands ``joint_delta`` (:func:`sim.policies.presets.joint_contract`)."""
    import torch

    from sim.policies.card import ActionScaling, PolicyCard
    from sim.policies.contract import PolicyContract
    from sim.policies.onnx_policy import export_onnx
    from sim.policies.policy import PolicyArch, VisuomotorPolicy
    from sim.policies.presets import joint_contract

    contract_fields, arch_fields = joint_contract(spec, "joint_delta")
    arch = PolicyArch(arch="resnet18", image_size=size, small_stem=small_stem, **arch_fields)
    contract = PolicyContract(**contract_fields)
    torch.manual_seed(0)
    policy = VisuomotorPolicy(arch, contract=contract)
    ep = spec.episode
    card = PolicyCard(
        arch=arch, action=ActionScaling(max_step_m=ep.max_step_m, max_step_rad=ep.max_step_rad), contract=contract
    )
    return export_onnx(policy, path, card=card)


def summarize(xs_s: list[float], cpu_s: list[float]) -> dict:
    """Median and p95 (ms) of wall times ``xs_s`` (s) and of process CPU times ``cpu_s`` (s)."""
    a, c = np.asarray(xs_s) * 1000.0, np.asarray(cpu_s) * 1000.0
    return {
        "wall_median_ms": float(np.median(a)),
        "wall_p95_ms": float(np.percentile(a, 95)),
        "cpu_median_ms": float(np.median(c)),
        "cpu_p95_ms": float(np.percentile(c, 95)),
    }


def stats(s: dict) -> str:
    """One printed stage: the figures of :func:`summarize` (the same numbers the JSON holds)."""
    return (
        f"median {s['wall_median_ms']:6.2f} ms   p95 {s['wall_p95_ms']:6.2f} ms   "
        f"(process CPU median {s['cpu_median_ms']:6.2f} ms, p95 {s['cpu_p95_ms']:6.2f} ms)"
    )


def write_json(path: Path, doc: dict) -> None:
    """Write ``doc`` to ``path`` atomically (:func:`sim.files.write_atomic`): a failure leaves
    neither a half-written file nor the temporary."""
    from sim.files import write_atomic  # lazy: after the argument checks (sim.errors)

    write_atomic(path, (json.dumps(doc, indent=1, allow_nan=False) + "\n").encode())


class TcpLoop:
    """One ``delta_tcp`` policy step: the policy's action, scaled by the scene's step limits,
    through ``SafeArm.step_delta``."""

    stages = ("policy (onnxruntime)", None, "safety + arm command")

    def __init__(self, policy, arm, spec):
        from sim.policies.contract import policy_contract

        contract = policy_contract(policy)
        if contract.is_joint_space:
            raise ValueError(f"--arm tcp: the policy ({contract.describe()}) moves joints; give --arm joint")
        self.policy, self.arm = policy, arm
        ep = spec.episode
        self.scale = np.array([ep.max_step_m] * 3 + [ep.max_step_rad] * 3)

    def act(self, frame):
        return self.policy.act(frame.rgb[None])[0]

    def decode(self, raw):
        return raw

    def command(self, action, frame):
        return self.arm.step_delta(action.astype(np.float64) * self.scale, frame)

    def restart(self) -> None:
        pass  # world.reset() put the TCP at a new start


class JointLoop:
    """One joint-space policy step, as the real-trial runner makes it: the measured joints as the
    state, the contract's decoding, the joint target at those joints through ``SafeArm.step_joints``."""

    stages = ("joint state + policy", "decode + joint target", "safety (FK) + arm command")

    def __init__(self, policy, arm, spec):
        from sim.policies.contract import check_scene, policy_contract

        self.contract = policy_contract(policy)
        if not self.contract.is_joint_space:
            raise ValueError(f"--arm joint: the policy ({self.contract.describe()}) is not a joint-space policy")
        check_scene(policy, spec)  # joints that are not the scene arm's: PolicyError, one line
        self.policy, self.arm = policy, arm
        self.gripper_m = float(spec.gripper.opening_m)
        self.q_home = np.asarray(arm.kinematics().q_home, dtype=np.float64)

    def act(self, frame):
        from sim.policies.contract import call_policy, state_vector

        self.q = self.arm.joint_positions()
        state = state_vector(self.contract, self.arm.tcp_pose()[None], self.gripper_m, self.q[None])
        return call_policy(self.policy, frame.rgb[None], state)

    def decode(self, raw):
        from sim.policies.contract import decode_actions, to_joint_target

        a = decode_actions(np.asarray(raw, dtype=np.float64), self.contract, 1)[:, 0]  # the chunk's first action
        return to_joint_target(self.q[None], a, self.contract.action.kind)[0]

    def command(self, q_target, frame):
        return self.arm.step_joints(q_target, frame)

    def restart(self) -> None:
        self.arm.move_joints(self.q_home)  # the arm's start, not wherever the random policy parked it


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--arm",
        choices=["tcp", "joint"],
        default="tcp",
        help="tcp: a delta_tcp policy moving the floating gripper; joint: a joint-space policy on the joint-driven "
        "sim arm of --scene through SafeArm.step_joints (FK and the joint checks timed)",
    )
    ap.add_argument("--onnx", type=Path, help="policy ONNX file (input (B, 3, S, S)); default: export resnet18")
    ap.add_argument("--size", type=int, default=128, help="image size when exporting the default policy")
    ap.add_argument(
        "--stem",
        choices=["small", "standard"],
        default="small",
        help="resnet18 stem of the default policy (small = the project's policy default)",
    )
    ap.add_argument("--config", type=Path, default=SIM_YAML, help="hardware YAML with sim camera + sim arm")
    ap.add_argument(
        "--scene",
        type=Path,
        help=f"scene YAML of the sim world (default: the config's; with --arm joint: {JOINT_SCENE.name})",
    )
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--warmup", type=int, default=20)
    # 1 thread by default: on 2 shared cores a second (spin-waiting) onnxruntime thread slowed the
    # sim render more than it sped up the policy (measured, see the module docstring).
    ap.add_argument("--threads", type=int, default=1, help="onnxruntime (and, with --arm joint, torch) threads")
    ap.add_argument("--spin", action="store_true", help="let idle onnxruntime threads spin-wait (off by default)")
    ap.add_argument("--out", type=Path, help="also write the figures as JSON here (its folder must exist)")
    args = ap.parse_args()
    for flag, value, least in (
        ("--steps", args.steps, 1),
        ("--warmup", args.warmup, 0),
        ("--threads", args.threads, 0),
    ):
        if value < least:
            ap.error(f"{flag} must be >= {least}, got {value}")
    if args.out is not None:
        if not args.out.parent.is_dir():
            ap.error(f"--out {args.out}: folder {args.out.parent} does not exist")
        if args.out.is_dir():
            ap.error(f"--out {args.out}: is a folder; give a file name")
        if not os.access(args.out.parent, os.W_OK):
            ap.error(f"--out {args.out}: folder {args.out.parent} is not writable")
    t_start, c_start = time.perf_counter(), time.process_time()

    from robot_io.config import build_arm, build_camera, build_world, load_hardware_config
    from sim.policies.onnx_policy import OnnxPolicy
    from sim.runtime import set_torch_threads
    from sim.spec import load_spec

    cfg = load_hardware_config(args.config)
    scene = args.scene or (JOINT_SCENE if args.arm == "joint" else None)
    if scene is not None:
        cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"scene": scene})})
    if args.arm == "joint":
        set_torch_threads(args.threads)  # the safety layer's FK
    with tempfile.TemporaryDirectory() as tmp:
        if args.onnx is not None:
            onnx_path = args.onnx
        elif args.arm == "joint":
            spec = load_spec(cfg.sim.scene)  # the arm the default policy is made for
            if spec.arm is None:
                ap.error(f"--arm joint: scene {spec.name!r} has no arm (give --scene a scene with arm:)")
            name = f"resnet18_{args.stem}_stem_joint.onnx"
            onnx_path = export_joint_resnet18(Path(tmp) / name, args.size, args.stem == "small", spec)
        else:
            name = f"resnet18_{args.stem}_stem.onnx"
            onnx_path = export_resnet18(Path(tmp) / name, args.size, args.stem == "small")
        policy = OnnxPolicy(onnx_path, threads=args.threads, spin=args.spin)
        S = policy.image_size
        cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"image_size": (S, S)})})
        world = build_world(cfg)
        if args.arm == "joint" and world.spec.arm is None:
            ap.error(f"--arm joint: scene {world.spec.name!r} has no arm (give --scene a scene with arm:)")
        camera, arm = build_camera(cfg, world), build_arm(cfg, world)
        try:
            loop = (JointLoop if args.arm == "joint" else TcpLoop)(policy, arm, world.spec)
        except ValueError as err:  # the policy does not fit the arm mode or the scene's arm
            ap.error(str(err))
        t_cam, t_pol, t_dec, t_arm, t_total = [], [], [], [], []
        # Process CPU time per stage (all threads): on a shared machine wall time includes waiting
        # for other processes, CPU time does not, so the two bracket the unloaded latency.
        c_cam, c_pol, c_dec, c_arm, c_total = [], [], [], [], []
        clipped = refused = 0
        with camera, arm:
            arm.start_trial()
            for i in range(args.warmup + args.steps):
                if i and i % 100 == 0:
                    world.reset()  # keep the random policy from parking the TCP at a wall
                    loop.restart()
                    camera.read()  # the first render after a reset uploads the new look: not timed
                    arm.start_trial()
                c0, t0 = time.process_time(), time.monotonic()
                frame = camera.read()
                c1, t1 = time.process_time(), time.monotonic()
                raw = loop.act(frame)
                c2, t2 = time.process_time(), time.monotonic()
                action = loop.decode(raw)
                c3, t3 = time.process_time(), time.monotonic()
                res = loop.command(action, frame)
                c4, t4 = time.process_time(), time.monotonic()
                if i >= args.warmup:
                    for out, a, b in (
                        (t_cam, t0, t1),
                        (t_pol, t1, t2),
                        (t_dec, t2, t3),
                        (t_arm, t3, t4),
                        (c_cam, c0, c1),
                        (c_pol, c1, c2),
                        (c_dec, c2, c3),
                        (c_arm, c3, c4),
                        (c_total, c0, c4),
                    ):
                        out.append(b - a)
                    t_total.append(t4 - frame.timestamp_s)
                    clipped += res.status == "clipped"
                    refused += res.status == "refused"
        world.close()
    wall_s, cpu_s = time.perf_counter() - t_start, time.process_time() - c_start
    pol, dec, cmd = loop.stages
    stages = {
        "camera": ("camera read (sim render)", summarize(t_cam, c_cam)),
        "policy": (pol, summarize(t_pol, c_pol)),
        "decode": (dec or "decode (none: the action as the policy gave it)", summarize(t_dec, c_dec)),
        "safety_arm_command": (cmd, summarize(t_arm, c_arm)),
        "loop": ("frame -> arm command", summarize(t_total, c_total)),
    }
    total_med = stages["loop"][1]["wall_median_ms"]
    print(
        f"control loop ({args.arm} arm, scene {world.spec.name}), {args.steps} steps, {S}x{S} px, policy "
        f"{onnx_path.name}, onnxruntime threads={args.threads} spin={args.spin}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}"
    )
    for key, (label, s) in stages.items():
        if key == "decode" and dec is None:
            continue  # a delta_tcp action goes to the arm as it is: nothing to show
        tail = f"   (= {1000.0 / total_med:.1f} Hz at the median)" if key == "loop" else ""
        print(f"  {label:<26} {stats(s)}{tail}")
    print(f"  commands clipped {clipped}, refused {refused}")
    print(f"  target <= {TARGET_MS:.0f} ms median: {'met' if total_med <= TARGET_MS else 'NOT met'}")
    if args.out is not None:
        from sim.runinfo import git_commit
        from trials.experiments.tradeoff import machine_info  # lazy: after the timed loop (torch, onnxruntime)

        if args.onnx is not None:
            policy_text = str(args.onnx)
        else:
            moves = "reads the arm's joints, commands joint_delta" if args.arm == "joint" else "commands delta_tcp"
            policy_text = (
                f"untrained resnet18 ({args.stem} stem, {args.size} px, torch seed 0; {moves}), exported to ONNX"
            )
        write_json(
            args.out,
            {
                "command": "python benchmarks/bench_control_loop.py " + shlex.join(sys.argv[1:]),
                "commit": git_commit(),
                "machine": machine_info(args.threads),
                "arm": args.arm,
                "scene": world.spec.name,
                "policy": policy_text,
                "image_size": S,
                "steps": args.steps,
                "warmup": args.warmup,
                "threads": args.threads,
                "spin": args.spin,
                "stages": {key: {"label": label, **s} for key, (label, s) in stages.items()},
                "commands": {"clipped": int(clipped), "refused": int(refused)},
                "target_median_ms": TARGET_MS,
                "target_met": total_med <= TARGET_MS,
                "wall_s": round(wall_s, 2),
                "cpu_s": round(cpu_s, 2),  # this process, every thread
            },
        )
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
