"""The base of every user-facing error: the CLI prints these as one clear message, no traceback."""

__all__ = ["AdvobjError"]


class AdvobjError(Exception):
    """An error caused by input or environment the user can fix; its message says how."""
