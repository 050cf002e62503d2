"""Loaded by every Python process started with this folder on ``PYTHONPATH`` (pytest's workers,
the CLI's subprocesses, Dask's workers): appends JAX's compile events, each with the test that
caused it (``PYTEST_CURRENT_TEST``, inherited by subprocesses) and the innermost line of
bayesdrive's own code on the stack (the call site: which line of ours made JAX compile), to
``$COMPILE_LOG_DIR/<pid>.log``. Imports no JAX: the test suite must set its compilation cache
before JAX is imported."""

import logging
import os
import time
import traceback

_FOLDER = os.environ.get("COMPILE_LOG_DIR")
_OURS = f"{os.sep}bayesdrive{os.sep}"


def _call_site() -> str:
    for frame in reversed(traceback.extract_stack()):
        if _OURS in frame.filename and f"{os.sep}site-packages{os.sep}" not in frame.filename:
            path = frame.filename.split(_OURS, 1)[1]
            return f"{path}:{frame.lineno} {frame.name}"
    return "-"


class _CompileLog(logging.Handler):
    def emit(self, record):
        message = record.getMessage()
        lowered = message.lower()
        if "finished" in lowered or "compilation cache" in lowered:
            test = os.environ.get("PYTEST_CURRENT_TEST", "-")
            with open(os.path.join(_FOLDER, f"{os.getpid()}.log"), "a") as log:
                log.write(f"{time.time():.2f}\t{test}\t{_call_site()}\t{message}\n")


if _FOLDER:
    # These loggers report tracing, lowering, compiling and cache hits at DEBUG; only this
    # handler sees them, so no process prints more than it did.
    for name in ("jax._src.dispatch", "jax._src.compiler"):
        logger = logging.getLogger(name)
        logger.setLevel(logging.DEBUG)
        logger.addHandler(_CompileLog(level=logging.DEBUG))
        logger.propagate = False
