"""Building blocks for the real-trial tests: tiny ONNX policies, attack textures, a small plan, sim hardware."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[3]
SIM_HW = REPO / "examples" / "hardware" / "sim.yaml"


def tiny_onnx(path: Path, size: int = 32) -> Path:
    """An untrained small-CNN policy exported without a card (the runner then never imports torch for it)."""
    import torch

    from sim.policies.onnx_policy import export_onnx
    from sim.policies.policy import VisuomotorPolicy

    torch.manual_seed(0)
    return export_onnx(VisuomotorPolicy(arch="small_cnn", image_size=size), path)


def straight_ahead_onnx(path: Path, size: int = 32) -> Path:
    """A small-CNN policy whose action is always "move straight ahead" (TCP +z, the camera's view axis).

    The last head layer has zero weights and a bias of 4 on action 2: tanh gives 0.9993 there and
    0 elsewhere, whatever the image. A real ONNX network run by onnxruntime, whose rollouts reach
    the goal from some start poses and the adversarial object from others (the untrained one
    mostly reaches nothing), so the trial outcomes a session logs are not all 'none'.
    """
    import torch

    from sim.policies.onnx_policy import export_onnx
    from sim.policies.policy import VisuomotorPolicy

    torch.manual_seed(0)
    policy = VisuomotorPolicy(arch="small_cnn", image_size=size)
    last = policy.mlp[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
        last.bias[2] = 4.0
    return export_onnx(policy, path)


def attack_dir(path: Path, mesh: str, seed: int = 0) -> Path:
    from attack.artifact import AttackArtifact

    texture = np.random.default_rng(seed).random((16, 16, 3)).astype(np.float32)
    return AttackArtifact(texture, {"attack": {"adversarial_mesh": mesh}}).save(path)


def small_plan(
    out: Path,
    textures_dir: Path,
    n_tcp: int = 2,
    n_layouts: int = 1,
    max_steps: int = 6,
    seed: int = 0,
    conditions=("clean", "adv3d", "patch"),
    scene: Path | None = None,
) -> Path:
    """A cube plan (clean/adv3d/patch x poses x layouts) with short trials, written to ``out``
    (on ``scene``, recorded in the plan; default: the built-in scene)."""
    from sim.spec import load_spec
    from trials.real.plan import make_plan, save_plan, texture_ref

    spec = load_spec(scene)
    textures = {}
    if "adv3d" in conditions:
        textures["cube/adv3d"] = texture_ref(attack_dir(textures_dir / "adv_cube", "cube"), "cube/adv3d", spec)
    if "patch" in conditions:
        textures["cube/patch"] = texture_ref(attack_dir(textures_dir / "patch_cube", "patch", 1), "cube/patch", spec)
    plan = make_plan(
        spec,
        seed,
        ["A"],
        ["cube"],
        list(conditions),
        textures,
        n_tcp_poses=n_tcp,
        n_object_layouts=n_layouts,
        max_steps=max_steps,
        scene=None if scene is None else str(scene),
    )
    save_plan(plan, out)
    return out


def sim_hardware(out: Path, image_size: int = 32, **fields) -> Path:
    """The example sim hardware YAML with a small camera image (speed); ``fields`` are set at its top
    level (``scene_cameras={...}``)."""
    data = yaml.safe_load(SIM_HW.read_text())
    data["sim"]["image_size"] = [image_size, image_size]
    data.update(fields)
    out.write_text(yaml.safe_dump(data))
    return out


def two_camera_onnx(path: Path, front_px: int = 128, forward: float = 3.0) -> Path:
    """A LeRobot-named ONNX policy reading the wrist camera (32 px) and the ``front`` scene camera
    (``front_px``) plus the state (:class:`tests.policy_zoo.TwoCameraPolicy`), whose deltas lean
    "straight ahead" (TCP +z: a head bias of ``forward`` on action 2) so trials reach objects; its
    small head weights still carry both cameras' features."""
    import torch

    from tests.policy_files import two_camera_onnx as export
    from tests.policy_zoo import TwoCameraPolicy, two_camera_card

    policy = TwoCameraPolicy(wrist_px=32, front_px=front_px)
    last = policy.mlp[-1]
    with torch.no_grad():
        last.weight.mul_(0.1)
        last.bias.zero_()
        last.bias[2] = forward
    return export(path, policy, two_camera_card())
