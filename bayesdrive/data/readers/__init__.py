"""Readers: every supported format into one validated :class:`Trajectories`.

``read(path)`` detects the format from folder and file names and from CSV header signatures;
``read(path, format=...)`` overrides the detection. One module per format declares its units:

============== ====================================================================
format         source
============== ====================================================================
ngsim_raw      US DOT NGSIM trajectory files (feet), :mod:`.ngsim_raw`
ngsim_chains   NGSIM I-80 6-vehicle chains (m), deduplicated, :mod:`.ngsim_chains`
openacc        JRC OpenACC platoon CSVs (SI), :mod:`.openacc`
highd          highD tracks + meta files (SI, 25 Hz), :mod:`.highd`
interaction    INTERACTION vehicle tracks on a lanelet2 map, :mod:`.interaction`
merge_episodes NGSIM on-ramp merge episodes (ego-centric), :mod:`.merge_episodes`
columns        any table through a column map (incl. the held-out folders), :mod:`.columns`
============== ====================================================================

:data:`FORMATS` also holds the format of every data set whose description
(:mod:`bayesdrive.data.catalog`) gives it a :class:`~bayesdrive.data.catalog.Layout` under a
format name of its own (``openacc_extract``, ``ngsim_pairs``, ...): the layout's reader with the
layout's options. A folder named after such a data set is read through its layout.
"""

from __future__ import annotations

import csv
import functools
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bayesdrive.data.catalog import DATASETS, HOLDOUT, LAYOUTS, Layout
from bayesdrive.data.errors import DataError
from bayesdrive.data.readers._common import open_text, require_regular_file
from bayesdrive.data.readers.columns import read_columns
from bayesdrive.data.readers.highd import read_highd
from bayesdrive.data.readers.interaction import read_interaction
from bayesdrive.data.readers.merge_episodes import read_merge_episodes
from bayesdrive.data.readers.ngsim_chains import read_ngsim_chains
from bayesdrive.data.readers.ngsim_raw import read_ngsim_raw
from bayesdrive.data.readers.openacc import MAX_METADATA_ROWS as OPENACC_METADATA_ROWS
from bayesdrive.data.readers.openacc import read_openacc
from bayesdrive.data.trajectories import Trajectories

__all__ = ["FORMATS", "detect_format", "read"]

_READERS: dict[str, Callable[..., Trajectories]] = {
    "ngsim_raw": read_ngsim_raw,
    "ngsim_chains": read_ngsim_chains,
    "openacc": read_openacc,
    "highd": read_highd,
    "interaction": read_interaction,
    "merge_episodes": read_merge_episodes,
    "columns": read_columns,
}


def _layout_reader(name: str, layout: Layout) -> Callable[..., Trajectories]:
    """The reader behind a data set's own format name: its layout's reader, with the layout."""
    if layout.reader == "columns":
        return functools.partial(read_columns, layout=name)
    return _READERS[layout.reader]


FORMATS: dict[str, Callable[..., Trajectories]] = {
    **_READERS,
    **{
        d.format: _layout_reader(d.name, d.layout)
        for d in (*DATASETS.values(), *HOLDOUT.values())
        if d.layout is not None and d.format not in _READERS
    },
}
# Lines read to recognise a CSV: OpenACC puts metadata rows before its header, as many as its
# reader accepts.
SNIFF_LINES = OPENACC_METADATA_ROWS + 1
# Suffixes of text tables recognised by content (the name decides nothing more).
TEXT_SUFFIXES = (".csv", ".txt", ".dat", ".tsv")


def read(
    path: str | Path, format: str | None = None, *, strict: bool = False, **options: Any
) -> Trajectories:
    """Read ``path`` (file or folder) into validated trajectories.

    ``format`` names a reader in :data:`FORMATS`; without it the format is detected
    (:func:`detect_format`). ``options`` go to the reader (e.g. ``missing_leaders="drop"`` for
    ngsim_raw, ``columns={...}`` for columns). ``strict=True`` refuses, with a :class:`DataError`,
    data that has flags (physically impossible samples such as negative gaps, otherwise kept and
    flagged) or that the reader had to repair (samples or leader links left out: the notes
    starting with ``"repair: "``).
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        require_regular_file(path)
    if format is None:
        format, detected = detect_format(path)
        options = {**detected, **options}
    elif format not in FORMATS:
        raise DataError(f"unknown format {format!r}; known formats: {', '.join(FORMATS)}")
    traj = FORMATS[format](path, **options)
    if strict:
        _refuse_flags_and_repairs(traj, path)
    return traj


def _refuse_flags_and_repairs(traj: Trajectories, path: Path) -> None:
    if len(traj.flags):
        first = traj.flags.iloc[0]
        kinds = traj.flags.groupby("kind").size()
        raise DataError(
            f"{path}: strict mode refuses flagged data: "
            + ", ".join(f"{n} {kind} sample(s)" for kind, n in kinds.items())
            + f"; first: vehicle {first['vehicle_id']} at t={first['t']:g} s: {first['message']}"
        )
    repairs = traj.repairs
    if repairs:
        raise DataError(
            f"{path}: strict mode refuses data that needed {len(repairs)} repair(s); first: "
            f"{repairs[0]}"
        )


def detect_format(path: str | Path) -> tuple[str, dict[str, Any]]:
    """The reader for ``path`` and the options it needs, from names and header signatures.

    Raises a :class:`DataError` listing the known formats and what was seen.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if path.is_dir():
        return _detect_folder(path)
    require_regular_file(path)
    found = _detect_file(path)
    if found is None:
        raise DataError(
            f"{path}: cannot tell the format (first line: {_first_line(path)!r}). Known formats: "
            f"{', '.join(FORMATS)}; pass format=... (columns needs a column map)"
        )
    return found, {}


def _detect_folder(path: Path) -> tuple[str, dict[str, Any]]:
    if path.name in LAYOUTS:
        reader = LAYOUTS[path.name].reader
        return reader, {"layout": path.name} if reader == "columns" else {}
    names = {f.name for f in path.iterdir()}
    if any(n.endswith("_tracks.csv") for n in names) and any(
        n.endswith("_tracksMeta.csv") for n in names
    ):
        return "highd", {}
    if any(re.fullmatch(r"vehicle_tracks_.*\.csv", n) for n in names):
        return "interaction", {}
    if "dataset_with_episode_ids.csv" in names or "dataset.npy" in names:
        return "merge_episodes", {}
    seen = {}
    tables = [f for suffix in TEXT_SUFFIXES for f in sorted(path.glob(f"*{suffix}"))[:20]]
    for file in (f for f in tables if f.is_file()):
        found = _detect_file(file)
        if found is not None:
            return found, {}
        seen[file.name] = _first_line(file)[:80]
    raise DataError(
        f"{path}: cannot tell the format of this folder (files: "
        f"{', '.join(sorted(names)[:10])}{' ...' if len(names) > 10 else ''}; first lines: "
        f"{seen}). Known formats: {', '.join(FORMATS)}; known held-out layouts: "
        f"{', '.join(LAYOUTS)}; pass format=..."
    )


def _first_line(path: Path) -> str:
    try:
        with open_text(path) as handle:
            return handle.readline().strip()
    except (OSError, DataError):
        return ""


def _detect_file(path: Path) -> str | None:
    if path.suffix == ".npy":
        return "merge_episodes"
    if path.name.endswith("_tracks.csv"):
        return "highd"
    if path.suffix.lower() not in TEXT_SUFFIXES:
        return None
    try:
        with open_text(path) as handle:
            lines = [line for _, line in zip(range(SNIFF_LINES), handle, strict=False)]
    except (OSError, DataError):
        return None
    delimiter = "\t" if lines and "\t" in lines[0] and "," not in lines[0] else ","
    rows = list(csv.reader(lines, delimiter=delimiter))
    if not rows:
        return None
    header = {c.strip().lower() for c in rows[0]}
    if {"t1", "id1", "y1", "v1"} <= header:
        return "ngsim_chains"
    if {"vehicle_id", "frame_id", "local_y", "preceding"} <= header:
        return "ngsim_raw"
    if {"track_id", "frame_id", "timestamp_ms", "vx", "vy"} <= header:
        return "interaction"
    if {"episode", "ego_v_mps", "ego_dist_to_accel_lane_end_m"} <= header:
        return "merge_episodes"
    if {"frame", "id", "xvelocity", "precedingid"} <= header:
        return "highd"
    for row in rows:
        if row and row[0].strip() == "Time" and any(c.strip() == "Speed1" for c in row):
            return "openacc"
    tokens = rows[0][0].split() if len(rows[0]) == 1 else []
    if len(tokens) == 18 and all(re.fullmatch(r"-?[\d.]+(e[-+]?\d+)?", t) for t in tokens):
        return "ngsim_raw"  # the original headerless whitespace-separated NGSIM .txt
    return None
