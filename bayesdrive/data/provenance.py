"""Which code made a result: the git commit of the bayesdrive checkout and whether it was clean.

Every result, report, model card and export records :func:`code_provenance`. Inside a git
checkout of bayesdrive it reads the commit and whether the code (the ``bayesdrive`` package and
``pyproject.toml``) differs from it; elsewhere (an installed wheel, no git on the path) the commit
and the cleanliness are unknown (``None``) and only the installed version is recorded. It never
fails: provenance is a record, not a precondition of a run.

Only the code counts towards ``clean``: a run writes results and reports into the checkout, and
those must not make the run that wrote them look dirty.
"""

from __future__ import annotations

import subprocess
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

__all__ = ["code_provenance", "describe_code", "provenance_line"]

_PACKAGE_DIR = Path(__file__).resolve().parents[1]
_CODE_PATHS = ("bayesdrive", "pyproject.toml")


def _git(*args: str, cwd: Path) -> str | None:
    try:
        done = subprocess.run(
            ["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def _installed_version() -> str | None:
    try:
        return version("bayesdrive")
    except PackageNotFoundError:
        return None


def code_provenance() -> dict[str, Any]:
    """``{"version", "commit", "clean"}`` of the running bayesdrive (module docstring); computed
    once per process, so every file a run writes names the same code."""
    return dict(_provenance_of(_PACKAGE_DIR))


@cache
def _provenance_of(package_dir: Path) -> dict[str, Any]:
    found: dict[str, Any] = {"version": _installed_version(), "commit": None, "clean": None}
    root = _git("rev-parse", "--show-toplevel", cwd=package_dir)
    # The package must be tracked in that repository: an installed copy inside some unrelated
    # git work tree would otherwise borrow that repository's commit.
    tracked = root and _git("ls-files", "--error-unmatch", "bayesdrive/__init__.py", cwd=Path(root))
    if not tracked:
        return found
    found["commit"] = _git("rev-parse", "HEAD", cwd=Path(root))
    status = _git("status", "--porcelain", "--", *_CODE_PATHS, cwd=Path(root))
    found["clean"] = None if status is None else status == ""
    return found


def describe_code(code: dict[str, Any] | None) -> str:
    """A :func:`code_provenance` record (as a result's metadata holds it) as one readable line;
    ``None`` for results written before the code was recorded."""
    if not code:
        return "code not recorded (the result predates provenance records)"
    name = f"bayesdrive {code['version'] or '(version unknown)'}"
    if code["commit"] is None:
        return f"{name}, not a git checkout: commit unknown"
    state = "clean tree" if code["clean"] else "UNCOMMITTED CHANGES to the code"
    return f"{name} at commit {code['commit']} ({state})"


def provenance_line() -> str:
    """The running code, as one line for reports and model cards."""
    return describe_code(code_provenance())
