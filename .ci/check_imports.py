"""Import hygiene of the ceemx package: no import cycles, no private names across modules.

1. Cycles. Parses every module under ``src/ceemx`` with ``ast`` and builds the graph of imports
   between ceemx modules — within one folder as across folders — at module level, in class
   bodies, ``try``/``if`` blocks and inside functions: an import deferred into a function still
   ties the two modules together (one cannot be understood, moved or tested without the other),
   it only hides the circle from the interpreter. Imports under ``if TYPE_CHECKING:`` (for
   annotations only) are left out. ``from X import name`` is an edge to the module ``X.name``
   when there is one, otherwise to ``X``. Fails on any cycle and prints it.
2. Layers. The package's folders are ordered as the data flow (``LAYERS``: lib and infra at the
   bottom, then models, data, systems and datasets, inference, identification, evaluation,
   baselines, experiments, and the top-level modules). A module may import its own folder and
   folders of a lower layer only — never a higher layer or a sibling of the same layer — at import
   time or inside a function (``TYPE_CHECKING`` imports, for annotations only, are exempt). The
   public facade ``ceemx`` (lazy names from every layer) is for the experiments and the top only.
3. Private names. Fails when a module imports a name with one leading underscore (``_foo``, not
   ``__dunder__``) from another ceemx module, anywhere in the file, functions included. A private
   module (``_impl.py``) may be imported only from within its own package.

Usage: ``python .ci/check_imports.py [SRC_DIR]`` (default: ``src``). Exit status 1 on a finding.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

PACKAGE = "ceemx"

#: folders of the package, lowest first; one tuple per layer (siblings may not import each other)
LAYERS: list[tuple[str, ...]] = [
    ("lib",),
    ("infra",),
    ("models",),
    ("data",),
    ("systems",),
    ("datasets",),  # a dataset's registry entry names its gray-box model (systems)
    ("inference",),
    ("identification",),
    ("evaluation",),
    ("baselines",),
    ("experiments",),
    ("",),  # the top-level modules: __init__, __main__, cli
]


def layer_of(module: str) -> tuple[int, str]:
    """(layer index, folder) of a dotted ceemx module; top-level modules are the last layer."""
    parts = module.split(".")
    folder = parts[1] if len(parts) > 2 or (len(parts) == 2 and _is_folder(parts[1])) else ""
    for i, names in enumerate(LAYERS):
        if folder in names:
            return i, folder
    raise KeyError(f"{module}: folder {folder!r} is not in LAYERS (.ci/check_imports.py)")


_FOLDERS: set[str] = set()


def _is_folder(name: str) -> bool:
    return name in _FOLDERS


def layer_problem(importer: str, target: str) -> str | None:
    """Why ``importer`` may not import ``target`` (``None``: allowed)."""
    layer, folder = layer_of(importer)
    if target == PACKAGE:  # the public facade (lazy names from every layer): users' API
        if layer >= len(LAYERS) - 2:  # experiments use ceemx as a user does; so does the top
            return None
        return f"{importer} (layer {folder}) imports the public facade ceemx (names from any layer)"
    target_layer, target_folder = layer_of(target)
    if folder == target_folder or target_layer < layer:
        return None
    kind = "a sibling layer" if target_layer == layer else "a higher layer"
    return (
        f"{importer} (layer {folder or 'top'}) imports {target} ({kind}: {target_folder or 'top'})"
    )


def module_names(src: Path) -> dict[str, Path]:
    """Dotted module name → file, for every ``.py`` file of the package."""
    out = {}
    for path in sorted((src / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def is_private(name: str) -> bool:
    """``_foo`` is private; ``__foo__`` and ``__foo`` dunder-style names are not flagged."""
    return name.startswith("_") and not name.startswith("__")


def is_type_checking(test: ast.expr) -> bool:
    """Whether an ``if`` test is ``TYPE_CHECKING`` or ``typing.TYPE_CHECKING``."""
    if isinstance(test, ast.Name):
        return test.id == "TYPE_CHECKING"
    return isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"


class Imports(ast.NodeVisitor):
    """Collect the imports of one module as ``(node, import-time?)`` pairs."""

    def __init__(self) -> None:
        self.found: list[tuple[ast.Import | ast.ImportFrom, bool, bool]] = []
        self.deferred = 0  # depth inside functions / TYPE_CHECKING blocks
        self.typing_only = 0  # depth inside TYPE_CHECKING blocks

    def _defer(self, node: ast.AST) -> None:
        self.deferred += 1
        self.generic_visit(node)
        self.deferred -= 1

    def visit_FunctionDef(self, node: ast.FunctionDef) -> None:  # noqa: D102
        self._defer(node)

    def visit_AsyncFunctionDef(self, node: ast.AsyncFunctionDef) -> None:  # noqa: D102
        self._defer(node)

    def visit_Lambda(self, node: ast.Lambda) -> None:  # noqa: D102
        self._defer(node)

    def visit_If(self, node: ast.If) -> None:  # noqa: D102
        if is_type_checking(node.test):
            self.deferred += 1
            self.typing_only += 1
            for stmt in node.body:
                self.visit(stmt)
            self.deferred -= 1
            self.typing_only -= 1
            for stmt in node.orelse:
                self.visit(stmt)
        else:
            self.generic_visit(node)

    def visit_Import(self, node: ast.Import) -> None:  # noqa: D102
        self.found.append((node, self.deferred == 0, self.typing_only > 0))

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:  # noqa: D102
        self.found.append((node, self.deferred == 0, self.typing_only > 0))


def resolve_base(module: str, is_package: bool, node: ast.ImportFrom) -> str | None:
    """The absolute module named by ``from <base> import ...`` (``None``: outside ceemx)."""
    if node.level == 0:
        base = node.module or ""
    else:
        parts = module.split(".") if is_package else module.split(".")[:-1]
        if node.level - 1 > len(parts):
            return None
        parts = parts[: len(parts) - (node.level - 1)]
        base = ".".join(parts + ([node.module] if node.module else []))
    return base if base == PACKAGE or base.startswith(PACKAGE + ".") else None


def private_module_problem(importer: str, target: str) -> str | None:
    """A private component of ``target`` outside its own package, if any."""
    parts = target.split(".")
    for i, part in enumerate(parts):
        if is_private(part):
            owner = ".".join(parts[:i])  # the package that holds the private module
            if not (importer == owner or importer.startswith(owner + ".")):
                return f"private module {'.'.join(parts[: i + 1])}"
    return None


def analyse(src: Path) -> tuple[dict[str, set[str]], list[str]]:
    """(import graph between ceemx modules, deferred imports included; private-import findings)."""
    modules = module_names(src)
    _FOLDERS.update(p.parent.name for p in (src / PACKAGE).glob("*/__init__.py"))
    graph: dict[str, set[str]] = {m: set() for m in modules}
    problems: list[str] = []
    for module, path in modules.items():
        is_package = path.name == "__init__.py"
        visitor = Imports()
        visitor.visit(ast.parse(path.read_text(encoding="utf-8"), filename=str(path)))
        for node, _import_time, typing_only in visitor.found:
            where = f"{path}:{node.lineno}"
            targets: list[str] = []
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name == PACKAGE or alias.name.startswith(PACKAGE + "."):
                        targets.append(alias.name)
            else:
                base = resolve_base(module, is_package, node)
                if base is None:
                    continue
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    if sub in modules:
                        targets.append(sub)
                    else:
                        targets.append(base)
                        if is_private(alias.name):
                            problems.append(
                                f"{where}: {module} imports private name {alias.name!r} from {base}"
                            )
            for target in targets:
                reason = private_module_problem(module, target)
                if reason:
                    problems.append(f"{where}: {module} imports {reason}")
                layer = None if typing_only else layer_problem(module, target)
                if layer:
                    problems.append(f"{where}: {layer}")
                if not typing_only and target in modules and target != module:
                    graph[module].add(target)
    return graph, problems


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (as a closed path) per strongly connected component with more than one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = 0

    def strongconnect(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strongconnect(w)
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
                components.append(sorted(component))

    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))
    for v in sorted(graph):
        if v not in index:
            strongconnect(v)

    out = []
    for component in components:
        members = set(component)
        start = component[0]
        # Breadth-first search back to `start` inside the component: a shortest cycle through it.
        parent: dict[str, str] = {}
        frontier = [start]
        found = None
        while frontier and found is None:
            nxt = []
            for v in frontier:
                for w in sorted(graph[v] & members):
                    if w == start:
                        found = v
                        break
                    if w not in parent:
                        parent[w] = v
                        nxt.append(w)
                if found is not None:
                    break
            frontier = nxt
        path = [start]
        v = found
        while v is not None and v != start:
            path.append(v)
            v = parent.get(v)
        path = [start] + path[1:][::-1] + [start]
        out.append(path)
    return out


def main(argv: list[str]) -> int:
    """Run both checks; print findings; return the exit status."""
    src = Path(argv[1]) if len(argv) > 1 else Path("src")
    if not (src / PACKAGE).is_dir():
        print(f"check_imports: no package {PACKAGE!r} under {src}", file=sys.stderr)
        return 2
    graph, problems = analyse(src)
    found = cycles(graph)
    for path in found:
        print("import cycle: " + " -> ".join(path))
    for problem in problems:
        print(problem)
    problems = list(dict.fromkeys(problems))
    n_edges = sum(len(v) for v in graph.values())
    if found or problems:
        print(f"check_imports: {len(found)} cycle(s), {len(problems)} layer or private finding(s)")
        return 1
    print(
        f"check_imports: {len(graph)} modules, {n_edges} import edges (deferred ones included), "
        "no cycles, "
        "layers in order, no private imports"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
