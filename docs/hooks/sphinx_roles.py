"""A griffe extension for the API reference: the docstrings' Sphinx roles as Markdown code.

The docstrings write cross-references as Sphinx does (``:func:`~dem_graph.pipeline.config.run_config```);
Markdown would show the role's name as text. This turns each role into inline code, the name
shortened as Sphinx shortens it (``~a.b.c`` shows ``c``). It changes only what the site shows,
not the docstrings (mkdocs.yml loads it; the site's build leaves this folder out).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|meth|class|mod|data|attr|obj|exc|const|ref|term):`(~?)([^`]+)`")


def _plain(match: re.Match) -> str:
    short, target = match.group(1), match.group(2)
    if "<" in target and target.endswith(">"):  # :ref:`text <target>`
        return f"`{target.split('<', 1)[0].strip()}`"
    return f"`{target.rsplit('.', 1)[-1] if short else target}`"


def sphinx_roles_as_code(text: str) -> str:
    return ROLE.sub(_plain, text)


class SphinxRolesAsCode(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = sphinx_roles_as_code(obj.docstring.value)
