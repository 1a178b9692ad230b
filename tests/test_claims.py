"""Claims as data (`monolib.report.claims`, ``params/claims.yaml``) and `monolib verify` (`monolib.report.verify`):
unit tests on small synthetic per-query values, and the smoke study's own files (the session's `smoke_study`
fixture of conftest.py: the study runs once per session)."""
import shutil
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import yaml

from monolib import paths
from monolib.params import load_study
from monolib.report import bootstrap, claims, verify
from monolib.retrieval import grid


pytestmark = pytest.mark.shares_runs


def synthetic_queries(hit_rates: dict, n_seeds: int = 2, n_settings: int = 4, n_queries: int = 6,
                      seed: int = 0) -> pd.DataFrame:
    """Per-query recall@1 of a few (method, scenario, threshold) groups of the paper protocol: each query a hit
    with the group's probability, drawn with `seed`."""
    rng = np.random.default_rng(seed)
    rows = []
    for (method, scenario, threshold), p in hit_rates.items():
        for s in range(n_seeds):
            for g in range(n_settings):
                for q in range(n_queries):
                    rows.append((method, scenario, float(threshold), s, "paper", f"ai_90{g}_001", f"q{q}",
                                 100.0 * float(rng.random() < p)))
    return pd.DataFrame(rows, columns=["method", "scenario", "threshold", "seed", "protocol", "setting", "query",
                                       "recall@1"])


def claims_file(tmp_path, entries: list, study: str = "toy"):
    path = tmp_path / "claims.yaml"
    path.write_text(yaml.safe_dump({study: entries}))
    return path


def claim(cid, a, b, relation, sentence="{a} against {b}", margin=None):
    out = {"id": cid, "a": a, "b": b, "relation": relation, "sentence": sentence}
    return out if margin is None else {**out, "margin": margin}


A = {"method": "good", "scenario": "s1", "threshold": 0}
B = {"method": "bad", "scenario": "s1", "threshold": 0}
A2 = {"method": "good2", "scenario": "s1", "threshold": 0}


@pytest.fixture(scope="module")
def toy():
    """Three groups: `good` finds 90 % of places, `bad` 15 %, `good2` the very same hits as `good`."""
    qv = synthetic_queries({("good", "s1", 0): 0.9, ("bad", "s1", 0): 0.15})
    twin = qv[qv["method"] == "good"].assign(method="good2")
    qv = pd.concat([qv, twin], ignore_index=True)
    boot = bootstrap.Bootstrap.for_queries(qv, 400)
    return qv, bootstrap.intervals(qv, boot), {"paper": boot}


def test_relations_read_the_difference_interval():
    assert claims.holds("above", 0.5, 3.0) and not claims.holds("above", -0.5, 3.0)
    assert claims.holds("below", -3.0, -0.1) and not claims.holds("below", -3.0, 0.1)
    assert claims.holds("level", -1.0, 2.0, 2.0) and claims.holds("level", 0.0, 0.0, 0.5)
    assert not claims.holds("level", -1.0, 2.5, 2.0) and not claims.holds("level", -3.0, 0.5, 2.0)  # an end outside
    assert claims.holds("level", 0.1, 2.0, 3.0)  # equivalent within the margin, whether or not the interval holds 0
    with pytest.raises(ValueError, match="level: needs a margin"):
        claims.holds("level", -1.0, 1.0)
    assert claims.holds("not_above", -1.0, 2.0) and claims.holds("not_above", -3.0, -1.0)
    assert not claims.holds("not_above", 0.1, 2.0)
    assert claims.holds("not_below", -1.0, 2.0) and claims.holds("not_below", 1.0, 3.0)
    assert not claims.holds("not_below", -2.0, -0.1)
    with pytest.raises(ValueError, match="relation 'beside'"):
        claims.holds("beside", 0, 1)


def test_claims_on_synthetic_rankings(toy, tmp_path):
    qv, iv, boots = toy
    path = claims_file(tmp_path, [claim("up", A, B, "above"), claim("down", B, A, "below"),
                                  claim("same", A, A2, "level", margin=1), claim("wrong", A, B, "level", margin=5)])
    table = claims.evaluate(claims.load("toy", path), qv, iv, boots).set_index("id")
    assert table.loc["up", "holds"] and table.loc["down", "holds"] and table.loc["same", "holds"]
    assert not table.loc["wrong", "holds"]
    assert table.loc["same", ["diff", "diff_lo", "diff_hi"]].tolist() == [0.0, 0.0, 0.0]  # paired: exactly 0
    good = qv[qv["method"] == "good"]["recall@1"].mean()
    bad = qv[qv["method"] == "bad"]["recall@1"].mean()
    assert table.loc["up", "a_mean"] == pytest.approx(good) and table.loc["up", "b_mean"] == pytest.approx(bad)
    assert table.loc["up", "diff"] == pytest.approx(good - bad) == -table.loc["down", "diff"]
    assert table.loc["up", "diff_lo"] > 0 and table.loc["down", "diff_hi"] < 0
    assert table["stability"].between(0, 1).all()
    assert table.loc["same", "stability"] == 1.0 and table.loc["up", "stability"] == 1.0  # no draw of seeds moves them
    md = claims.markdown(table.reset_index(), "toy")
    assert f"| up | {good:.1f} [" in md and "| wrong |" in md and "**FAILS**" in md
    assert md.count("holds |") == 3 and "| level (±1) |" in md


@pytest.mark.parametrize("entry, message", [
    ({**claim("x", A, B, "above"), "colour": "red"}, r"claims.yaml: toy\[0\].colour: unknown key"),
    (claim("x", {**A, "seed": 1}, B, "above"), r"toy\[0\] \(x\).a.seed: unknown key"),
    (claim("x", A, B, "beside"),
     r"toy\[0\] \(x\).relation: expected one of above, below, level, not_above, not_below, got 'beside'"),
    (claim("x", A, B, "above", "{a} is {c}"), r"toy\[0\] \(x\).sentence: unknown placeholder \{c\}"),
    ({**claim("x", A, B, "above"), "metric": "map@1"}, r"\(x\).metric: expected recall@K or precision@K"),
    (claim("x", A, {**B, "protocol": "siblings"}, "above"), r"\(x\): a and b on protocols 'paper' and 'siblings'"),
    ({k: v for k, v in claim("x", A, B, "above").items() if k != "relation"}, r"toy\[0\].relation: missing"),
    (claim("x", A, B, "level"), r"\(x\).margin: relation level needs the margin of equivalence in points"),
    (claim("x", A, B, "level", margin="wide"), r"\(x\).margin: relation level needs .* got 'wide'"),
    (claim("x", A, B, "above", margin=5), r"\(x\).margin: only relation level takes a margin \(relation: above\)"),
])
def test_a_malformed_claim_is_one_error_naming_the_file_and_key(tmp_path, entry, message):
    with pytest.raises(claims.ClaimsError, match=message):
        claims.load("toy", claims_file(tmp_path, [entry]))


def test_stability_is_the_share_of_seed_draws_that_keep_the_verdict(tmp_path):
    """Three seeds in which `good` is far ahead of `meh` and one in which the two are the same: the verdict `above`
    of the four holds, and in the draws of the seeds (with replacement) that hold mostly the fourth it fails."""
    strong = [synthetic_queries({("good", "s1", 0): 0.9, ("meh", "s1", 0): 0.3}, n_seeds=1, n_settings=6,
                                n_queries=10, seed=s).assign(seed=s) for s in range(3)]
    null = synthetic_queries({("good", "s1", 0): 0.5, ("meh", "s1", 0): 0.5}, n_seeds=1, n_settings=6,
                             n_queries=10, seed=3).assign(seed=3)
    null.loc[null["method"] == "meh", "recall@1"] = null.loc[null["method"] == "good", "recall@1"].to_numpy()
    qv = pd.concat([*strong, null], ignore_index=True)
    boot = bootstrap.Bootstrap.for_queries(qv, 400)
    path = claims_file(tmp_path, [claim("up", A, {**B, "method": "meh"}, "above")])
    r = claims.evaluate(claims.load("toy", path), qv, bootstrap.intervals(qv, boot), {"paper": boot}).iloc[0]
    iv = bootstrap.seed_resampled_intervals(bootstrap.rows_of(qv, "good", "s1", 0), bootstrap.rows_of(
        qv, "meh", "s1", 0), boot, ["recall@1"])
    assert iv.shape == (bootstrap.STABILITY_RESAMPLES, 2) and r["holds"]
    draws = np.random.default_rng([bootstrap.BOOT_SEED, 2]).integers(0, 4, size=(bootstrap.STABILITY_RESAMPLES, 4))
    mostly_null = (draws == 3).sum(axis=1) >= 3  # the draws in which the null seed counts three times or four
    assert mostly_null.any() and not (iv[mostly_null, 0] > 0).any()
    assert r["stability"] == pytest.approx(float(np.mean(iv[:, 0] > 0))) and r["stability"] <= 1 - mostly_null.mean()
    one_seed = claims.evaluate(claims.load("toy", path), strong[0], bootstrap.intervals(strong[0], boot),
                               {"paper": boot})
    assert np.isnan(one_seed["stability"].iloc[0])  # one seed: nothing to resample


def test_a_claim_on_cells_the_study_lacks_names_them(toy, tmp_path):
    qv, iv, boots = toy
    path = claims_file(tmp_path, [claim("ghost", {**A, "threshold": 5}, B, "above")])
    with pytest.raises(claims.ClaimsError, match=r"claims.yaml: claim ghost.a: no recall@1 of method=good, "
                                                 r"scenario=s1, threshold=5, protocol=paper"):
        claims.evaluate(claims.load("toy", path), qv, iv, boots, str(path))


def test_a_study_that_runs_part_of_the_grid_tests_the_claims_it_ran(toy, tmp_path, capsys):
    """A study file that runs part of a study's grid under its name (a subset, a test): the claims on its cells are
    evaluated, those on cells outside its grid are left out and named, and none of them is an error."""
    qv, iv, boots = toy
    path = claims_file(tmp_path, [claim("ran", A, B, "above"), claim("not-ran", {**A, "threshold": 5}, B, "above")])
    out = tmp_path / "figures"
    written = claims.write("toy", out, qv, iv, boots, path, grid={"good/s1__t0__s0", "bad/s1__t0__s0"})
    table = pd.read_csv(written["claims_csv"])
    assert list(table["id"]) == ["ran"]
    assert "not evaluated: not-ran" in capsys.readouterr().out
    assert claims.write("toy", out, qv, iv, boots, path, grid={"bad/s1__t0__s0"}) == {}


def test_every_committed_claim_names_cells_of_its_studys_grid():
    data = yaml.safe_load(claims.CLAIMS_FILE.read_text())
    assert {"quick", "smoke"} <= set(data)
    for study_name in data:
        study = load_study(study_name, check_files=False)
        cells = {(c.method, c.scenario, float(c.threshold)) for c in grid.grid(study)}
        found = claims.load(study_name)
        assert found
        for c in found:
            for cell in (c.a, c.b):
                assert (cell.method, cell.scenario, cell.threshold) in cells, (study_name, c.id, cell)
                assert cell.protocol in ("paper", "siblings")


# ---- the smoke study's files ----------------------------------------------------------------------------------

@pytest.mark.slow
def test_smoke_claims_are_written_with_the_tables_numbers(smoke_study):
    fig = paths.figures_dir("smoke")
    table = claims.read(fig / "claims.csv")
    stated = claims.load("smoke")
    assert list(table["id"]) == [c.id for c in stated]
    iv = pd.read_csv(fig / "intervals.csv")
    for c, r in zip(stated, table.itertuples(index=False)):
        row = iv[(iv.method == c.a.method) & (iv.scenario == c.a.scenario) & (iv.threshold == c.a.threshold)
                 & (iv.protocol == c.a.protocol) & (iv.metric == "recall") & (iv.k == 1)]
        assert r.a_mean == pytest.approx(float(row["mean"].iloc[0]), abs=1e-4)
        assert r.holds == claims.holds(c.relation, r.diff_lo, r.diff_hi, c.margin)
        one_seed = len(load_study("smoke").seeds) == 1  # one seed: nothing to resample
        assert np.isnan(r.stability) if one_seed else 0 <= r.stability <= 1
        assert r.diff_lo <= r.diff <= r.diff_hi
    md = (fig / "claims.md").read_text()
    assert all(f"| {c.id} |" in md for c in stated)


@pytest.mark.slow
def test_verify_against_the_runs_own_figures_passes(smoke_study, tmp_path):
    against = shutil.copytree(paths.figures_dir("smoke"), tmp_path / "committed")
    out = subprocess.run([sys.executable, "-m", "monolib.cli", "verify", "smoke", "--against", str(against)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.startswith("dataset: identical to the committed one")  # the dataset first, then the files
    assert "identical (" in out.stdout and "intervals.csv" in out.stdout.splitlines()[1]
    assert "PROBLEM" not in out.stdout and "verify: every claim holds" in out.stdout


@pytest.mark.slow
def test_verify_names_a_mean_outside_its_committed_interval(smoke_study, tmp_path):
    against = shutil.copytree(paths.figures_dir("smoke"), tmp_path / "committed")
    iv = pd.read_csv(against / "intervals.csv")
    i = iv.index[(iv.method == "gcn") & (iv.scenario == "s1") & (iv.threshold == 1) & (iv.protocol == "paper")
                 & (iv.metric == "recall") & (iv.k == 1)][0]
    fresh = float(iv.loc[i, "mean"])
    moved = fresh - 30 if fresh >= 50 else fresh + 30  # committed 30 points away, with a 10-point interval
    iv.loc[i, ["mean", "ci_lo", "ci_hi"]] = [moved, moved - 5, moved + 5]
    inside = iv.index[(iv.index != i) & (iv.ci_lo < iv["mean"]) & (iv["mean"] < iv.ci_hi - 1)][0]
    iv.loc[inside, "mean"] = float(iv.loc[inside, "mean"]) + 0.5  # moved half a point, inside its interval
    iv.to_csv(against / "intervals.csv", index=False)
    v = verify.verify("smoke", against)
    assert not v.ok and len(v.problems) == 1, v.problems
    assert v.problems[0].startswith("moved outside its committed interval: gcn s1 1 m paper recall@1: "
                                     f"{moved:.1f} -> {fresh:.1f}")
    assert "intervals.csv" in v.different and "results.csv" in v.identical
    assert any(line.startswith("moved within its interval:") for line in v.info)


@pytest.mark.slow
def test_verify_names_a_claim_whose_relation_flipped(smoke_study, tmp_path):
    against = shutil.copytree(paths.figures_dir("smoke"), tmp_path / "committed")
    data = yaml.safe_load(claims.CLAIMS_FILE.read_text())
    first = data["smoke"][0]
    first["relation"] = {"above": "below", "below": "above", "level": "above", "not_above": "above",
                          "not_below": "below"}[first["relation"]]
    path = tmp_path / "claims.yaml"
    path.write_text(yaml.safe_dump(data))
    v = verify.verify("smoke", against, claims_path=path)
    assert len(v.problems) == 1, v.problems
    assert v.problems[0].startswith(f"claim {first['id']} FAILS (flipped: it held in the committed claims.csv): "
                                    f"{first['relation']} expected")


def test_verify_outside_a_checkout_without_against_says_what_to_do(tmp_path, monkeypatch):
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    (tmp_path / "figures").mkdir()
    with pytest.raises(verify.VerifyError, match="not a git checkout.*pass --against DIR"):
        verify.committed_figures("quick", tmp_path / "out", root=tmp_path)


def test_committed_figures_are_the_files_at_head(tmp_path):
    """The quick study's figures as committed: the folder's own files at HEAD (not the other studies' subfolders),
    byte for byte what git holds."""
    if subprocess.run(["git", "rev-parse", "HEAD"], cwd=paths.ROOT, capture_output=True).returncode != 0:
        pytest.skip("not a git checkout")
    out = verify.committed_figures("quick", tmp_path / "head")
    listed = subprocess.run(["git", "ls-tree", "--name-only", "HEAD:figures"], cwd=paths.ROOT, capture_output=True,
                            text=True, check=True).stdout.split()
    files = sorted(p.name for p in out.iterdir())
    assert files and set(files) < set(listed) and "table1_recall.md" in files
    assert not any((paths.ROOT / "figures" / f).is_dir() for f in files)
    blob = subprocess.run(["git", "show", "HEAD:figures/table1_recall.md"], cwd=paths.ROOT, capture_output=True,
                          check=True).stdout
    assert (out / "table1_recall.md").read_bytes() == blob
