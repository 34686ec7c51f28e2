"""MkDocs hook: every public name of ``ceemx`` is in the API reference, with a docstring.

Under ``mkdocs build --strict`` a warning fails the build, so a name added to ``ceemx.__all__``
without a ``::: ceemx.NAME`` entry on an API page, or without a docstring, fails CI (modules of
the facade are exempt: the pages document the ones users read whole).
"""

from __future__ import annotations

import logging
import re
import types

log = logging.getLogger("mkdocs.hooks.ceemx_api")
_DIRECTIVE = re.compile(r"^::: *ceemx\.([A-Za-z_][\w.]*)", re.M)
_documented: set[str] = set()


def on_pre_build(config) -> None:
    """Start each build with no page read."""
    _documented.clear()


def on_page_markdown(markdown: str, page, config, files) -> str:
    """Note the ``::: ceemx.NAME`` entries of a page."""
    _documented.update(_DIRECTIVE.findall(markdown))
    return markdown


def on_env(env, config, files):
    """After every page is read: warn for each public name undocumented or without a docstring."""
    import ceemx

    for name in ceemx.__all__:
        obj = getattr(ceemx, name)
        if isinstance(obj, types.ModuleType):
            continue
        if name not in _documented:
            log.warning("ceemx.%s is public (ceemx.__all__) but on no API page (docs/api/).", name)
        if not (getattr(obj, "__doc__", None) or "").strip():
            log.warning("ceemx.%s has no docstring.", name)
    return env
