"""requirements.lock: written from pip's report, read back; the environment running the tests is the locked one."""
import json
import subprocess
import sys

import pytest

from monolib import lockfile, paths


def _entry(name, version, digest="ab" * 32, url=None):
    archive = {"hashes": {"sha256": digest}} if digest else {}
    return {"metadata": {"name": name, "version": version},
            "download_info": {"url": url or f"https://files.example/{name}-{version}.whl", "archive_info": archive}}


def test_a_report_becomes_a_sorted_lock_that_reads_back(tmp_path):
    report = {"install": [_entry("Torch_Geometric", "2.8.0"), _entry("numpy", "2.3.1", "cd" * 32),
                          {"metadata": {"name": "monolib", "version": "0.1.0"},
                           "download_info": {"url": "file:///work/main", "dir_info": {"editable": True}}}]}
    (tmp_path / "r.json").write_text(json.dumps(report))
    assert lockfile.main([str(tmp_path / "r.json"), str(tmp_path / "req.lock")]) == 0
    text = (tmp_path / "req.lock").read_text()
    assert text.index("numpy==2.3.1 \\\n    --hash=sha256:" + "cd" * 32) < text.index("torch-geometric==2.8.0")
    assert "monolib" not in text.split("\n", 3)[3]  # the project itself is not locked
    assert lockfile.locked_versions(tmp_path / "req.lock") == {"numpy": "2.3.1", "torch-geometric": "2.8.0"}
    assert lockfile.usable(tmp_path / "req.lock") is None  # written here: for this interpreter


def test_what_cannot_be_locked_or_read_is_one_error_naming_it(tmp_path):
    with pytest.raises(ValueError, match="scipy 1.16.0 has no sha256"):
        lockfile.lock_text({"install": [_entry("scipy", "1.16.0", digest=None)]}, "platform: x")
    bad = tmp_path / "bad.lock"
    bad.write_text("# platform: CPython 3.11 Linux x86_64\nnumpy>=2\n")
    with pytest.raises(ValueError, match=r"bad.lock:2: expected 'name==version"):
        lockfile.locked_versions(bad)
    other = tmp_path / "other.lock"
    other.write_text("# platform: CPython 3.12 Darwin arm64\nnumpy==2.3.1 \\\n    --hash=sha256:" + "ab" * 32 + "\n")
    assert "Darwin arm64" in lockfile.usable(other)
    assert lockfile.usable(tmp_path / "none.lock").endswith("no lock file")
    assert lockfile.differences({"numpy": "2.3.1", "h5py": "3.14.0"}, {"numpy": "2.3.1", "pip": "25.0"}) == [
        "h5py missing (locked 3.14.0)"]


def test_the_committed_lock_holds_every_dependency_and_this_environment_is_it():
    locked = lockfile.locked_versions()
    tomllib = pytest.importorskip("tomllib")
    from packaging.requirements import Requirement  # (pip's and pytest's dependency: in every environment here)

    project = tomllib.loads((paths.ROOT / "pyproject.toml").read_text())["project"]
    wanted = project["dependencies"] + project["optional-dependencies"]["test"]
    names = {lockfile.normalise(Requirement(d).name) for d in wanted}  # the name, without extras, markers or pins
    assert names <= set(locked), sorted(names - set(locked))
    assert locked["torch"] == "2.14.1" and locked["torchvision"] == "0.29.1"
    if lockfile.usable() is not None:
        pytest.skip(f"installed from pyproject.toml's ranges: {lockfile.usable()}")
    record = lockfile.environment_record()
    assert record["matches"], record["differences"]


def test_make_install_asks_the_bare_interpreter_whether_the_lock_fits():
    """`make install` runs this before anything is installed: it must need nothing beyond the standard library."""
    out = subprocess.run([sys.executable, "-S", "-m", "monolib.lockfile", "--usable"], cwd=paths.ROOT,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
