"""Data sets by name: where their folders are, loading them, and checking them against their pins.

What each data set is (format, layout, origins, licence, files and checksums, role) is described
once, in :mod:`bayesdrive.data.catalog`; its tables :data:`DATASETS` and :data:`HOLDOUT` and
:func:`get` are re-exported here. :func:`resolve` and :func:`load` refuse the names of
:data:`HOLDOUT`, so no fit, default, prior, threshold or seed can be chosen on them by accident;
evaluation code loads them with :func:`load_holdout`.

Where the data live (first match wins; see :func:`data_dir` and :func:`holdout_dir`):

1. the explicit argument (``--data-dir`` / ``--holdout-dir`` on the command line);
2. the environment variable ``BAYESDRIVE_DATA_DIR`` / ``BAYESDRIVE_HOLDOUT_DIR``;
3. ``<root>/../shared/data`` / ``<root>/../shared/holdout`` if that folder exists, where ``<root>``
   is the repository holding the current directory (the nearest parent with ``.git`` or
   ``pyproject.toml``), else the current directory itself.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
from pathlib import Path
from typing import NamedTuple

from bayesdrive.data import readers
from bayesdrive.data.catalog import DATASETS, HOLDOUT, DataFile, DataSet, Origin, Role, get
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories

log = logging.getLogger(__name__)

__all__ = [
    "DATASETS",
    "DATA_DIR_ENV",
    "HELD_OUT_NOTE",
    "HOLDOUT",
    "HOLDOUT_DIR_ENV",
    "DataFile",
    "DataSet",
    "Mismatch",
    "Origin",
    "check_files",
    "data_dir",
    "get",
    "holdout_dir",
    "is_holdout_name",
    "load",
    "load_any",
    "load_holdout",
    "resolve",
    "resolve_holdout",
    "sha256_file",
    "verify",
]

DATA_DIR_ENV = "BAYESDRIVE_DATA_DIR"
HOLDOUT_DIR_ENV = "BAYESDRIVE_HOLDOUT_DIR"
_SHARED_FOLDER = {"fit": "data", "holdout": "holdout"}
_DIR_ENV = {"fit": DATA_DIR_ENV, "holdout": HOLDOUT_DIR_ENV}
_DIR_OPTION = {"fit": "--data-dir", "holdout": "--holdout-dir"}


class Mismatch(NamedTuple):
    """A file of a data-set folder that differs from the registry.

    ``problem`` is ``"missing"``, ``"unexpected"`` (a file the registry does not list: a reader
    would read it unchecked), ``"size"`` or ``"sha256"``.
    """

    file: str
    problem: str
    expected: str
    actual: str

    def __str__(self) -> str:
        if self.problem == "missing":
            return f"{self.file}: missing"
        if self.problem == "unexpected":
            return f"{self.file}: not in the registry"
        return f"{self.file}: {self.problem} {self.actual}, expected {self.expected}"


def _repository_root(start: Path) -> Path:
    for folder in (start, *start.parents):
        if (folder / ".git").exists() or (folder / "pyproject.toml").exists():
            return folder
    return start


def _lookup_dir(explicit: str | os.PathLike | None, role: Role) -> Path:
    if explicit is not None:
        return Path(explicit)
    env = _DIR_ENV[role]
    if os.environ.get(env):
        return Path(os.environ[env])
    shared = _repository_root(Path.cwd()) / ".." / "shared" / _SHARED_FOLDER[role]
    if shared.is_dir():
        return shared.resolve()
    raise DataError(
        f"no {'data' if role == 'fit' else 'holdout'} directory: pass {_DIR_OPTION[role]}, "
        f"or set {env}, or create {shared}"
    )


def data_dir(explicit: str | os.PathLike | None = None) -> Path:
    """The folder holding the named data sets (lookup order in the module docstring)."""
    return _lookup_dir(explicit, "fit")


def holdout_dir(explicit: str | os.PathLike | None = None) -> Path:
    """The folder holding the held-out data sets (lookup order in the module docstring)."""
    return _lookup_dir(explicit, "holdout")


def _resolve(
    name_or_path: str | os.PathLike, directory: str | os.PathLike | None, role: Role
) -> tuple[Path, DataSet | None]:
    """The path to read, and the registered data set when a name was given."""
    path = Path(name_or_path)
    if path.exists():
        return path, None
    name = str(name_or_path)
    table, other = (DATASETS, HOLDOUT) if role == "fit" else (HOLDOUT, DATASETS)
    if name in table:
        folder = _lookup_dir(directory, role) / name
        if not folder.is_dir():
            raise DataError(
                f"data set {name!r} is not in {folder.parent}: fetch it with "
                f"`bayesdrive data fetch {name}`"
            )
        return folder, table[name]
    if name in other:
        if role == "fit":
            raise DataError(
                f"{name!r} is held out for evaluation only and cannot be loaded for fitting "
                "(evaluation code loads it with load_holdout)"
            )
        raise DataError(f"{name!r} is a data set for fitting, not a held-out data set")
    raise DataError(
        f"{name!r} is neither an existing file or folder nor a known data set "
        f"(known: {', '.join(table)})"
    )


def resolve(name_or_path: str | os.PathLike, data_dir: str | os.PathLike | None = None) -> Path:
    """The file or folder to read for ``name_or_path``.

    An existing path is used as it is; otherwise a name from :data:`DATASETS` is looked up in the
    data directory. A held-out name, an unknown name and a missing data set raise
    :class:`DataError` (the last naming ``bayesdrive data fetch NAME``).
    """
    return _resolve(name_or_path, data_dir, "fit")[0]


def resolve_holdout(name: str, holdout_dir: str | os.PathLike | None = None) -> Path:
    """The folder of the held-out data set ``name`` (an existing path is used as it is)."""
    return _resolve(name, holdout_dir, "holdout")[0]


def _read(
    path: Path, dataset: DataSet | None, format: str | None, strict: bool, options: dict
) -> Trajectories:
    if dataset is None:
        return readers.read(path, format=format, strict=strict, **options)
    traj = readers.read(path, format=format or dataset.format, strict=strict, **options)
    # A name is portable across machines; the folder it was found in is not.
    return dataclasses.replace(traj, source=dataset.name)


def load(
    name_or_path: str | os.PathLike,
    format: str | None = None,
    data_dir: str | os.PathLike | None = None,
    strict: bool = False,
    **options,
) -> Trajectories:
    """Read a data set by name (with its registered format as the default) or a path.

    ``options`` go to the reader (e.g. ``columns``, ``units``, ``headway`` for the column-map
    reader). Checksums are not re-checked on every load: run :func:`verify` (or
    ``bayesdrive data list``) for that.
    """
    path, dataset = _resolve(name_or_path, data_dir, "fit")
    return _read(path, dataset, format, strict, options)


def load_holdout(
    name: str,
    format: str | None = None,
    holdout_dir: str | os.PathLike | None = None,
    strict: bool = False,
    **options,
) -> Trajectories:
    """Read a held-out data set by name, for evaluation only (see :func:`load`)."""
    path, dataset = _resolve(name, holdout_dir, "holdout")
    return _read(path, dataset, format, strict, options)


HELD_OUT_NOTE = (
    "%s is held out for evaluation only: fit it with fixed, documented settings to measure the "
    "toolkit; never choose or tune a default, prior, threshold, seed or model on it"
)


def is_holdout_name(name_or_path: str | os.PathLike) -> bool:
    """Whether ``name_or_path`` names a held-out data set (and no existing path)."""
    return str(name_or_path) in HOLDOUT and not Path(name_or_path).exists()


def load_any(
    name_or_path: str | os.PathLike,
    format: str | None = None,
    data_dir: str | os.PathLike | None = None,
    strict: bool = False,
    note_held_out: bool = True,
    **options,
) -> Trajectories:
    """:func:`load`, or for a held-out name :func:`load_holdout` (``data_dir`` then names the
    held-out folder) with :data:`HELD_OUT_NOTE` logged (unless not ``note_held_out``: a caller
    that only looks at the data or evaluates on it): what users call, where fitting a held-out
    set's vehicles with fixed settings is evaluation."""
    if is_holdout_name(name_or_path):
        if note_held_out:
            log.warning(HELD_OUT_NOTE, name_or_path)
        return load_holdout(str(name_or_path), format, data_dir, strict, **options)
    return load(name_or_path, format, data_dir, strict, **options)


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, read in chunks."""
    with open(path, "rb") as stream:
        return hashlib.file_digest(stream, "sha256").hexdigest()


def check_files(folder: Path, files: tuple[DataFile, ...]) -> list[Mismatch]:
    """Mismatches between ``files`` as registered and as found in ``folder`` (extras not checked)."""
    mismatches = []
    for file in files:
        path = folder / file.name
        if not path.is_file():
            mismatches.append(Mismatch(file.name, "missing", "present", "absent"))
            continue
        size = path.stat().st_size
        if size != file.size:
            mismatches.append(Mismatch(file.name, "size", f"{file.size} B", f"{size} B"))
            continue
        digest = sha256_file(path)
        if digest != file.sha256:
            mismatches.append(Mismatch(file.name, "sha256", file.sha256, digest))
    return mismatches


def verify(name: str, data_dir: str | os.PathLike | None = None) -> list[Mismatch]:
    """Every difference between the folder of data set ``name`` and the registry.

    ``data_dir`` is the folder holding the data set's folder (looked up as in :func:`data_dir`,
    or :func:`holdout_dir` for a held-out name). Files the registry does not list are reported
    too: a reader would read them unchecked. An empty list means the folder is exactly as pinned.
    """
    dataset = get(name)
    folder = _lookup_dir(data_dir, dataset.role) / name
    registered = {file.name for file in dataset.files}
    present = (
        sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
        if folder.is_dir()
        else []
    )
    unexpected = [
        Mismatch(name, "unexpected", "absent", "present")
        for name in present
        if name not in registered
    ]
    return check_files(folder, dataset.files) + unexpected
