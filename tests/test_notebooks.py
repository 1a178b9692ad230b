"""The notebooks: the house rules (one `parameters` cell of literals whose defaults the code accepts, no
definitions, kernel python3), the outputs nbval compares (kept only in the cells marked `# NBVAL_CHECK_OUTPUT`,
through nbstripout's `keep_output` metadata; free of timings and paths), nbval failing on a changed number, and
a notebook run as a new user runs it: papermill from another directory, on an empty runs folder, with a threshold
and seed that no study lists. (`make test` then runs every notebook itself: `pytest --nbval-lax notebooks/`.)"""
import ast
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from monolib import methods, paths
from monolib.params import load_study

pytestmark = pytest.mark.shares_runs


NOTEBOOKS = sorted(paths.NOTEBOOKS.glob("*.ipynb"))
SANITIZE = Path(__file__).with_name("nbval_sanitize.cfg")
CHECK = "# NBVAL_CHECK_OUTPUT"
# what a checked output must not hold: it is compared on every machine (nbval), so no timings, no paths
MACHINE_DEPENDENT = re.compile(r"/tmp/|/home/|/work/|/runs/|\d+(\.\d+)? ?(s|ms|sec|seconds)\b|\bs/it\b|it/s\b")


def load(path: Path) -> dict:
    return json.loads(path.read_text())


def code_cells(nb: dict) -> list[dict]:
    return [c for c in nb["cells"] if c["cell_type"] == "code"]


def source(cell: dict) -> str:
    return "".join(cell["source"])


def parameters(nb: dict) -> dict:
    """The defaults of the one cell tagged `parameters` ({name: literal})."""
    cells = [c for c in code_cells(nb) if "parameters" in c.get("metadata", {}).get("tags", [])]
    assert len(cells) == 1, "exactly one cell tagged parameters"
    out = {}
    for node in ast.parse(source(cells[0])).body:
        assert isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name), \
            "the parameters cell holds `name = literal` lines only"
        out[node.targets[0].id] = ast.literal_eval(node.value)  # raises on anything but a literal
    return out


def checked(nb: dict) -> list[dict]:
    return [c for c in code_cells(nb) if source(c).lstrip().startswith(CHECK)]


def output_text(cell: dict) -> str:
    return "".join("".join(o.get("text", "")) for o in cell["outputs"])


def test_the_notebooks_and_their_parameters_are_those_the_code_expects():
    """The five notebooks exist; the runner's grid and report parameters are declared (papermill's own reading);
    every notebook's defaults are the smoke study and values that its calls accept; every parameter is used."""
    import papermill

    from monolib.study.notebooks import CELL_NOTEBOOK, REPORT_NOTEBOOK, check_notebook_parameters

    assert {p.stem for p in NOTEBOOKS} == {"ablation_cell", "report", "data", "segmentation", "depth", "localize"}
    check_notebook_parameters(CELL_NOTEBOOK, {"study", "method", "scenario", "threshold", "seed", "out_dir"})
    check_notebook_parameters(REPORT_NOTEBOOK, {"study"})
    for path in NOTEBOOKS:
        nb = load(path)
        defaults = parameters(nb)
        assert set(papermill.inspect_notebook(str(path))) == set(defaults), path.name
        assert defaults["study"] == "smoke", f"{path.name}: the defaults are the smoke study"
        later = "".join(source(c) for c in code_cells(nb) if "parameters" not in c["metadata"].get("tags", []))
        for name in defaults:
            assert re.search(rf"\b{name}\b", later), f"{path.name}: parameter {name} is never used"
    smoke = load_study("smoke")
    cell = parameters(load(CELL_NOTEBOOK))
    assert cell["method"] in methods.METHODS and cell["scenario"] in smoke.scenarios
    assert float(cell["threshold"]) in smoke.thresholds and cell["seed"] in smoke.seeds  # a cell of the grid
    assert cell["out_dir"] == ""
    assert isinstance(parameters(load(paths.NOTEBOOKS / "data.ipynb"))["frames_shown"], int)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_rules(path):
    nb = load(path)
    assert nb["metadata"]["kernelspec"]["name"] == "python3"
    parameters(nb)
    for c in code_cells(nb):
        tree = ast.parse("".join(line for line in c["source"] if not line.lstrip().startswith(("%", "!"))))
        assert not any(isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda))
                       for n in ast.walk(tree)), "no definitions in a notebook: they belong in monolib"
        assert c.get("execution_count") is None, "committed without execution counts (the git filter clears them)"
        if c["outputs"]:
            assert source(c).lstrip().startswith(CHECK), "only the cells nbval checks keep outputs"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_checked_cells_keep_their_outputs_and_print_no_timings_or_paths(path):
    """Each notebook checks its numbers (# NBVAL_CHECK_OUTPUT), keeps those outputs through the git filter
    (nbstripout's `keep_output` cell metadata) and prints in them nothing that differs between machines."""
    cells = checked(load(path))
    assert cells, f"{path.name}: no cell marked {CHECK}"
    for c in cells:
        assert c["metadata"].get("keep_output") is True, "a checked cell needs keep_output, or git strips it"
        assert c["outputs"], f"{path.name}: a checked cell without outputs compares nothing"
        for o in c["outputs"]:
            assert o["output_type"] == "stream" and o["name"] == "stdout", "printed text only: no figures, no stderr"
        text = output_text(c)
        assert re.search(r"\d", text), "a checked cell prints numbers"
        assert not MACHINE_DEPENDENT.search(text), MACHINE_DEPENDENT.search(text).group(0)


def test_nbstripout_verify():
    """The committed notebooks are what the git filter makes of them: stripped, checked outputs kept."""
    out = subprocess.run([sys.executable, "-m", "nbstripout", "--verify", *map(str, NOTEBOOKS)],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_git_filter_keeps_checked_outputs_and_strips_the_rest(tmp_path):
    """nbstripout as `git add` runs it (`python -m nbstripout`, no options): a cell with `keep_output` keeps its
    outputs (its execution count is cleared; notebooks/conftest.py gives nbval one back), any other cell loses them."""
    path = paths.NOTEBOOKS / "data.ipynb"
    nb = load(path)
    kept = checked(nb)[0]
    other = next(c for c in code_cells(nb) if not c["outputs"] and "parameters" not in c["metadata"].get("tags", []))
    kept["execution_count"] = other["execution_count"] = 7
    other["outputs"] = [{"name": "stdout", "output_type": "stream", "text": ["/tmp/x took 3.2 s\n"]}]
    executed = tmp_path / "data.ipynb"
    executed.write_text(json.dumps(nb))
    out = subprocess.run([sys.executable, "-m", "nbstripout", "-t", str(executed)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == load(path)


def test_the_sanitizers_touch_no_checked_output():
    """nbval's sanitizers (tests/nbval_sanitize.cfg) are for timings and paths; none of them may rewrite a number
    that a checked cell prints, or nbval would stop seeing it change."""
    from nbval.plugin import get_sanitize_patterns  # nbval's own reading of the file

    rules = get_sanitize_patterns(SANITIZE.read_text())
    assert len(rules) == 3
    for path in NOTEBOOKS:
        for c in checked(load(path)):
            text = output_text(c)
            for regex, replace in rules:
                assert re.sub(regex, replace, text) == text, f"{path.name}: [{regex}] rewrites a checked output"


def nbval(args: list[str], cwd: Path, runs: Path, timeout: int = 900) -> subprocess.CompletedProcess:
    """pytest --nbval-lax as `make test` runs it, in a subprocess, with its runs in `runs`."""
    env = {**os.environ, "MONOLIB_RUNS": str(runs / "runs"), "MONOLIB_FIGURES": str(runs / "figures"),
           "MPLBACKEND": "agg", "PYTHONHASHSEED": "0"}
    cmd = [sys.executable, "-m", "pytest", *args, "--nbval-lax", "--nbval-current-env", "--nbval-sanitize-with",
           str(SANITIZE), "-p", "no:cacheprovider", "-q", "--color=no", "-o", "addopts=", "--rootdir", str(cwd)]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
def test_nbval_fails_on_a_changed_number_with_a_readable_difference(tmp_path):
    """The data notebook twice, in a folder laid out as notebooks/ (with its conftest.py): as committed, and with
    one number of its checked output changed by hand. nbval passes the first and fails the second, naming both
    numbers (a fresh runs folder: the notebook renders its dataset itself)."""
    folder = tmp_path / "notebooks"
    folder.mkdir()
    shutil.copy(paths.NOTEBOOKS / "conftest.py", folder / "conftest.py")
    nb = load(paths.NOTEBOOKS / "data.ipynb")
    shutil.copy(paths.NOTEBOOKS / "data.ipynb", folder / "data.ipynb")
    cell = checked(nb)[0]
    line = next(ln for o in cell["outputs"] for ln in o["text"] if re.search(r"\d", ln))
    number = re.search(r"\d+", line).group(0)
    changed = line.replace(number, str(int(number) + 1), 1)
    for o in cell["outputs"]:
        o["text"] = [changed if ln == line else ln for ln in o["text"]]
    (folder / "data_changed.ipynb").write_text(json.dumps(nb, indent=1))

    out = nbval([str(folder)], tmp_path, tmp_path)
    log = out.stdout + out.stderr
    assert out.returncode == 1, log[-4000:]
    failures = re.findall(r"^FAILED (\S+::Cell \d+)", log, flags=re.M)
    assert failures == [f"notebooks/data_changed.ipynb::Cell {cell_number(nb, cell)}"], log[-4000:]
    assert "Cell outputs differ" in log and "Unrun reference cell" not in log, log[-4000:]
    # pytest's diff of the two texts: `+` the committed (changed) number, `-` the computed one
    assert re.search(rf"^[E\s]*\+ .*\b{int(number) + 1}\b", log, flags=re.M), log[-4000:]
    assert re.search(rf"^[E\s]*- .*\b{number}\b", log, flags=re.M), log[-4000:]


def cell_number(nb: dict, cell: dict) -> int:
    """nbval's number of a code cell (its index among the code cells)."""
    return next(i for i, c in enumerate(code_cells(nb)) if c is cell)


@pytest.mark.slow
def test_papermill_on_a_fresh_clone_from_another_directory(tmp_path):
    """The issue's command: papermill on ablation_cell.ipynb from another working directory, with a threshold and
    seed that no study lists, before any study has been run (empty MONOLIB_RUNS). The notebook builds what its
    scenario needs and nothing else: for s1 (ground-truth depth and semantics) the dataset, its graphs and the cell,
    no network. (s2-s4 add their perception networks through the same code; tests/test_perception.py and the smoke
    study train them.)"""
    runs = tmp_path / "runs"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "MONOLIB_RUNS": str(runs), "MONOLIB_FIGURES": str(tmp_path / "figures"),
           "MPLBACKEND": "agg"}
    papermill = Path(sys.executable).with_name("papermill")
    out = subprocess.run([str(papermill), str(paths.NOTEBOOKS / "ablation_cell.ipynb"), "out.ipynb", "-p", "study",
                          "smoke", "-p", "scenario", "s1", "-p", "threshold", "3.5", "-p", "seed", "11"],
                         cwd=elsewhere, env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, (out.stdout + out.stderr)[-4000:]
    cell = json.loads((runs / "smoke" / "cells" / "gcn" / "s1__t3.5__s11" / "cell.json").read_text())
    assert (cell["scenario"], cell["threshold"], cell["seed"]) == ("s1", 3.5, 11)
    executed = load(elsewhere / "out.ipynb")
    printed = output_text(checked(executed)[0])
    assert printed.startswith("paper: recall@1") and "siblings: recall@1" in printed
    s = load_study("smoke")
    assert (s.scenarios["s1"].depth, s.scenarios["s1"].semantic) == ("gt", "gt")
    trained = {p.parent.name.split("-")[0] for p in (runs / "smoke").rglob("models/*/model.pt")}
    assert trained == set(), trained
    graphs = sorted(p.name.split("-")[0] for p in (runs / "smoke").rglob("graphs/*.pt"))
    assert graphs == ["s1"]
