"""What a person watching the runner sees: progress that stays a few plain lines in a log file (monolib.progress),
no kernel transport warnings, and a failed notebook cell reported with its cell and its executed notebook."""
import io
import json
import subprocess
import sys
import textwrap

import pytest

from monolib import progress


pytestmark = pytest.mark.shares_runs


def lines_of(**kwargs) -> tuple[progress.Lines, io.StringIO]:
    out = io.StringIO()
    return progress.Lines(file=out, **kwargs), out


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_long_loop_is_a_dozen_plain_lines_in_a_log(monkeypatch):
    clock = Clock()
    monkeypatch.setattr(progress, "_clock", clock)
    bar, out = lines_of(total=1000, desc="cells", unit="cell")
    for _ in range(1000):
        clock.now += 1.0  # one second a cell: 100 s between tenths
        bar.update(1)
    bar.set_postfix(loss="0.125")
    bar.close()
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    assert len(lines) == 11, lines  # start, every tenth from 10% to 90%, end
    assert lines[0] == "cells: 0/1000 cell"
    assert lines[1] == "cells: 100/1000 cell (10%, 100 s)"
    assert lines[-1] == "cells: 1000/1000 cell done in 1000 s (loss=0.125)"


def test_a_fast_loop_is_two_lines(monkeypatch):
    clock = Clock()
    monkeypatch.setattr(progress, "_clock", clock)
    bar, out = lines_of(total=12, desc="render settings", unit="setting")
    for _ in range(12):
        clock.now += 0.25  # 3 s in all: no tenth is EVERY_SECONDS after the line before it
        bar.update(1)
    bar.close()
    assert out.getvalue().splitlines() == ["render settings: 0/12 setting",
                                           "render settings: 12/12 setting done in 3.0 s"]


def test_iteration_short_transient_loops_and_empty_loops():
    bar, out = lines_of(iterable=range(5), desc="render settings")
    assert list(bar) == list(range(5))
    assert out.getvalue().splitlines()[-1].startswith("render settings: 5/5 it done in ")
    bar, out = lines_of(iterable=range(50), desc="deeplab epoch 1/1", leave=False)  # batches of one epoch
    assert list(bar) == list(range(50)) and out.getvalue() == ""  # the epoch's own log line says it ran
    bar, out = lines_of(total=0, desc="render settings")  # nothing to render: nothing to say
    bar.close()
    assert out.getvalue() == ""


def test_lines_unless_a_terminal_or_told_otherwise(monkeypatch, capsys):
    monkeypatch.delenv("MONOLIB_PROGRESS", raising=False)
    assert progress.mode() == "lines"  # pytest's captured stderr is no terminal, nor is a log file or a kernel
    assert isinstance(progress.tqdm(range(3)), progress.Lines)
    monkeypatch.setenv("MONOLIB_PROGRESS", "off")
    assert list(progress.tqdm(range(3), desc="quiet")) == [0, 1, 2]
    monkeypatch.setenv("MONOLIB_PROGRESS", "bar")
    from tqdm import tqdm

    assert isinstance(progress.tqdm(range(3), disable=True), tqdm)
    assert "quiet" not in capsys.readouterr().err


def test_a_failed_notebook_is_one_error_line_with_its_cell_and_executed_notebook(monkeypatch, capsys):
    from monolib import cli
    from monolib.study import runner
    from monolib.study.notebooks import NotebookFailed

    def fail(*args, **kwargs):
        raise NotebookFailed("ablation_cell.ipynb: In [3] (x = 1 / 0) raised ZeroDivisionError: division by zero"
                                   "\n  executed notebook: /somewhere/cell.ipynb")

    monkeypatch.setattr(runner, "run", fail)
    assert cli.main(["study", "smoke"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ablation_cell.ipynb: In [3] (x = 1 / 0) raised ZeroDivisionError")
    assert "Traceback" not in err and "executed notebook: /somewhere/cell.ipynb" in err


@pytest.mark.slow
def test_execute_names_the_failed_cell_and_its_notebook_without_transport_warnings(tmp_path):
    """A real kernel through `monolib.study.notebooks.execute`: the cell that raised, its error and the executed
    notebook (written by papermill, traceback included) in the message; no "running over TCP without encryption"."""
    nb = {"cells": [
        {"cell_type": "code", "execution_count": None, "id": "0", "metadata": {"tags": ["parameters"]}, "outputs": [],
         "source": ["n = 1"]},
        {"cell_type": "code", "execution_count": None, "id": "1", "metadata": {}, "outputs": [],
         "source": ["# a comment first\n", "total = n + 1\n", "raise ValueError(f'boom {total}')"]}],
        "metadata": {"kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"}},
        "nbformat": 4, "nbformat_minor": 5}
    (tmp_path / "fails.ipynb").write_text(json.dumps(nb))
    script = textwrap.dedent(f"""
        from pathlib import Path
        from monolib.study.notebooks import NotebookFailed, execute
        try:
            execute(Path({str(tmp_path / 'fails.ipynb')!r}), Path({str(tmp_path / 'out' / 'fails.ipynb')!r}),
                    {{"n": 41}}, timeout=120)
        except NotebookFailed as exc:
            print("FAILED:", exc)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "without encryption" not in out.stdout + out.stderr, out.stderr
    message = out.stdout.split("FAILED: ", 1)[1]
    assert message.startswith("fails.ipynb: In [3] (total = n + 1) raised ValueError: boom 42"), message
    assert message.rstrip().endswith(f"executed notebook: {tmp_path / 'out' / 'fails.ipynb'}")
    assert "\x1b" not in message
    executed = json.loads((tmp_path / "out" / "fails.ipynb").read_text())
    assert any(o.get("ename") == "ValueError" for c in executed["cells"] for o in c.get("outputs", []))
