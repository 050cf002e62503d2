"""Fetch a registered data set from its pinned origin or a mirror, checking every sha256.

Files are downloaded into the staging folder beside the destination that every results folder
uses (:func:`bayesdrive.data.outputs.staging_path`); only when every file has its registered size
and sha256 is it renamed into place, in one step. Any failure (an HTTP error, a timeout, a wrong
checksum, SIGTERM) removes the staging folder: nothing is left behind, and the error names the
file, the URL and, for a checksum, both digests. A staging folder left by a killed process is
recognised by the next fetch, which keeps the files in it that match the registry and downloads
the rest. The registry is the data folder's manifest: a folder that matches it is complete, and
fetching it again changes nothing.

Without ``base_url`` each file comes from its origin (raw file URLs at the pinned commit); files
the origin does not publish (notes written with the copy) are then skipped and reported. A mirror
(``base_url``) serves the data-directory layout, ``BASE_URL/<data set>/<file>``, and so has every
file; ``file://`` URLs work too, for a mirror on disk.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple
from urllib.parse import quote

from bayesdrive.data.catalog import DataFile, DataSet, get
from bayesdrive.data.errors import DataError
from bayesdrive.data.outputs import staging_path
from bayesdrive.data.registry import check_files

__all__ = ["FetchResult", "fetch", "file_url", "files_to_fetch"]

_CHUNK = 1 << 20


class FetchResult(NamedTuple):
    """What :func:`fetch` did.

    Attributes:
        name: the data set.
        path: its folder.
        fetched: files downloaded and verified (empty when it was already present).
        not_published: registered files the origin does not publish, so not fetched.
        already_present: the folder already held every file to fetch, as registered.
    """

    name: str
    path: Path
    fetched: tuple[str, ...]
    not_published: tuple[str, ...]
    already_present: bool


def file_url(dataset: DataSet, file: DataFile, base_url: str | None = None) -> str | None:
    """Where to download ``file``: the mirror's copy, else the origin's (None if unpublished)."""
    if base_url is not None:
        return f"{base_url.rstrip('/')}/{quote(dataset.name)}/{quote(file.name)}"
    return dataset.origin_url(file)


def files_to_fetch(
    dataset: DataSet, base_url: str | None = None
) -> tuple[tuple[DataFile, ...], tuple[str, ...]]:
    """The files a fetch downloads, and the names of those it cannot (unpublished at the origin)."""
    wanted = tuple(f for f in dataset.files if file_url(dataset, f, base_url) is not None)
    skipped = tuple(f.name for f in dataset.files if file_url(dataset, f, base_url) is None)
    return wanted, skipped


def fetch(
    name: str,
    dest_dir: str | os.PathLike,
    *,
    base_url: str | None = None,
    timeout: float = 60.0,
    progress: Callable[[int], None] | None = None,
) -> FetchResult:
    """Download every file of data set ``name`` into ``dest_dir/name``, verified, atomically.

    ``base_url`` replaces the pinned origin by a mirror (see the module docstring); ``progress``
    is called with the number of bytes of each chunk received. A folder that already holds every
    file as registered is left alone; one that differs raises :class:`DataError` (move it away
    first: fetch never overwrites data).
    """
    dataset = get(name)
    dest_dir = Path(dest_dir)
    target = dest_dir / dataset.name
    wanted, skipped = files_to_fetch(dataset, base_url)
    if target.exists():
        problems = check_files(target, wanted)
        if problems:
            shown = "; ".join(str(p) for p in problems[:3])
            more = f" and {len(problems) - 3} more" if len(problems) > 3 else ""
            raise DataError(
                f"{target} exists but differs from the registry ({shown}{more}): "
                "move it away and fetch again"
            )
        return FetchResult(dataset.name, target, (), skipped, already_present=True)

    created_dest = not dest_dir.exists()
    dest_dir.mkdir(parents=True, exist_ok=True)
    staging = staging_path(target)
    staging.mkdir(exist_ok=True)
    try:
        # Files a killed fetch finished are kept (the registry vouches for them); others redone.
        unfinished = {mismatch.file for mismatch in check_files(staging, wanted)}
        for file in wanted:
            if file.name not in unfinished:
                if progress is not None:
                    progress(file.size)
                continue
            _download(dataset, file, file_url(dataset, file, base_url), staging, timeout, progress)
        os.rename(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if created_dest and not any(dest_dir.iterdir()):
            dest_dir.rmdir()
        raise
    return FetchResult(
        dataset.name, target, tuple(f.name for f in wanted), skipped, already_present=False
    )


def _download(
    dataset: DataSet,
    file: DataFile,
    url: str,
    staging: Path,
    timeout: float,
    progress: Callable[[int], None] | None,
) -> None:
    """Stream ``url`` into ``staging/file.name``, hashing as it goes; raise on any mismatch."""
    where = f"{dataset.name}/{file.name}"
    path = staging / file.name
    path.parent.mkdir(parents=True, exist_ok=True)
    digest = hashlib.sha256()
    size = 0
    with open(path, "wb") as out:
        try:
            with urllib.request.urlopen(url, timeout=timeout) as response:
                while chunk := response.read(_CHUNK):
                    size += len(chunk)
                    if size > file.size:  # never store more than the pinned file holds
                        break
                    out.write(chunk)
                    digest.update(chunk)
                    if progress is not None:
                        progress(len(chunk))
        except urllib.error.HTTPError as error:
            raise DataError(f"{where}: {url} answered HTTP {error.code} {error.reason}") from None
        except (urllib.error.URLError, TimeoutError, ConnectionError) as error:
            reason = getattr(error, "reason", error)
            raise DataError(f"{where}: cannot download {url}: {reason}") from None
    if size != file.size:
        sent = f"more than {file.size}" if size > file.size else str(size)
        raise DataError(f"{where}: {url} sent {sent} bytes, expected {file.size}; nothing was kept")
    actual = digest.hexdigest()
    if actual != file.sha256:
        raise DataError(
            f"{where}: checksum mismatch for {url}: expected sha256 {file.sha256}, "
            f"got {actual}; nothing was kept"
        )
