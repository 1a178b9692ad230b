"""Claims as data: each comparison the README's prose makes ("A above B", "A level with B") is an entry of
``params/claims.yaml``, evaluated on the study's cells with the paired bootstrap the tables use, and written to
``claims.md`` and ``claims.csv`` beside the tables (`write`, called by `monolib.report.write.write_report`).

``params/claims.yaml`` holds one list of claims per study name. A claim::

    - id: layout-level-with-histogram           # unique within the study
      a: {method: layout, scenario: s1, threshold: .inf, protocol: paper}
      b: {method: color_hist, scenario: rgb, threshold: .inf}   # protocol: paper when left out
      metric: recall@1                           # the default
      relation: level                            # above | below | level | not_above | not_below
      margin: 15                                 # level only: the interval within +/- 15 points
      sentence: "`layout` on ground truth ({a}) is level with the colour histogram ({b})."

Both cells of a claim belong to one protocol (the bootstrap pairs queries within a protocol, never across). The
difference is mean(a) - mean(b) with the paired bootstrap's 95 % interval (`bootstrap.paired_difference`, the
protocol's `bootstrap.Bootstrap`); the two means and their intervals are the tables' (``intervals.csv``).
``above`` holds when the difference's interval lies entirely above 0, ``below`` entirely below 0, ``level`` when
it lies within +/- the claim's ``margin`` (points: equivalent within what the claim states, not merely "the
interval contains 0"); ``not_above`` when it does not lie entirely above 0 (level or below), ``not_below`` when it does
not lie entirely below 0 (level or above): what a comparison whose verdict moves between level and one side from one
CPU to another (training is not bit for bit across CPUs) can state on every one. The sentence is a template
without numbers: ``{a}`` and ``{b}`` become each cell's mean with its interval, ``{diff}`` the difference with its
interval.

Each claim's stability is the share of resamples of the seeds (`bootstrap.seed_resampled_intervals`) in which its
verdict stays: a claim under `STABLE` hangs on the seeds drawn (and on the CPU, which trains each seed a little
differently), so the study states it otherwise, gives it more seeds, or drops it.
"""
from __future__ import annotations

import math
import string
from dataclasses import dataclass
from pathlib import Path
from typing import Collection, Optional

import pandas as pd
import yaml

from monolib import io, paths
from monolib.params import PAPER
from monolib.report import bootstrap, results

CLAIMS_FILE = paths.PARAMS / "claims.yaml"
RELATIONS = ("above", "below", "level", "not_above", "not_below")
CELL_KEYS = ("method", "scenario", "threshold", "protocol")
CLAIM_KEYS = ("id", "a", "b", "metric", "relation", "margin", "sentence")
STABLE = 0.9  # a claim whose verdict stays in fewer of the seeds' resamples is not stated (`stability`)
PLACEHOLDERS = ("a", "b", "diff")
COLUMNS = ["id", "relation", "metric", "protocol", "a_method", "a_scenario", "a_threshold", "a_mean", "a_lo", "a_hi",
           "b_method", "b_scenario", "b_threshold", "b_mean", "b_lo", "b_hi", "diff", "diff_lo", "diff_hi", "margin",
           "holds", "stability", "sentence"]


class ClaimsError(ValueError):
    """A claims file that cannot be read as claims, or a claim naming cells the study does not have."""


@dataclass(frozen=True)
class Cell:
    method: str
    scenario: str
    threshold: float
    protocol: str


@dataclass(frozen=True)
class Claim:
    id: str
    a: Cell
    b: Cell
    metric: str
    relation: str
    sentence: str
    margin: Optional[float] = None   # points; `level` only: the interval must lie within +/- margin


def _check_mapping(raw, where: str, keys: tuple, required: tuple) -> None:
    """One `ClaimsError` naming `where` unless `raw` is a mapping of `keys` holding every key of `required`."""
    if not isinstance(raw, dict):
        raise ClaimsError(f"{where}: expected a mapping with keys {', '.join(keys)}, got {raw!r}")
    unknown = sorted(set(raw) - set(keys))
    if unknown:
        raise ClaimsError(f"{where}.{unknown[0]}: unknown key (expected {', '.join(keys)})")
    for key in required:
        if key not in raw:
            raise ClaimsError(f"{where}.{key}: missing")


def _cell(raw, where: str) -> Cell:
    _check_mapping(raw, where, CELL_KEYS, ("method", "scenario", "threshold"))
    try:
        threshold = float(raw["threshold"])
    except (TypeError, ValueError):
        raise ClaimsError(f"{where}.threshold: expected a number in metres or .inf, got {raw['threshold']!r}") from None
    return Cell(str(raw["method"]), str(raw["scenario"]), threshold, str(raw.get("protocol", PAPER)))


def _claim(raw, where: str) -> Claim:
    _check_mapping(raw, where, CLAIM_KEYS, ("id", "a", "b", "relation", "sentence"))
    where = f"{where} ({raw['id']})"
    a, b = _cell(raw["a"], f"{where}.a"), _cell(raw["b"], f"{where}.b")
    if a.protocol != b.protocol:
        raise ClaimsError(f"{where}: a and b on protocols {a.protocol!r} and {b.protocol!r}; the bootstrap pairs "
                          f"queries within one protocol")
    if raw["relation"] not in RELATIONS:
        raise ClaimsError(f"{where}.relation: expected one of {', '.join(RELATIONS)}, got {raw['relation']!r}")
    margin = raw.get("margin")
    if raw["relation"] == "level":
        if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not 0 < margin < 100:
            raise ClaimsError(f"{where}.margin: relation level needs the margin of equivalence in points (a number "
                              f"between 0 and 100: the interval of a - b must lie within +/- margin), got {margin!r}")
        margin = float(margin)
    elif margin is not None:
        raise ClaimsError(f"{where}.margin: only relation level takes a margin (relation: {raw['relation']})")
    metric = str(raw.get("metric", "recall@1"))
    name, _, k = metric.partition("@")
    if name not in results.METRICS or not k.isdigit():
        raise ClaimsError(f"{where}.metric: expected recall@K or precision@K, got {metric!r}")
    sentence = str(raw["sentence"])
    fields = {f for _, f, _, _ in string.Formatter().parse(sentence) if f is not None}
    if fields - set(PLACEHOLDERS):
        raise ClaimsError(f"{where}.sentence: unknown placeholder {{{sorted(fields - set(PLACEHOLDERS))[0]}}} "
                          f"(expected {', '.join('{' + p + '}' for p in PLACEHOLDERS)})")
    return Claim(str(raw["id"]), a, b, metric, str(raw["relation"]), sentence, margin)


def load(study_name: str, path: Path = CLAIMS_FILE) -> list[Claim]:
    """The claims of `study_name` in `path` (an empty list when the study has none or the file does not exist)."""
    path = Path(path)
    if not path.is_file():
        return []
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ClaimsError(f"{path}: not YAML ({exc})") from None
    if not isinstance(data, dict):
        raise ClaimsError(f"{path}: expected a mapping of study names to lists of claims")
    raw = data.get(study_name) or []
    if not isinstance(raw, list):
        raise ClaimsError(f"{path}: {study_name}: expected a list of claims, got {type(raw).__name__}")
    claims = [_claim(c, f"{path}: {study_name}[{i}]") for i, c in enumerate(raw)]
    ids = [c.id for c in claims]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ClaimsError(f"{path}: {study_name}: claim id {dup[0]!r} appears twice")
    return claims


def holds(relation: str, lo: float, hi: float, margin: Optional[float] = None) -> bool:
    """Whether a difference with 95 % interval [lo, hi] satisfies `relation` (`level`: within +/- `margin`)."""
    if relation == "above":
        return lo > 0
    if relation == "below":
        return hi < 0
    if relation == "level":
        if margin is None:
            raise ValueError("relation level: needs a margin (points)")
        return -margin <= lo and hi <= margin
    if relation == "not_above":
        return lo <= 0
    if relation == "not_below":
        return hi >= 0
    raise ValueError(f"relation {relation!r}: expected one of {', '.join(RELATIONS)}")


def _mean_of(iv: pd.DataFrame, cell: Cell, metric: str, where: str) -> tuple[float, float, float]:
    name, _, k = metric.partition("@")
    iv = results.with_protocol(iv)
    r = iv[(iv["method"] == cell.method) & (iv["scenario"] == cell.scenario) & (iv["threshold"] == cell.threshold)
           & (iv["protocol"] == cell.protocol) & (iv["metric"] == name) & (iv["k"] == int(k))]
    if len(r) != 1:
        raise ClaimsError(f"{where}: no {metric} of method={cell.method}, scenario={cell.scenario}, "
                          f"threshold={cell.threshold:g}, protocol={cell.protocol} in the study's results")
    return float(r["mean"].iloc[0]), float(r["ci_lo"].iloc[0]), float(r["ci_hi"].iloc[0])


def evaluate(claims: list[Claim], qv: pd.DataFrame, iv: pd.DataFrame, boots: dict,
             source: str = str(CLAIMS_FILE)) -> pd.DataFrame:
    """One row per claim (columns `COLUMNS`): both means with the tables' intervals, the paired difference a - b
    with its interval, and whether the relation holds. `qv`: per-query values of every protocol
    (`results.query_table`); `iv`: their intervals; `boots`: each protocol's `bootstrap.Bootstrap` (a
    `bootstrap.FoldBootstrap` for a study over folds: `qv` then has a ``fold`` column)."""
    rows = []
    for c in claims:
        where = f"{source}: claim {c.id}"
        if c.a.protocol not in boots:
            raise ClaimsError(f"{where}: the study's results have no protocol {c.a.protocol!r}")
        a = _mean_of(iv, c.a, c.metric, f"{where}.a")
        b = _mean_of(iv, c.b, c.metric, f"{where}.b")
        boot = boots[c.a.protocol]  # over folds (a study cross-validated by volume alone): folds resampled too
        pair = bootstrap.fold_paired_difference if isinstance(boot, bootstrap.FoldBootstrap) \
            else bootstrap.paired_difference
        ra = bootstrap.rows_of(qv, c.a.method, c.a.scenario, c.a.threshold, c.a.protocol)
        rb = bootstrap.rows_of(qv, c.b.method, c.b.scenario, c.b.threshold, c.b.protocol)
        d = pair(ra, rb, boot, [c.metric])
        if d.empty:
            raise ClaimsError(f"{where}: cells a and b share no query of protocol {c.a.protocol}")
        diff, lo, hi = float(d["diff"].iloc[0]), float(d["ci_lo"].iloc[0]), float(d["ci_hi"].iloc[0])
        verdict = holds(c.relation, lo, hi, c.margin)
        rows.append((c.id, c.relation, c.metric, c.a.protocol, c.a.method, c.a.scenario, c.a.threshold, *a,
                     c.b.method, c.b.scenario, c.b.threshold, *b, diff, lo, hi, c.margin, verdict,
                     stability(c, ra, rb, boot, verdict), c.sentence))
    return pd.DataFrame(rows, columns=COLUMNS)


def stability(claim: Claim, a: pd.DataFrame, b: pd.DataFrame, boot, verdict: bool) -> float:
    """The share of the seeds' resamples (`bootstrap.seed_resampled_intervals`) in which the claim's verdict is
    `verdict`; NaN with one seed (nothing to resample)."""
    iv = bootstrap.seed_resampled_intervals(a, b, boot, [claim.metric])
    if not len(iv):
        return math.nan
    return float(sum(holds(claim.relation, lo, hi, claim.margin) == verdict for lo, hi in iv) / len(iv))


def _num(mean: float, lo: float, hi: float) -> str:
    return f"{mean:.1f} [{lo:.1f}, {hi:.1f}]"


def _relation(r) -> str:
    return f"level (±{r.margin:g})" if r.relation == "level" else r.relation


def _stability(r) -> str:
    if math.isnan(r.stability):
        return "one seed"
    return f"{r.stability:.2f}" + (" (**unstable**)" if r.stability < STABLE else "")


def markdown(table: pd.DataFrame, study_name: str, n_boot: int = bootstrap.N_BOOT) -> str:
    """``claims.md``: each claim's sentence with its numbers, the difference, the relation, `holds` or `FAILS`,
    and its stability."""
    lines = [f"Claims of the `{study_name}` study (`params/claims.yaml`), recall or precision in %, mean [95 % "
             f"bootstrap interval, {n_boot} resamples]; difference: the paired bootstrap of a - b on the same "
             f"seeds, settings and queries. `above` holds when its interval lies above 0, `below` below 0, `level "
             f"(±m)` when it lies within ±m points (equivalent within the margin the claim states), `not_above` when "
             f"it does not lie above 0, `not_below` when it does not lie below 0. Stability: the share of "
             f"{bootstrap.STABILITY_RESAMPLES} resamples of the seeds (with replacement) in which the verdict stays "
             f"the same; a claim under {STABLE:g} is marked unstable.",
             "", "| claim | sentence | difference a - b | relation | verdict | stability |",
             "|---|---|---|---|---|---:|"]
    for r in table.itertuples(index=False):
        sentence = r.sentence.format(a=_num(r.a_mean, r.a_lo, r.a_hi), b=_num(r.b_mean, r.b_lo, r.b_hi),
                                     diff=_num(r.diff, r.diff_lo, r.diff_hi))
        lines.append(f"| {r.id} | {sentence} | {_num(r.diff, r.diff_lo, r.diff_hi)} | {_relation(r)} | "
                     f"{'holds' if r.holds else '**FAILS**'} | {_stability(r)} |")
    return "\n".join(lines) + "\n"


def in_grid(claim: Claim, grid: Collection[str]) -> bool:
    """Whether both cells of `claim` are cells of a grid (cell names ``method/scenario__t<t>__s<seed>``)."""
    prefixes = {f"{c.method}/{paths.cell_stem(c.scenario, c.threshold)}__s" for c in (claim.a, claim.b)}
    return all(any(name.startswith(p) for name in grid) for p in prefixes)


def write(study_name: str, out: Path, qv: Optional[pd.DataFrame], iv: Optional[pd.DataFrame], boots: dict,
          path: Path = CLAIMS_FILE, n_boot: int = bootstrap.N_BOOT,
          grid: Optional[Collection[str]] = None) -> dict[str, Path]:
    """Evaluate the claims of `study_name` and write ``claims.md`` and ``claims.csv`` into `out`; ``{}`` when the
    study has no claims. With `grid` (the study's cell names), a claim on a cell outside the grid is left out and
    said so: a study file that runs a part of a study's grid under its name (a test, a subset) tests what it ran.
    Raises `ClaimsError` when it has claims but no per-query rankings to test them on."""
    claims = load(study_name, path)
    if grid is not None:
        outside = [c.id for c in claims if not in_grid(c, grid)]
        if outside:
            print(f"{study_name}: {len(outside)} claims on cells outside this grid not evaluated: "
                  f"{', '.join(outside)}")
        claims = [c for c in claims if in_grid(c, grid)]
    if not claims:
        return {}
    if qv is None or iv is None:
        raise ClaimsError(f"{path}: {study_name} has claims but the study has no per-query rankings to test them")
    table = evaluate(claims, qv, iv, boots, str(path))
    io.write_text(out / "claims.csv", table.to_csv(index=False, float_format="%.6g", lineterminator="\n"))
    io.write_text(out / "claims.md", markdown(table, study_name, n_boot))
    return {"claims_csv": out / "claims.csv", "claims_md": out / "claims.md"}


def read(path: Path) -> pd.DataFrame:
    """A written ``claims.csv`` (thresholds as floats, ``holds`` as bool)."""
    table = pd.read_csv(path)
    table["holds"] = table["holds"].astype(str).str.lower() == "true"
    for col in ("a_threshold", "b_threshold"):
        table[col] = table[col].map(lambda v: math.inf if str(v) in ("inf", "Infinity") else float(v))
    return table
