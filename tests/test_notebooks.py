"""The notebooks follow the house rules: one `parameters` cell of literals, no definitions, no stored outputs,
kernel python3. (nbval executes them separately: `pytest --nbval-lax notebooks/`.)"""
import ast
import json
import subprocess
import sys

import pytest

from monolib import paths

NOTEBOOKS = sorted(paths.NOTEBOOKS.glob("*.ipynb"))


def test_the_expected_notebooks_exist():
    names = {p.stem for p in NOTEBOOKS}
    assert {"ablation_cell", "report", "data", "segmentation", "depth"} <= names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_rules(path):
    nb = json.loads(path.read_text())
    assert nb["metadata"]["kernelspec"]["name"] == "python3"
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    params = [c for c in code if "parameters" in c.get("metadata", {}).get("tags", [])]
    assert len(params) == 1, "exactly one cell tagged parameters"
    for node in ast.parse("".join(params[0]["source"])).body:
        assert isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant), "parameters are literals only"
    for c in code:
        tree = ast.parse("".join(line for line in c["source"] if not line.lstrip().startswith(("%", "!"))))
        assert not any(isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) for n in ast.walk(tree))
        assert c.get("outputs", []) == [] and c.get("execution_count") is None, "committed without outputs"


def test_nbstripout_verify():
    out = subprocess.run([sys.executable, "-m", "nbstripout", "--verify", *map(str, NOTEBOOKS)], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
