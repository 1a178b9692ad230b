"""`monolib bench render COMMIT` (`make bench-render`, figures/render_bench.json): the dataset stage of a study
rendered by the generator of another commit and by this one, one after the other in one run."""
from __future__ import annotations

import platform
import time
from pathlib import Path

from monolib import paths
from monolib.io import write_json


def render_side_by_side(old: str, study: str = "quick", out: str | None = None) -> dict:
    """The dataset stage of `study` (its whole mini-Hypersim, the study file's own workers) rendered by the code of
    commit `old` (a temporary git worktree) and by this checkout's, one after the other on this machine: wall
    seconds, frames and bytes of each. Run it on a quiet machine; with `out`, also written as JSON."""
    import os
    import shutil
    import subprocess
    import sys
    import tempfile

    repo = paths.PACKAGE.parent
    record = {"machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
              "date": time.strftime("%Y-%m-%d"), "study": study, "old_commit": old,
              "new_commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True,
                                    text=True).stdout.strip() + " + working tree"}
    with tempfile.TemporaryDirectory(prefix="monolib-render-") as tmp:
        tree = Path(tmp) / "old"
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), old], cwd=repo, check=True,
                       capture_output=True)
        try:
            for label, root in (("old", tree), ("new", repo)):
                target = Path(tmp) / f"{label}-dataset"
                env = dict(os.environ, PYTHONPATH=str(root))
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "monolib.cli", "synth", study, "--out", str(target)],
                               cwd=root, env=env, check=True)
                seconds = time.perf_counter() - t0
                frames = sum(1 for _ in target.glob("ai_*/images/*_final_hdf5/*.color.hdf5"))
                size = sum(f.stat().st_size for f in target.rglob("*") if f.is_file())
                record[label] = {"seconds": round(seconds, 1), "frames": frames, "gigabytes": round(size / 1e9, 2)}
                print(f"render {study} with the generator of {record[label + '_commit']}: "
                      f"{seconds:.1f} s, {frames} frames, {size / 1e9:.2f} GB", flush=True)
                shutil.rmtree(target)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=repo, capture_output=True)
    record["ratio"] = round(record["new"]["seconds"] / record["old"]["seconds"], 2)
    print(f"new / old: {record['ratio']:.2f}x the time ({record['machine']}, {record['cpus']} cpus, {record['date']})")
    if out:
        write_json(out, record)
    return record
