"""Data fidelity: do a study's ground-truth scene graphs look like the scene graphs of real Hypersim?

The statistics and their definitions are those of `shared/docs/real-hypersim-statistics.md` (nodes per graph,
label-set Jaccard within / across settings, wall and floor colour distinctiveness, label frequency). They are computed
the way `shared/tools/fidelity_reference.py` computes them, draw for draw, so the two agree:

- a split's graphs are grouped by setting in the order the settings first appear; only the settings with at least
  `MIN_FRAMES` frames are used, and every statistic is taken over the frames of those settings;
- Jaccard: `PAIRS` pairs drawn with Python's `random` seeded `SEED`; each draw picks a setting, two different frames
  of it (within), then another setting and one of its frames (across, against the first frame of the within pair);
  two empty label sets count 0;
- colour of a label in a frame: its node's R, G, B (the first node with that label), log of the value floored at
  `COLOUR_FLOOR`; per setting the standard deviation over its frames (ddof 0), averaged over R, G, B, then over the
  settings with at least `MIN_COLOUR_FRAMES` frames showing the label (within); the standard deviation of the
  per-setting mean log colours, averaged over R, G, B (between); ratio = between / within.

The real Hypersim numbers cannot be computed here (the published files are not available); they are transcribed
from the doc into `monolib/resources/fidelity_reference.csv`. `write(study)` puts `fidelity.csv` (long format: statistic,
source, value) and `fidelity.md` (the doc's table, the label frequencies and the acceptance targets for the
generator) into `paths.figures_dir(study.name)`. Whatever cannot be measured (no settings, a label never seen)
is NaN.
"""
from __future__ import annotations

import csv
import io
import math
import random
from pathlib import Path

import numpy as np

from monolib import paths
from monolib.data import labels, stage as dataset
from monolib.graphs import stage as scenegraphs
from monolib.io import write_text
from monolib.params import Study, StudyError

MIN_FRAMES = 10          # a setting is used when the split holds at least this many of its frames
MIN_COLOUR_FRAMES = 5    # a setting enters the colour statistics of a label with at least this many frames showing it
PAIRS = 4000             # random frame pairs for the label-set Jaccard
SEED = 0
COLOUR_FLOOR = 1e-3
COLOUR_LABELS = (("wall", 1), ("floor", 2))
TOP_LABELS = 20
REFERENCE_CSV = paths.RESOURCES / "fidelity_reference.csv"
SPLITS = ("train", "test")

NODE_STATS = ("mean", "median", "p10", "p90")
# the generator's acceptance targets (issue 9), checked on the training split
TARGET_NODES = (7.0, 10.0)
TARGET_JACCARD_WITHIN = 0.65
TARGET_JACCARD_ACROSS = 0.40
TARGET_COLOUR_RATIO = 2.0
TARGET_FREQUENT = ("wall", "floor", "otherprop", "chair", "lamp", "ceiling")
TARGET_FREQUENCY = 0.30


def frequency_name(label_name: str) -> str:
    return f"label frequency, {label_name}"


def split_statistics(graphs: list, pairs: int = PAIRS, seed: int = SEED) -> dict[str, float]:
    """The doc's statistics of one split's scene graphs (`Data` with `x` = [NYU40 id, R, G, B] and `setting`)."""
    nan = float("nan")
    frames_of: dict[str, list[int]] = {}  # setting -> indices of its frames, settings in order of appearance
    for i, g in enumerate(graphs):
        frames_of.setdefault(str(g.setting), []).append(i)
    settings = [s for s, frames in frames_of.items() if len(frames) >= MIN_FRAMES]
    used = [i for s in settings for i in frames_of[s]]
    xs = [graphs[i].x.reshape(-1, 4) for i in used]
    node_label = np.concatenate([x[:, 0].long().numpy() for x in xs] + [np.zeros(0, np.int64)])
    node_colour = np.concatenate([x[:, 1:4].float().numpy() for x in xs] + [np.zeros((0, 3), np.float32)])
    nodes = np.array([len(x) for x in xs], dtype=np.int64)
    node_frame = np.repeat(np.arange(len(used)), nodes)  # position in `used` of each node's frame
    stats: dict[str, float] = {"settings": float(len(settings)), "graphs": float(len(used))}

    # nodes per graph
    if len(nodes):
        p10, median, p90 = np.percentile(nodes, [10, 50, 90])
        stats.update({"nodes per graph, mean": float(nodes.mean()), "nodes per graph, median": float(median),
                      "nodes per graph, p10": float(p10), "nodes per graph, p90": float(p90)})
    else:
        stats.update({f"nodes per graph, {name}": nan for name in NODE_STATS})

    # label sets: one row per frame, one column per label seen (a set: repeated labels count once)
    seen = np.unique(node_label)
    label_set = np.zeros((len(used), len(seen)), dtype=bool)
    label_set[node_frame, np.searchsorted(seen, node_label)] = True

    # label frequency: share of frames whose graph holds the label
    share = label_set.mean(0) if len(used) else np.full(len(seen), nan)
    for label_id in range(1, labels.NUM_CLASSES + 1):
        k = np.searchsorted(seen, label_id)
        found = k < len(seen) and seen[k] == label_id
        stats[frequency_name(labels.name(label_id))] = float(share[k]) if found else (0.0 if len(used) else nan)

    # label-set Jaccard: the reference's draws, in the same order (rows of label_set: the frames of `used`)
    count = [len(frames_of[s]) for s in settings]
    start = np.cumsum([0] + count)[:-1].tolist()  # row of each setting's first frame
    rng = random.Random(seed)
    a_rows, b_rows, c_rows = [], [], []
    if settings:
        for _ in range(pairs):
            k = rng.choice(range(len(settings)))
            a, b = rng.sample(range(count[k]), 2)
            a_rows.append(start[k] + a)
            b_rows.append(start[k] + b)
            if len(settings) > 1:
                j = rng.choice(range(len(settings) - 1))  # = a choice among the other settings, in their order
                other = j if j < k else j + 1
                c_rows.append(start[other] + rng.choice(range(count[other])))

    def jaccard(rows_1: list[int], rows_2: list[int]) -> float:
        if not rows_1:
            return nan
        one, two = label_set[rows_1], label_set[rows_2]
        both, either = (one & two).sum(1), (one | two).sum(1)
        return float(np.mean(both / np.maximum(1, either)))

    stats["label-set Jaccard, within settings"] = jaccard(a_rows, b_rows)
    stats["label-set Jaccard, across settings"] = jaccard(a_rows[: len(c_rows)], c_rows)

    # colour distinctiveness of walls and floors
    setting_of_frame = np.repeat(np.arange(len(settings)), count)
    for name, label_id in COLOUR_LABELS:
        showing = np.flatnonzero(node_label == label_id)
        frames, first_node = np.unique(node_frame[showing], return_index=True)  # first node of the label per frame
        log_colour = np.log(np.maximum(node_colour[showing[first_node]], np.float32(COLOUR_FLOOR)))
        per_setting = [log_colour[setting_of_frame[frames] == k] for k in range(len(settings))]
        per_setting = [v for v in per_setting if len(v) >= MIN_COLOUR_FRAMES]
        within = float(np.mean([v.std(0).mean() for v in per_setting])) if per_setting else nan
        between = float(np.array([v.mean(0) for v in per_setting]).std(0).mean()) if len(per_setting) >= 2 else nan
        with np.errstate(divide="ignore", invalid="ignore"):  # float32 as in the reference, to the last bit
            ratio = float(np.float32(between) / np.float32(within))
        stats[f"{name} colour sd, within settings"] = within
        stats[f"{name} colour sd, between settings"] = between
        stats[f"{name} colour ratio"] = ratio
    return stats


def ground_truth_scenario(study: Study) -> str | None:
    """The scenario with ground-truth depth and semantics (None when the study has none)."""
    for name, sc in study.scenarios.items():
        if sc.depth == "gt" and sc.semantic == "gt":
            return name
    return None


def study_statistics(study: Study) -> dict[str, dict[str, float]]:
    """{'this study, train': stats, 'this study, test': stats} of the study's ground-truth graphs (the dataset and
    the graphs built when missing)."""
    scenario = ground_truth_scenario(study)
    if scenario is None:
        raise StudyError(f"{study.path}: no scenario with depth: gt and semantic: gt, "
                         "so no ground-truth graphs to measure")
    if not study.graphs_root and not scenegraphs.graphs_path(study, scenario).exists():
        dataset.ensure_dataset(study)  # a synthetic study renders its mini-Hypersim first (cached)
    graphs = scenegraphs.load(study, scenario)
    return {f"this study, {split}": split_statistics(graphs[split]) for split in SPLITS}


def read_reference(path: str | Path = REFERENCE_CSV) -> dict[str, dict[str, float]]:
    """{source: {statistic: value}} of the real Hypersim numbers transcribed from the doc."""
    out: dict[str, dict[str, float]] = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            out.setdefault(row["source"], {})[row["statistic"]] = float(row["value"])
    return out


def _number(value: float | None, digits: int) -> str:
    """A value with `digits` decimals; 'NaN' for what could not be measured."""
    if value is None or math.isnan(value):
        return "NaN"
    return "inf" if math.isinf(value) else f"{value:.{digits}f}"


def _count(value: float) -> str:
    """A median or percentile of node counts: whole when whole ('9'), else one decimal ('8.5')."""
    return f"{value:.0f}" if not math.isnan(value) and float(value).is_integer() else _number(value, 1)


def table_rows(stats: dict[str, float]) -> list[str]:
    """The four cells of the doc's table for one source (missing statistics: NaN)."""
    get = lambda name: stats.get(name, float("nan"))
    nodes = [_number(get("nodes per graph, mean"), 1)] + [_count(get(f"nodes per graph, {s}")) for s in NODE_STATS[1:]]
    within, across = (_number(get(f"label-set Jaccard, {kind} settings"), 2) for kind in ("within", "across"))
    cells = [" / ".join(nodes), f"{within} / {across}"]
    for name, _ in COLOUR_LABELS:
        within, between = (_number(get(f"{name} colour sd, {kind} settings"), 2) for kind in ("within", "between"))
        cells.append(f"{within} / {between} ({_number(get(f'{name} colour ratio'), 1)})")
    return cells


def frequency_line(stats: dict[str, float], top: int = TOP_LABELS) -> str:
    """'wall 0.91, floor 0.86, ...': the `top` most frequent labels (labels never seen left out)."""
    prefix = frequency_name("")
    shares = [(key[len(prefix):], v) for key, v in stats.items() if key.startswith(prefix) and v > 0]  # NaN > 0: False
    shares.sort(key=lambda item: -item[1])  # stable: ties keep the order of `stats` (NYU40, or the doc's)
    return ", ".join(f"{n} {v:.2f}" for n, v in shares[:top]) or "none"


def acceptance(train: dict[str, float]) -> list[tuple[str, bool]]:
    """The generator's acceptance targets on the training split: [(text with the measured value, passed)]."""
    nan = float("nan")
    nodes = train.get("nodes per graph, mean", nan)
    within = train.get("label-set Jaccard, within settings", nan)
    across = train.get("label-set Jaccard, across settings", nan)
    out = [(f"nodes per graph mean {TARGET_NODES[0]:g}-{TARGET_NODES[1]:g}: {_number(nodes, 1)}",
            TARGET_NODES[0] <= nodes <= TARGET_NODES[1]),
           (f"Jaccard within >= {TARGET_JACCARD_WITHIN:.2f}: {_number(within, 2)}", within >= TARGET_JACCARD_WITHIN),
           (f"Jaccard across <= {TARGET_JACCARD_ACROSS:.2f}: {_number(across, 2)}", across <= TARGET_JACCARD_ACROSS)]
    for name, _ in COLOUR_LABELS:
        ratio = train.get(f"{name} colour ratio", nan)
        out.append((f"{name} colour ratio >= {TARGET_COLOUR_RATIO:.1f}: {_number(ratio, 1)}",
                    ratio >= TARGET_COLOUR_RATIO))
    for name in TARGET_FREQUENT:
        share = train.get(frequency_name(name), nan)
        out.append((f"{name} in >= {TARGET_FREQUENCY:.0%} of graphs: {_number(share, 2)}", share >= TARGET_FREQUENCY))
    return out  # NaN compares False: not measurable = not passed


def markdown(study_name: str, sources: dict[str, dict[str, float]]) -> str:
    """fidelity.md: the doc's reference table with this study's columns, label frequencies, acceptance targets."""
    header = ["statistic"] + [f"{src} ({_number(stats.get('settings', float('nan')), 0)} settings)"
                              for src, stats in sources.items()]
    names = ["nodes per graph: mean / median / p10 / p90", "label-set Jaccard within / across settings",
             "wall colour sd within / between settings (ratio)", "floor colour sd within / between settings (ratio)"]
    columns = [table_rows(stats) for stats in sources.values()]
    lines = [f"# Data fidelity of `{study_name}`: ground-truth scene graphs against real Hypersim", "",
             f"Definitions: shared/docs/real-hypersim-statistics.md (settings with >= {MIN_FRAMES} frames; "
             f"{PAIRS} seeded pairs; colour sd in log space over settings with >= {MIN_COLOUR_FRAMES} frames showing "
             "the label). Real Hypersim: transcribed from that doc (monolib/resources/fidelity_reference.csv).", "",
             "| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for k, name in enumerate(names):
        lines.append("| " + " | ".join([name] + [col[k] for col in columns]) + " |")
    lines.append("")
    for src, stats in sources.items():
        if any(key.startswith("label frequency, ") for key in stats):
            lines += [f"Label frequency, {src} (share of graphs): {frequency_line(stats)}.", ""]
    train = sources.get("this study, train", {})
    marks = [f"{text} {'pass' if ok else 'FAIL'}" for text, ok in acceptance(train)]
    passed = sum(ok for _, ok in acceptance(train))
    lines += [f"Acceptance targets for the generator (this study, train; {passed} of {len(marks)} pass): "
              + "; ".join(marks) + ".", ""]
    return "\n".join(lines)


def long_rows(sources: dict[str, dict[str, float]]) -> list[tuple[str, str, float]]:
    return [(statistic, src, value) for src, stats in sources.items() for statistic, value in stats.items()]


def write(study: Study, measured: dict[str, dict[str, float]] | None = None) -> tuple[Path, Path] | None:
    """Write fidelity.csv and fidelity.md into the study's figures folder; None for a study without a
    ground-truth scenario. `measured` (from `study_statistics`) saves the measurement when already done."""
    if measured is None:
        if ground_truth_scenario(study) is None:
            return None
        measured = study_statistics(study)
    sources = {**measured, **read_reference()}
    out = paths.figures_dir(study.name)
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(["statistic", "source", "value"])
    writer.writerows(long_rows(sources))
    write_text(out / "fidelity.csv", text.getvalue())
    write_text(out / "fidelity.md", markdown(study.name, sources))
    return out / "fidelity.csv", out / "fidelity.md"
