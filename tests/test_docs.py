"""The documentation site's sources (docs/, mkdocs.yml): cheap checks without building it.

The build itself (``mkdocs build --strict``, in ``.ci/run``) fails on a broken reference, and
``docs/hooks.py`` fails it on a public name that is on no API page or has no docstring.
"""

import ast
import pathlib
import re

import ceemx

ROOT = pathlib.Path(__file__).parents[1]
_BLOCK = re.compile(r"```python\n(.*?)```", re.S)


def test_getting_started_shows_the_readme_example():
    readme = _BLOCK.search((ROOT / "README.md").read_text()).group(1)
    page = _BLOCK.search((ROOT / "docs" / "getting_started.md").read_text()).group(1)
    assert page == readme  # tests/test_readme.py runs it


def _stub_names() -> tuple[set[str], set[str]]:
    """(public names, subpackages) as the facade's one table, ``__init__.pyi``, lists them."""
    tree = ast.parse((ROOT / "src" / "ceemx" / "__init__.pyi").read_text())
    names, modules = set(), set()
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            assert node.level == 1, "the table's imports are relative (lazy_loader reads them)"
            for alias in node.names:
                assert alias.asname == alias.name, f"{alias.name}: the re-export form `X as X`"
                (names if node.module else modules).add(alias.name)
    return names, modules


def test_every_public_name_is_on_an_api_page():
    text = "\n".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md"))
    documented = set(re.findall(r"^::: *ceemx\.(\w+)", text, re.M))
    public, _ = _stub_names()  # the names, not the modules (no import)
    assert public - documented == set()


def test_the_facade_is_its_table():
    """``ceemx.__all__`` is the stub's names and subpackages, each resolving to what it names."""
    public, modules = _stub_names()
    assert set(ceemx.__all__) == public | modules
    assert not any(hasattr(ceemx, legacy) for legacy in ("driver", "smoothing", "report"))
    assert ceemx.inference.__name__ == "ceemx.inference"  # the subpackage, not an alias of a module
