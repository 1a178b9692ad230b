"""Record this machine's smoke numbers in `tests/smoke_expected.yaml`: `python tests/refresh_smoke_expected.py`.

`monolib study smoke` first (or `make smoke`). The file holds, per CPU (`monolib.device.cpu_signature`), the means
that `tests/test_study.py::test_smoke_numbers_within_their_cross_machine_bands` holds to bands: from 12.5 points
below the lowest machine's number to 12.5 above the highest (0.05 for a perception metric). This machine's entry is
replaced and every other machine's kept, so the bands span every CPU the smoke study has run on. When a change of
the code changes the numbers on purpose, run it with ``--only-this-machine`` (the other machines' numbers are then
stale, and dropped) and review the diff before committing it.
"""
from __future__ import annotations

import math
import sys

import pandas as pd
import yaml

from monolib import paths
from monolib.device import cpu_signature
from monolib.io import write_text

EXPECTED = paths.ROOT / "tests" / "smoke_expected.yaml"
TABLE_ROWS = {  # (table, scenario, threshold, k) that carry the smoke study's shape: no edges, 2 m, all edges
    "table1_recall": [("s1", 0, 1), ("s1", 0, 10), ("s1", 2, 1), ("s1", 2, 10), ("s1", math.inf, 1),
                      ("s1", math.inf, 10), ("s2", 2, 1), ("s2", 2, 10), ("s3", 2, 1), ("s3", 2, 10), ("s4", 2, 1),
                      ("s4", 2, 10)],
    "table2_precision": [("s1", 0, 2), ("s1", 2, 2), ("s1", math.inf, 2), ("s2", 2, 2), ("s3", 2, 2), ("s4", 2, 2)],
}
PERCEPTION_ROWS = [("deeplab", "pixel_accuracy"), ("depth_a", "abs_rel"), ("depth_a", "delta1"),
                   ("depth_b", "abs_rel"), ("depth_b", "delta1")]
HEADER = ("# The smoke study's numbers on each CPU it has run on, written by tests/refresh_smoke_expected.py from\n"
          "# `monolib study smoke`; tests/test_study.py holds a rerun to bands around them (12.5 points below the\n"
          "# lowest machine's number and above the highest, 0.05 of a perception metric).\n")


def measured(figures=None) -> dict:
    """The smoke figures' values at TABLE_ROWS and PERCEPTION_ROWS."""
    fig = figures or paths.figures_dir("smoke")
    out = {"tables": [], "perception": []}
    for name, rows in TABLE_ROWS.items():
        t = pd.read_csv(fig / f"{name}.csv")
        for scenario, threshold, k in rows:
            row = t[(t.method == "gcn") & (t.scenario == scenario) & (t.threshold == threshold) & (t.k == k)]
            if len(row) != 1:
                raise SystemExit(f"{fig / name}.csv: expected one gcn row {scenario} {threshold} {k}, got {len(row)}")
            out["tables"].append({"table": name, "scenario": scenario, "threshold": str(threshold), "k": k,
                                  "mean": round(float(row["mean"].iloc[0]), 1)})
    p = pd.read_csv(fig / "perception.csv")
    for model, metric in PERCEPTION_ROWS:
        value = p[(p.model == model) & (p.metric == metric)]["value"]
        if len(value) != 1:
            raise SystemExit(f"{fig / 'perception.csv'}: expected one row {model} {metric}, got {len(value)}")
        out["perception"].append({"model": model, "metric": metric, "value": round(float(value.iloc[0]), 3)})
    return out


def recorded(machines: list[dict], only_this_machine: bool = False, figures=None) -> list[dict]:
    """`machines` with this machine's entry (`cpu_signature`, `measured`) in place of its old one."""
    cpu = cpu_signature()
    kept = [] if only_this_machine else [m for m in machines if m["cpu"] != cpu]
    return kept + [{"cpu": cpu, **measured(figures)}]


if __name__ == "__main__":
    old = yaml.safe_load(EXPECTED.read_text())["machines"] if EXPECTED.is_file() else []
    machines = recorded(old, "--only-this-machine" in sys.argv[1:])
    write_text(EXPECTED, HEADER + yaml.safe_dump({"machines": machines}, sort_keys=False))
    print(f"wrote {EXPECTED}: {len(machines)} machine(s)")
