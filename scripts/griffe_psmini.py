"""griffe extension for the API reference: psmini's docstrings as mkdocstrings' Google parser reads them.

psmini's docstrings are Google style with two habits from Sphinx that the parser would print verbatim: the
singular ``Example:`` heading (an admonition to griffe, so its doctest lines would render as nested quotes) and
roles such as ``:math:`(B, 3, H, W)``` or ``:func:`~psmini.io.find_samples```. This extension turns the first into
``Examples:`` and the roles into code spans, before the docstrings are parsed. It changes nothing in the code.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_EXAMPLE = re.compile(r"^(\s*)Example:\s*$", re.MULTILINE)
_ROLE = re.compile(r":(?:math|func|class|meth|mod|data|attr|obj|exc|ref):`~?\.?([^`]+)`")


def _code_span(match: re.Match) -> str:
    text = match.group(1)
    return f"`{text}`"


class PsminiDocstrings(griffe.Extension):
    """Rewrite ``Example:`` to ``Examples:`` and Sphinx roles to code spans in every docstring."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:  # noqa: ARG002 (griffe's hook signature)
        if obj.docstring is None:
            return
        value = _EXAMPLE.sub(r"\1Examples:", obj.docstring.value)
        obj.docstring.value = _ROLE.sub(_code_span, value)
