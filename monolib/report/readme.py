"""Keep the README's result blocks equal to the files in `figures/`: no number in the README is typed by hand.

A block in README.md is delimited by ``<!-- BEGIN figures/NAME -->`` and ``<!-- END figures/NAME -->``; `update`
replaces its content by the file (markdown tables as they are, CSV files as markdown tables, JSON as a code block).
`monolib study quick` calls it at the end; `tests/test_readme.py` checks the blocks are current.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import pandas as pd

from monolib import paths
from monolib.io import write_text

BLOCK = re.compile(r"(<!-- BEGIN figures/(?P<name>[^ ]+) -->\n)(?P<body>.*?)(<!-- END figures/(?P=name) -->)", re.S)


def render(path: Path) -> str:
    if not path.is_file():
        return f"_(not generated yet: run `make study` to write figures/{path.name})_\n"
    if path.suffix == ".md":
        return path.read_text().rstrip("\n") + "\n"
    if path.suffix == ".csv":
        return pd.read_csv(path).to_markdown(index=False, floatfmt=".3g") + "\n"
    if path.suffix == ".json":
        return "```json\n" + json.dumps(json.loads(path.read_text()), indent=2, sort_keys=True) + "\n```\n"
    return path.read_text()


def updated(text: str, figures: Path) -> str:
    return BLOCK.sub(lambda m: m.group(1) + render(figures / m.group("name")) + m.group(4), text)


def update(readme: Path = paths.ROOT / "README.md", figures: Path = paths.FIGURES) -> bool:
    """Rewrite the README's result blocks from `figures`; returns True when something changed."""
    text = readme.read_text()
    new = updated(text, figures)
    if new != text:
        write_text(readme, new)
    return new != text
