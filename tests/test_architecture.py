"""The house rules a newcomer relies on (docs/architecture.md, "Layers").

- no module in ``tasks/`` or ``flows/`` over 800 lines;
- no function over 120 lines outside the tests, except the allow-listed ones, each with a reason;
- no import circle between the project's modules;
- no reference to a document outside the repository (the design notes and the thesis text the
  project was started from are summarised in ``docs/``; code cites papers by section and equation).
"""

from __future__ import annotations

import ast
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("btfcore", "tasks", "flows")
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 120

#: Functions allowed over MAX_FUNCTION_LINES, ``"path::qualname"`` -> why it stays one piece.
LONG_FUNCTIONS: dict[str, str] = {}


def _python_files(*tops: str) -> list[Path]:
    return sorted(p for top in tops for p in (ROOT / top).rglob("*.py"))


def _module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _functions(tree: ast.AST, prefix: str = ""):
    """(qualname, first line, last line) of every function, methods and nested ones included."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            name = f"{prefix}{node.name}"
            yield name, node.lineno, node.end_lineno
            yield from _functions(node, name + ".")
        elif isinstance(node, ast.ClassDef):
            yield from _functions(node, f"{prefix}{node.name}.")
        else:
            yield from _functions(node, prefix)


def test_no_module_in_tasks_or_flows_over_800_lines() -> None:
    long = {str(p.relative_to(ROOT)): n for p in _python_files("tasks", "flows")
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines (split them along a seam): {long}"


def _long_functions() -> dict[str, int]:
    found = {}
    for path in _python_files(*PACKAGES, "benchmarks"):
        for name, first, last in _functions(ast.parse(path.read_text())):
            if last - first + 1 > MAX_FUNCTION_LINES:
                found[f"{path.relative_to(ROOT)}::{name}"] = last - first + 1
    return found


def test_no_function_over_120_lines_unless_allowed_with_a_reason() -> None:
    found = _long_functions()
    offenders = {k: n for k, n in found.items() if k not in LONG_FUNCTIONS}
    assert not offenders, (f"functions over {MAX_FUNCTION_LINES} lines: {offenders}; split them, "
                           "or add them to LONG_FUNCTIONS with the reason they stay whole")
    stale = sorted(set(LONG_FUNCTIONS) - set(found))
    assert not stale, f"allow-list entries no longer needed (remove them): {stale}"
    assert all(len(why) > 20 for why in LONG_FUNCTIONS.values()), "every entry needs a reason"


def _import_graph() -> dict[str, set[str]]:
    """Edges module -> project module it imports, at any depth of the file (function bodies too)."""
    files = _python_files(*PACKAGES)
    modules = {_module_name(p) for p in files}
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for path in files:
        me = _module_name(path)
        package = me if path.name == "__init__.py" else me.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                           for a in node.names]
            for target in targets:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                # a package importing its own submodules is how it re-exports them, not a circle
                if target and target != me and not target.startswith(me + "."):
                    graph[me].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_import_graph_has_no_circle() -> None:
    graph = _import_graph()
    assert "tasks.store" in graph or "tasks.stores" in graph, "the import graph missed the stores"
    assert not _cycles(graph), f"import circles: {_cycles(graph)}"


def test_the_circle_finder_finds_a_circle() -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


#: What a reference to a document outside the repository looks like.
OUTSIDE = re.compile(
    r"\bDESIGN\b|000_07a399c75a6bdea8|shared/notes|shared/reference"
    r"|\b(thesis|reference)( text)?,? (lines?|l\.) ?\d{2,}|\blines? \d{3,}"
)


def test_no_reference_to_a_document_outside_the_repository() -> None:
    tracked = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout.split()
    me = Path(__file__).relative_to(ROOT).as_posix()
    bad = []
    for name in tracked:
        path = ROOT / name
        if name == me or path.suffix not in {".py", ".md", ".toml", ".yaml", ".yml", ".cfg", ".txt",
                                             ".html", ".sh", ""} or not path.is_file():
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if OUTSIDE.search(line):
                bad.append(f"{name}:{number}: {line.strip()[:100]}")
    assert not bad, (f"{len(bad)} references to documents outside the repository (cite "
                     "docs/architecture.md or the paper's section and equation instead):\n"
                     + "\n".join(bad[:60]))


def test_the_outside_reference_pattern_catches_what_it_should() -> None:
    for cited in ("as DESIGN §5 says", "(DESIGN.md)", "reference/000_07a399c75a6bdea8.txt", "thesis line 1144",
                  "§1.1.2, lines 130-134", "../shared/notes/slurm.md"):
        assert OUTSIDE.search(cited), cited
    for fine in ("the design of the store", "paper 1 §4.1, eq. (3)", "../shared/data/MANIFEST.md",
                 "no function over 120 lines", "VMV paper Table 2"):
        assert not OUTSIDE.search(fine), fine
