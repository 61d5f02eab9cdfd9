"""The house rules, checked on the source: the layers, no import loops, the rooms of ``trials/``."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("sim", "calibration", "attack", "robot_io", "trials")
# sim and calibration are the ground floor; attack and robot_io stand on sim; trials is the top.
FLOOR = {"sim": 0, "calibration": 0, "attack": 1, "robot_io": 1, "trials": 2}


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = f
    return mods


def _edges(mods: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> project modules it imports, at the top or inside functions alike (a lazy import
    still makes a dependency)."""

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    edges: dict[str, set[str]] = {m: set() for m in mods}
    for m, f in mods.items():
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = m.split(".") if f.name == "__init__.py" else m.split(".")[:-1]
                    base = ".".join(pkg[: len(pkg) - node.level + 1] + ([node.module] if node.module else []))
                names = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for n in names:
                t = resolve(n)
                if t is not None and t != m:
                    edges[m].add(t)
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in edges:
        if v not in index:
            visit(v)
    return out


def test_no_module_imports_a_higher_floor():
    edges = _edges(_modules())
    upward = [f"{a} -> {b}" for a, ts in edges.items() for b in ts if FLOOR[b.split(".")[0]] > FLOOR[a.split(".")[0]]]
    assert not upward, "imports that run upward:\n" + "\n".join(sorted(upward))


def test_there_are_no_import_loops_not_even_through_lazy_imports():
    loops = _cycles(_edges(_modules()))
    assert not loops, "import loops: " + "; ".join(" <-> ".join(c) for c in loops)


def test_trials_is_split_into_its_rooms_and_the_docs_generator_is_a_dev_tool():
    rooms = {p.name for p in (ROOT / "trials").iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert rooms == {"cli", "eval", "experiments", "fabrication", "jobs", "real", "recordings"}
    loose = sorted(p.name for p in (ROOT / "trials").glob("*.py") if p.name != "__init__.py")
    assert not loose, f"modules outside the rooms of trials/: {loose}"
    assert (ROOT / "tools" / "docgen.py").is_file()
    cli = [p for p in (ROOT / "trials" / "cli").glob("*.py") if p.name not in ("__init__.py", "options.py")]
    for f in cli:  # typer apps only: no room below imports the CLI
        assert "typer" in f.read_text(), f"{f.relative_to(ROOT)} is in trials/cli/ but defines no typer command"
    edges = _edges(_modules())
    into_cli = [
        f"{a} -> {b}"
        for a, ts in edges.items()
        for b in ts
        if b.startswith("trials.cli") and not a.startswith("trials.cli")
    ]
    assert not into_cli, "modules outside trials/cli import the CLI:\n" + "\n".join(sorted(into_cli))


def _room(module: str) -> str:
    return ".".join(module.split(".")[:2])


# Rooms of trials/ that stand side by side: neither imports the other, not even lazily. What both
# need lives below them (the task-feasible pool builder: sim.policies.pool.build_feasible).
SIBLING_ROOMS = {("trials.jobs", "trials.eval"), ("trials.eval", "trials.jobs")}


def _between_siblings(edges: dict[str, set[str]]) -> list[str]:
    return sorted(f"{a} -> {b}" for a, ts in edges.items() for b in ts if (_room(a), _room(b)) in SIBLING_ROOMS)


def test_jobs_and_eval_do_not_import_each_other():
    across = _between_siblings(_edges(_modules()))
    assert not across, "trials/jobs and trials/eval import each other:\n" + "\n".join(across)


def test_the_check_itself_sees_a_loop_and_an_upward_import():
    edges = {"sim.a": {"sim.b"}, "sim.b": {"sim.a"}, "trials.x": set()}
    assert _cycles(edges) == [["sim.a", "sim.b"]]
    edges = {"trials.jobs.attack": {"trials.eval.evaluate", "sim.policies.pool"}, "trials.eval.evaluate": set()}
    assert _between_siblings(edges) == ["trials.jobs.attack -> trials.eval.evaluate"]


# Imports sit at the top of their module. An import inside a function stays only where a start-up
# budget needs it or the package may be missing, and says so on its line: ``# lazy: <kind> (<what>)``.
LAZY_KINDS = (
    "CLI start-up",  # keeps a heavy package or module out of `advobj --help` (benchmarks/bench_cli_startup.py)
    "robot_io start-up",  # importing robot_io loads no cv2, vendor SDK or torch (tests/robot_io/test_imports.py)
    "optional dependency",  # an extra that may not be installed (ray)
)
LAZY_MARK = re.compile(r"#\s*lazy:\s*(?P<kind>[^(]+?)\s*\((?P<what>[^)]+)\)")
# Files another change is rewriting now; each entry fails the test below once its file is clean.
PENDING_LAZY: set[str] = set()


def _unmarked_lazy_imports(source: str) -> list[int]:
    """Lines of imports inside a function whose statement carries no ``# lazy: <kind> (<what>)`` comment
    of a known kind."""
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string
    unmarked = set()
    for fn in ast.walk(ast.parse(source)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            marks = [LAZY_MARK.search(comments.get(n, "")) for n in range(node.lineno, node.end_lineno + 1)]
            if not any(m and m["kind"] in LAZY_KINDS for m in marks):
                unmarked.add(node.lineno)
    return sorted(unmarked)


def test_every_import_inside_a_function_says_why_it_is_lazy():
    unmarked, stale = [], []
    for pkg in (*PACKAGES, "tools"):
        for f in sorted((ROOT / pkg).rglob("*.py")):
            rel = f.relative_to(ROOT).as_posix()
            lines = _unmarked_lazy_imports(f.read_text())
            if rel in PENDING_LAZY:
                stale += [] if lines else [rel]
            else:
                unmarked += [f"{rel}:{n}" for n in lines]
    assert not unmarked, (
        "imports inside a function without '# lazy: <kind> (<what>)' (kinds: "
        + ", ".join(LAZY_KINDS)
        + "); move them to the top or say why:\n"
        + "\n".join(unmarked)
    )
    assert not stale, f"no unmarked lazy import left in {stale}: drop them from PENDING_LAZY"


def test_the_lazy_import_check_catches_an_unmarked_one():
    src = (
        "import os\n"
        "def f():\n"
        "    import json  # lazy: CLI start-up (json)\n"
        "    import cv2\n"
        "    from sim.env import (  # lazy: optional dependency (ray)\n"
        "        ReachEnv,\n"
        "    )\n"
        "    import torch  # lazy: because\n"
        "    import yaml  # lazy: faster (yaml)\n"
        "    def g():\n"
        "        from attack import optimize\n"
        "    return '# lazy: CLI start-up (x)'\n"
        "class C:\n"
        "    import re\n"
        "    def m(self):\n"
        "        import ray  # lazy: optional dependency (ray)\n"
    )
    assert _unmarked_lazy_imports(src) == [4, 8, 9, 11]


def test_the_cli_start_up_loads_no_heavy_package():
    """`advobj --help` stays within its start-up budget (benchmarks/bench_cli_startup.py): importing the
    CLI loads none of the packages its commands import lazily."""
    import subprocess
    import sys

    heavy = ("numpy", "torch", "pyrender", "OpenGL", "cv2", "matplotlib", "trimesh", "onnxruntime", "ray", "PIL")
    code = f"import sys, trials.cli.main; print(','.join(m for m in {heavy!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == ""
