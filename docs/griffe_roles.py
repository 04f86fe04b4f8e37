"""Griffe extension for the API pages: the docstrings' Sphinx roles (``:class:`~torchrl_bail.x.Y```) become links.

The docstrings are written for ``help()`` and IDEs as much as for the site, in Google style with Sphinx roles. A
role whose target is rendered on the site becomes a cross-reference (mkdocs-autorefs); any other target (torch,
TorchRL, a private helper) stays inline code, without a warning. As in Sphinx, ``~`` shows the last name only and
``title <target>`` shows the title.
"""

from __future__ import annotations

import html
import re

import griffe

_TITLED = re.compile(r"^(?P<title>.+?)\s*<(?P<target>[^<>]+)>$")
_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|exc|obj|const)\s*:`(?P<tilde>~?)(?P<target>[^`]+)`")


def _identifier(target: str, obj: griffe.Object) -> str:
    """The full dotted path a role's target names, read from where the docstring sits."""
    target = target.lstrip(".")
    if target.startswith("torchrl_bail"):
        return target
    scope = obj if obj.is_class or obj.is_module else obj.parent
    if scope is not None and scope.is_class and target.split(".")[0] not in scope.members:
        scope = scope.module
    return f"{scope.path}.{target}" if scope is not None else target


def convert(text: str, obj: griffe.Object) -> str:
    def link(match: re.Match) -> str:
        target = match["target"].strip()
        titled = _TITLED.match(target)  # :meth:`title <target>`
        if titled:
            shown, target = titled["title"], titled["target"]
        else:
            shown = target.rsplit(".", 1)[-1] if match["tilde"] else target
        return (f'<autoref identifier="{html.escape(_identifier(target, obj))}" optional>'
                f"<code>{html.escape(shown)}</code></autoref>")

    return _ROLE.sub(link, text)


class SphinxRoles(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = convert(obj.docstring.value, obj)
