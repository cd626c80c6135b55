"""The package's structure: sub-packages by pipeline stage, imports one way, no cycle.

The import graph is built from the source with `ast` (every import statement, including
the ones inside functions), so a lazy import cannot hide a cycle.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PKG = REPO / "generator"

# The stages, from input to the command line. A module may import from its own stage or
# an earlier one, never a later one. Top-level modules other than the ones named in
# APP sit below every stage (shared vocabulary: errors, progress).
STAGES = ("io", "fit", "flight", "trace", "campaign", "report")
APP = ("cli", "pipeline", "demo", "verbs")


def module_name(path: Path, root: Path = REPO) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _string_imports(tree):
    """importlib.import_module("x") and __import__("x") with a literal name."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            if name in ("import_module", "__import__"):
                yield node.args[0].value


def import_graph(pkg: Path = PKG, root: Path = REPO) -> dict:
    """{module: {generator modules it imports}} from every import in the source.

    `from P import N` is an edge to the module P.N where that is a module, else to P
    itself (a name from P's namespace, its __init__ for a package); `import a.b` and the
    literal names given to importlib.import_module / __import__ are edges to the longest
    module prefix. Imports inside functions count: a lazy import is still a dependency.
    """
    modules = {module_name(p, root): p for p in pkg.rglob("*.py")}

    def longest_module(dotted):
        parts = dotted.split(".")
        for k in range(len(parts), 0, -1):
            cand = ".".join(parts[:k])
            if cand in modules:
                return cand
        return None

    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        is_pkg = path.name == "__init__.py"
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                deps.update(longest_module(a.name) for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".")
                    base = base[:len(base) - node.level + (1 if is_pkg else 0)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                for a in node.names:
                    sub = f"{mod}.{a.name}"
                    deps.add(sub if sub in modules else longest_module(mod))
        deps.update(longest_module(s) for s in _string_imports(tree))
        deps.discard(None)
        deps.discard(name)
        graph[name] = deps
    return graph


def find_cycle(graph):
    state, stack = {}, []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if not state.get(m):
                c = visit(m)
                if c:
                    return c
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if not state.get(n):
            c = visit(n)
            if c:
                return c
    return None


def stage_of(module: str) -> int:
    parts = module.split(".")
    if len(parts) < 2:
        return -1      # the package's face (generator/__init__.py: the version)
    top = parts[1]
    if top in STAGES:
        return STAGES.index(top)
    if top in APP:
        return len(STAGES)
    return -1          # shared vocabulary below every stage


def test_the_graph_is_read_from_the_source():
    g = import_graph()
    assert "generator.flight.codegen" in g
    assert "generator.flight.chain" in g["generator.flight.codegen"]


def test_no_import_cycle():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_graph_sees_package_names_and_string_imports(tmp_path):
    """A cycle through a package's __init__ and an import by string are both seen."""
    pkg = tmp_path / "generator"
    (pkg / "flight").mkdir(parents=True)
    (pkg / "io").mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "flight" / "__init__.py").write_text("from generator.flight.codegen import render\n")
    (pkg / "flight" / "codegen.py").write_text("from generator.flight import FLAGS\n")
    (pkg / "io" / "__init__.py").write_text("")
    (pkg / "io" / "unit.py").write_text("import importlib\n"
                                        "def f():\n    importlib.import_module('generator.cli')\n")
    (pkg / "cli.py").write_text("")
    g = import_graph(pkg, tmp_path)
    assert find_cycle(g) == ["generator.flight", "generator.flight.codegen", "generator.flight"]
    assert "generator.cli" in g["generator.io.unit"]


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_imports_run_from_input_to_the_command_line():
    bad = []
    for mod, deps in import_graph().items():
        for d in deps:
            if stage_of(d) > stage_of(mod):
                bad.append(f"{mod} imports {d}")
    assert not bad, "imports against the pipeline's direction:\n" + "\n".join(sorted(bad))


def test_every_stage_is_a_folder():
    for s in STAGES:
        assert (PKG / s / "__init__.py").is_file(), s


def test_architecture_page_matches_the_tree():
    text = (REPO / "docs" / "architecture.md").read_text()
    named = set(re.findall(r"`((?:generator|templates|generated|host_tests|bench|docs)"
                           r"(?:/[A-Za-z0-9_.]+)*/?)`", text))
    assert named, "docs/architecture.md names no folder or file"
    missing = [n for n in sorted(named) if not (REPO / n.rstrip("/")).exists()]
    assert not missing, f"docs/architecture.md names what the tree does not hold: {missing}"
    for s in STAGES:
        assert f"`generator/{s}/`" in text, f"docs/architecture.md does not show stage {s}"
    linked = (REPO / "README.md").read_text()
    assert "docs/architecture.md" in linked, "README does not link the architecture page"


def test_the_wheel_lists_every_package_and_ships_the_templates():
    try:
        import tomllib
    except ModuleNotFoundError:          # Python 3.10
        import tomli as tomllib
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    code = {module_name(p.parent) for p in PKG.rglob("__init__.py")}
    listed = set(cfg["packages"])
    assert code <= listed, f"packages missing from pyproject.toml: {sorted(code - listed)}"
    for pkg, folder in cfg["package-dir"].items():
        assert pkg in listed and (REPO / folder).is_dir()
        assert any((REPO / folder).glob("*.j2")), folder
    assert cfg["package-dir"]["generator.templates"] == "templates"


PATH_RE = re.compile(r"\bgenerator/(?:[a-z_]+/)*[a-z_]+\.(?:py|toml)\b")


def test_every_module_path_named_in_the_docs_and_code_exists():
    """Docs, templates (and so the generated C's comments), benchmarks and the package's
    own strings name modules by path: after a move, none may point at a file that is gone."""
    places = [REPO / "README.md", *(REPO / "docs").glob("*.md"), *(REPO / "templates").rglob("*.j2"),
              *PKG.rglob("*.py"), *(REPO / "bench").rglob("*.py"), *(REPO / "bench").rglob("*.md")]
    stale = sorted({f"{p.relative_to(REPO)}: {m}" for p in places
                    for m in PATH_RE.findall(p.read_text(errors="replace"))
                    if not (REPO / m).exists()})
    assert not stale, "paths that do not exist:\n" + "\n".join(stale)
