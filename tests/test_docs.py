"""The documentation site's sources (docs/, mkdocs.yml): cheap checks without building it.

The build itself (``mkdocs build --strict``, in ``.ci/run``) fails on a broken reference, and
``docs/hooks.py`` fails it on a public name that is on no API page or has no docstring.
"""

import ast
import pathlib
import re
import sys

import numpy as np
import pytest

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


# Docs as tests (.ci/docs_blocks.py runs every page's Python blocks in CI; here its rules).
sys.path.insert(0, str(ROOT / ".ci"))  # CI tooling, not part of the library
import docs_blocks  # noqa: E402

_PAGE = """# A page

<!-- docs-test: skip (a reason) -->
```python
raise SystemExit("never run")
```

```python
print("a =", 1.23456)
```

prints

```text
a = 1.23456
```

```bash
echo not python
```
"""


def test_docs_blocks_reads_a_page():
    page = docs_blocks.parse(pathlib.Path("page.md"), _PAGE)
    assert [b.skip for b in page.blocks] == ["(a reason)", None]
    assert page.blocks[1].line == 9 and page.blocks[1].output == "a = 1.23456\n"
    with pytest.raises(ValueError, match="text fence before any Python block"):
        docs_blocks.parse(pathlib.Path("p.md"), "```text\nx\n```\n")
    with pytest.raises(ValueError, match="second text fence"):
        docs_blocks.parse(pathlib.Path("p.md"), _PAGE + "```text\ny\n```\n")


def test_docs_blocks_compares_words_numbers_and_not_times():
    same = docs_blocks.same_output
    assert same("J = 5883.9865 (start 4519.42)", "J   =  5883.99\n(start 4519.42)")
    assert not same("J = 5883.9865", "J = 5890.1")  # numbers to 1e-3
    assert not same("converged after 38 epochs", "not converged after 38 epochs")
    assert same("19.3 s in all (first epoch 16.4 s)", "7.56 s in all (first epoch 5.28 s)")
    assert same("saved 2026-11-29T06:58:55+00:00 by", "saved 2027-01-02T10:00:00+00:00 by")
    assert not same("dt = 4.0 s", "dt = 2.0 s")  # a sample time is not a wall-clock time


def test_docs_blocks_writes_outputs_into_the_page(tmp_path):
    path = tmp_path / "page.md"
    path.write_text(_PAGE)
    page = docs_blocks.parse(path)
    run = {"error": None, "blocks": [{"skip": "x"}, {"output": "a = 2\nWarn: w\n"}]}
    problems, checked = docs_blocks.check(page, run, write=False)
    assert checked == 1 and "differs" in problems[0]
    assert docs_blocks.write_outputs(page, run)
    assert docs_blocks.parse(path).blocks[1].output == "a = 2\nWarn: w\n"
    assert docs_blocks.check(docs_blocks.parse(path), run, write=False) == ([], 1)


def test_every_page_parses_for_the_docs_test():
    """Each text fence of every page is the output of the Python block before it."""
    counts = {p.name: len(docs_blocks.parse(p).blocks) for p in docs_blocks.pages()}
    assert counts["README.md"] >= 1 and counts["real_data.md"] >= 4


def test_figures_show_the_numbers_the_pages_print():
    """docs/make_figures.py records what each figure shows; the pages print the same runs."""
    import json

    shown = json.loads((ROOT / "docs" / "figures" / "figures.json").read_text())
    page = docs_blocks.parse(ROOT / "docs" / "getting_started.md")
    printed = page.blocks[1].output  # the scoring block: the fit the tanks figure draws
    assert printed is not None
    row = re.search(r"^0 .*$", printed, re.M).group(0)  # record 0: name, RMSE, NRMSE, fit %
    rmse = float(row.split()[-3])
    np.testing.assert_allclose(rmse, shown["benchmark_tanks"]["gray-box RMSE [V]"], rtol=1e-3)
    text = " ".join((ROOT / "docs" / "getting_started.md").read_text().split())
    quoted = re.search(r"RMSE ([\d.]+) mV on the arrow record", text).group(1)
    assert quoted == f"{shown['benchmark_silverbox']['gray-box RMSE [mV]']:.3g}"
    assert f"RMSE {rmse:.3g} V" in text
