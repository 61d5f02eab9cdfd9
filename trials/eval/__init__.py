"""The evaluation harness: conditions, paired rollouts, metrics, per-episode tables and reports."""
