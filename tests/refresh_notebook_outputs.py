"""Refresh the outputs the committed notebooks keep for nbval: `python tests/refresh_notebook_outputs.py [NAME...]`.

The cells marked `# NBVAL_CHECK_OUTPUT` (and `"keep_output": true`) hold the outputs of their notebook run at its
defaults on a fresh clone; `make test` (nbval) runs the notebooks again and compares. When a change of the code
changes those numbers on purpose, run this: each notebook is executed as nbval executes it (kernel in
`notebooks/`, its defaults) with MONOLIB_RUNS and MONOLIB_FIGURES in a new empty temporary folder, twice, and the
outputs of its checked cells are written into the notebook only when both runs agree (every other cell stays
stripped; `nbstripout --verify` holds). Review the diff of the numbers before committing it.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"


def checked_outputs(name: str, runs: Path) -> dict[str, list]:
    """{cell id: outputs} of the kept cells of one notebook executed at its defaults with its runs in `runs`."""
    import nbformat
    from nbclient import NotebookClient

    from monolib.study.notebooks import kernel_config

    os.environ.update(MONOLIB_RUNS=str(runs / "runs"), MONOLIB_FIGURES=str(runs / "figures"), MPLBACKEND="agg",
                      PYTHONHASHSEED="0")
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    NotebookClient(nb, timeout=3600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}},
                   config=kernel_config()).execute()
    out = {}
    for cell in nb.cells:
        if cell.get("metadata", {}).get("keep_output"):
            for o in cell.outputs:
                if "execution_count" in o:  # an execute_result's count: cleared, as the git filter clears it
                    o["execution_count"] = None
            out[cell.id] = cell.outputs
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="notebooks (default: every notebook with a checked cell)")
    args = parser.parse_args(argv)
    names = args.names or sorted(p.stem for p in NOTEBOOKS.glob("*.ipynb")
                                 if '"keep_output": true' in p.read_text())
    for name in names:
        runs = []
        for attempt in range(2):
            t0 = time.perf_counter()
            with tempfile.TemporaryDirectory(prefix=f"refresh-{name}-") as tmp:
                runs.append(checked_outputs(name, Path(tmp)))
            print(f"{name}: run {attempt + 1} in {time.perf_counter() - t0:.0f} s", flush=True)
        if json.dumps(runs[0], sort_keys=True) != json.dumps(runs[1], sort_keys=True):
            print(f"{name}: the checked outputs differ between two runs from empty folders; not written",
                  file=sys.stderr)
            return 1
        import nbformat

        path = NOTEBOOKS / f"{name}.ipynb"
        nb = nbformat.read(path, as_version=nbformat.NO_CONVERT)
        for cell in nb.cells:
            if cell.get("id") in runs[0]:
                cell.outputs = runs[0][cell.id]
                cell.execution_count = None  # as the git filter (nbstripout) leaves it; see notebooks/conftest.py
        nbformat.write(nb, path)
        print(f"{name}: checked outputs written", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
