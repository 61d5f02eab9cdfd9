"""The base of every user-facing error: the CLI prints these as one clear message, no traceback."""

__all__ = ["AdvobjError", "format_validation_error"]


class AdvobjError(Exception):
    """An error caused by input or environment the user can fix; its message says how."""


def format_validation_error(err, what: str, source: str | None = None) -> str:
    """One message for a pydantic ``ValidationError``: the source, then ``field.path: problem``.

    Always one line (the CLI prints it as the whole error): ``source: invalid what: field.path:
    problem``; several problems are joined with ``; `` (the first three, then how many more).

    ``what`` names the kind of input ("scene spec", "attack config"); ``source`` the file it
    came from, when there is one.
    """
    head = f"{source}: invalid {what}" if source else f"invalid {what}"
    problems = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "<root>"
        msg = " ".join(e["msg"].removeprefix("Value error, ").split())  # a validator's own ValueError text
        problems.append(f"{loc}: {msg}")
    shown = "; ".join(problems[:3]) + (f" (and {len(problems) - 3} more)" if len(problems) > 3 else "")
    return f"{head}: {shown}"
