"""One rule for every results folder a command writes: all of one run, or none of it.

A command's folder OUT is built in a staging folder beside it, ``.OUT.partial``, whose
``manifest.json`` names the command and its arguments from the start. When every file is
written, the manifest is marked complete (written last) and the staging folder is renamed to OUT
in one step. Whenever a process is killed, OUT is therefore the previous complete result or
absent, and what the killed run left is a staging folder the next run recognises by its manifest:

- the same command and arguments: the run resumes there (a command with finished pieces, such as
  ``reproduce``'s steps, reuses them; any other starts again);
- other ones: refused, naming what differs; ``force`` discards it.

A complete OUT is refused unless ``force``, or unless this run extends it (``extends``: a run of
wider scope over the same settings, such as ``reproduce --full`` over ``reproduce``), when it is
updated as ``report`` updates it; with ``force`` the new folder replaces it at the end
(OUT is renamed to ``.OUT.replaced``, the staging folder to OUT, then the old one is removed; a
kill between the two renames is repaired by the next run, which puts the old folder back). A
folder holding files but no manifest was not written by a command here and is never replaced.
Every file inside is written with :func:`bayesdrive.data.atomic.write_atomic`. A run holds a lock
on its staging folder, so a second run into the same OUT is refused while the first is alive.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from bayesdrive.data.atomic import existing_ancestor, write_text_atomic

__all__ = [
    "MANIFEST",
    "OutputError",
    "ResultsFolder",
    "open_results",
    "read_manifest",
    "recorded_arguments",
    "staging_path",
]

MANIFEST = "manifest.json"


class OutputError(Exception):
    """Why a results folder cannot be written where asked (a one-line message)."""


def staging_path(target: Path) -> Path:
    """Where the folder ``target`` is built before it is renamed into place."""
    return target.with_name(f".{target.name}.partial")


def _replaced_path(target: Path) -> Path:
    return target.with_name(f".{target.name}.replaced")


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _plain(arguments: dict[str, Any]) -> dict[str, Any]:
    """The arguments as JSON gives them back (paths as strings), so records compare equal."""
    return json.loads(json.dumps(arguments, default=str))


def read_manifest(folder: Path) -> dict[str, Any] | None:
    """The manifest of ``folder``, or None when it has none."""
    path = folder / MANIFEST
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as error:
        raise OutputError(f"{path}: cannot read the manifest ({error})") from None


def recorded_arguments(out: str | os.PathLike, command: str) -> dict[str, Any]:
    """The arguments ``command`` recorded in OUT, or in the partial folder an interrupted run left."""
    target = Path(os.path.abspath(out))
    for folder in (target, staging_path(target)):
        manifest = read_manifest(folder) if folder.is_dir() else None
        if manifest is not None and manifest.get("command") == command:
            return manifest["arguments"]
    raise OutputError(f"{target} holds no result of `bayesdrive {command}` ({MANIFEST} missing)")


def _differences(recorded: dict[str, Any], command: str, arguments: dict[str, Any]) -> str:
    """What differs between a recorded run and this one, or '' when nothing does."""
    if recorded.get("command") != command:
        return f"command: `{recorded.get('command')}` there, `{command}` here"
    old = recorded.get("arguments", {})
    return "; ".join(
        f"{name}: {old.get(name)!r} there, {arguments.get(name)!r} here"
        for name in sorted(set(old) | set(arguments))
        if old.get(name) != arguments.get(name)
    )


def _check_place(target: Path) -> None:
    """Refuse at once an OUT that names a file or a link, or lies where nothing can be written."""
    if target.is_symlink():
        raise OutputError(f"--out {target} is a link; give the folder itself")
    if target.exists() and not target.is_dir():
        raise OutputError(f"--out {target} is a file, not a folder")
    ancestor = existing_ancestor(target)
    if not ancestor.is_dir():
        raise OutputError(f"cannot write --out {target}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write --out {target}: no permission to write in {ancestor}")


def _recover(target: Path) -> None:
    """Repair a replacement killed between its two renames."""
    replaced = _replaced_path(target)
    if not replaced.exists():
        return
    if target.exists():
        shutil.rmtree(replaced)  # the new folder is in place; the old one was being removed
    else:
        os.rename(replaced, target)  # killed before the new one moved in: the old one is back


def _lock(staging: Path) -> int:
    """An exclusive lock on the staging folder, released when its descriptor closes (or the
    process dies); refused while another run holds it."""
    descriptor = os.open(staging, os.O_RDONLY)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(descriptor)
        raise OutputError(
            f"{staging} is being written by another run now; wait for it, or choose another --out"
        ) from None
    return descriptor


@contextmanager
def _signals_held() -> Iterator[None]:
    """SIGTERM and SIGINT wait until the enclosed renames are done (main thread only)."""
    held = {signal.SIGTERM, signal.SIGINT}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class ResultsFolder:
    """A results folder being written: files go under :attr:`path`; :meth:`commit` publishes them.

    Used as a context manager: leaving it without :meth:`commit` removes the staging folder,
    unless the command is ``resumable`` (its finished pieces are then kept for the next run).
    """

    def __init__(
        self,
        target: Path,
        command: str,
        arguments: dict[str, Any],
        *,
        replaces: bool,
        resumed: bool,
        resumable: bool,
        lock: int,
    ) -> None:
        self.target = target
        self.path = staging_path(target)
        self.command = command
        self.arguments = arguments
        self.replaces = replaces
        self.resumed = resumed
        self.resumable = resumable
        self.committed = False
        self._lock = lock

    def _manifest(self, complete: bool) -> dict[str, Any]:
        manifest = {
            "command": self.command,
            "arguments": self.arguments,
            "seed": self.arguments.get("seed"),
            "complete": complete,
            "written": _now(),
        }
        if complete:
            manifest["files"] = sorted(
                str(p.relative_to(self.path))
                for p in self.path.rglob("*")
                if p.is_file() and p.name != MANIFEST
            )
        return manifest

    def start(self) -> None:
        write_text_atomic(self.path / MANIFEST, json.dumps(self._manifest(False), indent=2) + "\n")

    def commit(self) -> Path:
        """Mark the manifest complete (last) and rename the folder into place; returns OUT."""
        manifest = json.dumps(self._manifest(True), indent=2) + "\n"
        with _signals_held():
            write_text_atomic(self.path / MANIFEST, manifest)
            replaced = _replaced_path(self.target)
            if self.replaces:
                os.rename(self.target, replaced)
            try:
                os.rename(self.path, self.target)  # over an empty folder too
            except OSError as error:
                if self.replaces:
                    os.rename(replaced, self.target)
                raise OutputError(f"cannot move the result into {self.target}: {error}") from None
            if self.replaces:
                shutil.rmtree(replaced)
        self.committed = True
        return self.target

    def discard(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)

    def close(self) -> None:
        """Remove the staging folder unless committed or resumable; release the lock."""
        if not self.committed and not self.resumable:
            self.discard()
        if self._lock >= 0:
            os.close(self._lock)
            self._lock = -1

    def __enter__(self) -> ResultsFolder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()


def open_results(
    out: str | os.PathLike,
    command: str,
    arguments: dict[str, Any],
    *,
    force: bool,
    resumable: bool = False,
    update: bool = False,
    extends: dict[str, Any] | None = None,
) -> ResultsFolder:
    """Check OUT before any work and open its staging folder (the rule: module docstring).

    ``update`` rebuilds a complete folder of the same command and arguments (``report``): its
    files are hard-linked into the staging folder, where atomic writes replace links, never the
    old files, so the old folder stays whole until :meth:`ResultsFolder.commit`. A complete folder
    whose arguments are ``extends`` is updated the same way, and records ``arguments`` after.
    Raises :class:`OutputError` with a one-line reason.
    """
    target = Path(os.path.abspath(out))
    staging = staging_path(target)
    arguments = _plain(arguments)
    try:
        _check_place(target)
        if staging.is_dir() and not staging.is_symlink():
            os.close(_lock(staging))  # refused while a live run writes it (or commits it)
        _recover(target)
        replaces = target.is_dir() and any(target.iterdir())
        if replaces:
            recorded = read_manifest(target)
            if recorded is None:
                raise OutputError(
                    f"{target} holds files but no {MANIFEST}, so no bayesdrive command wrote it "
                    "and none replaces it; choose a new or empty folder"
                )
            differ = _differences(recorded, command, arguments)
            grows = extends is not None and not _differences(recorded, command, _plain(extends))
            update = (update and not differ) or grows
            if not force and not update:
                settings = f"with other settings ({differ})" if differ else "of the same settings"
                raise OutputError(
                    f"{target} already holds a complete result of `bayesdrive "
                    f"{recorded.get('command')}` {settings}; use --force to replace it, "
                    "or another --out"
                )
        resumed = False
        if staging.exists() or staging.is_symlink():
            if not staging.is_dir() or staging.is_symlink():
                raise OutputError(f"{staging} is in the way of the staging folder; remove it")
            staged = read_manifest(staging)
            differ = "" if staged is None else _differences(staged, command, arguments)
            if differ and not force:
                raise OutputError(
                    f"{staging} holds a partial result with other settings ({differ}); use "
                    "--force to discard it, or another --out"
                )
            # A partial folder without a manifest was never started; one that is not resumed
            # has nothing worth keeping.
            resumed = staged is not None and not differ and not force
            if not (resumed and resumable):
                shutil.rmtree(staging)
        if not staging.exists():
            if update and replaces:
                shutil.copytree(target, staging, copy_function=os.link)
            else:
                staging.mkdir(parents=True)
        folder = ResultsFolder(
            target,
            command,
            arguments,
            replaces=replaces,
            resumed=resumed,
            resumable=resumable,
            lock=_lock(staging),
        )
        folder.start()
    except OSError as error:
        raise OutputError(f"cannot write --out {target}: {error}") from None
    return folder
