"""Reference visuomotor policies: backbones, the white-box torch policy, checkpoints, ONNX export
and the black-box onnxruntime policy, policy files attacked white-box (``.onnx`` through
onnx2torch, ``.pt2`` ExportedPrograms: :mod:`sim.policies.graph_policy`), DAgger and PPO
training, presets, the task-feasible pool.

Modules are imported directly (``from sim.policies.policy import VisuomotorPolicy``) so that
black-box use (:mod:`sim.policies.interface`) does not pull in torch.
"""
