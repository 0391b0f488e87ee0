"""mkdocs hook: the CLI reference page is generated from the ``hogsa`` parsers."""

from __future__ import annotations

import argparse
from typing import Any

MARKER = "<!-- cli-reference -->"


def _walk(parser: argparse.ArgumentParser, name: str, out: list[tuple[str, argparse.ArgumentParser]]) -> None:
    out.append((name, parser))
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, sp in action.choices.items():
                _walk(sp, f"{name} {sub}", out)


def cli_reference() -> str:
    """Markdown: every ``hogsa`` sub-command's ``--help``, in order."""
    from hogsa_loader.cli.build import build_parser as build
    from hogsa_loader.cli.main import build_parser

    parsers: list[tuple[str, argparse.ArgumentParser]] = []
    _walk(build_parser(), "hogsa", parsers)
    parsers = [(n, build() if n == "hogsa build" else p) for n, p in parsers]
    parts = []
    for name, parser in parsers:
        parser.prog = name
        parts.append(f"## `{name}`\n\n```text\n{parser.format_help()}```\n")
    return "\n".join(parts)


def on_page_markdown(markdown: str, page: Any, **_: Any) -> str:
    if MARKER in markdown:
        return markdown.replace(MARKER, cli_reference())
    return markdown
