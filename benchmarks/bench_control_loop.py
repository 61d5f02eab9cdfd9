"""Latency from camera frame to arm command: SimCamera -> ONNX resnet18 policy (128x128) -> safety -> SimArm.

Run: ``.venv/bin/python benchmarks/bench_control_loop.py [--arm tcp|joint] [--onnx policy.onnx]
[--stem small|standard] [--threads 1]``.

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
JOINT_SCENE = HERE.parent / "scenes" / "panda-joint.yaml"


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


def stats(xs_s: list[float], cpu_s: list[float] | None = None) -> str:
    """Median and p95 (ms) of wall times ``xs_s`` (s) and, when given, of process CPU times ``cpu_s``."""
    a = np.asarray(xs_s) * 1000.0
    text = f"median {np.median(a):6.2f} ms   p95 {np.percentile(a, 95):6.2f} ms"
    if cpu_s is not None:
        c = np.asarray(cpu_s) * 1000.0
        text += f"   (process CPU median {np.median(c):6.2f} ms, p95 {np.percentile(c, 95):6.2f} ms)"
    return text


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
    args = ap.parse_args()
    for flag, value, least in (
        ("--steps", args.steps, 1),
        ("--warmup", args.warmup, 0),
        ("--threads", args.threads, 0),
    ):
        if value < least:
            ap.error(f"{flag} must be >= {least}, got {value}")

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
    total_med = float(np.median(t_total)) * 1000.0
    print(
        f"control loop ({args.arm} arm, scene {world.spec.name}), {args.steps} steps, {S}x{S} px, policy "
        f"{onnx_path.name}, onnxruntime threads={args.threads} spin={args.spin}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}"
    )
    pol, dec, cmd = loop.stages
    print(f"  camera read (sim render)   {stats(t_cam, c_cam)}")
    print(f"  {pol:<26} {stats(t_pol, c_pol)}")
    if dec is not None:
        print(f"  {dec:<26} {stats(t_dec, c_dec)}")
    print(f"  {cmd:<26} {stats(t_arm, c_arm)}")
    print(f"  frame -> arm command       {stats(t_total, c_total)}   (= {1000.0 / total_med:.1f} Hz at the median)")
    print(f"  commands clipped {clipped}, refused {refused}")
    print(f"  target <= 30 ms median: {'met' if total_med <= 30.0 else 'NOT met'}")


if __name__ == "__main__":
    main()
