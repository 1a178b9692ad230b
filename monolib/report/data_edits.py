"""The tables of the data edits (`monolib.study.data_edits`): figures/data_edits/data_edits.{csv,md}.

Each run's record holds its paper-protocol hits at rank 1 by test setting; a penalty pairs a run with the 0 m run of
the same leg, edit, fold and seed (the same queries), and an edit's change pairs it further with the unedited runs.
Intervals: 95% of a bootstrap over runs and, within each, over test settings (`paired_intervals`).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from monolib.io import write_text

N_BOOT = 1000
BOOT_SEED = 0


def per_setting(record: dict) -> pd.Series:
    """A run's recall@1 (0-1) per test setting of its paper protocol."""
    return pd.Series(record["hits"], index=record["query_settings"], dtype=float).groupby(level=0).mean()


def paired_intervals(runs: list[tuple[pd.Series, ...]], combine, n_boot: int = N_BOOT,
                     seed: int = BOOT_SEED) -> tuple[float, float, float]:
    """Mean over runs of `combine(*per-setting recalls)` (points) and its 95% bootstrap interval: runs drawn with
    replacement and, within each, its test settings with replacement, the same draw for every term (paired)."""
    rng = np.random.default_rng(seed)
    values = []
    for terms in runs:
        index = terms[0].index
        for t in terms[1:]:
            if not t.index.equals(index):
                raise ValueError("paired_intervals: the runs of one comparison have other test settings")
        values.append(100.0 * np.asarray(combine(*[t.to_numpy() for t in terms]), dtype=float))
    observed = float(np.mean([v.mean() for v in values]))
    draws = np.empty(n_boot)
    pick = rng.integers(0, len(values), size=(n_boot, len(values)))
    for b in range(n_boot):
        total = 0.0
        for r in pick[b]:
            v = values[r]
            total += v[rng.integers(0, len(v), size=len(v))].mean()
        draws[b] = total / len(values)
    lo, hi = np.percentile(draws, [2.5, 97.5])
    return observed, float(lo), float(hi)


def penalty_table(frame: pd.DataFrame, es) -> pd.DataFrame:
    """One row per (leg, edit, method, threshold): recall@1 without edges, the penalty (threshold minus 0 m) and the
    edit's change of it (the edited penalty minus the unedited one), each paired on folds, seeds and queries."""
    records = {(r.leg, r.edit, r.method, float(r.threshold), r.seed, r.fold if r.fold == r.fold else None): r
               for r in frame.itertuples()}
    rows = []
    for leg, spec in es.legs.items():
        runs = [(f, s) for f in (spec.folds or [None]) for s in es.seeds]
        for edit in es.edits:
            for method in es.methods:
                for threshold in es.thresholds:
                    def terms(e, m, t):
                        return [per_setting(records[(leg, e, m, t, s, f)]._asdict()) for f, s in runs]
                    at, zero = terms(edit, method, threshold), terms(edit, "gcn", 0.0)
                    base_at, base_zero = terms("none", method, threshold), terms("none", "gcn", 0.0)
                    z = paired_intervals([(a,) for a in zero], lambda a: a)
                    pen = paired_intervals(list(zip(at, zero)), lambda a, b: a - b)
                    change = paired_intervals(list(zip(at, zero, base_at, base_zero)),
                                              lambda a, b, c, d: (a - b) - (c - d))
                    rows.append({"leg": leg, "edit": edit, "method": method, "threshold": threshold,
                                 "runs": len(runs), "recall_no_edges": z[0], "penalty": pen[0],
                                 "penalty_lo": pen[1], "penalty_hi": pen[2], "change": change[0],
                                 "change_lo": change[1], "change_hi": change[2]})
    return pd.DataFrame(rows)


def _interval(v: float, lo: float, hi: float, star: bool = True) -> str:
    mark = "*" if star and (lo > 0 or hi < 0) else ""
    return f"{v:+.1f} [{lo:+.1f}, {hi:+.1f}]{mark}".replace("-", "−")


def markdown(table: pd.DataFrame, es, stats: dict) -> str:
    """figures/data_edits/data_edits.md: the properties of each leg, then the penalty under each edit."""
    legs = list(es.legs)
    lines = [f"# What the edges cost, one property of the data changed at a time (`{Path(es.path).name}`)", "",
             "Each edit moves one property of one leg's graphs to the other leg's value (`monolib/graphs/edits.py`);"
             " the encoders are trained and evaluated on the edited graphs as a cell is (`monolib/study/"
             "data_edits.py`). Penalty: recall@1 on `paper` at the threshold minus the paper's encoder without "
             "edges (0 m) on the same edited graphs; change: the edited penalty minus the unedited one. Means over "
             "runs (seeds x folds) [95% bootstrap interval over runs and test settings, paired]; *: the interval "
             "excludes 0.", "", "| property (training graphs of the first run) | " + " | ".join(legs) + " |",
             "| --- | " + " | ".join("---:" for _ in legs) + " |"]
    for lab, name in ((35, "lamp"), (22, "ceiling"), (9, "window")):
        lines.append(f"| {name}: median brightness / the wall's | "
                     + " | ".join(f"{stats[g]['light_ratios'].get(lab, float('nan')):.2f}" for g in legs) + " |")
        lines.append(f"| {name}: share of graphs | "
                     + " | ".join(f"{stats[g]['label_shares'].get(lab, float('nan')):.2f}" for g in legs) + " |")
    lines.append("| settings' light levels: sd of log brightness | "
                 + " | ".join(f"{stats[g]['setting_light_sd']:.2f}" for g in legs) + " |")
    lines += ["", "| leg | edit | method | threshold (m) | runs | recall@1 without edges | penalty | change by the "
              "edit |", "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in table.itertuples():
        change = "" if r.edit == "none" else _interval(r.change, r.change_lo, r.change_hi)
        lines.append(f"| {r.leg} | {r.edit} | `{r.method}` | {r.threshold:g} | {r.runs} | {r.recall_no_edges:.1f} | "
                     f"{_interval(r.penalty, r.penalty_lo, r.penalty_hi)} | {change} |")
    return "\n".join(lines + [""] + reading(table, legs)) + "\n"


def _share(value: float) -> str:
    return "n/a" if math.isnan(value) else f"{value:+.0%}".replace("-", "−")


def reading(table: pd.DataFrame, legs: list[str]) -> list[str]:
    """One generated paragraph per (method, threshold): the gap between the legs' unedited penalties, and for each
    edit how far it moves each leg's penalty toward the other's, as a share of that gap (an edit of a property that
    sets the penalty closes part of the gap from both sides)."""
    a, b = legs
    out = []
    for (method, threshold), rows in table.groupby(["method", "threshold"], sort=False):
        pen = {r.leg: r for r in rows[rows.edit == "none"].itertuples()}
        gap = pen[b].penalty - pen[a].penalty
        parts = []
        for edit, er in rows[rows.edit != "none"].groupby("edit", sort=False):
            by = {r.leg: r for r in er.itertuples()}
            toward = {a: by[a].change / gap, b: -by[b].change / gap} if gap else {a: math.nan, b: math.nan}
            parts.append(f"`{edit}` moves {a}'s penalty by {_interval(by[a].change, by[a].change_lo, by[a].change_hi)}"
                         f" ({_share(toward[a])} of the gap) and {b}'s by "
                         f"{_interval(by[b].change, by[b].change_lo, by[b].change_hi)} ({_share(toward[b])})")
        out.append(f"**`{method}` at {threshold:g} m.** Unedited, {b}'s penalty minus {a}'s is {gap:+.1f} points "
                   f"({pen[b].penalty:+.1f} against {pen[a].penalty:+.1f}). ".replace("-", "−")
                   + "; ".join(parts) + ". A share is the change toward the other leg's penalty over that gap "
                   "(negative: away from it); a property that sets the penalty closes part of the gap from both sides, "
                   "each change with an interval that excludes 0.")
        out.append("")
    return out


def write(es, frame: pd.DataFrame, stats: dict, out: Path) -> Path:
    """data_edits.csv and data_edits.md into `out`, from the runs (`frame`) and each leg's statistics (as the runner
    wrote them into statistics.json)."""
    stats = {leg: {k: ({int(a): b for a, b in v.items()} if isinstance(v, dict) else v) for k, v in s.items()}
             for leg, s in stats.items()}
    table = penalty_table(frame, es)
    write_text(Path(out) / "data_edits.csv", table.to_csv(index=False, float_format="%.2f"))
    write_text(Path(out) / "data_edits.md", markdown(table, es, stats))
    return Path(out) / "data_edits.md"
