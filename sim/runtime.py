"""Process-wide runtime settings: the one place torch's thread count is set.

Commands default to one torch thread. On a few CPU cores OpenMP's idle threads spin-wait for
work and steal the cores the (llvmpipe) renderer and the control loop need; one thread was the
fastest setting measured for render-bound work here (``benchmarks/bench_eval.py --threads``).
"""

from __future__ import annotations

__all__ = ["DEFAULT_TORCH_THREADS", "set_torch_threads"]

DEFAULT_TORCH_THREADS = 1


def set_torch_threads(threads: int | None = DEFAULT_TORCH_THREADS) -> None:
    """Set torch's intra-op threads; ``0`` or ``None`` leaves torch's own default.

    Raises ``ValueError`` for a negative count (the CLI names its ``--threads`` flag).
    """
    if threads is None or int(threads) == 0:
        return
    if int(threads) < 0:
        raise ValueError(f"threads must be >= 0, got {threads}")
    import torch  # lazy: CLI start-up (torch)

    torch.set_num_threads(int(threads))
