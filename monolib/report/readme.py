"""Keep the result blocks of README.md and docs/*.md equal to the files in `figures/`: no number is typed by hand.

A block is delimited by ``<!-- BEGIN figures/NAME -->`` and ``<!-- END figures/NAME -->``; `update` replaces its
content by the file (markdown as it is, CSV files as markdown tables, JSON as a code block). A file that does not
exist yet renders as one line saying which command writes it. Headings inside a block are demoted below the heading
of the section the block sits in (a `#` under a `##` section becomes `###`), so that every page keeps one title.
`monolib study quick` and `make readme` call `update`; `tests/test_readme.py` checks the blocks are current.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import pandas as pd

from monolib import paths
from monolib.io import write_text

BLOCK = re.compile(r"(<!-- BEGIN figures/(?P<name>[^ ]+) -->\n)(?P<body>.*?)(<!-- END figures/(?P=name) -->)", re.S)
HEADING = re.compile(r"^(#{1,6}) ")
FENCE = "```"


def all_pages(root: Path = paths.ROOT) -> list[Path]:
    """The pages whose blocks `update` refreshes: README.md and every docs/*.md."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def render(path: Path, name: str = "") -> str:
    """A figures file as markdown; a line naming it when it is not written yet (`name`: its path in figures/)."""
    if not path.is_file():
        return f"_(not generated yet: figures/{name or path.name}, written by its study's command in README.md)_\n"
    if path.suffix == ".md":
        return path.read_text().rstrip("\n") + "\n"
    if path.suffix == ".csv":
        return pd.read_csv(path).to_markdown(index=False, floatfmt=".3g") + "\n"
    if path.suffix == ".json":
        return "```json\n" + json.dumps(json.loads(path.read_text()), indent=2, sort_keys=True) + "\n```\n"
    return path.read_text()


def heading_levels(lines: list[str]) -> list[int]:
    """The level of each line that is a markdown heading (0 for other lines and for lines inside code fences)."""
    levels, fenced = [], False
    for line in lines:
        if line.startswith(FENCE):
            fenced = not fenced
        m = None if fenced else HEADING.match(line)
        levels.append(len(m.group(1)) if m else 0)
    return levels


def demote(body: str, by: int) -> str:
    """`body` with each heading `by` levels deeper (code fences left alone)."""
    lines = body.split("\n")
    return "\n".join("#" * by + line if level else line for line, level in zip(lines, heading_levels(lines)))


def section_level(text: str) -> int:
    """The level of the last heading of `text` (0 when it has none)."""
    return next((level for level in reversed(heading_levels(text.split("\n"))) if level), 0)


def updated(text: str, figures: Path) -> str:
    def block(m: re.Match) -> str:
        body = demote(render(figures / m.group("name"), m.group("name")), section_level(text[: m.start()]))
        return m.group(1) + body + m.group(4)

    return BLOCK.sub(block, text)


def update(pages: list[Path] | None = None, figures: Path = paths.FIGURES) -> bool:
    """Rewrite the result blocks of `pages` (default: README.md and docs/*.md) from `figures`; True when one changed."""
    changed = False
    for page in all_pages() if pages is None else pages:
        text = page.read_text()
        new = updated(text, figures)
        if new != text:
            write_text(page, new)
            changed = True
    return changed
