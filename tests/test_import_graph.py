"""The import graph of `dissil_jax/` has no cycle, and nothing imports a private name across
a package boundary (tests and benchmarks go through `dissil_jax.internal`).

The graph is read from the source with `ast` (every `import`, module-level or inside a
function, except under `if TYPE_CHECKING:`), so a lazy import that merely hides a cycle
counts as one.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "dissil_jax"


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking_nodes(tree) -> set:
    """Nodes under `if TYPE_CHECKING:` (imports for annotations only)."""
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                skip.update(ast.walk(child))
    return skip


def _imports(path: Path, modules, root: Path) -> set[str]:
    """The package modules that the file at `path` imports."""
    tree = ast.parse(path.read_text())
    name = _module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    skip, found = _type_checking_nodes(tree), set()
    for node in ast.walk(tree):
        if node in skip:
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                full = f"{target}.{alias.name}"
                found.add(full if full in modules else target)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {m for m in found if m in modules and m != name}


def import_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    paths = {_module_name(p, package.parent): p for p in package.rglob("*.py")}
    return {name: _imports(path, paths, package.parent) for name, path in paths.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1 or v in graph[v]:
                        out.append(sorted(comp))
    return out


def test_cycle_finder_finds_cycles():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []


def test_graph_reads_relative_and_lazy_imports(tmp_path):
    pkg = tmp_path / "dissil_jax"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from ._a import f\n")
    (pkg / "_a.py").write_text("def f():\n    from . import sub\n")
    (pkg / "sub" / "__init__.py").write_text("from .. import _a\n")
    (pkg / "sub" / "g.py").write_text("from typing import TYPE_CHECKING\n"
                                      "if TYPE_CHECKING:\n    from .. import _a\n")
    graph = import_graph(pkg)
    assert graph["dissil_jax._a"] == {"dissil_jax.sub"}
    assert graph["dissil_jax.sub.g"] == set()
    assert cycles(graph) == [["dissil_jax._a", "dissil_jax.sub"]]


def test_dissil_jax_has_no_import_cycle():
    graph = import_graph()
    assert len(graph) > 40 and "dissil_jax._train.pgd" in graph
    assert cycles(graph) == []


def _private_imports(path: Path) -> list[str]:
    """`from dissil_jax... import _x` or `import dissil_jax._x` in a file outside the package."""
    bad = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dissil_jax"):
            names = [node.module] + [a.name for a in node.names]
            if any(part.startswith("_") and not part.startswith("__")
                   for n in names for part in n.split(".")):
                bad.append(ast.unparse(node))
        elif isinstance(node, ast.Import):
            bad += [a.name for a in node.names if a.name.startswith("dissil_jax._")]
    return bad


@pytest.mark.parametrize("folder", ["tests", "benchmarks", "examples"])
def test_no_private_imports_outside_the_package(folder):
    found = {str(p.relative_to(ROOT)): _private_imports(p)
             for p in sorted((ROOT / folder).rglob("*.py"))}
    assert {k: v for k, v in found.items() if v} == {}


@pytest.mark.parametrize("folder", ["dissil_jax", "tests", "benchmarks", "examples"])
def test_sources_compile_without_warnings(folder):
    # The docstrings carry LaTeX in non-raw strings, so every backslash is doubled. A single
    # one is either an invalid escape ("\\P": a SyntaxWarning on import, an error under
    # `python -W error`) or, worse, a valid one that silently changes the text ("\\top" is
    # a tab and "op", "\\beta" a backspace): no string constant holds such a control
    # character.
    import warnings

    bad = {}
    for path in sorted((ROOT / folder).rglob("*.py")):
        name, text = str(path.relative_to(ROOT)), path.read_text()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                tree = compile(text, name, "exec", ast.PyCF_ONLY_AST)
            except SyntaxError as err:
                bad[name] = str(err)
                continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                found = set(node.value) & {chr(c) for c in (7, 8, 9, 11, 12, 13)}
                if found:
                    bad[f"{name}:{node.lineno}"] = f"control characters {sorted(found)}"
    assert bad == {}
