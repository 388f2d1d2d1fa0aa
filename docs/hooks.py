"""MkDocs hook: the docstrings' Sphinx roles (:func:`x`, :class:`~a.b.C`) read as plain code.

The library's docstrings name other objects the Sphinx way; mkdocstrings renders them as Markdown,
where the role stays in front of the code span. This drops the role, and with a leading ``~`` the
module path, as Sphinx shows them."""

import re

ROLE = re.compile(r":(?:func|meth|class|attr|mod|data|exc|obj):<code>(~?)([^<]*)</code>")


def _code(match: re.Match) -> str:
    name = match.group(2)
    return f"<code>{name.rsplit('.', 1)[-1] if match.group(1) else name}</code>"


def on_page_content(html: str, **kwargs) -> str:
    return ROLE.sub(_code, html)
