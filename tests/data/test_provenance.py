"""The code provenance every result records: commit and cleanliness from git, never a failure."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from bayesdrive.data import provenance
from bayesdrive.data.provenance import _provenance_of, code_provenance, describe_code

REPO = Path(__file__).resolve().parents[2]
needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")


def _git(cwd: Path, *args: str) -> str:
    return subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
        cwd=cwd,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()


def _checkout(root: Path) -> Path:
    """A minimal git checkout of a package named bayesdrive; returns the package folder."""
    package = root / "bayesdrive"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (root / "pyproject.toml").write_text("[project]\nname = 'bayesdrive'\n")
    _git(root, "init", "-q")
    _git(root, "add", ".")
    _git(root, "commit", "-q", "-m", "first")
    return package


@needs_git
def test_a_clean_checkout_records_its_commit_and_files_outside_the_code_keep_it_clean(tmp_path):
    package = _checkout(tmp_path)
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "fit.nc").write_text("a run's output")
    found = _provenance_of.__wrapped__(package)
    assert found["commit"] == _git(tmp_path, "rev-parse", "HEAD")
    assert found["clean"] is True
    assert "clean tree" in describe_code(found)


@needs_git
def test_a_changed_or_new_code_file_makes_the_tree_unclean(tmp_path):
    package = _checkout(tmp_path)
    (package / "__init__.py").write_text("x = 1\n")
    assert _provenance_of.__wrapped__(package)["clean"] is False
    _git(tmp_path, "checkout", "--", "bayesdrive/__init__.py")
    (package / "new_module.py").write_text("")
    assert _provenance_of.__wrapped__(package)["clean"] is False
    assert "UNCOMMITTED" in describe_code(_provenance_of.__wrapped__(package))


@needs_git
def test_an_untracked_copy_inside_another_repository_does_not_borrow_its_commit(tmp_path):
    _git(tmp_path, "init", "-q")
    package = tmp_path / "site-packages" / "bayesdrive"
    package.mkdir(parents=True)
    found = _provenance_of.__wrapped__(package)
    assert found["commit"] is None and found["clean"] is None


def test_outside_any_git_checkout_or_without_git_nothing_fails(tmp_path, monkeypatch):
    package = tmp_path / "bayesdrive"
    package.mkdir()
    monkeypatch.setenv("PATH", str(tmp_path))  # no git executable to be found
    found = _provenance_of.__wrapped__(package)
    assert found == {"version": found["version"], "commit": None, "clean": None}
    assert "commit unknown" in describe_code(found)
    assert "not recorded" in describe_code(None)


@needs_git
def test_this_checkout_is_described_by_its_own_head():
    if not (REPO / ".git").exists():
        pytest.skip("the tests do not run from a git checkout")
    assert code_provenance()["commit"] == _git(REPO, "rev-parse", "HEAD")
    # A copy: callers cannot change what later results record.
    code_provenance()["commit"] = "changed"
    assert code_provenance()["commit"] != "changed"
    assert provenance._PACKAGE_DIR == REPO / "bayesdrive"
