"""The shape of the code, checked: the rules of docs/architecture.md as tests.

- no import cycle inside ``mvreg`` (module-level and function-level imports both count);
- no module imports another module's ``_private`` name;
- no file in ``mvreg/`` over 600 lines, no function body over 80 lines (the solvers'
  numeric kernels listed below excepted);
- no block of 6 or more repeated lines inside ``mvreg/``;
- ``import mvreg.config`` loads nothing of the algorithms; ``import mvreg.cli`` loads
  neither ``data_synth`` nor open3d.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "mvreg"
MAX_FILE_LINES = 600
MAX_FUNCTION_LINES = 80
REPEAT_LINES = 6
# Numeric kernels of the solvers: one long loop each, easier to check against the papers
# as one piece (module:function).
LONG_FUNCTIONS_ALLOWED = {
    "mvreg.solver.c_admm:c_admm",
    "mvreg.solver.polish:polish",
    "mvreg.solver.reg_admm:run_reg_admm",
}


def modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imports_of(name: str, path: Path, known: set[str]) -> list[tuple[str, list[str], int]]:
    """(imported module, imported names, line) for every import in the file."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = package.split(".")
                base = ".".join(pkg[: len(pkg) - node.level + 1] + ([base] if base else []))
            names = [a.name for a in node.names]
            # ``from pkg import module`` imports the module too
            subs = [f"{base}.{n}" for n in names if f"{base}.{n}" in known]
            out.append((base, [n for n in names if f"{base}.{n}" not in known], node.lineno))
            out += [(s, [], node.lineno) for s in subs]
    return out


def test_no_import_cycles():
    mods = modules()
    known = set(mods)
    graph = defaultdict(set)
    for name, path in mods.items():
        for target, _, _ in imports_of(name, path, known):
            if target in known and target != name:
                # importing a package runs its __init__; a module inside the package it is
                # in does not import that package's __init__ in a cycle we care about
                if not name.startswith(target + "."):
                    graph[name].add(target)
    # Tarjan's strongly connected components
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                strong(w)
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
                comps.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in list(mods):
        if v not in index:
            strong(v)
    assert not comps, f"import cycles: {comps}"


def test_no_private_names_imported_across_modules():
    mods = modules()
    known = set(mods)
    bad = []
    for name, path in mods.items():
        for target, names, line in imports_of(name, path, known):
            if not target.startswith("mvreg"):
                continue
            for n in names:
                if n.startswith("_") and not n.startswith("__"):
                    bad.append(f"{path.relative_to(ROOT)}:{line} imports {target}.{n}")
            if any(p.startswith("_") and not p.startswith("__") for p in target.split(".")):
                if not name.startswith(target.rsplit(".", 1)[0]):
                    bad.append(f"{path.relative_to(ROOT)}:{line} imports private {target}")
    assert not bad, "\n".join(bad)


def test_tests_and_scripts_import_no_private_mvreg_names():
    bad = []
    for folder in (ROOT / "tests", ROOT / "scripts", ROOT / "bench"):
        for path in sorted(folder.rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mvreg"):
                    for a in node.names:
                        if a.name.startswith("_") and not a.name.startswith("__"):
                            bad.append(f"{path.relative_to(ROOT)}:{node.lineno} {a.name}")
    assert not bad, "\n".join(bad)


def test_file_lengths():
    long = {
        str(p.relative_to(ROOT)): n
        for p in PKG.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > MAX_FILE_LINES
    }
    assert not long, f"files over {MAX_FILE_LINES} lines: {long}"


def test_function_lengths():
    long = []
    for name, path in modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                # the body, docstring excluded (a command's options make long signatures)
                body = node.body
                if isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                    body = body[1:] or body
                n = node.end_lineno - body[0].lineno + 1
                key = f"{name}:{node.name}"
                if n > MAX_FUNCTION_LINES and key not in LONG_FUNCTIONS_ALLOWED:
                    long.append(f"{key} ({n} lines)")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


_SKIP = re.compile(r"^(#.*|[\)\]\}\(\[\{,:]*|\"\"\"|'''|(from|import) .*|@.*)$")


def _normalized(path: Path) -> list[tuple[int, str]]:
    """Lines that carry code: stripped, whitespace folded; blank, comment, import and lone
    punctuation lines left out; docstrings and function signatures left out (a no-op twin
    repeats its class's signatures on purpose)."""
    text = path.read_text()
    doc_lines = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            doc_lines.update(range(node.lineno, node.body[0].lineno))
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = getattr(node, "body", [])
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                if isinstance(body[0].value.value, str):
                    doc_lines.update(range(body[0].lineno, body[0].end_lineno + 1))
    out = []
    for k, line in enumerate(text.splitlines(), 1):
        s = " ".join(line.split())
        if k in doc_lines or not s or _SKIP.match(s):
            continue
        out.append((k, s))
    return out


def test_no_repeated_blocks():
    seen: dict[tuple[str, ...], tuple[str, int]] = {}
    repeats = []
    for path in sorted(PKG.rglob("*.py")):
        lines = _normalized(path)
        rel = str(path.relative_to(ROOT))
        last_end = -1
        for k in range(len(lines) - REPEAT_LINES + 1):
            window = tuple(s for _, s in lines[k : k + REPEAT_LINES])
            where = (rel, lines[k][0])
            if (
                window in seen
                and seen[window][0:1] != (rel,)
                or (window in seen and abs(seen[window][1] - where[1]) >= REPEAT_LINES)
            ):
                if k > last_end:
                    repeats.append(f"{rel}:{where[1]} repeats {seen[window][0]}:{seen[window][1]}")
                last_end = k + REPEAT_LINES
            else:
                seen.setdefault(window, where)
    assert not repeats, "\n".join(repeats)


@pytest.mark.parametrize(
    ("module", "forbidden"),
    [
        ("mvreg.config", ("mvreg.pairwise", "mvreg.solver", "mvreg.globalstage", "open3d")),
        ("mvreg.cli", ("data_synth", "open3d", "mvreg.pairwise", "mvreg.solver")),
        ("mvreg.solver.base", ("mvreg.pairwise", "mvreg.globalstage", "open3d")),
    ],
)
def test_light_imports(module, forbidden):
    code = (
        f"import sys, {module}; "
        f"bad = [m for m in sys.modules if m.split('.')[0] in {forbidden!r} "
        f"or any(m == f or m.startswith(f + '.') for f in {forbidden!r})]; "
        "print(','.join(sorted(bad)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True
    )
    assert out.stdout.strip() == "", f"import {module} loads {out.stdout.strip()}"
