"""`monolib bench allocator` (`make bench-allocator`, figures/allocator.json): one image cell of a finished study
with glibc's malloc as it is and with `device.keep_freed_memory`, in a new process each: seconds, system CPU,
page faults, and whether the two wrote the same files."""
from __future__ import annotations

import platform
import time
from pathlib import Path

from monolib import methods
from monolib.bench.common import written
from monolib.io import sha256
from monolib.params import StudyError, load_study

ALLOCATOR_CELL = """
import json, resource, sys, time
from monolib.params import load_study
from monolib.retrieval import cell

study, method, seed, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
s = load_study(study)
r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
cell.run_cell(s, method, "rgb", float("inf"), seed, out_dir=out, force=True)
wall, r1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"seconds": wall, "user_s": r1.ru_utime - r0.ru_utime, "system_s": r1.ru_stime - r0.ru_stime,
                  "page_faults": r1.ru_minflt - r0.ru_minflt}))
"""


def allocator_side_by_side(study_name: str = "quick", method: str = "imagenet_triplet", seed: int = 0,
                           out: str | None = None) -> dict:
    """One image cell of a finished study (`method`, `seed`: its data and features cached) run twice in a new
    process each, one after the other: with malloc as glibc sets it (``MONOLIB_ALLOCATOR=default``) and with
    `device.keep_freed_memory` (``keep``). Per run: wall, user and system CPU seconds and minor page faults of the
    cell alone; and whether the two wrote the same files, bit for bit. With `out`, also JSON and its Markdown."""
    import json
    import os
    import subprocess
    import sys
    import tempfile

    study = load_study(study_name)
    if methods.kind(method, study) != "image":
        raise StudyError(f"bench allocator: {method!r} is not an image method of {study.path}")
    record = {"study": study.name, "method": method, "seed": seed, "torch_threads": study.threads,
              "machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
              "date": time.strftime("%Y-%m-%d"), "runs": {}}
    digests = {}
    with tempfile.TemporaryDirectory(prefix="monolib-allocator-") as tmp:
        for mode in ("default", "keep"):
            folder = Path(tmp) / mode
            done = subprocess.run([sys.executable, "-c", ALLOCATOR_CELL, str(study.path), method, str(seed),
                                   str(folder)], env={**os.environ, "MONOLIB_ALLOCATOR": mode}, check=True,
                                  capture_output=True, text=True)
            run = {k: round(v, 1) if k != "page_faults" else int(v)
                   for k, v in json.loads(done.stdout.strip().splitlines()[-1]).items()}
            run["system_share"] = round(run["system_s"] / max(run["user_s"] + run["system_s"], 1e-9), 3)
            run["page_faults_per_s"] = int(run["page_faults"] / max(run["seconds"], 1e-9))
            record["runs"][mode] = run
            digests[mode] = {f.name: sha256(f) for f in sorted(folder.iterdir())
                             if f.suffix in (".npy", ".csv", ".pt")}
            print(f"{method} seed {seed} of {study.name}, MONOLIB_ALLOCATOR={mode}: {run['seconds']:.1f} s "
                  f"(user {run['user_s']:.1f} s, system {run['system_s']:.1f} s), {run['page_faults']:,} page faults",
                  flush=True)
    record["same_files"] = digests["default"] == digests["keep"]
    record["files_compared"] = sorted(digests["keep"])
    record["speedup"] = round(record["runs"]["default"]["seconds"] / record["runs"]["keep"]["seconds"], 2)
    print(f"default / keep: {record['speedup']:.2f}x the time; the same files: {record['same_files']} "
          f"({', '.join(record['files_compared'])})")
    return written(record, out, allocator_table)


def allocator_table(record: dict) -> str:
    """The table of `allocator_side_by_side`'s record (docs/benchmarks.md)."""
    lines = [f"**The allocator** (`make bench-allocator`: one `{record['method']}` cell of `{record['study']}`, seed "
             f"{record['seed']}, in a new process each, {record['torch_threads']} torch thread(s), "
             f"{record['machine']}, {record['cpus']} cpus, {record['date']}). The same files, bit for bit "
             f"({', '.join(record['files_compared'])}): **{'yes' if record['same_files'] else 'NO'}**.", "",
             "| MONOLIB_ALLOCATOR | seconds | user CPU s | system CPU s | system share | page faults | faults / s |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for mode, r in record["runs"].items():
        lines.append(f"| `{mode}` | {r['seconds']:.1f} | {r['user_s']:.1f} | {r['system_s']:.1f} | "
                     f"{100 * r['system_share']:.0f}% | {r['page_faults']:,} | {r['page_faults_per_s']:,} |")
    return "\n".join(lines) + "\n"
