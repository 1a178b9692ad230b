"""README.md and docs/*.md: result blocks are copies of figures/, and every page reads as one outline.

The blocks are rewritten by `make readme` (and at the end of `monolib study quick`); the other checks hold the pages
to what a clone of the repository can read: one title, no skipped heading level, no long lines of prose, links that
resolve, and no history (issue numbers, commit hashes, generator versions, paths outside the repository).
"""
import re
from pathlib import Path

import pytest

from monolib import paths
from monolib.report import readme

FIGURES = paths.ROOT / "figures"
PAGES = readme.all_pages()
DOCS = ("results", "data", "perception", "ablations", "benchmarks", "cluster", "usage", "conventions",
        "reproducibility", "real-data")  # the last two are written with `make verify` and the real-data study
ids = [str(p.relative_to(paths.ROOT)) for p in PAGES]


def prose(text: str) -> list[str]:
    """The lines of `text` outside generated blocks, code fences and tables."""
    text = readme.BLOCK.sub("", text)
    lines, fenced = [], False
    for line in text.split("\n"):
        if line.startswith(readme.FENCE):
            fenced = not fenced
        elif not fenced and not line.startswith("|"):
            lines.append(line)
    return lines


def test_readme_shows_the_two_commands_and_fits_a_front_page():
    text = (paths.ROOT / "README.md").read_text()
    assert "make study" in text and "make test" in text
    assert len(text.splitlines()) <= 250


def test_every_docs_page_exists():
    missing = [name for name in DOCS if not (paths.ROOT / "docs" / f"{name}.md").is_file()]
    assert not missing, f"docs pages missing: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=ids)
def test_result_blocks_match_figures(page: Path):
    text = page.read_text()
    assert text == readme.updated(text, FIGURES), f"{page.name}: run `make readme`"


@pytest.mark.parametrize("page", PAGES, ids=ids)
def test_one_title_and_no_skipped_heading_level(page: Path):
    levels = [level for level in readme.heading_levels(page.read_text().split("\n")) if level]
    assert levels[0] == 1 and levels.count(1) == 1, "one `#` title, first"
    skips = [(a, b) for a, b in zip(levels, levels[1:]) if b > a + 1]
    assert not skips, f"heading levels skipped: {skips}"


@pytest.mark.parametrize("page", [*PAGES, paths.ROOT / "CHANGELOG.md"], ids=[*ids, "CHANGELOG.md"])
def test_prose_lines_are_short(page: Path):
    long = [line[:60] for line in prose(page.read_text()) if len(line) > 200]
    assert not long, long


HISTORY = {
    "an issue number": re.compile(r"\bissues? #?\d+", re.I),
    "a commit hash": re.compile(r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b"),
    "a generator version": re.compile(r"\bgenerator (version )?\d+", re.I),
    "a path outside the repository": re.compile(r"\.\./shared|/work/"),
}


@pytest.mark.parametrize("page", PAGES, ids=ids)
def test_pages_state_what_is_true_now(page: Path):
    text = "\n".join(prose(page.read_text()))
    found = {what: m.group(0) for what, rx in HISTORY.items() if (m := rx.search(text))}
    assert not found, f"{page.name} holds history (CHANGELOG.md is its place): {found}"


def anchors(page: Path) -> set[str]:
    """GitHub's anchors of `page`'s headings: lower case, punctuation dropped, spaces as hyphens."""
    lines = page.read_text().split("\n")
    return {re.sub(r"[^\w\- ]", "", line.lstrip("#").strip().lower()).replace(" ", "-")
            for line, level in zip(lines, readme.heading_levels(lines)) if level}


def broken_links(page: Path) -> list[str]:
    """The relative links of `page` whose file, or whose anchor in that file, does not exist."""
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
        if "://" in target:
            continue
        file, _, anchor = target.partition("#")
        path = page.parent / file if file else page
        if not path.exists() or (anchor and path.suffix == ".md" and anchor not in anchors(path)):
            broken.append(target)
    return broken


def test_readme_links_resolve():
    broken = broken_links(paths.ROOT / "README.md")
    assert not broken, f"README links to missing files or anchors: {broken}"


def test_docs_links_resolve():
    broken = {page.name: b for page in PAGES[1:] if (b := broken_links(page))}
    assert not broken, broken


def test_block_headings_sit_below_their_section(tmp_path: Path):
    (tmp_path / "t.md").write_text("# A table\n\n## Part\n\ntext\n")
    (tmp_path / "t.json").write_text('{"a": 1}')
    page = ("# Page\n\n## Section\n\n<!-- BEGIN figures/t.md -->\n<!-- END figures/t.md -->\n\n"
            "### Sub\n\n<!-- BEGIN figures/t.json -->\nold\n<!-- END figures/t.json -->\n")
    out = readme.updated(page, tmp_path)
    assert "\n### A table\n\n#### Part\n" in out
    assert '```json\n{\n  "a": 1\n}\n```\n<!-- END figures/t.json -->' in out
    assert readme.updated(out, tmp_path) == out


def test_a_missing_figure_leaves_a_line_saying_what_writes_it(tmp_path: Path):
    page = "# Page\n\n## Claims\n\n<!-- BEGIN figures/claims.md -->\n<!-- END figures/claims.md -->\n"
    out = readme.updated(page, tmp_path)
    assert ("_(not generated yet: figures/claims.md, written by its study's command in README.md)_\n"
            "<!-- END figures/claims.md -->") in out


def test_update_rewrites_every_page(tmp_path: Path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / "t.md").write_text("# T\n")
    for page in (tmp_path / "README.md", tmp_path / "docs" / "a.md"):
        page.write_text("# P\n\n<!-- BEGIN figures/t.md -->\n<!-- END figures/t.md -->\n")
    assert readme.update(readme.all_pages(tmp_path), tmp_path / "figures")
    for page in readme.all_pages(tmp_path):
        assert "<!-- BEGIN figures/t.md -->\n## T\n<!-- END" in page.read_text()
    assert not readme.update(readme.all_pages(tmp_path), tmp_path / "figures")


NOTEBOOKS = sorted((paths.ROOT / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[n.name for n in NOTEBOOKS])
def test_notebook_text_states_what_is_true_now(notebook: Path):
    import nbformat

    text = "\n".join(c.source for c in nbformat.read(notebook, as_version=4).cells if c.cell_type == "markdown")
    rules = {**HISTORY, "a date": re.compile(r"\b20\d\d-\d\d-\d\d\b"),
             "no pretrained weights (the zoo ships them)": re.compile(r"no pretrained weights", re.I)}
    found = {what: m.group(0) for what, rx in rules.items() if (m := rx.search(text))}
    assert not found, f"{notebook.name}'s text holds history: {found}"
