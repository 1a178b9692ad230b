"""`monolib bench imagenet` (`make bench-imagenet`, figures/imagenet_choices.json): `imagenet_vlad` as it is
against PCA-whitened on the training split, recall@1 on both protocols (what decided `pretrained.VLAD_WHITEN`)."""
from __future__ import annotations

import platform
import time

import numpy as np
import torch

from monolib.bench.common import written
from monolib.data import selection
from monolib.data import dataset
from monolib.params import load_study
from monolib.perception import features
from monolib.retrieval import evaluate, pretrained


def imagenet_choices(study_name: str = "quick", seeds=(0, 1), dims=(None, 128, 256, 512),
                     out: str | None = None) -> dict:
    """The measurement behind `pretrained.VLAD_WHITEN`: `imagenet_vlad` without and with PCA whitening learnt on the
    training split, per seed, recall@1 of both protocols on the study's test split (`evaluate.evaluate_protocols`,
    the cells' evaluation). (How `imagenet_triplet` trains is chosen on the training split alone:
    `monolib.retrieval.model_selection`.)"""
    study = load_study(study_name)
    torch.set_num_threads(study.threads)
    sel = selection.select_frames(study, dataset.open_dataset(study), study.gcn.val_settings)
    train = np.concatenate([features.load(study, sel.train), features.load(study, sel.val)])
    test = features.load(study, sel.test)
    _, head = features.networks()
    keys, settings = [f.key for f in sel.test], [f.setting for f in sel.test]
    record = {"study": study.name, "machine": f"{platform.machine()} {platform.processor()}".strip(),
              "date": time.strftime("%Y-%m-%d"), "vlad_whitening": []}
    for seed in seeds:
        for d in dims:
            t = time.perf_counter()
            emb, _, _ = pretrained.vlad_embed(train, test, head, seed, whiten_dims=d)
            r = evaluate.evaluate_protocols(emb, keys, settings, study.protocol, seed)
            row = {"seed": seed, "whitened_dims": d, "dimensions": int(emb.shape[1]),
                   **{f"recall@1_{p}": round(float(v.metrics["recall@1"]), 1) for p, v in r.items()},
                   "seconds": round(time.perf_counter() - t, 1)}
            record["vlad_whitening"].append(row)
            print(f"imagenet_vlad seed {seed}, whitened to {d or 'none (as it is)'}: {row['dimensions']}-d, "
                  + ", ".join(f"{k} {v}" for k, v in row.items() if k.startswith("recall")), flush=True)
    return written(record, out, imagenet_choices_table)


def imagenet_choices_table(record: dict) -> str:
    protos = [k for k in record["vlad_whitening"][0] if k.startswith("recall@1_")] if record["vlad_whitening"] else []
    head = " | ".join(p.replace("recall@1_", "recall@1 ") for p in protos)
    lines = [f"**Whitening of `imagenet_vlad`** (`monolib bench imagenet`, study `{record['study']}`, "
             f"{record['machine']}, {record['date']}; recall@1 on the test split, both protocols).", "",
             f"| imagenet_vlad | seed | dimensions | {head} |", "|---|---:|---:|" + "---:|" * len(protos)]
    for r in record["vlad_whitening"]:
        what = f"PCA-whitened to {r['whitened_dims']}" if r["whitened_dims"] else "as it is (chosen)"
        lines.append(f"| {what} | {r['seed']} | {r['dimensions']:,} | "
                     + " | ".join(f"{r[p]:.1f}" for p in protos) + " |")
    return "\n".join(lines) + "\n"
