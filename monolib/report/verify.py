"""`monolib verify STUDY`: compare a study's freshly written figures with the committed ones.

The committed figures are the files of the study's figures folder at git HEAD (`committed_figures`; or any folder
given with ``--against``). `compare` reports four things:

- first, the dataset: its digest (``dataset_digest.json``, `monolib.data.digest`) against the committed one, naming
  each setting and kind of file that differs (a problem: the rendered data should be the same bytes everywhere);
- which files are byte for byte identical, and which differ (information: timings and figures differ freely);
- every mean of ``intervals.csv`` (every number of the tables, with its 95 % interval) that moved: by how much,
  and whether it left its committed interval (a problem) or stayed inside it;
- every claim of ``params/claims.yaml``: its relation tested on the fresh ``claims.csv``'s difference interval; a
  claim that fails is a problem, and one that held in the committed ``claims.csv`` is named as flipped.

One line per problem; the run passes (exit 0) when the dataset is the committed one, every claim holds and every
mean lies within its committed interval.
"""
from __future__ import annotations

import filecmp
import math
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import pandas as pd

from monolib import paths
from monolib.data import digest
from monolib.device import cpu_signature
from monolib.report import claims as claims_mod
from monolib.report.results import SUMMARY_KEYS

TOLERANCE = 1e-9  # a mean that moved less than this (the CSV's 6 significant digits) has not moved


class VerifyError(RuntimeError):
    """Nothing to compare with: no git checkout and no ``--against``, or a folder without the files."""


@dataclass
class Verdict:
    dataset: list[str] = field(default_factory=list)
    identical: list[str] = field(default_factory=list)
    different: list[str] = field(default_factory=list)
    info: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def lines(self) -> list[str]:
        """What `monolib verify` prints: the dataset, the files, the information, then one line per problem and the
        verdict."""
        out = self.dataset + [f"identical ({len(self.identical)}): {', '.join(self.identical) or '-'}",
               f"different ({len(self.different)}): {', '.join(self.different) or '-'}"]
        out += self.info + [f"PROBLEM: {p}" for p in self.problems]
        out.append("verify: every claim holds and every mean is within its committed interval" if self.ok else
                   f"verify: {len(self.problems)} problem(s)")
        return out


def _git(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, check=False)


def committed_figures(study_name: str, dest: Path, root: Path = paths.ROOT, rev: str = "HEAD") -> Path:
    """Write the files of the study's figures folder as committed at `rev` into `dest` (the folder's own files,
    not its subfolders: those are other studies'); returns `dest`."""
    fig = paths.figures_dir(study_name).resolve()
    try:
        rel = fig.relative_to(Path(root).resolve()).as_posix()
    except ValueError:
        raise VerifyError(f"{fig}: the figures of {study_name} are outside the checkout {root}; pass --against DIR "
                          f"with the figures to compare with") from None
    if _git(["rev-parse", "--is-inside-work-tree"], root).returncode != 0:
        raise VerifyError(f"{root}: not a git checkout, so no committed figures of {study_name}; pass --against DIR "
                          f"with the figures to compare with")
    listing = _git(["ls-tree", f"{rev}:{rel}"], root)
    if listing.returncode != 0:
        raise VerifyError(f"{rel}: no committed figures of {study_name} at {rev} "
                          f"({listing.stderr.decode().strip()}); pass --against DIR")
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    for line in listing.stdout.decode().splitlines():
        meta, name = line.split("\t", 1)
        if meta.split()[1] != "blob":
            continue
        blob = _git(["show", f"{rev}:{rel}/{name}"], root)
        if blob.returncode != 0:
            raise VerifyError(f"git show {rev}:{rel}/{name}: {blob.stderr.decode().strip()}")
        (dest / name).write_bytes(blob.stdout)
    return dest


def _dataset(v: Verdict, fresh: Path, committed: Path) -> None:
    """The dataset's digest (`monolib.data.digest`) against the committed one, before any mean: a dataset that
    differs is a problem that names its settings and kinds of file (every number after it may move because of it)."""
    old, new = committed / digest.FILE, fresh / digest.FILE
    if not old.is_file():
        return
    if not new.is_file():
        v.problems.append(f"{new}: missing (the committed figures have the dataset's digest; run the study)")
        return
    a, b = digest.read(old), digest.read(new)
    lines = digest.differences(a, b)
    if not lines:
        markers = digest.markers_only(a, b)
        v.dataset.append(f"dataset: identical to the committed one ({b['files']} files in {len(b['settings'])} "
                         f"settings, sha256 {b['sha256'][:16]})" if not markers else
                         f"dataset: every rendered file identical to the committed one ({b['files']} files in "
                         f"{len(b['settings'])} settings); the markers of {len(markers)} settings differ (rendered "
                         "under another key: the dataset stage's code or libraries changed, its files did not)")
        return
    v.dataset.append(f"dataset: differs from the committed one in {len(lines)} place(s) (sha256 {b['sha256'][:16]}, "
                     f"committed {a['sha256'][:16]}), rendered here on {cpu_signature()} (with `dataset.coplanar: "
                     "exact`, the default, the dataset is the same on every x86 CPU measured; with `embree`, only on "
                     "CPUs of the vendor that rendered it: docs/reproducibility.md); the means below say whether the "
                     "results held")
    v.problems += [f"dataset: {line}" for line in lines]


def _files(v: Verdict, fresh: Path, committed: Path) -> None:
    for p in sorted(q for q in committed.iterdir() if q.is_file()):
        mine = fresh / p.name
        if not mine.is_file():
            v.info.append(f"missing from the fresh figures: {p.name}")
        elif filecmp.cmp(p, mine, shallow=False):
            v.identical.append(p.name)
        else:
            v.different.append(p.name)


def _label(row) -> str:
    t = "inf" if math.isinf(row.threshold) else f"{row.threshold:g} m"
    return f"{row.method} {row.scenario} {t} {row.protocol} {row.metric}@{int(row.k)}"


def _means(v: Verdict, fresh: Path, committed: Path) -> None:
    if not (committed / "intervals.csv").is_file():
        v.info.append("no committed intervals.csv: means not compared")
        return
    if not (fresh / "intervals.csv").is_file():
        v.problems.append(f"{fresh / 'intervals.csv'}: missing (the study wrote no intervals)")
        return
    old, new = pd.read_csv(committed / "intervals.csv"), pd.read_csv(fresh / "intervals.csv")
    both = old.merge(new, on=SUMMARY_KEYS, how="left", suffixes=("", "_new"), indicator="which")
    moved = within = 0
    for row in both.itertuples(index=False):
        if row.which == "left_only" or pd.isna(row.mean_new):
            v.problems.append(f"{_label(row)}: committed {row.mean:.1f}, missing from the fresh intervals.csv")
            continue
        d = row.mean_new - row.mean
        if abs(d) <= TOLERANCE:
            continue
        moved += 1
        where = f"{_label(row)}: {row.mean:.1f} -> {row.mean_new:.1f} ({d:+.1f}), committed interval " \
                f"[{row.ci_lo:.1f}, {row.ci_hi:.1f}]"
        if row.ci_lo - TOLERANCE <= row.mean_new <= row.ci_hi + TOLERANCE:
            within += 1
            v.info.append(f"moved within its interval: {where}")
        else:
            v.problems.append(f"moved outside its committed interval: {where}")
    v.info.append(f"means: {len(old)} committed, {moved} moved, {within} of them within their committed interval")


def _claims(v: Verdict, study_name: str, fresh: Path, committed: Path, claims_path: Path) -> None:
    stated = claims_mod.load(study_name, claims_path)
    if not stated:
        v.info.append(f"claims: {study_name} has none in {claims_path}")
        return
    if not (fresh / "claims.csv").is_file():
        v.problems.append(f"{fresh / 'claims.csv'}: missing, the claims of {claims_path} were not evaluated")
        return
    new = claims_mod.read(fresh / "claims.csv").set_index("id")
    old = claims_mod.read(committed / "claims.csv").set_index("id") if (committed / "claims.csv").is_file() else None
    for c in stated:
        if c.id not in new.index:
            v.problems.append(f"claim {c.id}: not in the fresh claims.csv (rerun the report)")
            continue
        r = new.loc[c.id]
        cells = (r.a_method, r.a_scenario, float(r.a_threshold), r.b_method, r.b_scenario, float(r.b_threshold))
        if cells != (c.a.method, c.a.scenario, c.a.threshold, c.b.method, c.b.scenario, c.b.threshold) \
                or r.metric != c.metric or r.protocol != c.a.protocol:
            v.problems.append(f"claim {c.id}: the fresh claims.csv compares other cells than {claims_path} "
                              f"(rerun the report)")
            continue
        ok = claims_mod.holds(c.relation, float(r.diff_lo), float(r.diff_hi), c.margin)
        was = None if old is None or c.id not in old.index else bool(old.loc[c.id, "holds"])
        diff = f"difference {r['diff']:.1f} [{r.diff_lo:.1f}, {r.diff_hi:.1f}]"
        if not ok:
            flipped = " (flipped: it held in the committed claims.csv)" if was else ""
            v.problems.append(f"claim {c.id} FAILS{flipped}: {c.relation} expected, {diff}")
        elif was is False:
            v.info.append(f"claim {c.id} holds now (flipped: it failed in the committed claims.csv), {diff}")
    v.info.append(f"claims: {len(stated)} in {claims_path.name}")


def compare(study_name: str, fresh: Path, committed: Path, claims_path: Path = claims_mod.CLAIMS_FILE) -> Verdict:
    """The `Verdict` of the figures in `fresh` against those in `committed`."""
    fresh, committed = Path(fresh), Path(committed)
    for folder in (fresh, committed):
        if not folder.is_dir():
            raise VerifyError(f"{folder}: no such folder of figures")
    v = Verdict()
    _dataset(v, fresh, committed)
    _files(v, fresh, committed)
    _means(v, fresh, committed)
    _claims(v, study_name, fresh, committed, Path(claims_path))
    return v


def verify(study_name: str, against: Optional[Path] = None, claims_path: Path = claims_mod.CLAIMS_FILE) -> Verdict:
    """The study's figures (`paths.figures_dir`) against `against`, or against their committed versions at HEAD."""
    import tempfile

    fresh = paths.figures_dir(study_name)
    if against is not None:
        return compare(study_name, fresh, Path(against), claims_path)
    with tempfile.TemporaryDirectory() as tmp:
        return compare(study_name, fresh, committed_figures(study_name, Path(tmp)), claims_path)
