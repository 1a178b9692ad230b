"""The report stage on hand-built cells: metrics recomputed from rankings, protocol checks, tables, figures."""
from __future__ import annotations

import ast
import hashlib
import json
import math

import numpy as np
import pandas as pd
import pytest

import matplotlib

matplotlib.use("agg")

from monolib import paths, report  # noqa: E402

A, B, C = "ai_001_001", "ai_001_002", "ai_002_001"


def key(setting: str, i: int, cam: str = "cam_00") -> str:
    return f"{setting}/{cam}/{i:04d}"


# ---- a hand-built cell: 2 settings, 4 queries, known ranks ---------------------------------------------------------
# A: queries A0, A1; positive A9.   B: queries B0, B1; positives B8, B9.
# hits per query (own setting in ranks 1..3):
#   A0: A9 B5 B6 -> 1 0 0      A1: B5 A9 B7 -> 0 1 0
#   B0: A5 A6 A7 -> 0 0 0      B1: B9 B8 A5 -> 1 1 0
# recall@1 = 2/4, recall@2 = recall@3 = 3/4
# precision@2 = mean(1/2, 1/2, 0, 2/2) = 50 %, precision@3 = mean(1/3, 1/3, 0, 2/3) = 100/3 %
# with positives {A: 1, B: 2}: precision@2 = mean(1, 1, 0, 1) = 75 %, precision@3 = 75 %
HAND = {
    key(A, 0): [key(A, 9), key(B, 5), key(B, 6)],
    key(A, 1): [key(B, 5), key(A, 9), key(B, 7)],
    key(B, 0): [key(A, 5), key(A, 6), key(A, 7)],
    key(B, 1): [key(B, 9), key(B, 8), key(A, 5)],
}


def rankings_of(table: dict[str, list[str]]) -> pd.DataFrame:
    rows = [(q, q.split("/")[0], r, m, m.split("/")[0], 0.1 * r) for q, ms in table.items() for r, m in enumerate(ms, 1)]
    return pd.DataFrame(rows, columns=report.RANKING_COLUMNS)


def hand_protocol() -> pd.DataFrame:
    rows = [(key(A, 0), A, "query"), (key(A, 1), A, "query"), (key(A, 9), A, "positive"),
            (key(B, 0), B, "query"), (key(B, 1), B, "query"), (key(B, 8), B, "positive"), (key(B, 9), B, "positive")]
    return pd.DataFrame(rows, columns=report.PROTOCOL_COLUMNS)


def test_recompute_metrics_by_hand():
    m = report.recompute_metrics(rankings_of(HAND), [1, 2, 3], [2, 3])
    assert m == pytest.approx({"recall@1": 50.0, "recall@2": 75.0, "recall@3": 75.0,
                               "precision@2": 50.0, "precision@3": 100.0 / 3})
    capped = report.recompute_metrics(rankings_of(HAND), [1], [2, 3], positives_per_setting={A: 1, B: 2})
    assert capped["precision@2"] == pytest.approx(75.0)
    assert capped["precision@3"] == pytest.approx(75.0)
    same = report.recompute_metrics(rankings_of(HAND), [], [3], positives_per_setting=6)
    assert same["precision@3"] == pytest.approx(100.0 / 3)


def test_recompute_metrics_row_order_and_depth():
    r = rankings_of(HAND).sample(frac=1.0, random_state=3)        # order of rows does not matter
    assert report.recompute_metrics(r, [1], [2])["recall@1"] == pytest.approx(50.0)
    with pytest.raises(ValueError, match="top"):
        report.recompute_metrics(r, [1, 5], [2])


def test_check_protocol_accepts_the_hand_cell():
    counts = report.check_protocol(rankings_of(HAND), hand_protocol(), positives=2)
    assert counts == {"queries": 4, "settings": 2, "positives": 3}


def test_check_protocol_rejects_a_query_of_its_own_setting():
    bad = dict(HAND)
    bad[key(A, 0)] = [key(A, 1), key(B, 5), key(B, 6)]         # A0 retrieves A1, another query of A
    with pytest.raises(report.ProtocolError, match="another query of its own setting"):
        report.check_protocol(rankings_of(bad), hand_protocol())


def test_check_protocol_rejects_self_and_outsiders_and_too_many_positives():
    self_hit = dict(HAND)
    self_hit[key(B, 0)] = [key(B, 0), key(A, 6), key(A, 7)]
    with pytest.raises(report.ProtocolError, match="itself"):
        report.check_protocol(rankings_of(self_hit), hand_protocol())
    outsider = dict(HAND)
    outsider[key(B, 0)] = [key(B, 4), key(A, 6), key(A, 7)]    # a frame of B that is neither query nor positive
    with pytest.raises(report.ProtocolError, match="outside the positives"):
        report.check_protocol(rankings_of(outsider), hand_protocol())
    with pytest.raises(report.ProtocolError, match="more than 1 positives"):
        report.check_protocol(rankings_of(HAND), hand_protocol(), positives=1)


# ---- a fake study on disk ------------------------------------------------------------------------------------------

RECALL = {1: 60.0, 5: 80.0, 10: 90.0}
PRECISION = {2: 50.0, 4: 40.0, 6: 30.0}
LABELS = {"s1": "GT depth, GT semantics", "s2": "GT depth, DeepLabV3 semantics"}


def value(method, scenario, threshold, seed, metric, k) -> float:
    base = (RECALL if metric == "recall" else PRECISION)[k]
    if method == "color_hist":
        return base - 20.0 + seed
    bonus = {1.0: 5.0, 2.0: 1.0, 5.0: 0.0, 10.0: 0.5, math.inf: 2.0}[threshold] + (3.0 if scenario == "s1" else 0.0)
    return base + bonus + 2.0 * seed      # seeds 0 and 1: mean = base + bonus + 1, std = sqrt(2)


def write_cell(study, method, scenario, threshold, seed, queries_right: set[str]):
    d = paths.cell_dir(study, method, scenario, threshold, seed)
    d.mkdir(parents=True)
    metrics = {f"{m}@{k}": value(method, scenario, threshold, seed, m, k)
               for m, ks in (("recall", RECALL), ("precision", PRECISION)) for k in ks}
    cell = {"method": method, "scenario": scenario, "threshold": "inf" if math.isinf(threshold) else threshold,
            "seed": seed, "study": study, "scenario_label": LABELS.get(scenario, "RGB only"), "depth": "gt",
            "semantic": "gt", "timings": {"train": 1.0}, "metrics": metrics,
            "protocol": {"settings": 3, "frames": 4, "queries": 2, "positives": 2}}
    (d / "cell.json").write_text(json.dumps(cell))
    rows = []
    for s in (A, B, C):
        for i in (0, 1):
            q = key(s, i)
            other = [x for x in (A, B, C) if x != s][0]
            top1 = key(s, 9) if q in queries_right else key(other, 3)
            rows.append((q, s, 1, top1, top1.split("/")[0], 0.5))
            rows.append((q, s, 2, key(other, 2), other, 0.7))
    pd.DataFrame(rows, columns=report.RANKING_COLUMNS).to_csv(d / "rankings.csv", index=False)


@pytest.fixture
def study(tmp_path, monkeypatch):
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    name = "fake"
    for sc in ("s1", "s2"):
        for t in (1.0, 5.0, math.inf):
            for seed in (0, 1):
                right = {key(A, 0), key(B, 1)} | ({key(C, 0)} if sc == "s1" else set())
                write_cell(name, "gcn", sc, t, seed, right)
    for seed in (0, 1):
        write_cell(name, "color_hist", "rgb", math.inf, seed, set())
    return name


def test_paths_follow_the_monkeypatched_roots(study, tmp_path):
    assert paths.study_dir(study) == tmp_path / "runs" / study
    assert paths.figures_dir("quick") == tmp_path / "figures"


def test_collect_one_row_per_number(study):
    r = report.collect(study)
    assert list(r.columns) == report.RESULT_COLUMNS
    assert len(r) == (2 * 3 * 2 + 2) * 6
    assert not r.duplicated(["method", "scenario", "threshold", "seed", "metric", "k"]).any()
    assert r["threshold"].dtype == float and np.isinf(r["threshold"]).any()
    assert list(r["method"].unique()) == ["gcn", "color_hist"]
    one = r[(r.method == "gcn") & (r.scenario == "s1") & (r.threshold == 1.0) & (r.seed == 1)
            & (r.metric == "recall") & (r.k == 5)]
    assert one["value"].tolist() == [80.0 + 5 + 3 + 2]
    pd.testing.assert_frame_equal(r, report.collect(study))      # deterministic


def test_collect_without_cells_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    with pytest.raises(FileNotFoundError, match="no cell.json"):
        report.collect("nothing")


def test_summary_mean_std_n(study):
    s = report.summary(report.collect(study))
    row = s[(s.method == "gcn") & (s.scenario == "s2") & (s.threshold == math.inf) & (s.metric == "precision")
            & (s.k == 4)].iloc[0]
    vals = [40.0 + 2 + 0, 40.0 + 2 + 2]
    assert row["mean"] == pytest.approx(np.mean(vals))
    assert row["std"] == pytest.approx(np.std(vals, ddof=1))
    assert row["n"] == 2


def test_paper_tables_transcription():
    p = report.paper_tables()
    assert len(p) == 4 * 5 * 6
    get = lambda sc, t, m, k: p[(p.scenario == sc) & (p.threshold == t) & (p.metric == m) & (p.k == k)]["value"].item()
    assert get("s1", 1.0, "recall", 1) == 94.3
    assert get("s4", math.inf, "recall", 10) == 91.0
    assert get("s1", math.inf, "precision", 2) == 90.7
    assert get("s3", 5.0, "precision", 6) == 59.2


def test_tables_bold_best_and_paper_numbers(study, tmp_path):
    results = report.collect(study)
    written = report.write_tables(results, tmp_path / "out", LABELS)
    assert set(written) == {f"table{i}_{e}" for i in (1, 2) for e in ("md", "csv", "tex")}
    md = written["table1_md"].read_text()
    # s1 recall@1: threshold 1 is best: 60 + 5 + 3 + 1 = 69.0 ± 1.4, bold; paper 94.3 beside it
    line = next(l for l in md.splitlines() if l.startswith("| gcn | s1: GT depth, GT semantics | 1 |"))
    assert f"**69.0 ± {math.sqrt(2):.1f}**" in line and "94.3" in line
    line_inf = next(l for l in md.splitlines() if "| ∞ |" in l and "gcn" not in l.split("|")[1] + "x")
    assert "**" not in line_inf.split("|")[4]
    assert "color_hist | RGB only" in md and "n = 2 seeds" in md
    tex = written["table1_tex"].read_text()
    assert r"\textbf{69.0 $\pm$ 1.4}" in tex and r"color\_hist" in tex and r"$\infty$" in tex
    csv = pd.read_csv(written["table1_csv"])
    assert list(csv.columns) == ["method", "scenario", "threshold", "k", "mean", "std", "n", "paper"]
    row = csv[(csv.method == "gcn") & (csv.scenario == "s1") & (csv.threshold == 1.0) & (csv.k == 1)].iloc[0]
    assert row["mean"] == pytest.approx(69.0) and row["std"] == pytest.approx(math.sqrt(2), abs=1e-4)
    assert row["n"] == 2 and row["paper"] == 94.3
    assert csv[csv.method == "color_hist"]["paper"].isna().all()
    assert csv["method"].iloc[-1] == "color_hist"
    assert (tmp_path / "out" / "table2_precision.md").read_text().count("**") > 0


def test_single_seed_shows_mean_only(study):
    r = report.collect(study)
    md = report.table_markdown(r[r.seed == 0], "recall", LABELS)
    assert "±" not in md.split("\n", 2)[2] and "one seed" in md


def fake_rgb(frame_key: str) -> np.ndarray:
    h = int(hashlib.sha256(frame_key.encode()).hexdigest()[:6], 16)
    img = np.zeros((24, 32, 3), dtype=np.uint8)
    img[:] = [(h >> 16) & 255, (h >> 8) & 255, h & 255]
    return img


def test_write_report_and_deterministic_bytes(study):
    written = report.write_report(study, fake_rgb, LABELS)
    out = paths.figures_dir(study)
    assert written["results"] == out / "results.csv"
    for name in ("results", "table1_md", "table2_tex", "recall_vs_threshold", "fig5_matches"):
        assert written[name].is_file() and written[name].parent == out
    assert written["fig5_matches"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    before = {k: p.read_bytes() for k, p in written.items()}
    again = report.write_report(study, fake_rgb, LABELS)
    assert {k: p.read_bytes() for k, p in again.items()} == before
    assert len(pd.read_csv(written["results"])) == len(report.collect(study))


def test_fig_matches_picks_hard_easy_hard(study):
    cells = report.match_cells(study)
    assert {sc: c[:2] for sc, c in cells.items()} == {"s1": (1.0, 0), "s2": (1.0, 0)}
    top1 = {sc: pd.read_csv(c[2] / "rankings.csv").query("rank == 1") for sc, c in cells.items()}
    chosen = report.pick_queries(top1, 3)
    # right in both scenarios: A0, B1; right in s1 only: C0; never right: A1, B0, C1.
    # easy: A0 (first key among the best); hard ones from other settings: B0, C1; shown hard, easy, hard
    assert chosen == [key(B, 0), key(A, 0), key(C, 1)]


def test_recall_figure_resaves_identically(study, tmp_path):
    r = report.collect(study)
    p = report.fig_recall_vs_threshold(r, tmp_path / "a.png", scenario_labels=LABELS)
    first = p.read_bytes()
    report.fig_recall_vs_threshold(r, tmp_path / "a.png", scenario_labels=LABELS)
    assert p.read_bytes() == first


def test_report_notebook_is_thin_and_clean():
    import nbformat

    nb = nbformat.read(paths.NOTEBOOKS / "report.ipynb", as_version=4)
    assert nb.metadata["kernelspec"]["name"] == "python3"
    code = [c for c in nb.cells if c.cell_type == "code"]
    tagged = [c for c in code if "parameters" in c.metadata.get("tags", [])]
    assert len(tagged) == 1 and tagged[0] is code[0]
    assert tagged[0].source.strip() == 'study = "smoke"'
    for c in code:
        assert c.execution_count is None and c.outputs == []
        tree = ast.parse(c.source)
        assert not [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))]
    assert any(c.source.startswith("# NBVAL_IGNORE_OUTPUT") and "table1" in c.source for c in code)
