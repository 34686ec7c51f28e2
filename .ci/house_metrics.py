"""Counts that describe how the house is kept (read-only; prints one line per count).

- import cycles between ceemx modules, imports inside functions counted (``check_imports``'s graph
  with deferred imports included; ``TYPE_CHECKING`` imports left out);
- functions over 80 and over 120 lines (``def`` to its last line, docstring included);
- modules over 500 lines;
- ``isinstance`` checks on a concrete noise or fit-solver class outside the module that defines it;
- sizes of the notebook-prone documents, result JSONs and probe scripts.

Usage: ``python .ci/house_metrics.py [--list]`` from the repository root (``--list`` names each
long function and each finding).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
import check_imports  # noqa: E402

SRC = Path("src")
#: abstract bases whose concrete subclasses (found in src, any file) count as concrete classes
EXTENSION_BASES = {"AbstractNoise", "AbstractGaussianNoise"}
CONCRETE = {
    # fit solvers
    "Alternating",
    "JointLM",
    "JointMatrixFree",
    "LaplaceEM",
    "ParticleEM",
}


def deferred_graph(src: Path) -> dict[str, set[str]]:
    """The import graph with imports inside functions included (TYPE_CHECKING excluded)."""
    modules = check_imports.module_names(src)
    check_imports._FOLDERS.update(p.parent.name for p in (src / "ceemx").glob("*/__init__.py"))
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        is_package = path.name == "__init__.py"
        visitor = check_imports.Imports()
        visitor.visit(ast.parse(path.read_text(encoding="utf-8")))
        for node, _import_time, typing_only in visitor.found:
            if typing_only:
                continue
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names if a.name.startswith("ceemx")]
            else:
                base = check_imports.resolve_base(module, is_package, node)
                if base is None:
                    continue
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    targets.append(sub if sub in modules else base)
            for target in targets:
                if target in modules and target != module and target != "ceemx":
                    graph[module].add(target)
    return graph


def long_functions(src: Path) -> list[tuple[int, str]]:
    """(lines, "path:name") of every function, longest first."""
    out = []
    for path in sorted((src / "ceemx").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                start = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                out.append((node.end_lineno - start + 1, f"{path}:{node.name}"))
    return sorted(out, reverse=True)


def concrete_isinstance(src: Path) -> list[str]:
    """``isinstance(x, Concrete)`` outside the module that defines ``Concrete``."""
    defined: dict[str, Path] = {}
    paths = sorted((src / "ceemx").rglob("*.py"))
    classes = [
        (node, path)
        for path in paths
        for node in ast.parse(path.read_text(encoding="utf-8")).body
        if isinstance(node, ast.ClassDef)
    ]
    bases, grown = set(EXTENSION_BASES), True
    while grown:  # every subclass of an extension base, however deep
        before = len(bases)
        bases |= {c.name for c, _ in classes if {getattr(b, "id", None) for b in c.bases} & bases}
        grown = len(bases) > before
    for node, path in classes:
        if node.name in CONCRETE or (node.name in bases and not node.name.startswith("Abstract")):
            defined[node.name] = path
    found = []
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == "isinstance"
                and len(node.args) == 2
            ):
                continue
            names = {n.id for n in ast.walk(node.args[1]) if isinstance(n, ast.Name)}
            names |= {n.attr for n in ast.walk(node.args[1]) if isinstance(n, ast.Attribute)}
            for name in sorted(names & set(defined)):
                if defined[name] != path:
                    found.append(f"{path}:{node.lineno}: isinstance(..., {name})")
    return found


def main(argv: list[str]) -> int:
    """Print the counts."""
    show = "--list" in argv
    cycles = check_imports.cycles(deferred_graph(SRC))
    print(f"import cycles (deferred imports counted): {len(cycles)}")
    if show:
        for c in cycles:
            print("   ", " -> ".join(c))
    funcs = long_functions(SRC)
    over80 = [f for f in funcs if f[0] > 80]
    over120 = [f for f in funcs if f[0] > 120]
    print(f"functions over 80 lines: {len(over80)}; over 120: {len(over120)}")
    if show:
        for n, name in over80:
            print(f"    {n:4d} {name}")
    sizes = [
        (len(p.read_text(encoding="utf-8").splitlines()), p)
        for p in sorted((SRC / "ceemx").rglob("*.py"))
    ]
    big = [(n, p) for n, p in sizes if n > 500]
    print(f"modules over 500 lines: {len(big)} (of {len(sizes)}; {sum(n for n, _ in sizes)} lines)")
    if show:
        for n, p in sorted(big, reverse=True):
            print(f"    {n:4d} {p}")
    checks = concrete_isinstance(SRC)
    print(f"isinstance on a concrete noise/solver class outside its module: {len(checks)}")
    if show:
        for c in checks:
            print("   ", c)
    for doc in ("benchmarks/README.md", "docs/design.md", "docs/results.md", "docs/decisions.md"):
        p = Path(doc)
        print(f"{doc}: {p.stat().st_size / 1000:.1f} kB" if p.exists() else f"{doc}: absent")
    results = sorted(Path("benchmarks/results").rglob("*.json"))
    probes = (
        sorted(Path("benchmarks/probes").glob("*.py")) if Path("benchmarks/probes").exists() else []
    )
    print(f"result JSONs: {len(results)}; probes: {len(probes)}")
    refs = sum(
        p.read_text(encoding="utf-8").count("benchmarks/") for p in (SRC / "ceemx").rglob("*.py")
    )
    print(f"'benchmarks/' references in src: {refs}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
