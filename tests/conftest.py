"""Shared fixtures: where the real data live.

``data_dir`` is ``$BAYESDRIVE_DATA_DIR`` or ``<repo>/../shared/data``; ``holdout_dir`` is
``$BAYESDRIVE_HOLDOUT_DIR`` or ``<repo>/../shared/holdout``. When the folder is missing, a test
using it fails in CI (``$CI`` set) and is skipped, with the reason shown, elsewhere.

Tests marked ``slow`` are collected first: ``--dist worksteal`` hands each worker a contiguous
share of the collection and later moves work from the tail of the busier worker's queue, so the
longest tests start at the beginning of the first worker's share instead of being left for last
while the other worker has nothing left to do.

JAX's persistent compilation cache: a run of the suite compiles each program once into a fresh
folder that every worker and every ``bayesdrive`` subprocess shares (the environment carries it),
and removes the folder at the end; a ``JAX_COMPILATION_CACHE_DIR`` already set is used instead.

Hypothesis: with ``$CI`` set the ``ci`` profile is loaded, derandomized, so a CI run draws the
same examples every time (a failure there is reproducible, never a flake).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import settings

from bayesdrive.cli.main import COMPILATION_CACHE_ENV, compilation_cache

settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

REPO = Path(__file__).resolve().parents[1]


CACHE_ENV = "JAX_COMPILATION_CACHE_DIR"
_created_cache: list[str] = []


def pytest_configure(config):
    """Share one fresh compilation cache across the run (module docstring), set up as the
    ``bayesdrive`` command sets up its own. Runs in the xdist controller before it starts the
    workers, which inherit the environment; no plugin has imported JAX yet, so JAX reads it."""
    if CACHE_ENV not in os.environ:
        folder = tempfile.mkdtemp(prefix="bayesdrive-jax-cache-")
        _created_cache.append(folder)
        os.environ[COMPILATION_CACHE_ENV] = folder
        compilation_cache()


def pytest_unconfigure(config):
    for folder in _created_cache:
        shutil.rmtree(folder, ignore_errors=True)


def pytest_collection_modifyitems(config, items):
    """Slow tests first, otherwise the collection's order (a stable sort)."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


def _shared_folder(env: str, default: Path) -> Path:
    folder = Path(os.environ.get(env) or default)
    if not folder.is_dir():
        message = f"real data folder {folder} not found (set {env} to point at it)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return folder


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real-data folder (``../shared/data`` from the repository)."""
    return _shared_folder("BAYESDRIVE_DATA_DIR", REPO.parent / "shared" / "data")


@pytest.fixture(scope="session")
def holdout_dir() -> Path:
    """The held-out data folder (``../shared/holdout``): for evaluation and loading tests only."""
    return _shared_folder("BAYESDRIVE_HOLDOUT_DIR", REPO.parent / "shared" / "holdout")
