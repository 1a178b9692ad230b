"""The `monolib` command: `monolib study STUDY`, `monolib synth STUDY --out DIR`, `monolib perception STUDY`,
`monolib fidelity STUDY`, `monolib unpack ARCHIVE`, `monolib verify [STUDY]`, `monolib index STUDY --out DB`,
`monolib localize IMAGE... --db DB`, `monolib bench`."""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from monolib import paths
from monolib.data import synth
from monolib.io import CacheUnreadable, DataFileError
from monolib.params import StudyError, load_study, resolve_path

# Each handler imports its stage itself ("# deferred: torch"), so that --help and a bad argument answer at once.


def _study_parsers(sub) -> None:
    p = sub.add_parser("study", help="run every stage of a study (dataset, perception, graphs, cells, report)")
    p.add_argument("study", help="a study name from params/ (smoke, quick, paper) or a YAML path")
    p.add_argument("--jobs", type=int, default=None, help="parallel papermill workers (default: the study's jobs)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the cells on the workers of this Dask scheduler (tcp://host:8786, or the file of "
                   "`dask scheduler --scheduler-file`); they must share this project's runs folder")
    p.add_argument("--cold-kernels", action="store_true",
                   help="a new notebook kernel per cell (full isolation) instead of one warm kernel per worker "
                   "(= MONOLIB_KERNELS=cold)")
    p = sub.add_parser("synth", help="render a study's mini-Hypersim in the Hypersim layout")
    p.add_argument("study")
    p.add_argument("--out", required=True, help="output folder")
    p = sub.add_parser("perception", help="train, evaluate and cache the perception models of a study")
    p.add_argument("study")
    p = sub.add_parser("zoo", help="pretrain the perception networks on their own mini-Hypersim and ship them")
    p.add_argument("study", nargs="?", default="zoo", help="the pretraining study (default params/zoo.yaml)")
    p.add_argument("--eval", default="quick", help="the study whose test split measures them (default quick)")
    p.add_argument("--out", default=None, help="folder of the weights and manifests (default monolib/resources/zoo)")
    p.add_argument("--only", nargs="*", default=None, help="train only these networks")
    p.add_argument("--pilot", action="store_true", help="measure the learning curve at a few sizes instead "
                                                        "(figures/zoo_pilot.md); ships nothing")
    p.add_argument("--figures", action="store_true", help="only rewrite figures/zoo.md and zoo_curve.png from the "
                                                          "shipped manifests")
    p = sub.add_parser("fidelity", help="compare a study's ground-truth scene graphs with real Hypersim (fidelity.md)")
    p.add_argument("study", nargs="?", help="the study to measure (with --reference: optional)")
    p.add_argument("--reference", metavar="DIR", help="first measure the published graphs' development set in DIR "
                                                      "(runs/published_graphs_dev) into the reference table")
    p = sub.add_parser("data-edits", help="the edge penalty with one property of the data changed at a time "
                                          "(params/data_edits.yaml -> figures/data_edits/)")
    p.add_argument("study", nargs="?", default="data_edits")
    p.add_argument("--leg", help="run only this leg's runs, no tables (a second process runs the other leg)")
    p = sub.add_parser("unpack", help="check the published graphs' development set (archive or folder) and put it "
                                      "where params/real.yaml reads it")
    p.add_argument("source", help="published_graphs_dev.tar.xz, or a folder with its train/ folder")
    p.add_argument("--out", default="runs/published_graphs_dev",
                   help="folder to write (relative to the project root; default runs/published_graphs_dev)")
    sub.add_parser("training-size", help="the training-size curve of both legs and the README's reproduction table "
                                         "from the committed studies (figures/training_size.md, reproduces.md)")
    p = sub.add_parser("verify", help="compare a study's fresh figures with the committed ones: identical files, "
                                      "means moved against their intervals, claims that fail (exit 1 on a problem)")
    p.add_argument("study", nargs="?", default="quick", help="the study (default quick)")
    p.add_argument("--against", default=None, metavar="DIR",
                   help="the figures to compare with (default: the study's figures as committed at git HEAD)")


def _localize_parsers(sub) -> None:
    p = sub.add_parser("index", help="a localization database: a study's test frames, or your own places (--places)")
    p.add_argument("study")
    p.add_argument("--out", required=True, help="database folder (indexing into it again embeds only new images)")
    p.add_argument("--places", default=None, metavar="DIR", help="your own places: DIR/<place>/ holds .jpg, .jpeg "
                   "or .png images of each place (other files and nested folders are skipped and listed); default: "
                   "the study's test frames, one place per setting")
    p.add_argument("--method", default=None, help="method of the study whose best cell encodes: a graph "
                   "method (gcn or a variant; its best predicted-input cell; default: any) or an image method "
                   "(color_hist, orb_bow, image_triplet, imagenet_gem, imagenet_vlad, imagenet_triplet); another "
                   "name is an error")
    p = sub.add_parser("localize", help="find the place of RGB images (PNG/JPEG) in a database")
    p.add_argument("images", nargs="+")
    p.add_argument("--db", required=True)
    p.add_argument("--k", type=int, default=None, help="nearest places to list: 1 to the database's number of "
                   "places (outside that range: an error, not a clamp; default 5, or all of a smaller database)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table (with each place's matched "
                   "image)")
    p.add_argument("--show", default=None, metavar="OUT.png", help="also draw what it saw: the image, its predicted "
                   "semantics and depth, its scene graph, the nearest places' images (several images: OUT-1.png, ...)")


BENCHMARKS = {  # name: (help, takes --out); each one of `monolib.bench`'s modules (its docstring says what it does)
    "frames": ("one frame's stages, graph construction against the original code's, kNN, perception fps", True),
    "render": ("the study's dataset stage rendered by the generator of COMMIT and by this checkout's (minutes)", True),
    "localizers": ("a localizer of each method of the finished --study: database bytes per frame, ms per query "
                   "image, recall@1 (minutes)", True),
    "localize": ("recall@1 of each method's localizer on the finished --study's test frames as JPEG photos, and one "
                 "image's latency on one thread (--out, default figures/localize.md of the study; minutes)", True),
    "imagenet": ("imagenet_vlad of --study with and without PCA whitening (about a minute)", True),
    "allocator": ("one imagenet_triplet cell of the finished --study with glibc's malloc as it is and with "
                  "monolib's (MONOLIB_ALLOCATOR), side by side (minutes)", True),
    "cell": ("where the finished --study's grid cells spend their seconds: the grid by method, one gcn cell's "
             "training profiled, the dense floor (a minute)", True),
    "selection": ("the model-selection rules of the trained encoders compared on the training split of --study "
                  "(figures/selection.md; minutes)", False),
    "grid": ("the smoke grid on the local path and on local Dask clusters of 1 and 2 workers, and the paper study "
             "projected on 1/8/64 workers (minutes)", True),
}


def _bench_parser(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks that print figures: monolib bench NAME (one of "
                       f"{', '.join(BENCHMARKS)})")
    names = p.add_subparsers(dest="benchmark", required=True, metavar="NAME")
    for name, (text, out) in BENCHMARKS.items():
        b = names.add_parser(name, help=text, description=text)
        if name == "render":
            b.add_argument("commit", metavar="COMMIT", help="the commit whose generator renders beside this one")
        if name != "grid":
            b.add_argument("--study", default="quick", help="the study measured (default: %(default)s)")
        if name == "frames":
            b.add_argument("--width", type=int, default=256)
            b.add_argument("--height", type=int, default=192)
        if out:
            b.add_argument("--out", default=None, help="also write the figures as JSON, and a page beside it")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="monolib", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    _study_parsers(sub)
    _localize_parsers(sub)
    _bench_parser(sub)
    return parser


def _study(args) -> int:
    from monolib.study import runner  # deferred: torch

    t0 = time.perf_counter()
    if args.cold_kernels:
        import os

        os.environ["MONOLIB_KERNELS"] = "cold"
    times = runner.run(load_study(args.study), jobs=args.jobs, scheduler=args.scheduler)
    print("stage seconds: " + ", ".join(f"{k[:-2]} {v:.0f}" for k, v in times.items())
          + f"; total {time.perf_counter() - t0:.0f}")
    return 0


def _synth(args) -> int:
    synth.render_dataset(load_study(args.study), Path(args.out))
    return 0


def _perception(args) -> int:
    from monolib.perception import predictions  # deferred: torch
    from monolib.report import perception_figures  # deferred: torch

    spec = load_study(args.study)
    print(predictions.run(spec).to_string(index=False))
    perception_figures.draw_figures(spec)  # perception_training.png, fig3_depth.png, fig4_semantics.png
    print(f"figures: {paths.figures_dir(spec.name)}")
    return 0


def _zoo(args) -> int:
    from monolib.perception import zoo  # deferred: torch

    # the evaluation study gives its test split only: its own zoo weights need not exist yet
    evaluation = load_study(args.eval, check_files=False)
    if args.figures:
        zoo.write_figures(zoo.shipped_manifests(load_study(args.study), args.out), paths.FIGURES)
        print(f"written: {paths.FIGURES / 'zoo.md'} and zoo_curve.png")
        return 0
    if args.pilot:
        print(zoo.pilot(load_study(args.study), evaluation, paths.FIGURES, only=args.only).to_string(index=False))
        return 0
    done = zoo.run(load_study(args.study), evaluation, Path(args.out) if args.out else None, only=args.only)
    for name, m in done.items():
        print(f"{name}: {m['file']} {m['bytes'] / 1e6:.1f} MB sha256 {m['sha256'][:12]} "
              f"test {json.dumps({k: round(v, 4) for k, v in m['test_metrics'].items() if isinstance(v, float)})}")
    return 0


def _data_edits(args) -> int:
    from monolib.study import data_edits  # deferred: torch

    path = data_edits.main(args.study, leg=args.leg)
    if path is not None:
        print(path.read_text(), end="")
    return 0


def _fidelity(args) -> int:
    from monolib.graphs import fidelity  # deferred: torch

    if args.reference:
        stats = fidelity.write_reference(args.reference)
        print(f"{fidelity.REFERENCE_CSV}: {len(stats)} statistics of {args.reference} as {fidelity.DEVELOPMENT!r}")
    if not args.study:
        if args.reference:
            return 0
        raise StudyError("monolib fidelity: name a study (or --reference DIR)")
    spec = load_study(args.study)
    _, table = fidelity.write(spec, fidelity.study_statistics(spec))
    print(table.read_text(), end="")
    print(f"written: {table} and fidelity.csv")
    return 0


def _unpack(args) -> int:
    from monolib.graphs import devset  # deferred: torch

    out = devset.unpack(args.source, resolve_path(args.out))
    print(f"development set: {len(list((out / 'train').glob('*_graphs.pt')))} graph files in {out}")
    return 0


def _training_size(args) -> int:
    from monolib.report import readme, training_size  # deferred: torch

    for path in training_size.write().values():
        print(f"wrote {path.relative_to(paths.ROOT)}")
    readme.update()
    return 0


def _verify(args) -> int:
    from monolib.report import verify  # deferred: torch

    try:
        verdict = verify.verify(args.study, args.against)
    except (verify.VerifyError, verify.claims_mod.ClaimsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(verdict.lines()))
    return 0 if verdict.ok else 1


def _index(args) -> int:
    from monolib import localize  # deferred: torch

    db = localize.build_index(load_study(args.study), args.out, args.method, args.places)
    print(localize.describe_database(db))
    return 0


def _localize(args) -> int:
    from monolib import localize  # deferred: torch

    results = localize.localize(args.images, args.db, args.k, args.show)
    print(json.dumps(results, indent=2) if args.json else localize.format_results(results))
    return 0


def _bench(args) -> int:
    name, out = args.benchmark, getattr(args, "out", None)
    if name == "selection":
        from monolib.retrieval import model_selection  # deferred: torch

        study = load_study(args.study)
        print(model_selection.write(study, paths.figures_dir(study.name))["md"])
    elif name == "grid":
        from monolib.study import scaling  # deferred: torch

        scaling.run(out=out)
    elif name == "frames":
        from monolib.bench import frames  # deferred: torch

        frames.run(args.width, args.height, args.study, out)
    elif name == "render":
        from monolib.bench import render  # deferred: torch

        render.render_side_by_side(args.commit, args.study, out)
    elif name == "localizers":
        from monolib.bench import localizers  # deferred: torch

        localizers.localizer_costs(args.study, out=out)
    elif name == "localize":
        from monolib.bench import photos  # deferred: torch

        photos.localize_photos(args.study, out=out or paths.figures_dir(load_study(args.study).name) / "localize.md")
    elif name == "imagenet":
        from monolib.bench import imagenet  # deferred: torch

        imagenet.imagenet_choices(args.study, out=out)
    elif name == "allocator":
        from monolib.bench import allocator  # deferred: torch

        allocator.allocator_side_by_side(args.study, out=out)
    else:
        from monolib.bench import cell  # deferred: torch

        cell.run(args.study, out=out)
    return 0


HANDLERS = {"study": _study, "synth": _synth, "perception": _perception, "zoo": _zoo, "fidelity": _fidelity,
            "data-edits": _data_edits, "unpack": _unpack, "training-size": _training_size, "verify": _verify,
            "index": _index, "localize": _localize, "bench": _bench}


def _setup() -> None:
    from monolib.device import keep_freed_memory  # deferred: torch

    keep_freed_memory()  # (the allocator: freed tensors reused, not mapped again by the kernel each step)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    for noisy in ("papermill", "traitlets", "nbclient", "distributed"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def main(argv: list[str] | None = None) -> int:
    """Parse `argv`, run its command's handler; a bad study, input file or cache is one line on stderr (exit 2), a
    failed notebook cell names its notebook (exit 1)."""
    args = build_parser().parse_args(argv)
    _setup()
    try:
        return HANDLERS[args.command](args)
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        from monolib.localize import LocalizeError  # deferred: torch
        from monolib.study.notebooks import NotebookFailed  # deferred: torch

        if isinstance(exc, (LocalizeError, DataFileError, CacheUnreadable)):
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if isinstance(exc, NotebookFailed):  # the notebook's cell and path say it all; the runner's stack does not
            print(f"error: {exc}", file=sys.stderr)
            return 1
        raise


if __name__ == "__main__":
    sys.exit(main())
