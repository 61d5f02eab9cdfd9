"""One owner per file format, checked on the source against the table in docs/architecture.md.

The table ("File formats and their owners") names each format's files and its owner modules. A
module that is not an owner must not spell an owned file name as a path (a code string without
spaces equal to it or ending in ``/<name>``: a constant, a path part, a glob, an f-string's literal
part): it reads and writes the file through the owner's functions instead, so a format changes in
one place. Prose that mentions a name (docstrings, messages and help such as "a directory with
policy.json") is not a path and is allowed.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "architecture.md"
PACKAGES = ("sim", "attack", "trials", "calibration", "robot_io", "tools")
SECTION = "## File formats and their owners"
FILE = re.compile(r"`([\w<>*./-]+\.(?:json|jsonl|csv|npy|png|safetensors|sqlite))`")
MODULE = re.compile(r"`([\w/]+\.py)`")

# Non-owners that still spell an owned name, each with its reason. Remove an entry once the module
# goes through the owner (test_pending_exemptions_are_still_needed fails when one is stale).
PENDING: dict[tuple[str, str], str] = {}


def owner_table(text: str) -> list[tuple[list[str], list[str]]]:
    """The rows of the owner table as (file names, owner modules); names are base names."""
    sec = text[text.index(SECTION) + len(SECTION) :]
    sec = sec[: sec.index("\n## ")] if "\n## " in sec else sec
    rows = []
    for line in sec.splitlines():
        if not line.startswith("|") or line.startswith("|---"):
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells[0] == "format":
            continue
        assert len(cells) >= 3, f"docs/architecture.md: table row without format, files and owner: {line}"
        files = [Path(f).name for f in FILE.findall(cells[1]) if "*" not in Path(f).name]
        rows.append((files, MODULE.findall(cells[2])))
    return rows


def owners_by_file(rows) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for files, mods in rows:
        for f in files:
            out.setdefault(f, set()).update(mods)
    return out


def _docstrings(tree: ast.AST) -> set[int]:
    ids = set()
    for n in ast.walk(tree):
        if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and n.body:
            first = n.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


def spelled_paths(source: str, names) -> list[tuple[int, str]]:
    """(line, name) of every code string that is one of ``names`` as a path: no spaces, and equal
    to it or ending in ``/<name>`` (also a literal part of an f-string); docstrings are prose."""
    tree = ast.parse(source)
    docs = _docstrings(tree)
    hits = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs:
            if any(c.isspace() for c in n.value):
                continue
            for name in names:
                if n.value == name or n.value.endswith("/" + name):
                    hits.append((n.lineno, name))
    return hits


def _modules() -> list[Path]:
    return sorted(f for pkg in PACKAGES for f in (ROOT / pkg).rglob("*.py"))


def violations(rows) -> list[tuple[str, int, str]]:
    owners = owners_by_file(rows)
    out = []
    for f in _modules():
        rel = f.relative_to(ROOT).as_posix()
        for line, name in spelled_paths(f.read_text(), owners):
            if rel not in owners[name]:
                out.append((rel, line, name))
    return out


@functools.cache
def _current() -> tuple[tuple[str, int, str], ...]:
    """The tree's violations of the table as it is now (parsed once per test run)."""
    return tuple(violations(owner_table(DOC.read_text())))


def test_the_owner_table_parses_and_names_files_and_owners():
    rows = owner_table(DOC.read_text())
    named = [r for r in rows if r[0]]
    assert len(named) >= 8, "docs/architecture.md: the owner table lost its rows"
    for files, mods in named:
        assert mods, f"docs/architecture.md: {', '.join(files)} have no owner module"
    for name in ("episodes.csv", "job.json", "trials.sqlite", "policy.json", "texture.npy", "feasible_pool.json"):
        assert name in owners_by_file(rows), f"docs/architecture.md: {name} is missing from the owner table"


def test_the_owner_modules_exist_and_spell_their_files():
    """The table cannot drift: every owner exists, names one of its row's files in code, and every
    file of a row is named in code by one of the row's owners."""
    for files, mods in owner_table(DOC.read_text()):
        spelled = {}
        for m in mods:
            path = ROOT / m
            assert path.is_file(), f"docs/architecture.md: owner {m} does not exist"
            spelled[m] = {name for _, name in spelled_paths(path.read_text(), files)}
        for m in mods:
            assert not files or spelled[m], f"docs/architecture.md: owner {m} names none of {', '.join(files)}"
        for name in files:
            assert any(name in s for s in spelled.values()), (
                f"docs/architecture.md: {name} is named by none of its owners ({', '.join(mods)})"
            )


def test_no_module_but_the_owner_spells_an_owned_file_name():
    found = [v for v in _current() if (v[0], v[2]) not in PENDING]
    assert not found, "modules that open an owned file by name instead of through its owner:\n" + "\n".join(
        f"  {f}:{line}: {name}" for f, line, name in found
    )


def test_pending_exemptions_are_still_needed():
    found = {(f, name) for f, _, name in _current()}
    stale = [k for k in PENDING if k not in found]
    assert not stale, f"exemptions no longer needed (remove them from PENDING): {stale}"


def test_the_check_flags_a_planted_path_and_spares_prose():
    rows = [(["episodes.csv", "job.json"], ["trials/eval/episodes.py"])]
    planted = (
        '"""Reads episodes.csv."""\n'
        "from pathlib import Path\n"
        "def f(d):\n"
        '    """The rows of ``episodes.csv``."""\n'
        '    print("no episodes.csv here")\n'
        '    print(f"rebuilt from {d}/episodes.csv only")\n'
        '    a = Path(d) / "episodes.csv"\n'
        '    b = f"{d}/job.json"\n'
        '    return a, b, list(Path(d).rglob("sub/episodes.csv"))\n'
    )
    assert spelled_paths(planted, owners_by_file(rows)) == [(7, "episodes.csv"), (8, "job.json"), (9, "episodes.csv")]
