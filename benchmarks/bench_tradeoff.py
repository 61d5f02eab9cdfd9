"""Speed vs accuracy of the attack, evaluation and deployment knobs (issue 9).

Usage:
    python benchmarks/bench_tradeoff.py --policy CKPT --out DIR [--res-policy 96=CKPT ...] [--train-missing]
                                        [--rows KNOB_OR_KEY ...] [--episodes 100] [--big-episodes 500]
                                        [--quick-check] [--plot PNG] [--report-only]

(also ``advobj bench tradeoff``). Runs the one-knob-at-a-time sweep of :mod:`trials.experiments.tradeoff`:
every row is an attack (or a snapshot of the baseline attack, or a deployment variant) plus a
paired evaluation on one fixed task-feasible set, in its own process; rows are appended to
``DIR/rows.jsonl`` as they finish and a re-run resumes. Then prints the table and writes
``DIR/report.md`` and the Pareto plot of T-ASR against attack wall time.

``--train-missing`` trains the ``policy_resolution`` rows' policies (quick preset at 96 / 128 px)
into ``DIR/policies/px<S>`` after the other rows, then runs those rows. ``--quick-check`` uses
tiny settings (seconds per row) to check the machinery, not to measure anything.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", required=True, help="baseline policy checkpoint directory")
    ap.add_argument("--out", required=True, help="sweep directory (resumable)")
    ap.add_argument(
        "--res-policy",
        action="append",
        default=[],
        metavar="SIZE=DIR",
        help="policy for a policy_resolution row (repeatable)",
    )
    ap.add_argument(
        "--train-missing",
        action="store_true",
        help="train missing policy_resolution policies (quick preset) into OUT/policies",
    )
    ap.add_argument(
        "--train-iterations",
        type=int,
        default=None,
        help="DAgger iterations for --train-missing (default: the quick preset's 5)",
    )
    ap.add_argument("--rows", action="append", default=[], help="knob or row key to run (repeatable; default: all)")
    ap.add_argument("--episodes", type=int, default=None, help="paired episodes per row (default 100)")
    ap.add_argument("--big-episodes", type=int, default=None, help="episodes of the eval_episodes row (default 500)")
    ap.add_argument("--pool", default=None, help="task-feasible pool of the baseline policy (default: its own)")
    ap.add_argument("--scene", default=None)
    ap.add_argument(
        "--max-steps", type=int, default=None, help="steps per episode (default 60; the pool must be made for it)"
    )
    ap.add_argument("--quick-check", action="store_true", help="tiny settings: checks the machinery in a few minutes")
    ap.add_argument("--plot", default=None, help="Pareto plot PNG (default OUT/tradeoff_pareto.png)")
    ap.add_argument(
        "--redo",
        action="store_true",
        help="measure the selected --rows again even if done (the newest record is reported)",
    )
    ap.add_argument("--report-only", action="store_true", help="only rebuild the table and plot from OUT/rows.jsonl")
    args = ap.parse_args(argv)
    from trials.cli.options import key_values
    from trials.experiments.tradeoff import TradeoffJob

    a = vars(args)
    job = TradeoffJob.build(
        a.pop("policy"),
        a.pop("out"),
        key_values(a.pop("res_policy"), "--res-policy", "SIZE", "DIR"),
        a.pop("quick_check"),
        **{**a, "rows": tuple(a["rows"])},
    )
    job.run()


if __name__ == "__main__":
    main()
