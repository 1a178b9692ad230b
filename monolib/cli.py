"""The `monolib` command: `monolib study STUDY`, `monolib synth STUDY --out DIR`, `monolib perception STUDY`,
`monolib bench`."""
from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from monolib.params import StudyError, load_study


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="monolib", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("study", help="run every stage of a study (dataset, perception, graphs, cells, report)")
    p.add_argument("study", help="a study name from params/ (smoke, quick, paper) or a YAML path")
    p.add_argument("--jobs", type=int, default=None, help="parallel papermill workers (default: the study's jobs)")
    p = sub.add_parser("synth", help="render a study's mini-Hypersim in the Hypersim layout")
    p.add_argument("study")
    p.add_argument("--out", required=True, help="output folder")
    p = sub.add_parser("perception", help="train, evaluate and cache the perception models of a study")
    p.add_argument("study")
    p = sub.add_parser("bench", help="benchmarks: rendering, graph construction")
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=192)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        if args.command == "study":
            from monolib import study as study_mod

            t0 = time.perf_counter()
            times = study_mod.run(load_study(args.study), jobs=args.jobs)
            print("stage seconds: " + ", ".join(f"{k[:-2]} {v:.0f}" for k, v in times.items())
                  + f"; total {time.perf_counter() - t0:.0f}")
        elif args.command == "synth":
            from monolib import synth

            synth.render_dataset(load_study(args.study), Path(args.out))
        elif args.command == "perception":
            from monolib import perception

            print(perception.run(load_study(args.study)).to_string(index=False))
        elif args.command == "bench":
            from monolib import bench

            bench.run(args.width, args.height)
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
