"""Any other trajectory table (CSV or parquet) through an explicit column map.

Units: whatever the caller declares. ``units`` is ``"m"``, ``"ft"`` or a factor to metres (see
:func:`bayesdrive.data.units.to_metres_factor`); it scales every length-based column (positions,
speeds, accelerations, gaps, lengths). The reader never guesses units; feet passed as metres are
refused by the schema checks (lengths > 8 m, jam spacings > 15 m).

Three layouts (``mode``; when not given, ``"pairs"`` for a column map naming ``x_follower``,
else ``"vehicles"``):

- ``"vehicles"``: one row per vehicle and time. Map ``vehicle_id``, ``t``, ``x``, ``v`` and
  optionally ``a``, ``lane_id``, ``leader_id``, ``gap``, ``length``, ``scene_id``. Leader ids
  ``0``, ``-1`` or empty mean none (``no_leader``).
- ``"pairs"``: one row per leader-follower pair and time. Map ``t``, ``x_follower``,
  ``v_follower``, ``x_leader``, ``v_leader`` and optionally ``a_follower``, ``a_leader``,
  ``follower_id``, ``leader_id``, ``length_follower``, ``length_leader``, ``gap``, ``lane_id``,
  ``scene_id``. Without id columns the ids come from ``id_pattern`` (a regex with groups
  ``follower``, ``leader`` and optionally ``scope``, searched in the file stem) or are
  ``"<stem>:follower"``/``"<stem>:leader"``. A car appearing in several pairs (leader here,
  follower there) is merged: its copies must agree.
- ``"wide"``: matrices without header, one column per pair and one row per time step, one file per
  quantity: ``files={"x_leader": ..., "v_leader": ..., "x_follower": ..., "v_follower": ...,
  optional "a_leader", "a_follower"}``; ``dt`` required.

Gaps: a mapped ``gap`` column is used, as a bumper gap (``headway="bumper"``) or front-to-front
(``headway="front"``: minus the leader's length). Without one, the gap is computed from positions,
``x_leader - x - length_leader``, which needs ``x`` to be the FRONT bumper; ``position="centre"``
or ``"rear"`` shifts x by half or a whole length first. Lengths: a vehicle without a length column
value gets the median of its own measured lengths, else ``length`` (4.5 m, noted). Time: ``t`` is
``column * time_factor`` (``0.1`` for 10 Hz frame numbers, ``0.001`` for ms); ``dt=None`` infers
the sampling interval from the median step (noted).

A data set whose folder is read through a column map names it in its description
(:data:`bayesdrive.data.catalog.LAYOUTS`); ``read_columns(folder, layout=name)`` uses it.
"""

from __future__ import annotations

import hashlib
import logging
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from bayesdrive.data.catalog import LAYOUTS, Layout
from bayesdrive.data.errors import DataError
from bayesdrive.data.readers._common import (
    DEFAULT_LENGTH_M,
    Notes,
    exact_ids,
    finish,
    gaps_from_positions,
    harmonise_lengths,
    input_files,
    integer_column,
    make_tracks,
    merge_copies,
    numeric_columns,
    open_text,
    read_table,
    require_columns,
    snap_to_grid,
    time_steps,
)
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.units import to_metres_factor

__all__ = ["MODES", "UNITS", "read_columns", "read_dataframe"]

log = logging.getLogger(__name__)

FORMAT = "columns"
UNITS = "declared by the caller: units='m' | 'ft' | factor to metres; time in s (x time_factor)"
MODES = ("vehicles", "pairs", "wide")
VEHICLE_KEYS = {
    "required": ("vehicle_id", "t", "x", "v"),
    "optional": ("a", "lane_id", "leader_id", "gap", "length", "scene_id"),
}
PAIR_KEYS = {
    "required": ("t", "x_follower", "v_follower", "x_leader", "v_leader"),
    "optional": (
        "a_follower",
        "a_leader",
        "follower_id",
        "leader_id",
        "length_follower",
        "length_leader",
        "gap",
        "lane_id",
        "scene_id",
    ),
}
WIDE_KEYS = {
    "required": ("x_leader", "v_leader", "x_follower", "v_follower"),
    "optional": ("a_leader", "a_follower"),
}
# Copies of one sample from different pair files must agree to float precision (same source).
COPY_TOLERANCE = 1e-6

_DEFAULTS: dict[str, Any] = {
    "columns": None,
    "units": "m",
    "headway": "bumper",
    "position": "front",
    "dt": None,
    "mode": "vehicles",
    "length": DEFAULT_LENGTH_M,
    "time_factor": 1.0,
    "patterns": ("*.csv", "*.parquet"),
    "id_pattern": None,
    "files": None,
    "no_leader": (0, -1),
}


def read_columns(
    path: str | Path,
    columns: Mapping[str, str] | None = None,
    *,
    units: str | float | None = None,
    headway: str | None = None,
    dt: float | None = None,
    mode: str | None = None,
    layout: str | Mapping[str, Any] | None = None,
    position: str | None = None,
    length: float | None = None,
    time_factor: float | None = None,
    patterns: Sequence[str] | None = None,
    id_pattern: str | None = None,
    files: Mapping[str, str] | None = None,
    no_leader: Sequence[Any] | None = None,
) -> Trajectories:
    """Read a table (file or folder) through a column map; see the module docstring.

    ``layout`` names a data set with a layout (:data:`bayesdrive.data.catalog.LAYOUTS`), or is a
    :class:`~bayesdrive.data.catalog.Layout` or a dict of these options (with ``format`` naming
    another reader to hand the path to); explicit arguments override it.
    """
    given = {
        "columns": columns,
        "units": units,
        "headway": headway,
        "dt": dt,
        "mode": mode,
        "position": position,
        "length": length,
        "time_factor": time_factor,
        "patterns": patterns,
        "id_pattern": id_pattern,
        "files": files,
        "no_leader": no_leader,
    }
    preset: dict[str, Any] = {}
    if isinstance(layout, str):
        if layout not in LAYOUTS:
            raise DataError(f"unknown layout {layout!r}; known: {', '.join(sorted(LAYOUTS))}")
        layout = LAYOUTS[layout]
    if isinstance(layout, Layout):
        preset = {"format": layout.reader, **layout.reader_options()}
    elif layout is not None:
        preset = dict(layout)
    if preset.get("format", FORMAT) != FORMAT:
        from bayesdrive.data.readers import FORMATS  # that module imports this one

        return FORMATS[preset["format"]](path)
    options = {**_DEFAULTS}
    options.update({k: v for k, v in preset.items() if k in _DEFAULTS})
    options.update({k: v for k, v in given.items() if v is not None})
    if "mode" not in preset and mode is None and "x_follower" in (options["columns"] or {}):
        options["mode"] = "pairs"
    return _read(Path(path), **options)


def read_dataframe(
    frame: pd.DataFrame,
    columns: Mapping[str, str],
    *,
    mode: str = "vehicles",
    units: str | float = "m",
    name: str = "dataframe",
    **options: Any,
) -> Trajectories:
    """A pandas DataFrame in layout ``mode`` ("vehicles" or "pairs") through the column map
    ``columns``, exactly as :func:`read_columns` reads a file of the same columns (same options,
    same checks, same repairs). Messages name the frame ``name`` and a row by its position
    (``frame.iloc[row]``); the result's ``source`` is ``name``."""
    if mode not in ("vehicles", "pairs"):
        raise DataError(f"{name}: a DataFrame is read in mode 'vehicles' or 'pairs', not {mode!r}")
    known = sorted(set(_DEFAULTS) - {"columns", "mode", "units", "patterns", "files"})
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise DataError(f"{name}: unknown DataFrame option(s) {unknown}; known: {', '.join(known)}")
    table = frame.reset_index(drop=True).assign(_row=np.arange(len(frame)), _file=name)
    settings = {**_DEFAULTS, **options, "columns": columns, "mode": mode, "units": units}
    # sha256 of the frame's values and index, so a result records which table it was fitted on.
    digest = hashlib.sha256(pd.util.hash_pandas_object(frame, index=True).to_numpy().tobytes())
    return _read(Path(name), tables=[table], table_digests={name: digest.hexdigest()}, **settings)


def _read(
    path: Path,
    *,
    tables: list[pd.DataFrame] | None = None,
    table_digests: Mapping[str, str] | None = None,
    columns,
    units,
    headway,
    position,
    dt,
    mode,
    length,
    time_factor,
    patterns,
    id_pattern,
    files,
    no_leader,
) -> Trajectories:
    if mode not in MODES:
        raise DataError(f"mode must be one of {MODES}, got {mode!r}")
    if headway not in ("bumper", "front"):
        raise DataError(f"headway must be 'bumper' or 'front', got {headway!r}")
    if position not in ("front", "centre", "rear"):
        raise DataError(f"position must be 'front', 'centre' or 'rear', got {position!r}")
    factor = to_metres_factor(str(units))
    notes = Notes(log)
    notes.assume(
        f"columns ({mode}): lengths, speeds and accelerations scaled by {factor:.6g} to metres "
        f"(units={units!r}); headway={headway!r}; position={position!r}"
    )
    if mode == "wide":
        tracks, dt = _wide(path, files, factor, dt, notes)
    else:
        keys = VEHICLE_KEYS if mode == "vehicles" else PAIR_KEYS
        if not columns:
            raise DataError(
                f"{path}: the columns reader needs a column map: columns={{...}} with keys "
                f"{', '.join(keys['required'])} (optional: {', '.join(keys['optional'])})"
            )
        unknown = set(columns) - set(keys["required"]) - set(keys["optional"])
        missing = [k for k in keys["required"] if k not in columns]
        if unknown or missing:
            raise DataError(
                f"column map for mode {mode!r}: "
                + (f"missing {', '.join(missing)}; " if missing else "")
                + (f"unknown keys {', '.join(sorted(unknown))}; " if unknown else "")
                + f"expected {', '.join(keys['required'])} (optional: "
                + f"{', '.join(keys['optional'])})"
            )
        ids = ("vehicle_id", "leader_id", "follower_id", "scene_id")
        text = [name for key, name in columns.items() if key in ids]
        if tables is None:
            sources = input_files(path, patterns, what="trajectory")
            tables = [
                read_table(f, fmt="trajectory", notes=notes, text_columns=text) for f in sources
            ]
        else:
            sources = [path] * len(tables)
            # Ids are kept as exact text, as the file reader keeps them.
            tables = [_ids_as_text(table, text) for table in tables]
        frames = [_with_time(table, columns, time_factor) for table in tables]
        if dt is None:
            dt = _infer_dt(frames, columns, mode, notes)
        maker = _vehicles if mode == "vehicles" else _pairs
        parts = [
            maker(
                f,
                frame,
                columns,
                factor,
                dt,
                id_pattern=id_pattern,
                no_leader=no_leader,
                notes=notes,
            )
            for f, frame in zip(sources, frames, strict=True)
        ]
        tracks = pd.concat(parts, ignore_index=True)
    scenes = (
        tracks[["_scene", "vehicle_id"]]
        .rename(columns={"_scene": "scene_id"})
        .drop_duplicates()
        .reset_index(drop=True)
    )
    if mode == "pairs":
        tracks = merge_copies(
            tracks,
            tolerances={c: COPY_TOLERANCE for c in ("x", "v", "_length")},
            notes=notes,
            what="pairs",
        )
    tracks = _finish_tracks(
        tracks, headway=headway, position=position, dt=dt, length=length, notes=notes
    )
    names = {
        k: v for k, v in (columns or {}).items() if k in ("vehicle_id", "t", "x", "v", "a", "gap")
    }
    return finish(
        tracks.drop(columns=["_scene"]),
        fmt=FORMAT,
        source=path,
        dt=dt,
        scenes=scenes,
        notes=notes,
        column_names=names,
        file_units=dict.fromkeys(("x", "v", "a", "gap", "length"), factor),
        measured_gap=mode != "wide" and "gap" in columns,
        table_digests=table_digests,
    )


def _ids_as_text(frame: pd.DataFrame, id_columns: list[str]) -> pd.DataFrame:
    """``frame`` with its id columns as strings; float ids are refused (they may have lost digits)."""
    frame = frame.copy()
    for column in id_columns:
        if column not in frame.columns:
            continue
        values = frame[column]
        if pd.api.types.is_float_dtype(values):
            raise DataError(
                f"{frame['_file'].iloc[0]}, column {column!r}: ids are floats, which may have "
                "lost digits; pass them as integers or strings"
            )
        frame[column] = values.where(values.isna(), values.astype(str))
    return frame


def _with_time(frame: pd.DataFrame, columns: Mapping[str, str], time_factor: float) -> pd.DataFrame:
    """``frame`` (with ``_row`` and ``_file``) checked for the mapped columns, time in ``_t``."""
    source = frame["_file"].iloc[0] if len(frame) else "table"
    if frame.empty:
        raise DataError(f"{source}: no data rows")
    require_columns(frame, list(dict.fromkeys(columns.values())), source=source, fmt="mapped")
    time_column = columns["t"]
    numeric_columns(frame, [time_column])
    frame["_t"] = frame[time_column] * float(time_factor)
    return frame


def _infer_dt(frames: list[pd.DataFrame], columns, mode: str, notes: Notes) -> float:
    steps = []
    for frame in frames:
        key = columns.get("vehicle_id" if mode == "vehicles" else "follower_id")
        t = frame["_t"]
        diffs = t.groupby(frame[key]).diff() if key else t.diff()
        steps.append(diffs[diffs > 0].to_numpy())
    joined = np.concatenate(steps) if steps else np.array([])
    if not len(joined):
        raise DataError("cannot infer the sampling interval (no vehicle has two samples); pass dt=")
    dt = float(np.round(np.median(joined), 6))
    notes.assume(f"sampling interval inferred from the median time step: dt = {dt} s")
    return dt


def _ids(frame: pd.DataFrame, column: str) -> pd.Series:
    """Ids as exact strings (:func:`exact_ids`); None where missing."""
    ids = exact_ids(frame, column)
    return ids.where(ids.notna(), None)


def _required_ids(frame: pd.DataFrame, column: str) -> np.ndarray:
    ids = _ids(frame, column)
    missing = ids.isna().to_numpy()
    if missing.any():
        first = int(np.argmax(missing))
        raise DataError(
            f"{frame['_file'].iloc[first]}, row {frame['_row'].iloc[first]}, column {column!r}: "
            "vehicle id is empty"
        )
    return ids.to_numpy()


def _none_leaders(leaders: pd.Series, no_leader: Sequence[Any]) -> pd.Series:
    empty = {str(v) for v in no_leader} | {""}
    return leaders.where(leaders.notna() & ~leaders.isin(empty), None)


def _optional(frame: pd.DataFrame, columns, key: str, factor: float = 1.0, default=np.nan):
    if key not in columns:
        return default
    numeric_columns(frame, [columns[key]], allow_nan=[columns[key]])
    return frame[columns[key]].to_numpy() * factor


def _vehicles(path, frame, columns, factor, dt, *, no_leader, **_) -> pd.DataFrame:
    numeric_columns(frame, [columns["x"], columns["v"]])
    steps = snap_to_grid(frame["_t"], dt, frame, column=columns["t"])
    leader = (
        _none_leaders(_ids(frame, columns["leader_id"]), no_leader)
        if "leader_id" in columns
        else None
    )
    tracks = make_tracks(
        vehicle_id=_required_ids(frame, columns["vehicle_id"]),
        t=time_steps(steps, dt),
        x=frame[columns["x"]].to_numpy() * factor,
        v=frame[columns["v"]].to_numpy() * factor,
        a=_optional(frame, columns, "a", factor),
        lane_id=_lanes(frame, columns),
        leader_id=None if leader is None else leader.to_numpy(),
        gap=_optional(frame, columns, "gap", factor),
        length=np.nan,
        row=frame["_row"].to_numpy(),
        file=str(path),
    )
    tracks["_length"] = _optional(frame, columns, "length", factor)
    tracks["_has_gap"] = "gap" in columns
    tracks["_scene"] = (
        _ids(frame, columns["scene_id"]).to_numpy() if "scene_id" in columns else path.stem
    )
    return tracks


def _lanes(frame, columns):
    if "lane_id" not in columns:
        return pd.NA
    column = columns["lane_id"]
    numeric_columns(frame, [column], allow_nan=[column])
    known = frame[column].notna().to_numpy()
    lanes = pd.array(np.full(len(frame), pd.NA), dtype="Int64")
    lanes[known] = integer_column(frame[known], column)
    return lanes


def _pair_ids(path: Path, frame, columns, id_pattern) -> tuple[np.ndarray, np.ndarray]:
    if "follower_id" in columns and "leader_id" in columns:
        return (
            _required_ids(frame, columns["follower_id"]),
            _required_ids(frame, columns["leader_id"]),
        )
    if id_pattern:
        match = re.search(id_pattern, path.stem)
        if not match:
            raise DataError(f"{path}: file name does not match the id pattern {id_pattern!r}")
        scope = match.groupdict().get("scope")
        prefix = f"{scope}:" if scope else ""
        n = len(frame)
        return (
            np.full(n, prefix + match.group("follower"), dtype=object),
            np.full(n, prefix + match.group("leader"), dtype=object),
        )
    n = len(frame)
    return (
        np.full(n, f"{path.stem}:follower", dtype=object),
        np.full(n, f"{path.stem}:leader", dtype=object),
    )


def _pairs(path, frame, columns, factor, dt, *, id_pattern, notes, **_) -> pd.DataFrame:
    required = [columns[k] for k in ("x_follower", "v_follower", "x_leader", "v_leader")]
    numeric_columns(frame, required)
    steps = snap_to_grid(frame["_t"], dt, frame, column=columns["t"])
    follower, leader = _pair_ids(path, frame, columns, id_pattern)
    # Copies are merged in time order below; a pair's rows out of order are a repair to record.
    back = (frame["_t"].groupby(follower).diff() < 0).to_numpy()
    if back.any():
        notes.repair(
            f"{path.name}: rows of a pair are not in time order (first out of place: row "
            f"{frame['_row'].iloc[int(np.argmax(back))]}); sorted by time"
        )
    scene = _ids(frame, columns["scene_id"]).to_numpy() if "scene_id" in columns else path.stem
    t = time_steps(steps, dt)
    lanes = _lanes(frame, columns)
    common = {"t": t, "row": frame["_row"].to_numpy(), "file": str(path)}

    def role_tracks(role: str, vehicle_id: np.ndarray, **follows: Any) -> pd.DataFrame:
        """The rows of one role (follower or leader), its length kept aside in ``_length``."""
        tracks = make_tracks(
            vehicle_id=vehicle_id,
            x=frame[columns[f"x_{role}"]].to_numpy() * factor,
            v=frame[columns[f"v_{role}"]].to_numpy() * factor,
            a=_optional(frame, columns, f"a_{role}", factor),
            lane_id=lanes,
            length=np.nan,
            **follows,
            **common,
        )
        tracks["_length"] = _optional(frame, columns, f"length_{role}", factor)
        return tracks

    follows = role_tracks(
        "follower", follower, leader_id=leader, gap=_optional(frame, columns, "gap", factor)
    )
    tracks = pd.concat([follows, role_tracks("leader", leader)], ignore_index=True)
    tracks["_has_gap"] = "gap" in columns
    tracks["_scene"] = np.concatenate([np.broadcast_to(scene, len(frame))] * 2)
    tracks["_k"] = np.concatenate([steps, steps])
    return tracks


def _wide(path: Path, files, factor: float, dt, notes: Notes) -> tuple[pd.DataFrame, float]:
    if not files:
        raise DataError(
            f"{path}: mode 'wide' needs files={{quantity: file name}} with keys "
            f"{', '.join(WIDE_KEYS['required'])} (optional: {', '.join(WIDE_KEYS['optional'])})"
        )
    if dt is None:
        raise DataError(f"{path}: mode 'wide' has no time column; pass dt=")
    folder = path if path.is_dir() else path.parent
    missing = [k for k in WIDE_KEYS["required"] if k not in files]
    if missing:
        raise DataError(f"files map for mode 'wide' lacks {', '.join(missing)}")
    matrices = {}
    for key, name in files.items():
        file = folder / name
        if not file.exists():
            raise DataError(f"{file}: no such file (wide layout quantity {key!r})")
        matrices[key] = _read_matrix(file, notes)
    shapes = {k: m.shape for k, m in matrices.items()}
    if len(set(shapes.values())) > 1:
        raise DataError(f"{folder}: wide matrices differ in shape: {shapes}")
    rows, pairs = next(iter(shapes.values()))
    steps = np.arange(rows)
    t = time_steps(steps, dt)
    parts = []
    for j in range(pairs):
        pair = f"pair{j + 1}"
        for role, other in (("follower", "leader"), ("leader", None)):
            acc = matrices.get(f"a_{role}")
            parts.append(
                make_tracks(
                    vehicle_id=f"{pair}:{role}",
                    t=t,
                    x=matrices[f"x_{role}"][:, j] * factor,
                    v=matrices[f"v_{role}"][:, j] * factor,
                    a=np.nan if acc is None else acc[:, j] * factor,
                    leader_id=f"{pair}:{other}" if other else None,
                    length=np.nan,
                    row=steps + 1,
                    file=str(folder / files[f"x_{role}"]),
                ).assign(_length=np.nan, _has_gap=False, _scene=pair)
            )
    notes.assume(
        f"wide layout: {pairs} pairs x {rows} steps; column j of every matrix is pair j "
        "(ids pair<j>:leader / pair<j>:follower)"
    )
    return pd.concat(parts, ignore_index=True), dt


def _read_matrix(file: Path, notes: Notes) -> np.ndarray:
    """A headerless numeric matrix; its columns are named 1, 2, ... in error messages."""
    with open_text(file) as handle:
        first = handle.readline()
    if not first.strip():
        raise DataError(f"{file}: empty file (expected a wide matrix)")
    names = [str(j + 1) for j in range(len(first.split(",")))]
    frame = read_table(file, names=names, fmt="wide matrix", notes=notes)
    numeric_columns(frame, names)
    return frame[names].to_numpy(dtype=float)


def _finish_tracks(
    tracks: pd.DataFrame, *, headway: str, position: str, dt: float, length: float, notes: Notes
) -> pd.DataFrame:
    """Lengths per vehicle, x at the front bumper, gaps from the gap column or from positions."""
    tracks = tracks.reset_index(drop=True)
    tracks["length"] = harmonise_lengths(
        tracks, tracks["_length"], default=float(length), notes=notes, what="columns"
    )
    measured = tracks["_length"].notna()
    tracks.loc[measured, "length"] = tracks.loc[measured, "_length"]
    if position == "centre":
        tracks["x"] = tracks["x"] + tracks["length"] / 2
    elif position == "rear":
        tracks["x"] = tracks["x"] + tracks["length"]
    has_leader = tracks["leader_id"].notna()
    from_column = tracks["_has_gap"].astype(bool) & has_leader & tracks["gap"].notna()
    if headway == "front" and from_column.any():
        leader_length = tracks["leader_id"].map(tracks.groupby("vehicle_id")["length"].median())
        tracks.loc[from_column, "gap"] -= leader_length[from_column]
    derived = gaps_from_positions(tracks, dt)
    need = has_leader & ~from_column
    tracks.loc[need, "gap"] = derived[need]
    lost = need & tracks["gap"].isna()
    if lost.any():
        notes.repair(
            f"{int(lost.sum())} sample(s) name a leader with no sample at that time and no gap "
            "column value; leader link left out there"
        )
        tracks.loc[lost, "leader_id"] = None
    return tracks.drop(columns=["_length", "_has_gap"] + (["_k"] if "_k" in tracks else []))
