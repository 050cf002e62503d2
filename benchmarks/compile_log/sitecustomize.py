"""Loaded by every Python process started with this folder on ``PYTHONPATH`` (pytest's workers,
the CLI's subprocesses, Dask's workers): appends JAX's compile events, each with the test that
caused it (``PYTEST_CURRENT_TEST``, inherited by subprocesses), to ``$COMPILE_LOG_DIR/<pid>.log``.
Imports no JAX: the test suite must set its compilation cache before JAX is imported."""

import logging
import os
import time

_FOLDER = os.environ.get("COMPILE_LOG_DIR")


class _CompileLog(logging.Handler):
    def emit(self, record):
        message = record.getMessage()
        lowered = message.lower()
        if "finished" in lowered or "compilation cache" in lowered:
            test = os.environ.get("PYTEST_CURRENT_TEST", "-")
            with open(os.path.join(_FOLDER, f"{os.getpid()}.log"), "a") as log:
                log.write(f"{time.time():.2f}\t{test}\t{message}\n")


if _FOLDER:
    # These loggers report tracing, lowering, compiling and cache hits at DEBUG; only this
    # handler sees them, so no process prints more than it did.
    for name in ("jax._src.dispatch", "jax._src.compiler"):
        logger = logging.getLogger(name)
        logger.setLevel(logging.DEBUG)
        logger.addHandler(_CompileLog(level=logging.DEBUG))
        logger.propagate = False
