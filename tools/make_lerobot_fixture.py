"""LeRobot's own ACT, random weights, exported to ONNX as a test fixture (``tests/data/lerobot_act/``).

Run in a separate environment that has lerobot (0.4.4 pins torch < 2.11 and Python >= 3.10, so it
never goes into the project's environment), from the checkout's root::

    python -m tools.make_lerobot_fixture --out tests/data/lerobot_act

It builds ``lerobot.policies.act.modeling_act.ACTPolicy`` from an ``ACTConfig`` with two cameras
(``observation.images.wrist``, ``observation.images.front``), a 6-value ``observation.state`` (the
TCP pose), 6-value actions in chunks of 10 and the smallest transformer the config allows (no VAE,
no pretrained backbone: nothing is downloaded), and exports its inference path,
``ACTPolicy.predict_action_chunk`` (images + state -> ``action`` ``(B, chunk, 6)``), with torch's
TorchScript ONNX exporter under LeRobot's names. LeRobot 0.4 normalises outside the model (its
processor pipeline), so the graph takes normalised images; the pipeline's image statistics (the
ImageNet ones LeRobot's datasets use by default) are recorded in the provenance for the card.

**Size.** ACT's vision backbone is torchvision's ResNet-18 (about 11 M parameters, 45 MB of
float32), far too large to commit. Every convolution weight of at least :data:`MIN_STRIPPED`
values is therefore set, before the export, to values that :func:`refill_values` computes from
the tensor's name, its shape and the seed alone (He-uniform: ``U(-b, b)``, ``b = sqrt(6 / fan_in)``,
from numpy's PCG64), and the committed ``act.onnx`` keeps those tensors as ONNX external data whose
file is not shipped (name, type and shape stay in the graph). Every other tensor (the folded frozen
batch norms, biases, the transformer, the position embeddings, every integer constant) stays in the
file as exported. :func:`refill_onnx` writes the stripped values back and checks them against the
digest recorded at export, so the refilled graph is byte for byte the tensors LeRobot's module was
exported with; ``reference`` in the provenance holds that module's own output on seeded inputs
(:func:`reference_inputs`), which the refilled graph must reproduce.

Only numpy and onnx are imported at the top: the tests import :func:`refill_onnx` and
:func:`reference_inputs` from the project's environment, which has no lerobot.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

__all__ = [
    "MIN_STRIPPED",
    "STRIPPED_LOCATION",
    "refill_values",
    "weights_digest",
    "stripped_initializers",
    "refill_onnx",
    "reference_inputs",
    "main",
]

MIN_STRIPPED = 4096  # a convolution weight with at least this many values is stripped (16 KiB of float32)
STRIPPED_LOCATION = "stripped-weights-refill-with-tools.make_lerobot_fixture"  # an external-data file never shipped
SIZE_BUDGET_BYTES = 2_000_000  # the committed graph must stay under this
ONNX_NAME, PROVENANCE_NAME, LICENSE_NAME = "act.onnx", "provenance.json", "LICENSE"
OPSET = 17


def refill_values(name: str, shape, seed: int) -> np.ndarray:
    """The float32 values of stripped convolution weight ``name`` of ``shape`` ``(O, I, kh, kw)``:
    He-uniform ``U(-b, b)`` with ``b = sqrt(6 / (I * kh * kw))``, drawn from PCG64 seeded by
    ``seed`` and the name's sha256 (so each tensor's values depend on nothing else)."""
    shape = tuple(int(v) for v in shape)
    if len(shape) != 4 or min(shape) < 1:
        raise ValueError(f"{name}: a stripped weight is a convolution's (O, I, kh, kw), got {shape}")
    fan_in = shape[1] * shape[2] * shape[3]
    words = np.frombuffer(hashlib.sha256(name.encode()).digest()[:16], dtype="<u4")
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), *map(int, words)])))
    bound = np.sqrt(6.0 / fan_in)
    return ((rng.random(shape) * 2.0 - 1.0) * bound).astype(np.float32)


def weights_digest(tensors: dict[str, np.ndarray]) -> str:
    """sha256 over ``name, shape, little-endian float32 bytes`` of each tensor, in name order."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        a = np.ascontiguousarray(tensors[name], dtype="<f4")
        h.update(name.encode() + b"\0" + json.dumps(list(a.shape)).encode() + b"\0" + a.tobytes())
    return h.hexdigest()


def _conv_weights(model: onnx.ModelProto) -> set[str]:
    return {n.input[1] for n in model.graph.node if n.op_type == "Conv" and len(n.input) > 1}


def stripped_initializers(model: onnx.ModelProto) -> list[onnx.TensorProto]:
    """The initializers of ``model`` held as the never-shipped external data (shape only)."""
    out = []
    for t in model.graph.initializer:
        if t.data_location == onnx.TensorProto.EXTERNAL:
            where = {e.key: e.value for e in t.external_data}.get("location")
            if where != STRIPPED_LOCATION:
                raise ValueError(f"initializer {t.name!r}: external data in {where!r}, not a stripped weight")
            out.append(t)
    return out


def refill_onnx(skeleton: str | Path, out: str | Path, seed: int, digest: str) -> Path:
    """Write ``skeleton`` (the committed graph) to ``out`` with every stripped weight refilled by
    :func:`refill_values`; raises ``ValueError`` when the refilled values' :func:`weights_digest`
    is not ``digest`` (the one recorded at export) or a stripped tensor is not a float convolution
    weight."""
    model = onnx.load(str(skeleton), load_external_data=False)
    convs = _conv_weights(model)
    values = {}
    for t in stripped_initializers(model):
        if t.data_type != onnx.TensorProto.FLOAT or t.name not in convs:
            raise ValueError(f"stripped initializer {t.name!r} is not a float32 convolution weight")
        values[t.name] = refill_values(t.name, t.dims, seed)
        filled = numpy_helper.from_array(values[t.name], t.name)
        t.CopyFrom(filled)
    if not values:
        raise ValueError(f"{skeleton}: no stripped weights to refill")
    got = weights_digest(values)
    if got != digest:
        raise ValueError(f"refilled weights' digest {got} is not the recorded {digest}")
    out = Path(out)
    onnx.save(model, str(out))
    return out


def reference_inputs(seed: int, image_px: int, state_dim: int, mean, std, batch: int = 2) -> dict[str, np.ndarray]:
    """Model inputs by LeRobot name: images uniform in [0, 1] normalised by ``mean`` / ``std``
    (what LeRobot's processor hands ACT), and a state uniform in [-1, 1]; float32."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 1])))
    m = np.asarray(mean, np.float64).reshape(1, 3, 1, 1)
    s = np.asarray(std, np.float64).reshape(1, 3, 1, 1)
    out = {}
    for cam in ("wrist", "front"):
        x = rng.random((batch, 3, image_px, image_px))
        out[f"observation.images.{cam}"] = ((x - m) / s).astype(np.float32)
    out["observation.state"] = (rng.random((batch, state_dim)) * 2.0 - 1.0).astype(np.float32)
    return out


# ----------------------------------------------------------------------------- the export (lerobot's env)
def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in ("lerobot", "torch", "torchvision", "onnx", "numpy", "draccus"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def _lerobot_license() -> tuple[str, Path]:
    """lerobot's licence as its distribution declares it, and its licence file."""
    dist = metadata.distribution("lerobot")
    declared = dist.metadata.get("License-Expression") or dist.metadata.get("License") or "unknown"
    files = [f for f in dist.files or [] if f.name.upper().startswith("LICENSE")]
    if not files:
        raise SystemExit("lerobot's distribution ships no LICENSE file")
    return declared, Path(dist.locate_file(files[0]))


def _build(args):
    """LeRobot's ACTPolicy of the fixture's config, in eval mode, with the large convolution weights refilled."""
    import torch  # lazy: optional dependency (lerobot's torch)
    from lerobot.configs.types import FeatureType, PolicyFeature  # lazy: optional dependency (lerobot)
    from lerobot.policies.act.configuration_act import ACTConfig  # lazy: optional dependency (lerobot)
    from lerobot.policies.act.modeling_act import ACTPolicy  # lazy: optional dependency (lerobot)

    torch.manual_seed(args.seed)
    S = args.image_px
    config = ACTConfig(
        input_features={
            "observation.images.wrist": PolicyFeature(type=FeatureType.VISUAL, shape=(3, S, S)),
            "observation.images.front": PolicyFeature(type=FeatureType.VISUAL, shape=(3, S, S)),
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(args.state_dim,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(6,))},
        device="cpu",
        chunk_size=args.chunk,
        n_action_steps=args.chunk,
        vision_backbone="resnet18",
        pretrained_backbone_weights=None,
        dim_model=args.dim_model,
        n_heads=args.n_heads,
        dim_feedforward=args.dim_feedforward,
        n_encoder_layers=1,
        n_decoder_layers=1,
        use_vae=False,
        push_to_hub=False,
    )
    policy = ACTPolicy(config).eval()
    return config, policy


def _write(path: Path, data: bytes) -> None:
    """Replace ``path`` by ``data`` through a new temporary file beside it (O_EXCL)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _export(args, out_dir: Path) -> dict:
    import draccus  # lazy: optional dependency (lerobot's config library)
    import torch  # lazy: optional dependency (lerobot's torch)
    from lerobot.datasets.factory import IMAGENET_STATS  # lazy: optional dependency (lerobot)

    config, policy = _build(args)

    class Exported(torch.nn.Module):
        """``(wrist, front, state) -> action``: LeRobot's inference call under LeRobot's names."""

        def __init__(self, policy):
            super().__init__()
            self.policy = policy

        def forward(self, wrist, front, state):
            batch = {"observation.images.wrist": wrist, "observation.images.front": front, "observation.state": state}
            return self.policy.predict_action_chunk(batch)

    wrapper = Exported(policy).eval()
    refilled = {}
    with torch.no_grad():
        for name, p in wrapper.named_parameters():
            if p.ndim == 4 and p.numel() >= MIN_STRIPPED:
                refilled[name] = refill_values(name, tuple(p.shape), args.seed)
                p.copy_(torch.from_numpy(refilled[name]))
    mean, std = IMAGENET_STATS["mean"], IMAGENET_STATS["std"]
    mean = [float(v) for v in np.asarray(mean, np.float64).reshape(-1)]
    std = [float(v) for v in np.asarray(std, np.float64).reshape(-1)]
    ref_in = reference_inputs(args.seed, args.image_px, args.state_dim, mean, std)
    with torch.no_grad():
        ref_out = policy.predict_action_chunk({k: torch.from_numpy(v) for k, v in ref_in.items()}).numpy()

    names = ["observation.images.wrist", "observation.images.front", "observation.state"]
    buf = io.BytesIO()
    torch.onnx.export(
        wrapper,
        tuple(torch.from_numpy(ref_in[n]) for n in names),
        buf,
        input_names=names,
        output_names=["action"],
        dynamic_axes={**{n: {0: "batch"} for n in names}, "action": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )
    full_bytes = buf.getvalue()
    model = onnx.load_from_string(full_bytes)
    for marker in (b"/tmp/", b"/home/", b"/root/", b"/work/", b"site-packages"):
        if marker in full_bytes:
            raise SystemExit(f"the exported graph holds a machine path ({marker.decode()}); not writing it")

    convs = _conv_weights(model)
    stripped, kept_large = {}, []
    for t in model.graph.initializer:
        n = int(np.prod(t.dims)) if t.dims else 1
        if t.data_type != onnx.TensorProto.FLOAT or n < MIN_STRIPPED:
            continue
        if t.name not in convs or t.name not in refilled:
            kept_large.append(t.name)
            continue
        if not np.array_equal(numpy_helper.to_array(t), refilled[t.name]):
            raise SystemExit(f"{t.name}: the exported tensor is not the refilled one; not stripping it")
        stripped[t.name] = refilled[t.name]
        name, dims, dtype = t.name, list(t.dims), t.data_type
        t.Clear()
        t.name, t.data_type = name, dtype
        t.dims.extend(dims)
        t.data_location = onnx.TensorProto.EXTERNAL
        entry = t.external_data.add()
        entry.key, entry.value = "location", STRIPPED_LOCATION
    missing = sorted(set(refilled) - set(stripped))
    if missing:
        raise SystemExit(f"refilled weights not found as convolution initializers in the export: {missing[:3]}")
    skeleton = model.SerializeToString()
    if len(skeleton) > SIZE_BUDGET_BYTES:
        raise SystemExit(f"the stripped graph is {len(skeleton)} bytes, over the {SIZE_BUDGET_BYTES} budget")

    _write(out_dir / ONNX_NAME, skeleton)
    declared, license_file = _lerobot_license()
    _write(out_dir / LICENSE_NAME, license_file.read_bytes())
    n_params = sum(p.numel() for p in policy.parameters())
    return {
        "what": "LeRobot's ACTPolicy (random weights) exported to ONNX: predict_action_chunk, images + state -> "
        "action chunk, under LeRobot's names",
        "versions": _versions(),
        "lerobot_license": declared,
        "lerobot_license_file": LICENSE_NAME,
        "seed": args.seed,
        "config": draccus.encode(config),
        "parameters": n_params,
        "export": {
            "exporter": "torch.onnx.export (TorchScript, dynamo=False), constant folding on",
            "opset": OPSET,
            "inputs": names,
            "output": "action",
            "dynamic_axes": "batch (axis 0 of every input and of the output)",
            "wrapper": "forward(wrist, front, state) = ACTPolicy.predict_action_chunk({LeRobot name: tensor})",
        },
        "processor": {
            "note": "LeRobot 0.4 normalises in its processor pipeline, outside the model: the graph takes images "
            "(x - mean) / std with x in [0, 1] (the ImageNet statistics LeRobot's datasets use by default, "
            "use_imagenet_stats); the state and the actions are the model's own (identity statistics here)",
            "image_mean": mean,
            "image_std": std,
        },
        "stripping": {
            "why": "ACT's ResNet-18 backbone holds about 11 M float32 parameters (45 MB), too large to commit; "
            f"every convolution weight of at least {MIN_STRIPPED} values was set before the export to "
            "refill_values(name, shape, seed) (He-uniform U(-b, b), b = sqrt(6 / fan_in), PCG64 seeded by the "
            "seed and the name's sha256) and is stored as ONNX external data that is not shipped; "
            "tools.make_lerobot_fixture.refill_onnx writes them back and checks refilled_weights_sha256",
            "min_values": MIN_STRIPPED,
            "tensors": len(stripped),
            "values": int(sum(v.size for v in stripped.values())),
            "refilled_weights_sha256": weights_digest(stripped),
            "large_tensors_kept": kept_large,
        },
        "sha256": {
            "exported_onnx": hashlib.sha256(full_bytes).hexdigest(),
            "committed_onnx": hashlib.sha256(skeleton).hexdigest(),
        },
        "reference": {
            "what": "ACTPolicy.predict_action_chunk of the refilled module (lerobot's torch) on "
            "reference_inputs(seed, image_px, state_dim, image_mean, image_std, batch)",
            "seed": args.seed,
            "image_px": args.image_px,
            "state_dim": args.state_dim,
            "batch": int(ref_out.shape[0]),
            "action": ref_out.astype(np.float64).tolist(),
        },
        "script": "tools/make_lerobot_fixture.py",
        "script_commit": _git("rev-parse", "HEAD"),
        "script_changed_since_commit": _git("status", "--porcelain", "--", "tools/make_lerobot_fixture.py") != "",
        "command": " ".join(["python -m tools.make_lerobot_fixture", *sys.argv[1:]]),
    }


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="tests/data/lerobot_act", help="fixture folder (created)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-px", type=int, default=128, help="both cameras' square size (the two-camera scene's)")
    p.add_argument("--state-dim", type=int, default=6, help="observation.state values (the TCP pose)")
    p.add_argument("--chunk", type=int, default=10, help="chunk_size (= n_action_steps)")
    p.add_argument("--dim-model", type=int, default=16)
    p.add_argument("--n-heads", type=int, default=2)
    p.add_argument("--dim-feedforward", type=int, default=32)
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    out = Path(args.out)
    if out.is_absolute() or ".." in out.parts:
        print(f"--out: {out}: give a folder inside the checkout, relative to its root", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    prov = _export(args, out)
    _write(out / PROVENANCE_NAME, (json.dumps(prov, indent=1) + "\n").encode())
    print(f"{out / ONNX_NAME}: {(out / ONNX_NAME).stat().st_size} bytes; {out / PROVENANCE_NAME}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
