"""The one training of every encoder trained with the triplet loss: the graph encoders (`monolib.retrieval.gcn`),
the from-scratch CNN (`monolib.retrieval.baselines`) and the fine-tuned ImageNet head
(`monolib.retrieval.pretrained`).

How an encoder is trained is a `TrainingRule` (a spec's `monolib.params.TRAINING_KEYS`, `training_rule`): Adam at
the rule's learning rate along its schedule (`epoch_lr`), epochs of batches, and after each epoch the validation,
the history row and the model kept (`EarlyStopping`, under the rule's `select`, `patience` and `min_epochs`).
`train` is that loop; what differs between encoders is what they read and how a batch is drawn, which each passes
as a batch function: ``epoch_batches(rng, gen)``, called once per epoch with the run's seeded numpy generator and
torch generator, gives that epoch's `Batch`es (the paper's triplets: `draw_triplets`, then `triplet_batches`).
Triplets (paper): every training item is an anchor once per epoch; its positive is a random other item of the same
setting, its negative a random item of another setting; drawn afresh each epoch from the seed.
"""
from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, Optional

import numpy as np
import torch
from torch import nn

from monolib.device import device, seed_everything
from monolib.params import TRAINING_KEYS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainingRule:
    """How an encoder is trained (not what it is): the keys `TRAINING_KEYS` of a `GCNSpec`, which the study file
    sets under ``gcn:``, a variant's ``gcn:`` or a learned image encoder's ``image_training``."""
    epochs: int          # at most
    lr: float            # Adam's, at epoch 1
    schedule: str        # `monolib.params.SCHEDULES`
    select: str          # `monolib.params.SELECT`
    patience: int
    min_epochs: int
    batch_size: int
    weight_decay: float
    margin: float        # of the triplet loss


def training_rule(spec) -> TrainingRule:
    """The `TrainingRule` of an encoder spec (a `GCNSpec`, such as `Study.gcn_spec(method)`): its training keys."""
    return TrainingRule(**{key: getattr(spec, key) for key in TRAINING_KEYS})


def epoch_lr(rule: TrainingRule, epoch: int) -> float:
    """The learning rate of `epoch` (1-based) under `rule.schedule`: `rule.lr` throughout (``constant``), or from
    `rule.lr` at epoch 1 down a half cosine towards 0 after the last of `rule.epochs` (``cosine``)."""
    if rule.schedule == "cosine":
        return rule.lr * 0.5 * (1.0 + np.cos(np.pi * (epoch - 1) / rule.epochs))
    return rule.lr


def set_epoch_lr(opt: torch.optim.Optimizer, rule: TrainingRule, epoch: int) -> None:
    """Every parameter group of `opt` at `epoch_lr(rule, epoch)`."""
    for group in opt.param_groups:
        group["lr"] = epoch_lr(rule, epoch)


def triplet_loss(margin: float) -> nn.Module:
    """The paper's loss: the triplet margin loss on Euclidean distances, averaged over the triplets."""
    return nn.TripletMarginLoss(margin=margin, p=2)


def draw_triplets(settings: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(anchor, positive, negative) index arrays: every item is an anchor once, vectorised over anchors.

    A setting with a single item uses the anchor itself as its positive.
    """
    settings = np.asarray(settings)
    n = len(settings)
    order = np.argsort(settings, kind="stable")
    _, group_of_sorted, sizes = np.unique(settings[order], return_inverse=True, return_counts=True)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    pos_in_group = np.arange(n) - starts[group_of_sorted]
    size = sizes[group_of_sorted]
    # positive: another member of the group (offset 1..size-1), or itself for a singleton
    offset = np.where(size > 1, rng.integers(1, np.maximum(size, 2)), 0)
    positive_sorted = starts[group_of_sorted] + (pos_in_group + offset) % size
    # negative: a rank among the n - size items of other settings, shifted past the anchor's own group
    if (n - size <= 0).any():
        raise ValueError("triplets need items of at least two settings")
    r = rng.integers(0, n - size)
    negative_sorted = np.where(r >= starts[group_of_sorted], r + size, r)
    anchor = order
    return anchor, order[positive_sorted], order[negative_sorted]


@dataclass(frozen=True)
class Batch:
    """One optimiser step: what the model reads (`input`, moved to the model's device by `train`), the loss of
    the model's output on it (`loss(z)`, a mean over the batch), and how many samples that mean is over (`size`:
    the weight of the batch in the epoch's training loss)."""
    input: Any
    loss: Callable[[torch.Tensor], torch.Tensor]
    size: int


def triplet_batches(anchor: np.ndarray, positive: np.ndarray, negative: np.ndarray, *, batch_size: int,
                    rng: np.random.Generator, margin: float, input_of: Callable[[np.ndarray], Any]) -> Iterator[Batch]:
    """The triplets in a random order (one permutation from `rng`, drawn now), `batch_size` at a time: each batch
    the model's input for its anchors, then positives, then negatives (`input_of(indices)`, called as the batch is
    reached), and the triplet loss (`triplet_loss`) of the three thirds of the output."""
    perm = rng.permutation(len(anchor))
    loss_fn = triplet_loss(margin)

    def loss_of(b: int) -> Callable[[torch.Tensor], torch.Tensor]:
        return lambda z: loss_fn(z[:b], z[b : 2 * b], z[2 * b :])

    def batches() -> Iterator[Batch]:
        for s in range(0, len(perm), batch_size):
            idx = perm[s : s + batch_size]
            yield Batch(input_of(np.concatenate([anchor[idx], positive[idx], negative[idx]])), loss_of(len(idx)),
                        len(idx))

    return batches()


def leave_one_out_recall(emb: torch.Tensor, settings: np.ndarray) -> float:
    """Share of items whose nearest other item is of the same setting (validation metric)."""
    d = torch.cdist(emb, emb)
    d.fill_diagonal_(float("inf"))
    nn_idx = d.argmin(dim=1).cpu().numpy()
    return float((np.asarray(settings)[nn_idx] == np.asarray(settings)).mean())


def leave_one_out_map(emb: torch.Tensor, settings: np.ndarray) -> float:
    """Mean average precision of leave-one-out retrieval: each item queries all others, its own setting's items are
    the relevant ones (items alone in their setting are left out). Unlike recall@1 it moves with every rank, so it
    does not saturate once each item's nearest neighbour is right."""
    codes = torch.as_tensor(np.unique(np.asarray(settings), return_inverse=True)[1].reshape(-1), device=emb.device)
    d = torch.cdist(emb, emb)
    d.fill_diagonal_(float("inf"))
    order = d.argsort(dim=1, stable=True)[:, :-1]  # every other item, nearest first (the item itself last)
    hits = (codes[order] == codes[:, None]).to(emb.dtype)
    relevant = hits.sum(dim=1)
    ranks = torch.arange(1, hits.shape[1] + 1, device=emb.device, dtype=emb.dtype)
    ap = (hits * hits.cumsum(dim=1) / ranks).sum(dim=1) / relevant.clamp_min(1)
    keep = relevant > 0
    return float(ap[keep].mean()) if bool(keep.any()) else float("nan")


class EarlyStopping:
    """Validation after each epoch (leave-one-out recall@1 and mean average precision on the validation settings,
    triplet loss on fixed validation triplets drawn with ``seed + 1``), the history, the model kept, and the stop.

    Which epoch's model is kept is `select` (`monolib.params.SELECT`): the best validation recall@1 (ties: the lower
    validation loss), the best mean average precision (ties likewise), the lowest validation loss, or ``last`` (a
    fixed schedule: every epoch replaces the one before, and training runs all its epochs). Epochs before
    `min_epochs` are recorded but neither kept nor counted; training stops after `patience` counted epochs without
    a better score."""

    def __init__(self, *, patience: int, seed: int, model: nn.Module, select: str = "val_recall",
                 min_epochs: int = 1):
        self.patience, self.seed, self.select, self.min_epochs = patience, seed, select, min_epochs
        self.best: Optional[tuple] = None
        self.best_state, self.best_epoch, self.bad_epochs = copy.deepcopy(model.state_dict()), 0, 0
        self.history: list[dict] = []

    def score(self, row: dict) -> tuple:
        """The score of an epoch's record under `select` (higher is better; NaN recall or precision counts 0)."""
        zero = lambda v: 0.0 if np.isnan(v) else v  # noqa: E731
        if self.select == "last":
            return (row["epoch"],)
        if self.select == "val_loss":
            return (-row["val_loss"],)
        return (zero(row["val_map" if self.select == "val_map" else "val_recall@1"]), -row["val_loss"])

    def step(self, model: nn.Module, *, epoch: int, train_loss: float, val_emb: Optional[torch.Tensor],
             val_settings, loss_fn, progress: bool = False, extra: Optional[dict] = None) -> bool:
        """Record the epoch (with `extra` columns); True when training should stop. Without validation embeddings
        (or with a single validation setting) the validation loss is the training loss."""
        val_settings = np.asarray(val_settings)
        if val_emb is not None and len(set(val_settings)) > 1:
            val_recall, val_map = leave_one_out_recall(val_emb, val_settings), leave_one_out_map(val_emb, val_settings)
            va, vp, vn = draw_triplets(val_settings, np.random.default_rng(self.seed + 1))
            val_loss = float(loss_fn(val_emb[va], val_emb[vp], val_emb[vn]))
        else:
            val_recall, val_map, val_loss = float("nan"), float("nan"), train_loss
        row = {"epoch": epoch, "train_loss": train_loss, "val_loss": val_loss, "val_recall@1": val_recall,
               "val_map": val_map, **(extra or {})}
        if progress:
            log.info("epoch %d loss %.4f val loss %.4f val recall@1 %.3f val map %.3f", epoch, train_loss, val_loss,
                     val_recall, val_map)
        return self.advance(row, model)

    def advance(self, row: dict, model: nn.Module) -> bool:
        """Record an epoch's row (``epoch``, ``val_loss``, ``val_recall@1``, ``val_map``), keep `model`'s state when
        it scores best; True when training should stop. Replaying recorded rows through it tells which epoch a rule
        would have kept (`monolib.retrieval.model_selection`)."""
        self.history.append(row)
        if row["epoch"] < self.min_epochs:
            return False
        score = self.score(row)
        if self.best is None or score > self.best:
            self.best, self.best_epoch, self.bad_epochs = score, row["epoch"], 0
            self.best_state = copy.deepcopy(model.state_dict())
            return False
        self.bad_epochs += 1
        return self.bad_epochs >= self.patience


def stopper_of(rule: TrainingRule, *, seed: int, model: nn.Module) -> EarlyStopping:
    """The `EarlyStopping` of a training rule (its patience, select and min_epochs)."""
    return EarlyStopping(patience=rule.patience, seed=seed, model=model, select=rule.select,
                         min_epochs=rule.min_epochs)


@dataclass
class TrainResult:
    """A trained encoder (the kept epoch's weights), every epoch's history row, the kept epoch, and the seconds of
    the epochs."""
    model: nn.Module
    history: list[dict] = field(default_factory=list)
    best_epoch: int = 0
    seconds: float = 0.0


def run_epoch(model: nn.Module, opt: torch.optim.Optimizer, batches: Iterable[Batch], dev) -> float:
    """One optimiser step per batch; the epoch's training loss: the batches' losses weighted by their sizes."""
    losses, seen = [], 0
    for batch in batches:
        loss = batch.loss(model(batch.input.to(dev)))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item() * batch.size)
        seen += batch.size
    if not seen:
        raise ValueError("an epoch without a training sample: the training split is empty")
    return sum(losses) / seen


def train(make_model: Callable[[], nn.Module], epoch_batches: Callable[[np.random.Generator, torch.Generator],
                                                                       Iterable[Batch]],
          *, rule: TrainingRule, seed: int, val_inputs, val_settings, embed: Callable[[nn.Module, Any], torch.Tensor],
          threads: int = 2, deterministic: bool = True, progress: bool = False, on_epoch=None) -> TrainResult:
    """Train the encoder `make_model()` builds (after the seeding) with the triplet loss, by `rule`: Adam over its
    trainable parameters; each epoch at its learning rate (`set_epoch_lr`), the model in training mode over
    `epoch_batches(rng, gen)` (`rng`: numpy's generator of `seed`, `gen`: torch's, from `seed_everything`), then
    validated (`embed(model, val_inputs)`, the items' settings `val_settings`) and recorded (`EarlyStopping`); the
    kept epoch's weights are loaded at the end. `on_epoch(model)`, when given, runs after each epoch's validation
    (the model in eval mode) and returns extra columns for that epoch's history row (a curve of the test metric,
    say); it must not draw from the seed's random streams, so that the training is the same with and without it."""
    torch.set_num_threads(threads)
    gen = seed_everything(int(seed), deterministic)
    rng = np.random.default_rng(seed)
    dev = device()
    model = make_model().to(dev)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=rule.lr,
                           weight_decay=rule.weight_decay)
    loss_fn = triplet_loss(rule.margin)
    val_settings = np.asarray(val_settings)
    stopper = stopper_of(rule, seed=seed, model=model)
    t0 = time.perf_counter()
    for epoch in range(1, rule.epochs + 1):
        set_epoch_lr(opt, rule, epoch)
        model.train()
        train_loss = run_epoch(model, opt, epoch_batches(rng, gen), dev)
        val_emb = embed(model, val_inputs) if len(val_inputs) else None
        extra = on_epoch(model) if on_epoch is not None else None
        if stopper.step(model, epoch=epoch, train_loss=train_loss, val_emb=val_emb, val_settings=val_settings,
                        loss_fn=loss_fn, progress=progress, extra=extra):
            break
    model.load_state_dict(stopper.best_state)
    return TrainResult(model, stopper.history, stopper.best_epoch, time.perf_counter() - t0)
