"""The exact environment the study was run with: `requirements.lock` (every distribution ``name==version`` with the
sha256 of the file pip installs), written from pip's own resolution and read back to say whether an environment
is the locked one.

`make lock` asks pip to resolve the project with its ``test`` extra as a fresh install would (``pip install
--dry-run --ignore-installed --report``: nothing is installed, the report names each file and its hash) and turns
the report into the lock (`lock_text`); `make install` installs from the lock with ``--require-hashes``, then the
project itself without dependencies. The files are those of CPython 3.11 on Linux x86_64 (torch's wheel is
platform-specific), which is what the lock's header says and `make install` checks before it uses the lock.
`figures/timings.json` records the lock's digest and whether the environment that ran the study matched it
(`environment_record`).
"""
from __future__ import annotations

import argparse
import json
import platform
import re
import sys
from pathlib import Path
from typing import Optional

from monolib import paths  # (standard library only until the environment is installed: `make install` runs
                           # `usable` with the bare interpreter)

LOCK = paths.ROOT / "requirements.lock"
PROJECT = "monolib"


def normalise(name: str) -> str:
    """A distribution name as pip compares them (PEP 503)."""
    return re.sub(r"[-_.]+", "-", name).lower()


def lock_text(report: dict, platform_line: str) -> str:
    """The lock of a pip installation report (``pip install --dry-run --report``): one ``name==version \\
    --hash=sha256:...`` per distribution, sorted by name, the project itself left out. A distribution without a
    sha256 in the report (a local path, a VCS URL) cannot be locked: one `ValueError` naming it."""
    lines = []
    for item in report.get("install", []):
        meta = item.get("metadata", {})
        name, version = meta.get("name"), meta.get("version")
        if not name or not version:
            raise ValueError(f"pip report: an install entry without name or version: {item.get('download_info')}")
        if normalise(name) == PROJECT:
            continue
        digest = (item.get("download_info", {}).get("archive_info", {}).get("hashes") or {}).get("sha256")
        if not digest:
            raise ValueError(f"pip report: {name} {version} has no sha256 "
                             f"({item.get('download_info', {}).get('url')}): it cannot be locked")
        lines.append((normalise(name), f"{normalise(name)}=={version} \\\n    --hash=sha256:{digest}"))
    if not lines:
        raise ValueError("pip report: nothing to install")
    header = ("# The exact environment of this study: make lock writes it from pip's resolution of the project with\n"
              "# its test extra; make install installs from it (--require-hashes). Do not edit by hand.\n"
              f"# {platform_line}\n")
    return header + "\n".join(text for _, text in sorted(lines)) + "\n"


def platform_line() -> str:
    """What the locked files are built for: this interpreter's version and platform."""
    return (f"platform: CPython {platform.python_version_tuple()[0]}.{platform.python_version_tuple()[1]} "
            f"{platform.system()} {platform.machine()}")


def locked_versions(path: Path = LOCK) -> dict[str, str]:
    """``{normalised name: version}`` of a lock file; one `ValueError` naming the file and line of a line that is
    neither a comment, a hash nor ``name==version``."""
    out = {}
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#") or line.startswith("--hash="):
            continue
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s\\]+)\s*\\?", line)
        if not m:
            raise ValueError(f"{path}:{n}: expected 'name==version \\' or '--hash=sha256:...', got {line!r}")
        out[normalise(m.group(1))] = m.group(2)
    return out


def installed_versions() -> dict[str, str]:
    """``{normalised name: version}`` of every distribution this interpreter sees."""
    from importlib import metadata

    return {normalise(d.metadata["Name"]): d.version for d in metadata.distributions() if d.metadata["Name"]}


def differences(locked: dict[str, str], installed: dict[str, str]) -> list[str]:
    """What keeps `installed` from being the locked environment: each locked distribution missing or at another
    version (distributions beyond the lock, such as pip itself, do not count)."""
    return [f"{name} {installed.get(name) or 'missing'} (locked {version})"
            for name, version in sorted(locked.items()) if installed.get(name) != version]


def environment_record(path: Path = LOCK) -> Optional[dict]:
    """``{"lock": sha256 of the lock's first 12 hex digits, "matches": bool, "differences": [...]}`` for the run
    record; None without a lock file."""
    from monolib.io import sha256  # deferred: numpy, h5py (make install asks `usable` before they are installed)

    path = Path(path)
    if not path.is_file():
        return None
    diff = differences(locked_versions(path), installed_versions())
    return {"lock": sha256(path)[:12], "matches": not diff, "differences": diff}


def usable(path: Path = LOCK) -> Optional[str]:
    """None when this interpreter can install from the lock; otherwise why not (no lock file, or a lock for another
    Python or platform)."""
    path = Path(path)
    if not path.is_file():
        return f"{path}: no lock file"
    lines = [line for line in path.read_text().splitlines() if line.startswith("# platform: ")]
    if not lines:
        raise ValueError(f"{path}: no '# platform: ' line (written by make lock)")
    have = platform_line()
    if lines[0][2:] != have:
        return f"{path} holds the files of {lines[0][12:]}, this interpreter is {have[10:]}"
    return None


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m monolib.lockfile REPORT [LOCK]``: write the lock from pip's report (make lock).
    ``python -m monolib.lockfile --usable``: exit 0 when this interpreter can install from the lock, else say why
    (make install)."""
    ap = argparse.ArgumentParser(prog="python -m monolib.lockfile", description=main.__doc__)
    ap.add_argument("report", nargs="?", help="the JSON of pip install --dry-run --ignore-installed --report")
    ap.add_argument("lock", nargs="?", default=str(LOCK), help="the lock file to write (default: %(default)s)")
    ap.add_argument("--usable", action="store_true", help="whether this interpreter can install from the lock")
    args = ap.parse_args(argv)
    if args.usable:
        why = usable(Path(args.lock))
        if why:
            print(f"make install: {why}: installing from pyproject.toml's ranges instead", file=sys.stderr)
        return 1 if why else 0
    if not args.report:
        ap.error("REPORT is required (or --usable)")
    from monolib.io import write_text  # deferred: numpy, h5py

    try:
        text = lock_text(json.loads(Path(args.report).read_text()), platform_line())
    except (OSError, ValueError) as exc:
        print(f"error: {args.report}: {exc}", file=sys.stderr)
        return 1
    write_text(Path(args.lock), text)
    print(f"wrote {args.lock}: {len(locked_versions(Path(args.lock)))} distributions")
    return 0


if __name__ == "__main__":
    sys.exit(main())
