"""The house by stage: every import of monolib points down the pipeline (shared tools < data < perception < graphs
< retrieval < report < study < the entry points), at module level or inside a function, and a module imports
another of monolib inside a function only to defer a heavy library, saying so on that line."""
from __future__ import annotations

import ast
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.shares_runs


PACKAGE = Path(__file__).resolve().parents[1] / "monolib"
# the wings in the order data flows; a module may import its own wing (no cycle: tools/import_cycles) or a lower one
ORDER = ["shared", "data", "perception", "graphs", "retrieval", "report", "study", "entry"]
ENTRY = {"localize", "bench", "cli"}
DEFERRED = "# deferred:"  # the comment a function-level import of monolib carries: the heavy library it defers


def wing(module: str) -> str:
    parts = module.split(".")[1:]
    if len(parts) > 1 and parts[0] in ORDER:
        return parts[0]
    return "entry" if parts and parts[0] in ENTRY else "shared"


def modules() -> dict[str, Path]:
    out = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        rel = f.relative_to(PACKAGE.parent).with_suffix("")
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        out[name] = f
    return out


def imports(path: Path):
    """(line, imported module, at module level, the line's text) for each import of monolib in `path`."""
    text = path.read_text()
    lines = text.splitlines()
    tree = ast.parse(text, str(path))
    top = {id(n) for n in tree.body}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "monolib":
            targets = [node.module] if node.module != "monolib" else [f"monolib.{a.name}" for a in node.names]
            if node.module != "monolib":
                targets = [f"{node.module}.{a.name}"
                           if (PACKAGE.parent / f"{node.module}.{a.name}".replace(".", "/")).with_suffix(".py").exists()
                           or (PACKAGE.parent / f"{node.module}.{a.name}".replace(".", "/")).is_dir() else node.module
                           for a in node.names]
        elif isinstance(node, ast.Import):
            targets = [a.name for a in node.names if a.name.split(".")[0] == "monolib"]
        else:
            continue
        for t in targets:
            yield node.lineno, t, id(node) in top, lines[node.lineno - 1]


def test_every_import_points_down_the_pipeline():
    up = []
    for name, path in modules().items():
        for line, target, _, _ in imports(path):
            if ORDER.index(wing(target)) > ORDER.index(wing(name)):
                up.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {name} ({wing(name)}) imports {target} "
                          f"({wing(target)})")
    assert not up, "imports up the pipeline:\n" + "\n".join(up)


def test_function_level_imports_of_monolib_only_defer_a_heavy_library():
    hidden = []
    for name, path in modules().items():
        for line, target, at_top, text in imports(path):
            if not at_top and DEFERRED not in text:
                hidden.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {text.strip()}")
    assert not hidden, ("imports of monolib inside a function without '# deferred: <library>' (move them to the "
                        "top of the module):\n" + "\n".join(hidden))


@pytest.mark.parametrize("module,expected", [("monolib.data.synth", "data"), ("monolib.params", "shared"),
                                             ("monolib.cli", "entry"), ("monolib.study.runner", "study")])
def test_wing(module, expected):
    assert wing(module) == expected


@pytest.mark.slow
def test_a_cell_computes_each_upstream_key_once(smoke_study, tmp_path):
    """Following the study through `run_cell` of a scenario of predicted depth and semantics: the graph stage's key
    is computed once and passed on (to the cell's key and to the graph stage's loader), and it computes the data
    key once and hands it to each model's key, rather than each stage reaching back for the keys it depends on."""
    import sys
    from collections import Counter

    from monolib.params import load_study
    from monolib.retrieval import cell

    study = load_study("smoke")
    sc = study.scenarios["s3"]
    assert "gt" not in (sc.depth, sc.semantic)
    calls: Counter = Counter()

    def profile(frame, event, arg):
        if event == "call" and frame.f_globals.get("__name__", "").startswith("monolib."):
            calls[f"{frame.f_globals['__name__']}.{frame.f_code.co_name}"] += 1

    sys.setprofile(profile)
    try:
        record = cell.run_cell(study, "gcn", "s3", 1.0, study.seed, out_dir=str(tmp_path / "cell"))
    finally:
        sys.setprofile(None)
    assert record["metrics"]
    assert calls["monolib.graphs.scenegraphs.scenario_key"] == 1
    assert calls["monolib.data.dataset.dataset_key"] == 1
    assert calls["monolib.perception.predictions.model_key"] == 2  # its depth net and its segmentation net
    assert calls["monolib.retrieval.cell.cell_key"] == 1


HISTORY = [  # what a comment that tells history instead of the code says
    (re.compile(r"\b[Ii]ssues? ?#?\d+"), "an issue number"),
    (re.compile(r"\b20\d\d-\d\d-\d\d\b"), "a date"),
    (re.compile(r"\b[Gg]enerator(?: version)? \d"), "a generator version"),
    (re.compile(r"\.\./shared/docs"), "a document a clone does not have"),
]


def source_files() -> list[Path]:
    root = PACKAGE.parent
    files = [f for d in ("monolib", "tests") for f in sorted((root / d).rglob("*.py"))]
    files += sorted((root / "params").glob("*.yaml")) + sorted((root / "notebooks").glob("*.ipynb"))
    return [f for f in files if f.name != "test_layout.py"]


def test_code_and_studies_say_what_is_not_when():
    """Comments, docstrings, study files and notebooks explain the code as it is: no issue numbers, dates,
    generator versions or references to documents outside the repository (those live in CHANGELOG.md)."""
    found = []
    for f in source_files():
        for n, line in enumerate(f.read_text().splitlines(), 1):
            for pattern, what in HISTORY:
                if pattern.search(line):
                    found.append(f"{f.relative_to(PACKAGE.parent)}:{n}: {what}: {line.strip()[:120]}")
    assert not found, "\n".join(found)


def test_ruff_finds_nothing():
    """`ruff check` with the settings of pyproject.toml's [tool.ruff] passes on monolib/, tests/ and notebooks/ (what
    `make test-fast` runs first)."""
    if importlib.util.find_spec("ruff") is None:
        pytest.skip("ruff is not installed (the test extras install it: pip install -e '.[test]')")
    done = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "monolib", "tests", "notebooks"],
                          cwd=PACKAGE.parent, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
