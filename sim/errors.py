"""The base of every user-facing error: the CLI prints these as one clear message, no traceback."""

__all__ = ["AdvobjError", "format_validation_error", "flag_error"]


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


def flag_error(err, flag_of, what: str, error_cls, extra: str | None = None) -> "AdvobjError":
    """One error naming the command-line flags of a job model's pydantic ``ValidationError``.

    A validator's own :class:`AdvobjError` is returned as it is; otherwise each problem reads
    ``<flag_of(field)>: problem`` (``what`` when the problem has no field; with ``extra``, an unknown
    field reads ``field: extra``), the first three joined with ``; ``, then how many more, as one
    ``error_cls``."""
    problems = []
    for e in err.errors():
        cause = (e.get("ctx") or {}).get("error")
        if isinstance(cause, AdvobjError):
            return cause
        field = str(e["loc"][0]) if e["loc"] else ""
        msg = " ".join(e["msg"].removeprefix("Value error, ").split())
        if extra is not None and e["type"] == "extra_forbidden":
            problems.append(f"{field}: {extra}")
        else:
            problems.append(f"{flag_of(field) if field else what}: {msg}")
    more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
    return error_cls("; ".join(problems[:3]) + more)
