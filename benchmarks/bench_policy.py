"""Policy speed: ms per image for forward and forward+backward (to the input), torch and onnxruntime.

Usage:
    python benchmarks/bench_policy.py [--archs resnet18,small_cnn] [--sizes 64,128] [--batch 16] [--reps 5]

Prints one row per (backbone, size) with the median over ``--reps`` timed batches (after one
warm-up batch). Untrained weights: speed does not depend on them.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402

from sim.policies.backbones import BACKBONES  # noqa: E402
from sim.policies.onnx_policy import OnnxPolicy, export_onnx  # noqa: E402
from sim.policies.policy import VisuomotorPolicy  # noqa: E402


def _median_ms_per_image(fn, reps: int, batch: int) -> float:
    fn()  # warm-up (allocations, onnxruntime graph setup)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times) / batch


def bench(arch: str, size: int, batch: int, reps: int, device: str) -> dict:
    policy = VisuomotorPolicy(arch=arch, image_size=size).to(device).eval()
    x = torch.rand(batch, 3, size, size, device=device)

    def fwd():
        with torch.no_grad():
            policy(x)

    def fwd_bwd():
        xi = x.clone().requires_grad_(True)
        policy(xi).norm(dim=1).sum().backward()

    row = {
        "arch": arch,
        "size": size,
        "torch_fwd": _median_ms_per_image(fwd, reps, batch),
        "torch_fwd_bwd": _median_ms_per_image(fwd_bwd, reps, batch),
    }
    with tempfile.TemporaryDirectory() as tmp:
        onnx_policy = OnnxPolicy(export_onnx(policy, Path(tmp) / "p.onnx"))
        xn = x.cpu().numpy()
        row["onnx_fwd"] = _median_ms_per_image(lambda: onnx_policy.act(xn), reps, batch)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archs", default=",".join(BACKBONES), help="comma-separated backbone names")
    ap.add_argument("--sizes", default="64,128", help="comma-separated square image sizes (px)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--threads",
        type=int,
        default=0,
        help="torch intra-op threads (0 = torch's default); "
        "on an oversubscribed CPU, 1 avoids OpenMP spin-wait contention",
    )
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, batch {args.batch}, median of {args.reps}; "
        "ms per image"
    )
    print(f"{'backbone':<14}{'px':>5}{'torch fwd':>12}{'torch fwd+bwd':>15}{'onnxrt fwd':>12}")
    for arch in args.archs.split(","):
        for size in (int(s) for s in args.sizes.split(",")):
            r = bench(arch.strip(), size, args.batch, args.reps, args.device)
            print(
                f"{r['arch']:<14}{r['size']:>5}{r['torch_fwd']:>12.2f}{r['torch_fwd_bwd']:>15.2f}{r['onnx_fwd']:>12.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
