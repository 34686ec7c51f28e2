"""The documentation site's sources (docs/, mkdocs.yml): cheap checks without building it.

The build itself (``mkdocs build --strict``, in ``.ci/run``) fails on a broken reference, and
``docs/hooks.py`` fails it on a public name that is on no API page or has no docstring.
"""

import pathlib
import re

import ceemx

ROOT = pathlib.Path(__file__).parents[1]
_BLOCK = re.compile(r"```python\n(.*?)```", re.S)


def test_getting_started_shows_the_readme_example():
    readme = _BLOCK.search((ROOT / "README.md").read_text()).group(1)
    page = _BLOCK.search((ROOT / "docs" / "getting_started.md").read_text()).group(1)
    assert page == readme  # tests/test_readme.py runs it


def test_every_public_name_is_on_an_api_page():
    text = "\n".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md"))
    documented = set(re.findall(r"^::: *ceemx\.(\w+)", text, re.M))
    public = set(ceemx.__all__) & set(ceemx._LAZY)  # the names, not the modules (no import)
    assert public - documented == set()
