"""The package's shape: modules of at most 600 lines, functions of at most 80, and no
import cycle between its modules (imports inside functions included; imports for type
annotations alone, under ``if TYPE_CHECKING:``, excepted).

An exception is listed below with its reason; the list must only shrink: a listed
exception that no longer exceeds its limit fails the test until it is removed.
"""
from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "aqfg"
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80

# "module" or "module:function" -> why it is still over its limit
EXCEPTIONS: dict[str, str] = {}


def _modules():
    for p in sorted(PKG.rglob("*.py")):
        yield p, p.relative_to(PKG.parent).as_posix()


def _over_limits() -> set[str]:
    over = set()
    for p, rel in _modules():
        text = p.read_text(encoding="utf-8")
        if len(text.splitlines()) > MAX_MODULE_LINES:
            over.add(rel)
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES:
                    over.add(f"{rel}:{node.name}")
    return over


def test_modules_and_functions_within_their_limits():
    over = _over_limits()
    assert over <= set(EXCEPTIONS), f"over the limits, not listed: {sorted(over - set(EXCEPTIONS))}"
    assert set(EXCEPTIONS) <= over, f"listed but now within the limits (remove them): " \
                                     f"{sorted(set(EXCEPTIONS) - over)}"


def _runtime_imports(tree: ast.Module):
    """Every import statement except those under ``if TYPE_CHECKING:``."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for b in node.body for n in ast.walk(b))
    return [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
            and id(n) not in skip]


def _import_graph() -> dict[str, set[str]]:
    names = {}
    for p, rel in _modules():
        mod = rel[:-3].replace("/", ".")
        names[mod.removesuffix(".__init__")] = p
    graph: dict[str, set[str]] = {m: set() for m in names}
    for mod, p in names.items():
        for n in _runtime_imports(ast.parse(p.read_text(encoding="utf-8"))):
            if isinstance(n, ast.ImportFrom) and n.module and n.module in names:
                for a in n.names:
                    sub = f"{n.module}.{a.name}"
                    graph[mod].add(sub if sub in names else n.module)
            elif isinstance(n, ast.Import):
                graph[mod].update(a.name for a in n.names if a.name in names)
        graph[mod].discard(mod)
    return graph


def test_no_import_cycles():
    graph = _import_graph()
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append(path[path.index(d):] + [d])
            elif d not in state:
                visit(d, path + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_fg_never_imports_diagnose():
    """The factor graph is below the diagnosis: no module under ``aqfg/fg`` imports
    ``aqfg.diagnose`` or anything in it, at any level (inside functions and under
    ``if TYPE_CHECKING:`` included)."""
    up = []
    for p, rel in _modules():
        if not rel.startswith("aqfg/fg/"):
            continue
        for n in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if not isinstance(n, (ast.Import, ast.ImportFrom)):
                continue
            if isinstance(n, ast.Import):
                names = [a.name for a in n.names]
            else:                                   # relative imports resolved from ``rel``
                base = ".".join(rel[:-3].split("/")[:len(rel.split("/")) - n.level]) \
                    if n.level else ""
                mod = ".".join(x for x in (base, n.module or "") if x)
                names = [mod, *(f"{mod}.{a.name}" for a in n.names)]
            hit = [m for m in names if m == "aqfg.diagnose" or m.startswith("aqfg.diagnose.")]
            if hit:
                up.append(f"{rel}:{n.lineno} imports {hit[0]}")
    assert not up, "; ".join(up)


def test_the_checks_see_what_they_check():
    """The graph holds the package's known edges, and the limits see its long files."""
    graph = _import_graph()
    assert "aqfg.model.rotation" in graph["aqfg.model.terms"]
    assert "aqfg.model.terms" in graph["aqfg.model.effects"]
    assert "aqfg.result" in graph["aqfg.export"]
    assert len(graph) > 100


# documents a reader opens first, and the most lines each may have
DOC_LIMITS = {"README.md": 200, "docs/independent-vehicle.md": 400}


def test_documents_within_their_limits():
    root = PKG.parent
    long = {f: n for f, limit in DOC_LIMITS.items()
            if (n := len((root / f).read_text(encoding="utf-8").splitlines())) > limit}
    assert not long, f"documents over their line limits {DOC_LIMITS}: {long}"
