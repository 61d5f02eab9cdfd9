"""Speed vs accuracy of the attack, evaluation and deployment knobs (issue 9).

Usage:
    python benchmarks/bench_tradeoff.py --policy CKPT --out DIR [--res-policy 96=CKPT ...] [--train-missing]
                                        [--rows KNOB_OR_KEY ...] [--episodes 300] [--big-episodes N]
                                        [--attack-seeds 0,1,2] [--quick-check] [--plot PNG] [--report-only]

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
    from sim.errors import AdvobjError
    from trials.experiments.tradeoff import job_from_args, sweep_parser  # the one parser of the sweep's options

    ap = sweep_parser(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    try:
        job_from_args(ap.parse_args(argv)).run()
    except AdvobjError as err:  # bad input: one line, exit 2
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
