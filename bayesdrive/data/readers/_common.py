"""Helpers every reader shares, so no reader re-implements them.

Reading: :func:`input_files` (a file or a folder), :func:`open_text` (a regular text file, BOM
removed), :func:`read_table` (CSV, tab-separated or parquet, with the 1-based source line number of
every row in ``_row`` and the file in ``_file``), :func:`require_columns`, :func:`numeric_columns`
(non-numbers and NaN are errors naming file, row and column), :func:`integer_ids` and
:func:`integer_column` (ids kept as exact strings, frames refused unless whole numbers),
:func:`sort_rows` (time-ordered formats put in order, a logged repair), :func:`snap_to_grid` (times
onto the ``dt`` grid). Building: :func:`make_tracks` (a schema table with defaults),
:func:`integrate_speed`, :func:`leader_values`, :func:`gaps_from_positions`,
:func:`harmonise_lengths`, :func:`merge_copies` (samples present in several files). Ending:
:func:`finish` (the checks of :mod:`bayesdrive.data.validate`, input checksums, wrap in
:class:`Trajectories`). Every repair goes through :class:`Notes`, which logs it as a warning and
records it in ``Trajectories.notes``.
"""

from __future__ import annotations

import csv
import hashlib
import logging
import re
import stat
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple, TextIO

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import FLAG_COLUMNS, REPAIR_PREFIX, Trajectories
from bayesdrive.data.validate import check_tracks, leader_values, plain

__all__ = [
    "DEFAULT_LENGTH_M",
    "REPAIR_PREFIX",
    "FileFormat",
    "Notes",
    "exact_ids",
    "finish",
    "finish_parts",
    "gaps_from_positions",
    "harmonise_lengths",
    "input_files",
    "integer_column",
    "integer_ids",
    "integrate_speed",
    "leader_values",
    "make_tracks",
    "merge_copies",
    "numeric_columns",
    "open_text",
    "read_checked_table",
    "read_table",
    "require_columns",
    "require_regular_file",
    "snap_to_grid",
    "sort_rows",
    "time_steps",
]

# Length assumed where a source gives none: a typical passenger car (NGSIM I-80 cars are ~4.5 m).
DEFAULT_LENGTH_M = 4.5
# A time this far off the dt grid (in units of dt) is not float rounding but a wrong sampling rate.
GRID_TOLERANCE = 1e-3
# Frame numbers, lanes and episodes: a frame beyond this, at 10-25 Hz, has a time (frame x dt, in
# float64) that no longer resolves its step to GRID_TOLERANCE (and int64 overflows at 9.2e18), and
# no lane or episode is numbered so high.
MAX_WHOLE_NUMBER = 1e12
# An integer written by a float writer ("17.0") is the integer; leading zeros and "+" are dropped.
_INTEGER_TEXT = re.compile(r"(?P<sign>[+-]?)0*(?P<digits>\d+)(?:\.0*)?")


class Notes:
    """Documented assumptions and repairs of one read; repairs are also logged as warnings."""

    def __init__(self, logger: logging.Logger) -> None:
        self.items: list[str] = []
        self._log = logger

    def assume(self, message: str, *, warn: bool = False) -> None:
        """Record an assumption or interpretation (an assumed length, an inferred layout).

        ``warn`` also logs it, for interpretations a user should notice (approximate placement).
        """
        if message not in self.items:
            if warn:
                self._log.warning(message)
            self.items.append(message)

    def repair(self, message: str) -> None:
        """Record and log a change to the data: samples or leader links left out or replaced."""
        self._log.warning(message)
        self.items.append(REPAIR_PREFIX + message)


def require_regular_file(path: Path) -> None:
    """Refuse anything but a regular file: opening a named pipe or a device would hang or stream."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not stat.S_ISREG(mode):
        raise DataError(
            f"{path}: not a regular file (a named pipe, socket or device?); give a file"
        )


def open_text(path: Path) -> TextIO:
    """Open a regular file as text; a UTF-8 byte-order mark is removed, bad bytes replaced."""
    require_regular_file(path)
    return path.open("r", encoding="utf-8-sig", errors="replace", newline="")


def input_files(path: str | Path, patterns: Sequence[str], *, what: str) -> list[Path]:
    """The file ``path`` itself, or the files in folder ``path`` matching ``patterns`` (sorted)."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if not path.is_dir():
        require_regular_file(path)
        return [path]
    found = sorted({f for pattern in patterns for f in path.glob(pattern) if f.is_file()})
    if not found:
        raise DataError(
            f"{path}: no {what} files in this folder (looked for {', '.join(patterns)})"
        )
    return found


def _head(path: Path, count: int) -> list[str]:
    with open_text(path) as handle:
        return [line.rstrip("\r\n") for _, line in zip(range(count), handle, strict=False)]


def read_table(
    path: Path,
    *,
    notes: Notes,
    header_line: int = 0,
    names: Sequence[str] | None = None,
    sep: str | None = None,
    text_columns: Iterable[str] | Callable[[str], bool] = (),
    fmt: str,
) -> pd.DataFrame:
    """Read a table whose header is on 0-based line ``header_line``.

    The columns named in ``text_columns`` (case-insensitive; or those it accepts, if a function)
    are read as text, so ids keep every digit (:func:`integer_ids`); :func:`numeric_columns`
    checks and converts the number columns. ``sep`` None takes a tab when the header has tabs and
    no commas, else a comma. A UTF-8 byte-order mark is removed. Adds ``_row`` (1-based line number in
    the file, header included, so row 2 is the first data row of a file with a header on line 1)
    and ``_file``. ``names`` reads a file without a header. Blank lines are dropped with a logged
    note (line numbers stay true); data rows ending in one more, empty field than the header (a
    trailing comma) are read without it, noted; a non-empty extra field is an error.
    """
    path = Path(path)
    require_regular_file(path)
    if path.suffix == ".parquet":
        try:
            frame = pd.read_parquet(path)
        except Exception as exc:  # pyarrow raises several types for a broken file
            raise DataError(f"{path}: cannot read as parquet ({exc})") from None
        frame["_row"] = np.arange(len(frame)) + 1
        frame["_file"] = str(path)
        if frame.empty:
            raise DataError(f"{path}: no data rows")
        return frame
    head = _head(path, header_line + 12)
    if sep is None:
        header_text = head[header_line] if len(head) > header_line else ""
        sep = "\t" if "\t" in header_text and "," not in header_text else ","
    columns = list(names) if names is not None else None
    trailing = False
    data_lines = [line for line in head[header_line + 1 :] if line.strip()]
    if names is None and sep != r"\s+" and data_lines:
        header = next(csv.reader([head[header_line]], delimiter=sep))
        first = next(csv.reader(data_lines[:1], delimiter=sep))
        # pandas would take the extra first field for an index and shift every column.
        if len(first) == len(header) + 1:
            trailing = True
            columns = [c.strip() for c in header] + ["_trailing"]
    if not callable(text_columns):
        wanted = {str(c).lower() for c in text_columns}
        text_columns = lambda name: name.lower() in wanted  # noqa: E731
    if columns is not None:
        seen_names = columns
    elif sep == r"\s+":
        seen_names = head[header_line].split() if len(head) > header_line else []
    else:
        seen_names = next(csv.reader([head[header_line]], delimiter=sep), [])
    text = {c: str for c in seen_names if text_columns(c.strip())}
    try:
        frame = pd.read_csv(
            path,
            skiprows=header_line + (1 if trailing else 0),
            header=None if columns is not None else 0,
            names=columns,
            sep=sep,
            dtype=text or None,
            index_col=False,
            encoding="utf-8-sig",
            skip_blank_lines=False,
            low_memory=False,
        )
    except pd.errors.EmptyDataError:
        raise DataError(f"{path}: empty file (expected a {fmt} table)") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot parse as a {fmt} table ({exc})") from None
    first_data_line = header_line + (1 if names is not None else 2)
    frame.columns = [c.strip() if isinstance(c, str) else c for c in frame.columns]
    frame.index = pd.RangeIndex(len(frame)) + first_data_line
    if trailing:
        extra = frame["_trailing"].notna() & (frame["_trailing"].astype(str).str.strip() != "")
        if extra.any():
            raise DataError(
                f"{path}, row {extra.idxmax()}: {len(columns)} fields but the header has "
                f"{len(columns) - 1} (a stray delimiter?)"
            )
        frame = frame.drop(columns="_trailing")
        notes.assume(
            f"{path.name}: data rows end with a trailing delimiter (one empty field more than the "
            "header); the empty last field is ignored",
            warn=True,
        )
    blank = frame.isna().all(axis=1)
    if blank.any():
        lines = list(frame.index[blank])
        notes.assume(
            f"{path.name}: {len(lines)} blank line(s) skipped (line(s) "
            f"{', '.join(map(str, lines[:10]))}{' ...' if len(lines) > 10 else ''})",
            warn=True,
        )
        frame = frame[~blank]
    if frame.empty:
        raise DataError(f"{path}: no data rows (empty file or nothing left after the header)")
    where = pd.DataFrame({"_row": frame.index, "_file": str(path)}, index=frame.index)
    return pd.concat([frame, where], axis=1).reset_index(drop=True)


def require_columns(
    frame: pd.DataFrame, required: Iterable[str], *, source: str | Path, fmt: str
) -> None:
    """Raise a :class:`DataError` naming the missing columns and what the format expects."""
    required = list(required)
    missing = [c for c in required if c not in frame.columns]
    if missing:
        seen = [c for c in frame.columns if c not in ("_row", "_file")]
        raise DataError(
            f"{source}: not a {fmt} table: missing column(s) {', '.join(map(str, missing))}. "
            f"Expected columns: {', '.join(required)}; found: {', '.join(map(str, seen[:20]))}"
            + (" ..." if len(seen) > 20 else "")
        )


def read_checked_table(
    path: Path,
    required: Sequence[str],
    numeric: Iterable[str] | None = None,
    *,
    fmt: str,
    notes: Notes,
    **options: Any,
) -> pd.DataFrame:
    """:func:`read_table` (``options`` go to it) of a table that must hold the ``required``
    columns (:func:`require_columns`), the ``numeric`` ones (default: all required) numbers
    (:func:`numeric_columns`)."""
    frame = read_table(path, fmt=fmt, notes=notes, **options)
    require_columns(frame, required, source=path, fmt=fmt)
    numeric_columns(frame, required if numeric is None else numeric)
    return frame


def _first_bad(frame: pd.DataFrame, bad: np.ndarray) -> tuple[object, object]:
    index = int(np.argmax(bad))
    return frame["_row"].iloc[index], frame["_file"].iloc[index]


def numeric_columns(
    frame: pd.DataFrame, columns: Iterable[str], *, allow_nan: Iterable[str] = ()
) -> pd.DataFrame:
    """Convert ``columns`` to float, raising on non-numbers and NaN with file, row and column.

    Columns in ``allow_nan`` may hold NaN (the caller handles it), but never text that is not a
    number.
    """
    allow_nan = set(allow_nan)
    for column in columns:
        raw = frame[column]
        if isinstance(raw.dtype, pd.CategoricalDtype):  # parquet files store codes as categories
            raw = raw.astype(object)
        values = pd.to_numeric(raw, errors="coerce").astype(float)
        not_number = values.isna().to_numpy() & raw.notna().to_numpy()
        if not_number.any():
            row, file = _first_bad(frame, not_number)
            text = raw.iloc[int(np.argmax(not_number))]
            raise DataError(f"{file}, row {row}, column {column!r}: not a number: {text!r}")
        if column not in allow_nan:
            bad = ~np.isfinite(values.to_numpy())
            if bad.any():
                row, file = _first_bad(frame, bad)
                raise DataError(
                    f"{file}, row {row}, column {column!r}: value is NaN, empty or infinite "
                    f"({int(bad.sum())} such row(s) in this column)"
                )
        frame[column] = values
    return frame


def exact_ids(frame: pd.DataFrame, column: str) -> pd.Series:
    """The ids of ``column`` as exact text (object dtype); missing stays missing.

    Whole numbers lose what a float writer or padding adds ("0017", "+17", "17.0" are "17");
    other text is kept, stripped. A typed float id (parquet) above 2**53 cannot be exact: an error
    naming file, row and column. (Read id columns as text: :func:`read_table`'s ``text_columns``.)
    """
    raw = frame[column]
    if isinstance(raw.dtype, pd.CategoricalDtype):  # parquet files store codes as categories
        raw = raw.astype(object)
    codes, uniques = pd.factorize(raw)
    canonical = []
    for index, value in enumerate(uniques):
        try:
            canonical.append(_exact_id(value))
        except ValueError as exc:
            row, file = _first_bad(frame, codes == index)
            raise DataError(f"{file}, row {row}, column {column!r}: {exc}") from None
    # factorize marks missing values with -1: the appended None.
    return pd.Series(np.array([*canonical, None], dtype=object)[codes], index=frame.index)


def _exact_id(value: object) -> str:
    if isinstance(value, float | np.floating):
        if abs(value) > 2**53:
            raise ValueError(
                f"id {plain(value)} is stored as a float too large to be exact; store ids as "
                "integers or text"
            )
        value = int(value) if float(value).is_integer() else value
    text = str(value).strip()
    whole = _INTEGER_TEXT.fullmatch(text)
    if not whole:
        return text
    digits = whole.group("digits")
    return "-" + digits if whole.group("sign") == "-" and digits != "0" else digits


def integer_ids(frame: pd.DataFrame, column: str) -> np.ndarray:
    """The integer ids of ``column`` as exact strings (:func:`exact_ids`): never through a float,
    where 17 digits collide and 30 overflow. Empty cells and text that is not a whole number are
    errors naming file, row and column."""
    ids = exact_ids(frame, column)
    bad = ~ids.map(lambda v: isinstance(v, str) and _INTEGER_TEXT.fullmatch(v) is not None)
    bad = bad.to_numpy(dtype=bool)
    if bad.any():
        row, file = _first_bad(frame, bad)
        value = frame[column].iloc[int(np.argmax(bad))]
        shown = repr(value) if isinstance(value, str) else plain(value)
        what = "empty" if pd.isna(value) else f"not a whole number: {shown}"
        raise DataError(f"{file}, row {row}, column {column!r}: id is {what}")
    return ids.to_numpy(dtype=object)


def integer_column(frame: pd.DataFrame, column: str) -> np.ndarray:
    """A numeric column (already through :func:`numeric_columns`) as int64; a fraction refuses.

    Frame numbers and lane ids are whole numbers: ``100.5`` is a damaged cell, not frame 100.
    """
    values = frame[column].to_numpy(dtype=float)
    fractional = values != np.round(values)
    if fractional.any():
        row, file = _first_bad(frame, fractional)
        raise DataError(
            f"{file}, row {row}, column {column!r}: {plain(values[int(np.argmax(fractional))])} "
            "is not a whole number"
        )
    too_large = np.abs(values) > MAX_WHOLE_NUMBER
    if too_large.any():
        row, file = _first_bad(frame, too_large)
        raise DataError(
            f"{file}, row {row}, column {column!r}: {plain(values[int(np.argmax(too_large))])} "
            f"is out of range: frame, lane and episode numbers stay within +-{MAX_WHOLE_NUMBER:g} "
            "(a larger one overflows or loses the step between frames); a damaged cell?"
        )
    return values.astype(np.int64)


def sort_rows(
    frame: pd.DataFrame, by: Sequence[str], *, notes: Notes, path: Path, what: str
) -> pd.DataFrame:
    """``frame`` in the order of ``by`` (numeric columns); rows out of order are a logged repair.

    For formats whose rows are time steps (a shuffled file is still the same recording).
    """
    ordered = frame.sort_values(list(by), kind="stable")
    moved = ordered["_row"].to_numpy() != frame["_row"].to_numpy()
    if moved.any():
        first = frame["_row"].iloc[int(np.argmax(moved))]
        notes.repair(
            f"{path.name}: rows are not in {what} order (first out of place: row {first}); "
            f"{int(moved.sum())} row(s) sorted by {', '.join(by)}"
        )
    return ordered.reset_index(drop=True)


def snap_to_grid(
    times: pd.Series | np.ndarray, dt: float, frame: pd.DataFrame, *, column: str
) -> np.ndarray:
    """Integer step numbers ``round(t / dt)``; a time off the grid is an error naming its row.

    Removes the float rounding of time columns (``0.30000000000000004``, ``208970.39999997``)
    while refusing data sampled at another rate.
    """
    ratio = np.asarray(times, dtype=float) / dt
    steps = np.round(ratio)
    off = np.abs(ratio - steps) > GRID_TOLERANCE
    if off.any():
        row, file = _first_bad(frame, off)
        index = int(np.argmax(off))
        # The file's own value where the column is there (times may be shifted or scaled).
        value = frame[column].iloc[index] if column in frame.columns else np.asarray(times)[index]
        raise DataError(
            f"{file}, row {row}, column {column!r}: time {plain(value)} is not on the "
            f"{plain(dt)} s grid (expected samples every {plain(dt)} s)"
        )
    return steps.astype(np.int64)


def time_steps(steps: np.ndarray, dt: float) -> np.ndarray:
    """Times of integer step numbers, rounded so equal steps give bit-equal times."""
    return np.round(np.asarray(steps, dtype=np.int64) * dt, 9)


def make_tracks(
    *,
    vehicle_id,
    t,
    x,
    v,
    length,
    a=np.nan,
    lane_id=pd.NA,
    leader_id=None,
    gap=np.nan,
    driver="unknown",
    row=None,
    file=None,
) -> pd.DataFrame:
    """A table with every schema column, defaults filled in (no acceleration, lane or leader)."""
    tracks = pd.DataFrame(
        {
            "vehicle_id": vehicle_id,
            "t": t,
            "x": x,
            "v": v,
            "a": a,
            "lane_id": lane_id,
            "leader_id": leader_id,
            "gap": gap,
            "length": length,
            "driver": driver,
        }
    )
    tracks["vehicle_id"] = tracks["vehicle_id"].astype(str)
    leaders = tracks["leader_id"].astype(object)
    tracks["leader_id"] = leaders.where(leaders.notna(), None)
    if row is not None:
        tracks["_row"] = row
    if file is not None:
        tracks["_file"] = file
    return tracks


def integrate_speed(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Position from speed by the trapezoid rule, starting at 0 (gaps in ``t`` bridged linearly)."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(v, dtype=float)
    x = np.zeros(len(t))
    if len(t) > 1:
        x[1:] = np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))
    return x


def gaps_from_positions(tracks: pd.DataFrame, dt: float) -> pd.Series:
    """Bumper gap ``x_leader - x - length_leader`` at the same time; NaN where no leader sample."""
    return leader_values(tracks, "x", dt) - tracks["x"] - leader_values(tracks, "length", dt)


def harmonise_lengths(
    tracks: pd.DataFrame, measured: pd.Series, *, default: float, notes: Notes, what: str
) -> pd.Series:
    """One length per vehicle: the median of its measured lengths, else ``default`` (noted).

    ``measured`` holds the source's length per row (NaN where the row has none), e.g. pair files
    that give the leader's length but not the follower's.
    """
    per_vehicle = measured.groupby(tracks["vehicle_id"]).median()
    lengths = tracks["vehicle_id"].map(per_vehicle).astype(float)
    assumed = lengths.isna()
    if assumed.any():
        count = tracks.loc[assumed, "vehicle_id"].nunique()
        notes.assume(
            f"{what}: no length for {count} vehicle(s); assumed {default} m (a passenger car)"
        )
    return lengths.fillna(default)


class FileFormat(NamedTuple):
    """What :func:`finish` is told of a reader's format, the same for every file it reads: its
    name, time step (s), the file's names and units of the schema columns (for messages), and
    whether the file's gap is measured rather than derived from positions."""

    name: str
    dt: float
    column_names: Mapping[str, str] | None = None
    file_units: Mapping[str, float] | None = None
    measured_gap: bool = False


def finish_parts(
    parts: Sequence[tuple[Any, ...]],
    file_format: FileFormat,
    source: str | Path,
    notes: Notes,
    **options,
) -> Trajectories:
    """:func:`finish` of a reader's files read one by one: each part starts with its tracks and
    scenes tables (anything after them is the reader's own), concatenated in order."""
    tracks = pd.concat([part[0] for part in parts], ignore_index=True)
    scenes = pd.concat([part[1] for part in parts], ignore_index=True)
    return finish(
        tracks,
        fmt=file_format.name,
        source=source,
        dt=file_format.dt,
        scenes=scenes,
        notes=notes,
        column_names=file_format.column_names,
        file_units=file_format.file_units,
        measured_gap=file_format.measured_gap,
        **options,
    )


def finish(
    tracks: pd.DataFrame,
    *,
    fmt: str,
    source: str | Path,
    dt: float,
    scenes: pd.DataFrame,
    notes: Notes,
    column_names: Mapping[str, str] | None = None,
    file_units: Mapping[str, float] | None = None,
    measured_gap: bool = False,
    extra_flags: pd.DataFrame | None = None,
    extra_inputs: Iterable[Path] = (),
    table_digests: Mapping[str, str] | None = None,
) -> Trajectories:
    """Check ``tracks`` (:func:`bayesdrive.data.validate.check_tracks`), record what the checks
    found and the sha256 of every input (the rows' ``_file`` plus ``extra_inputs``: maps, metadata
    files), and wrap everything in a :class:`Trajectories`. ``table_digests`` gives the digests of
    inputs that are tables in memory rather than files (their rows' ``_file`` is the table's name)."""
    digests = dict(table_digests or {})
    files = (
        sorted({*map(str, pd.unique(tracks["_file"])), *map(str, extra_inputs)})
        if ("_file" in tracks.columns)
        else sorted(map(str, extra_inputs))
    )
    checked = check_tracks(
        tracks,
        source=str(source),
        dt=dt,
        column_names=column_names,
        file_units=file_units,
        measured_gap=measured_gap,
    )
    for message in checked.repairs:
        notes.repair(message)
    for message in checked.findings:
        notes.assume(message, warn=True)
    flags = checked.flags
    if extra_flags is not None and not extra_flags.empty:
        flags = pd.concat([flags, extra_flags[FLAG_COLUMNS]], ignore_index=True)
    if len(flags):
        kinds = flags.groupby("kind").size()
        message = "flagged (kept, left out of fitting): " + ", ".join(
            f"{n} {kind} sample(s)" for kind, n in kinds.items()
        )
        # Flags travel with the data and every summary counts them: a note for -v, not a warning.
        notes.assume(message)
    scenes = scenes.drop_duplicates(["scene_id", "vehicle_id"]).reset_index(drop=True)
    scenes["vehicle_id"] = scenes["vehicle_id"].astype(str)
    return Trajectories(
        tracks=checked.tracks,
        scenes=scenes,
        dt=float(checked.dt),
        format=fmt,
        source=str(source),
        flags=flags.reset_index(drop=True),
        notes=tuple(notes.items),
        inputs={f: digests[f] if f in digests else _sha256(Path(f)) for f in files},
    )


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def merge_copies(
    copies: pd.DataFrame, *, tolerances: Mapping[str, float], notes: Notes, what: str
) -> pd.DataFrame:
    """One row per (``vehicle_id``, ``_k``) from several copies of the same samples.

    Copies of one vehicle come from overlapping files (NGSIM chains, pair files where a car is the
    leader in one pair and the follower in another). Values in ``tolerances`` must agree within
    them, else a :class:`DataError` names both files and rows; non-null leaders must agree. The
    merged row takes the first copy's values and the leader (and gap) of any copy that has one.
    """
    copies = copies.sort_values(["vehicle_id", "_k", "_file", "_row"], kind="stable")
    grouped = copies.groupby(["vehicle_id", "_k"], sort=False)
    sizes = grouped.size()
    if not (sizes > 1).any():
        return copies.reset_index(drop=True)
    columns = list(tolerances)
    values = grouped[columns]
    spread = values.max() - values.min()
    bad = np.zeros(len(spread), dtype=bool)
    for column, tolerance in tolerances.items():
        bad |= spread[column].to_numpy() > tolerance
    if bad.any():
        vehicle, step = spread.index[int(np.argmax(bad))]
        rows = copies[(copies["vehicle_id"] == vehicle) & (copies["_k"] == step)]
        where = "; ".join(f"{f}, row {r}" for f, r in zip(rows["_file"], rows["_row"], strict=True))
        detail = ", ".join(f"{c} differs by {spread.loc[(vehicle, step), c]:.4g}" for c in columns)
        raise DataError(f"vehicle {vehicle}: copies of one sample disagree ({where}): {detail}")
    conflict = grouped["leader_id"].nunique() > 1
    if conflict.any():
        vehicle, step = conflict[conflict].index[0]
        rows = copies[(copies["vehicle_id"] == vehicle) & (copies["_k"] == step)]
        where = "; ".join(f"{f}, row {r}" for f, r in zip(rows["_file"], rows["_row"], strict=True))
        raise DataError(
            f"vehicle {vehicle}: copies give different leaders "
            f"{sorted(set(rows['leader_id'].dropna()))} at the same time ({where})"
        )
    worst = spread.max()
    notes.assume(
        f"{what}: merged {int((sizes > 1).sum())} samples present in several files; copies agree "
        "to " + ", ".join(f"max |d{c}| = {worst[c]:.2g}" for c in columns)
    )
    # first() skips missing values, so a copy that has a leader (and gap) at that time gives it.
    merged = grouped.first().reset_index()
    merged["leader_id"] = merged["leader_id"].where(merged["leader_id"].notna(), None)
    return merged
