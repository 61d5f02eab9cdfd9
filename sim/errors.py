"""The base of every user-facing error: the CLI prints these as one clear message, no traceback."""

__all__ = ["AdvobjError", "format_validation_error"]


class AdvobjError(Exception):
    """An error caused by input or environment the user can fix; its message says how."""


def format_validation_error(err, what: str, source: str | None = None) -> str:
    """One message for a pydantic ``ValidationError``: the source, then ``field.path: problem``.

    One problem gives one line (``source: invalid what: field.path: problem``); several give the
    head line and one indented line per problem.

    ``what`` names the kind of input ("scene spec", "attack config"); ``source`` the file it
    came from, when there is one.
    """
    head = f"{source}: invalid {what}" if source else f"invalid {what}"
    problems = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "<root>"
        msg = e["msg"].removeprefix("Value error, ")  # a validator's own ValueError text
        problems.append(f"{loc}: {msg}")
    if len(problems) == 1:  # the common case: one line, the CLI prints nothing else
        return f"{head}: {problems[0]}"
    return "\n".join([head] + [f"  {p}" for p in problems])
