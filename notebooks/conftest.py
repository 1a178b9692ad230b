"""nbval on the notebooks: the outputs it compares survive the git filter.

The cells marked `# NBVAL_CHECK_OUTPUT` carry nbstripout's `"keep_output": true` cell metadata, so the git filter
that `make install` sets up (`nbstripout`, without `--keep-count`) keeps their outputs and strips every other cell.
It still clears their execution count, and nbval reads a cell with outputs and no count as a cell that never ran
("Unrun reference cell has outputs"). Here each such cell gets its count back before it runs, so that nbval
compares its outputs (`pytest --nbval-lax`: only the cells marked `# NBVAL_CHECK_OUTPUT` are compared).
"""


def pytest_collection_modifyitems(items):
    for item in items:
        cell = getattr(item, "cell", None)
        if cell is None or not hasattr(item, "cell_num"):  # not a notebook cell of nbval
            continue
        if cell.get("metadata", {}).get("keep_output") and cell.get("outputs") and cell.get("execution_count") is None:
            cell["execution_count"] = item.cell_num + 1
