"""Typer apps only: each command parses its options, builds a validated job and runs it."""
