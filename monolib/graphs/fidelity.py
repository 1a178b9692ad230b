"""Data fidelity: do a study's ground-truth scene graphs look like the scene graphs of real Hypersim?

The statistics are those measured on real Hypersim's published scene graphs (nodes per graph, label-set Jaccard
within / across settings, wall and floor colour distinctiveness, label frequency; the real values in
`monolib/resources/fidelity_reference.csv`). They are computed the way the reference script that measured the real
values computes them, draw for draw, so the two agree:

- a split's graphs are grouped by setting in the order the settings first appear; only the settings with at least
  `MIN_FRAMES` frames are used, and every statistic is taken over the frames of those settings;
- Jaccard: `PAIRS` pairs drawn with Python's `random` seeded `SEED`; each draw picks a setting, two different frames
  of it (within), then another setting and one of its frames (across, against the first frame of the within pair);
  two empty label sets count 0;
- colour of a label in a frame: its node's R, G, B (the first node with that label), log of the value floored at
  `COLOUR_FLOOR`; per setting the standard deviation over its frames (ddof 0), averaged over R, G, B, then over the
  settings with at least `MIN_COLOUR_FRAMES` frames showing the label (within); the standard deviation of the
  per-setting mean log colours, averaged over R, G, B (between); ratio = between / within.

Geometry and light, like with like:

- the frames: every `DEPTH_EVERY`-th frame of the split (`light_sample`; the training split with its validation
  settings: the dataset's training split in its split file's order), the frames that the reference measurement of
  real Hypersim read, so that the two agree;
- pixel depth: the Euclidean `depth_meters` of every valid pixel (finite, > 0) of those frames, read from the
  files: p10, p25, median, p75, p90 and the share beyond `FAR` m, beside Hypersim's own image statistics;
- node pairs in the original code's camera (`monolib.graphs.build`, projection ``monograph``): every pair i < j of
  every ground-truth graph built from the pixels in that camera, whatever the study's own projection (the graph
  stage builds them, cached, under the scenario name ``<gt>_monograph`` when the study's own camera is ``exact``):
  p10, median, mean and p90 of the lengths, the share of pairs closer than 1, 2, 5 and 10 m, pairs per graph and
  edges per graph at each of those thresholds (a pair counted once), beside the published real graphs'; the same
  figures in the study's own projection when it is not ``monograph``;
- wall and floor colour from the HDR `color.hdf5` (linear radiance): each node's median (the pixels of the label with
  valid depth, as the node), then the colour statistics above over every setting of those frames (``HDR``), beside
  the same of the graphs' node colours of the same frames (``node``: in the study's `graphs.colour`, the HDR medians
  themselves or the tonemapped uint8 colours, which divide out each frame's brightness and scale log colour by
  1/2.2) and beside real Hypersim's (whose published node colours are HDR medians).

The real Hypersim numbers of the whole release are transcribed from the doc into
`monolib/resources/fidelity_reference.csv` (its files are not all available); those of the published graphs'
development set are measured here by the same code (`write_reference`, `monolib fidelity --reference DIR`), the
source `DEVELOPMENT` of the same table. `write(study)` puts `fidelity.csv` (long format:
statistic, source, value) and `fidelity.md` (the doc's table, the label frequencies and the acceptance targets for the
generator) into `paths.figures_dir(study.name)`. Whatever cannot be measured (no settings, a label never seen)
is NaN.
"""
from __future__ import annotations

import copy
import csv
import io
import math
import random
from pathlib import Path

import numpy as np

from monolib import paths
from monolib.data import dataset, labels
from monolib.graphs import edits, published, scenegraphs
from monolib.io import DataFileError, read_h5, write_text
from monolib.params import Study, StudyError

MIN_FRAMES = 10          # a setting is used when the split holds at least this many of its frames
MIN_COLOUR_FRAMES = 5    # a setting enters the colour statistics of a label with at least this many frames showing it
PAIRS = 4000             # random frame pairs for the label-set Jaccard
SEED = 0
COLOUR_FLOOR = 1e-3
COLOUR_LABELS = (("wall", 1), ("floor", 2))
LIGHT_LABELS = (("lamp", 35), ("ceiling", 22), ("window", 9))  # brightness against the wall's (`light_statistics`)
SETTING_LIGHT = "settings' light levels, sd of log brightness"
DEVELOPMENT = "real Hypersim, development set"  # the published graphs' development volumes (`reference_statistics`)
TOP_LABELS = 20
REFERENCE_CSV = paths.RESOURCES / "fidelity_reference.csv"
SPLITS = ("train", "test")

NODE_STATS = ("mean", "median", "p10", "p90")
# the generator's acceptance targets of scene graphs, checked on the training split
TARGET_NODES = (7.0, 10.0)
TARGET_JACCARD_WITHIN = 0.65
TARGET_JACCARD_ACROSS = 0.40
TARGET_COLOUR_RATIO = 2.0
TARGET_FREQUENT = ("wall", "floor", "otherprop", "chair", "lamp", "ceiling")
TARGET_FREQUENCY = 0.30

DEPTH_EVERY = 2          # pixel depth: every 2nd frame of the split (as the reference measurement)
MAX_DEPTH_FRAMES = 1000  # ... or fewer frames, evenly spaced, on a large split (a real download)
MAX_DEPTH_PIXELS = 256 * 192  # a larger frame gives every k-th valid pixel, about this many (quick: all of them)
DEPTH_QUANTILES = (("p10", 10), ("p25", 25), ("median", 50), ("p75", 75), ("p90", 90))
FAR = 20.0               # metres: the share of pixels beyond (views through windows and openings)
PAIR_THRESHOLDS = (1.0, 2.0, 5.0, 10.0)
PAIR_STATS = (("p10", 10), ("median", 50), ("p90", 90))
MONOGRAPH = "monograph"
# the generator's acceptance targets of real depth and light, checked on the training split: (low, high)
TARGET_RANGES = {
    "pixel depth, median": (4.0, 5.6), "pixel depth, p90": (10.0, math.inf),
    f"pixel depth, share beyond {FAR:g} m": (0.02, 0.10),
    "pair length (monograph), median": (3.6, 5.0),
    "pairs closer than 1 m (monograph)": (0.02, 0.07), "pairs closer than 2 m (monograph)": (0.09, 0.20),
    "pairs closer than 5 m (monograph)": (0.48, 0.72), "pairs closer than 10 m (monograph)": (0.86, 0.97),
    "wall HDR colour sd, within settings": (0.30, math.inf), "wall HDR colour ratio": (2.0, 4.0),
    "floor HDR colour sd, within settings": (0.30, math.inf), "floor HDR colour ratio": (2.0, 4.0),
    # how much brighter or darker one place is than another, every object of it alike: real places differ about
    # twice as much as the mini-Hypersim's (figures/data_edits/ measures what that does to the edge penalty); the
    # development set's value in fidelity_reference.csv, the range a quarter either side of it
    SETTING_LIGHT: (0.85, 1.4),
}


def frequency_name(label_name: str) -> str:
    return f"label frequency, {label_name}"


def split_statistics(graphs: list, pairs: int = PAIRS, seed: int = SEED) -> dict[str, float]:
    """The doc's statistics of one split's scene graphs (`Data` with `x` = [NYU40 id, R, G, B] and `setting`)."""
    nan = float("nan")
    frames_of, settings, used = used_frames([g.setting for g in graphs])
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
    stats.update(colour_statistics(node_label, node_colour, node_frame, np.repeat(np.arange(len(settings)), count)))
    stats.update(light_statistics([graphs[i] for i in used]))
    return stats


def light_statistics(graphs: list) -> dict[str, float]:
    """How light differs between places and between kinds of object, from the graphs' node colours: the spread (sd
    over settings) of the settings' light levels once each label's own level is taken out (`edits.light_effects`: an
    additive fit of every node's log brightness), and the median brightness of lamps, ceilings and windows against
    the walls' (`edits.light_ratios`)."""
    nan = float("nan")
    setting, _ = edits.light_effects(graphs)
    ratios = edits.light_ratios(graphs)
    stats = {SETTING_LIGHT: float(np.std(list(setting.values()))) if len(setting) >= 2 else nan}
    for name, label_id in LIGHT_LABELS:
        stats[f"{name} brightness / the wall's"] = ratios.get(label_id, nan)
    return stats


def used_frames(frame_settings: list) -> tuple[dict[str, list[int]], list[str], list[int]]:
    """``(frames of each setting, the settings used, the frames used)``: the frames (indices) of each setting in the
    order the settings first appear, the settings with at least `MIN_FRAMES` frames, and their frames in that order."""
    frames_of: dict[str, list[int]] = {}
    for i, setting in enumerate(frame_settings):
        frames_of.setdefault(str(setting), []).append(i)
    settings = [s for s, frames in frames_of.items() if len(frames) >= MIN_FRAMES]
    return frames_of, settings, [i for s in settings for i in frames_of[s]]


def colour_statistics(node_label: np.ndarray, node_colour: np.ndarray, node_frame: np.ndarray,
                      setting_of_frame: np.ndarray, kind: str = "") -> dict[str, float]:
    """Wall and floor colour distinctiveness (``<label> <kind>colour sd, within / between settings``, ``ratio``) of
    nodes (label, R, G, B) of frames (`node_frame`: index of the node's frame, `setting_of_frame`: that frame's
    setting, 0..S-1); the first node of a label in a frame is its colour."""
    nan = float("nan")
    stats: dict[str, float] = {}
    n_settings = int(setting_of_frame.max()) + 1 if len(setting_of_frame) else 0
    for name, label_id in COLOUR_LABELS:
        showing = np.flatnonzero(node_label == label_id)
        frames, first_node = np.unique(node_frame[showing], return_index=True)  # first node of the label per frame
        log_colour = np.log(np.maximum(node_colour[showing[first_node]], np.float32(COLOUR_FLOOR)))
        per_setting = [log_colour[setting_of_frame[frames] == k] for k in range(n_settings)]
        per_setting = [v for v in per_setting if len(v) >= MIN_COLOUR_FRAMES]
        within = float(np.mean([v.std(0).mean() for v in per_setting])) if per_setting else nan
        between = float(np.array([v.mean(0) for v in per_setting]).std(0).mean()) if len(per_setting) >= 2 else nan
        with np.errstate(divide="ignore", invalid="ignore"):  # float32 as in the reference, to the last bit
            ratio = float(np.float32(between) / np.float32(within))
        stats[f"{name} {kind}colour sd, within settings"] = within
        stats[f"{name} {kind}colour sd, between settings"] = between
        stats[f"{name} {kind}colour ratio"] = ratio
    return stats


def pair_statistics(graphs: list, projection: str) -> dict[str, float]:
    """Node pair lengths of graphs holding every pair (`pair_len`, as the graph stage and the published files do),
    over every graph given (`light_sample`): ``pair length (<projection>), p10 / median / mean / p90``,
    ``pairs closer than <t> m``, ``pairs per graph`` and ``edges per graph at <t> m`` (a pair counted once)."""
    lengths = np.concatenate([g.pair_len.double().numpy() for g in graphs] + [np.zeros(0)])
    n = len(graphs)
    tag = f"({projection})"
    nan = float("nan")
    stats = {f"pairs per graph {tag}": len(lengths) / n if n else nan}
    for name, q in PAIR_STATS:
        stats[f"pair length {tag}, {name}"] = float(np.percentile(lengths, q)) if len(lengths) else nan
    stats[f"pair length {tag}, mean"] = float(lengths.mean()) if len(lengths) else nan
    for t in PAIR_THRESHOLDS:
        closer = int(np.count_nonzero(lengths < t))  # an edge: a pair closer than the threshold (build.pair_mask)
        stats[f"pairs closer than {t:g} m {tag}"] = closer / len(lengths) if len(lengths) else nan
        stats[f"edges per graph at {t:g} m {tag}"] = closer / n if n else nan
    return stats


def light_sample(graphs: list) -> list:
    """The frames of a split that the geometry and light statistics read: every `DEPTH_EVERY`-th (or fewer, evenly
    spaced, so that at most `MAX_DEPTH_FRAMES`), in order. For the training split pass its training and validation
    settings together (`graphs["train"] + graphs["val"]`, the dataset's training split in the order of its split
    file): the frames the reference measurement of real Hypersim read."""
    return graphs[:: max(DEPTH_EVERY, -(-len(graphs) // MAX_DEPTH_FRAMES))]


def frame_colour_statistics(nodes: list[np.ndarray], frame_settings: list, kind: str) -> dict[str, float]:
    """`colour_statistics` of each frame's nodes (`nodes[i]`: (n, 4) [label, R, G, B] of frame i, whose setting is
    `frame_settings[i]`), every setting, in the order the settings first appear."""
    order = {s: k for k, s in enumerate(dict.fromkeys(str(s) for s in frame_settings))}
    flat = np.concatenate(list(nodes) + [np.zeros((0, 4))])
    return colour_statistics(flat[:, 0].astype(np.int64), flat[:, 1:4],
                             np.repeat(np.arange(len(nodes)), [len(n) for n in nodes]),
                             np.array([order[str(s)] for s in frame_settings], np.int64), kind)


def node_colour_statistics(graphs: list, kind: str) -> dict[str, float]:
    """`frame_colour_statistics` of the graphs' own node colours (x = [label, R, G, B])."""
    return frame_colour_statistics([g.x.reshape(-1, 4).double().numpy() for g in graphs],
                                   [g.setting for g in graphs], kind)


def depth_statistics(depths: np.ndarray) -> dict[str, float]:
    """``pixel depth, p10 / p25 / median / p75 / p90`` (metres) and ``share beyond FAR m`` of Euclidean depths."""
    depths = np.asarray(depths, np.float64)
    nan = float("nan")
    stats = {f"pixel depth, {name}": float(np.percentile(depths, q)) if len(depths) else nan
             for name, q in DEPTH_QUANTILES}
    stats[f"pixel depth, share beyond {FAR:g} m"] = float((depths > FAR).mean()) if len(depths) else nan
    stats["pixel depth, pixels"] = float(len(depths))
    return stats


def ground_truth_scenario(study: Study) -> str | None:
    """The scenario with ground-truth depth and semantics (None when the study has none)."""
    for name, sc in study.scenarios.items():
        if sc.depth == "gt" and sc.semantic == "gt":
            return name
    return None


def projected_graphs(study: Study, scenario: str, projection: str) -> dict[str, list]:
    """The graphs of `scenario` built from the pixels in `projection` (`monolib.graphs.build`): the scenario's own
    cache when that is its camera, else the graph stage's build of the same sources in that camera, cached as
    ``graphs/<scenario>_<projection>-<key>.pt``."""
    if study.graphs_root or study.projection(scenario) == projection:
        return scenegraphs.load(study, scenario)
    other, name = copy.deepcopy(study), f"{scenario}_{projection}"
    sc = copy.deepcopy(study.scenarios[scenario])
    sc.projection = projection
    other.scenarios = {name: sc}
    return scenegraphs.load(other, name)


def _frame_pixels(args) -> tuple:
    """Worker: ``(Euclidean depth of the valid pixels, HDR nodes (n, 4) [label, R, G, B] of the colour
    labels, error or None)`` of one frame; a node is the per-channel median of `color.hdf5` over the label's pixels
    with valid depth (finite, > 0), as a graph node; a missing or unreadable file gives no pixels and its error."""
    study, key = args
    try:
        f = scenegraphs.frame_of(study, key)
        depth, semantic = f.depth_meters, f.semantic
        if semantic is None:
            raise DataFileError(f"{f.files['semantic']}: file not found")
        colour = read_h5(f.files["color"])
        if colour.shape[:2] != depth.shape or semantic.shape != depth.shape:
            raise DataFileError(f"{f.files['color']}: colour {colour.shape}, depth {depth.shape} and semantic "
                                f"{semantic.shape} differ in size")
    except (DataFileError, FileNotFoundError) as exc:
        return None, np.zeros((0, 4)), str(exc)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
    values = depth[valid]
    values = values[:: max(1, -(-len(values) // MAX_DEPTH_PIXELS))]  # every k-th of a large frame's pixels
    nodes = []
    for _, label_id in COLOUR_LABELS:
        mask = valid & (semantic == label_id)
        if mask.any():
            nodes.append([label_id, *np.median(colour[mask].astype(np.float64), axis=0)])
    return values, np.array(nodes, np.float64).reshape(-1, 4), None


def frame_statistics(study: Study, graphs: list, progress: bool = False) -> dict[str, float]:
    """Pixel depth (`depth_statistics`) and HDR wall and floor colour (`colour_statistics` of ``HDR `` nodes, every
    setting) of the frames of `graphs` (`light_sample`), read from the dataset's files (`depth_meters`,
    `semantic`, `color.hdf5`)."""
    jobs = [(study, str(g.frame)) for g in graphs]
    read = scenegraphs.map_frames(_frame_pixels, jobs, study.dataset.workers, "fidelity: depth and HDR colour",
                                  progress)
    depths = [values for values, _, _ in read if values is not None]
    stats = depth_statistics(np.concatenate(depths) if depths else np.zeros(0))
    stats["pixel depth, frames"] = float(len(depths))
    stats["frames unreadable"] = float(sum(error is not None for _, _, error in read))
    stats.update(frame_colour_statistics([nodes for _, nodes, _ in read], [g.setting for g in graphs], "HDR "))
    return stats


def study_statistics(study: Study) -> dict[str, dict[str, float]]:
    """{'this study, train': stats, 'this study, test': stats} of the study's ground-truth graphs (the dataset and
    the graphs built when missing): the graph statistics (`split_statistics`), the node pairs in the original code's
    camera and, when it differs, in the study's own (`pair_statistics`), and the pixel depth and HDR colour read from
    the files (`frame_statistics`; not for published graphs, which come without their frames)."""
    scenario = ground_truth_scenario(study)
    if scenario is None:
        raise StudyError(f"{study.path}: no scenario with depth: gt and semantic: gt, "
                         "so no ground-truth graphs to measure")
    if not study.graphs_root:
        dataset.ensure_dataset(study)  # a synthetic study renders its mini-Hypersim first (cached)
    own = study.projection(scenario)
    graphs = scenegraphs.load(study, scenario)
    monograph = graphs if own == MONOGRAPH else projected_graphs(study, scenario, MONOGRAPH)
    whole = lambda g, split: g["train"] + g["val"] if split == "train" else g[split]  # noqa: E731
    out = {}
    for split in SPLITS:
        stats = split_statistics(graphs[split])
        sample = light_sample(whole(graphs, split))
        stats.update(pair_statistics(light_sample(whole(monograph, split)), MONOGRAPH))
        if own != MONOGRAPH:
            stats.update(pair_statistics(sample, own))
        stats.update(node_colour_statistics(sample, "node "))
        if not study.graphs_root:
            stats.update(frame_statistics(study, sample))
        stats["geometry and light, frames"] = float(len(sample))
        out[f"this study, {split}"] = stats
    return out


def reference_statistics(folder: str | Path) -> dict[str, float]:
    """The scene-graph and light statistics (`split_statistics`) and node pairs (`pair_statistics`) of the published
    real graphs in `folder` (the development set: its ``train/`` of ai_VVV_NNN_XX_graphs.pt files), measured here
    as on a study's graphs."""
    folder = Path(folder)
    graphs = published.read_folder(folder / "train" if (folder / "train").is_dir() else folder)
    stats = split_statistics(graphs)
    stats.update(pair_statistics(light_sample(graphs), MONOGRAPH))
    return stats


def write_reference(folder: str | Path, path: str | Path = REFERENCE_CSV) -> dict[str, float]:
    """Measure `reference_statistics` of `folder` and put them into the reference table as the source
    `DEVELOPMENT` (its earlier rows replaced; every other source's rows kept as they are)."""
    stats = reference_statistics(folder)
    path = Path(path)
    lines = path.read_text().splitlines(keepends=True)
    kept = [line for line in lines[1:] if next(csv.reader([line]))[1] != DEVELOPMENT]  # other sources: as written
    citation = (f"measured by `monolib fidelity --reference` on the published graphs' development set "
                f"({int(stats['settings'])} settings of volumes ai_001-ai_019 of the release's train/)")
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows([k, DEVELOPMENT, f"{v:.6g}", citation] for k, v in stats.items())
    write_text(path, "".join(lines[:1] + kept) + text.getvalue())
    return stats


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


def _cells(stats: dict[str, float], names: list[str], digits: int) -> str:
    """'a / b / c' of the statistics `names` ('NaN' where not measured)."""
    return " / ".join(_number(stats.get(name, float("nan")), digits) for name in names)


def _colour_cell(stats: dict[str, float], label: str, kind: str = "") -> str:
    """'within / between (ratio)' of a label's colour statistics of `kind` ('' graph node colours, 'HDR ')."""
    within, between = (_number(stats.get(f"{label} {kind}colour sd, {k} settings", float("nan")), 2)
                       for k in ("within", "between"))
    return f"{within} / {between} ({_number(stats.get(f'{label} {kind}colour ratio', float('nan')), 1)})"


def table_rows(stats: dict[str, float]) -> list[str]:
    """The two cells of the scene-graph table for one source (missing statistics: NaN)."""

    def get(name):
        return stats.get(name, float("nan"))

    nodes = [_number(get("nodes per graph, mean"), 1)] + [_count(get(f"nodes per graph, {s}")) for s in NODE_STATS[1:]]
    within, across = (_number(get(f"label-set Jaccard, {kind} settings"), 2) for kind in ("within", "across"))
    return [" / ".join(nodes), f"{within} / {across}"]


def geometry_rows(projections: list[str]) -> list[tuple[str, callable]]:
    """(row name, cell of a source's statistics) of the geometry table: pixel depth, then the node pairs in each
    camera of `projections`."""
    rows = [("pixel depth p10 / p25 / median / p75 / p90 (m), Euclidean",
             lambda st: _cells(st, [f"pixel depth, {n}" for n, _ in DEPTH_QUANTILES], 2)),
            (f"share of pixels beyond {FAR:g} m", lambda st: _cells(st, [f"pixel depth, share beyond {FAR:g} m"], 3))]
    for camera in projections:
        tag = f"({camera})"
        rows += [(f"node pairs per graph, {camera} camera", lambda st, t=tag: _cells(st, [f"pairs per graph {t}"], 1)),
                 (f"pair length p10 / median / mean / p90 (m), {camera} camera",
                  lambda st, t=tag: _cells(st, [f"pair length {t}, {n}" for n in ("p10", "median", "mean", "p90")], 2)),
                 (f"share of pairs closer than {' / '.join(f'{x:g}' for x in PAIR_THRESHOLDS)} m, {camera} camera",
                  lambda st, t=tag: _cells(st, [f"pairs closer than {x:g} m {t}" for x in PAIR_THRESHOLDS], 3)),
                 (f"edges per graph at {' / '.join(f'{x:g}' for x in PAIR_THRESHOLDS)} m, {camera} camera",
                  lambda st, t=tag: _cells(st, [f"edges per graph at {x:g} m {t}" for x in PAIR_THRESHOLDS], 2))]
    return rows


def frequency_line(stats: dict[str, float], top: int = TOP_LABELS) -> str:
    """'wall 0.91, floor 0.86, ...': the `top` most frequent labels (labels never seen left out)."""
    prefix = frequency_name("")
    shares = [(key[len(prefix):], v) for key, v in stats.items() if key.startswith(prefix) and v > 0]  # NaN > 0: False
    shares.sort(key=lambda item: -item[1])  # stable: ties keep the order of `stats` (NYU40, or the doc's)
    return ", ".join(f"{n} {v:.2f}" for n, v in shares[:top]) or "none"


def acceptance(train: dict[str, float]) -> list[tuple[str, bool]]:
    """The generator's acceptance targets on the training split: [(text with the measured value, passed)]: the
    scene-graph targets, then those of real depth and light (`TARGET_RANGES`)."""
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
        out.append((f"{name} colour ratio (graph node colours) >= {TARGET_COLOUR_RATIO:.1f}: {_number(ratio, 1)}",
                    ratio >= TARGET_COLOUR_RATIO))
    for name in TARGET_FREQUENT:
        share = train.get(frequency_name(name), nan)
        out.append((f"{name} in >= {TARGET_FREQUENCY:.0%} of graphs: {_number(share, 2)}", share >= TARGET_FREQUENCY))
    for name, (low, high) in TARGET_RANGES.items():
        value = train.get(name, nan)
        want = f">= {low:g}" if math.isinf(high) else f"in [{low:g}, {high:g}]"
        out.append((f"{name} {want}: {_number(value, 3 if abs(high) <= 1 else 2)}", low <= value <= high))
    return out  # NaN compares False: not measurable = not passed


COLOUR_SPACES = {  # what the graphs' node colours are, by `graphs.colour`, in the words of fidelity.md
    "hdr": ("medians of the HDR color.hdf5, like real Hypersim's: the same space, so the rows compare like with like"),
    "tonemapped": ("medians of Hypersim's tonemap of each frame, which divides out the frame's brightness and scales "
                   "log colour by 1/2.2: not comparable with real Hypersim's HDR medians; the light table's HDR rows "
                   "are the like-with-like comparison"),
}


def markdown(study_name: str, sources: dict[str, dict[str, float]], colour: str = "hdr") -> str:
    """fidelity.md: the scene-graph table, the geometry table (pixel depth, node pairs in the original code's camera
    and in the study's own when the statistics hold another), the light table (HDR against the graphs' node
    colours), label frequencies and the acceptance targets, each source beside real Hypersim. `colour`: the space of
    the ground-truth graphs' node colours (`graphs.colour`), named beside every colour row."""
    header = ["statistic"] + [f"{src} ({_number(stats.get('settings', float('nan')), 0)} settings)"
                              for src, stats in sources.items()]

    def table(rows: list[tuple[str, callable]]) -> list[str]:
        lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
        return lines + ["| " + " | ".join([name] + [cell(stats) for stats in sources.values()]) + " |"
                        for name, cell in rows]

    graph_rows = [("nodes per graph: mean / median / p10 / p90", lambda st: table_rows(st)[0]),
                  ("label-set Jaccard within / across settings", lambda st: table_rows(st)[1])]
    graph_rows += [(f"{label} colour sd within / between settings (ratio), node colours ({colour})",
                    lambda st, lab=label: _colour_cell(st, lab)) for label, _ in COLOUR_LABELS]
    others = sorted({key[len("pairs per graph ("):-1] for stats in sources.values() for key in stats
                     if key.startswith("pairs per graph (")} - {MONOGRAPH})
    projections, projection = [MONOGRAPH] + others, (others[0] if others else MONOGRAPH)
    light_rows = [(f"{label} colour sd within / between settings (ratio), {what}",
                   lambda st, lab=label, k=kind: _colour_cell(st, lab, k))
                  for label, _ in COLOUR_LABELS
                  for what, kind in (("HDR color.hdf5 medians", "HDR "), (f"the graphs' node colours ({colour})",
                                                                            "node "))]
    frames = {src: _number(st.get("geometry and light, frames", float("nan")), 0) for src, st in sources.items()
              if src.startswith("this study")}
    lines = [f"# Data fidelity of `{study_name}`: ground-truth scene graphs against real Hypersim", "",
             f"Definitions: `monolib/graphs/fidelity.py` (settings with >= {MIN_FRAMES} frames; "
             f"{PAIRS} seeded pairs; colour sd in log space over settings with >= {MIN_COLOUR_FRAMES} frames showing "
             "the label). Real Hypersim: measured on its published scene graphs and depth images "
             "(monolib/resources/fidelity_reference.csv), computed here the same way, on the ground-truth graphs "
             f"of each split. Node colours: the graphs' own, {COLOUR_SPACES[colour]}.", ""]
    lines += table(graph_rows) + [""]
    lines += [f"**Geometry.** On every {DEPTH_EVERY}nd frame of each split (the training split with its validation "
              f"settings: the frames the reference measurement read; "
              + ", ".join(f"{src}: {n} frames" for src, n in frames.items()) + "). Pixel depth: the Euclidean "
              "depth_meters of every valid pixel, read from the files (real Hypersim: its depth histograms over all "
              "public images, not per split). Node pairs: every pair i < j of every ground-truth graph in the "
              "original Monograph code's camera (`monograph`: f 577.35 / 433.01 px at 1024x768 scaled to the frame, "
              "Euclidean depth as z, nodes built from the pixels as the original did), the camera of the published "
              "real graphs' lengths and of the paper's thresholds"
              + (f"; and in this study's own camera (`{projection}`)" if projection != MONOGRAPH else "")
              + ". An edge at a threshold: a pair closer than it, counted once.", ""]
    lines += table(geometry_rows(projections)) + [""]
    lines += ["**Light.** On the same frames: wall and floor colour distinctiveness from each node's median of the "
              "HDR color.hdf5 (linear radiance, as the published graphs hold it), beside the same statistics of the "
              f"graphs' node colours of those frames (`{colour}`: {COLOUR_SPACES[colour]}). Real Hypersim's node "
              "colours are HDR medians: its rows are one measurement.", ""]
    lines += table(light_rows) + [""]
    lines += ["Light between places and between kinds of object, from the graphs' node colours (all frames of the "
              "settings used): the spread of the settings' light levels (sd over settings of each setting's level, "
              "once each label's own level is taken out of every node's log brightness) and the median brightness "
              "of lamps, ceilings and windows against the walls'. What each does to the cost of the edges: "
              "figures/data_edits/data_edits.md (`make data-edits`).", ""]
    lines += table([(SETTING_LIGHT, lambda st: _cells(st, [SETTING_LIGHT], 2)),
                    (" / ".join(n for n, _ in LIGHT_LABELS) + " median brightness / the wall's",
                     lambda st: _cells(st, [f"{n} brightness / the wall's" for n, _ in LIGHT_LABELS], 2))]) + [""]
    for src, stats in sources.items():
        if any(key.startswith("label frequency, ") for key in stats):
            lines += [f"Label frequency, {src} (share of graphs): {frequency_line(stats)}.", ""]
    train = sources.get("this study, train", {})
    marks = acceptance(train)
    passed = sum(ok for _, ok in marks)
    lines += [f"Acceptance targets for the generator (this study, train; {passed} of {len(marks)} pass): "
              + "; ".join(f"{text} {'pass' if ok else 'FAIL'}" for text, ok in marks) + ".", ""]
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
    write_text(out / "fidelity.md", markdown(study.name, sources, study.colour(ground_truth_scenario(study))))
    return out / "fidelity.csv", out / "fidelity.md"
