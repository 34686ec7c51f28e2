"""Griffe extension: Sphinx roles in the docstrings shown as code on the site.

The docstrings are read by Sphinx-minded tools too (``:func:`ceemx.fit```, ``:class:`~x.Y```);
on the MkDocs site a role would print as ``:func:``. Each becomes inline code of its target
(``~`` keeps the last component, as Sphinx does); ``.. math::`` blocks become ``$$`` blocks.
"""

from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|exc|obj|const|term):`(~?)([^`]+)`")
_MATH = re.compile(r"^( *)\.\. math::\n\n((?:\1 {4}.*\n|\n)+)", re.M)


def _role(m: re.Match) -> str:
    target = m.group(2)
    return f"`{target.rsplit('.', 1)[-1] if m.group(1) else target}`"


def _math(m: re.Match) -> str:
    indent = m.group(1)
    body = "\n".join(line.strip() for line in m.group(2).strip("\n").splitlines())
    return f"{indent}$$\n{body}\n{indent}$$\n\n"


class SphinxRoles(griffe.Extension):
    """Rewrite the roles and math blocks of every docstring (module notes)."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:  # noqa: D102
        if obj.docstring is not None:
            text = _MATH.sub(_math, obj.docstring.value)
            obj.docstring.value = _ROLE.sub(_role, text)
