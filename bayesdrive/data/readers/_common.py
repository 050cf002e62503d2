"""Helpers every reader shares, so no reader re-implements them.

Reading: :func:`input_files` (a file or a folder), :func:`read_table` (CSV with the 1-based source
line number of every row in ``_row`` and the file in ``_file``), :func:`require_columns`,
:func:`numeric_columns` (non-numbers and NaN are errors naming file, row and column),
:func:`snap_to_grid` (times onto the ``dt`` grid). Building: :func:`make_tracks` (a schema table with
defaults), :func:`integrate_speed`, :func:`leader_values`, :func:`gaps_from_positions`,
:func:`harmonise_lengths`, :func:`merge_copies` (samples present in several files). Ending:
:func:`finish` (validate, flag negative gaps, wrap in :class:`Trajectories`). Every repair goes
through :class:`Notes`, which logs it as a warning and records it in ``Trajectories.notes``.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import (
    FLAG_COLUMNS,
    Trajectories,
    flag_negative_gaps,
    validate_tracks,
)

__all__ = [
    "DEFAULT_LENGTH_M",
    "REPAIR_PREFIX",
    "Notes",
    "finish",
    "gaps_from_positions",
    "harmonise_lengths",
    "input_files",
    "integrate_speed",
    "leader_values",
    "make_tracks",
    "merge_copies",
    "numeric_columns",
    "read_table",
    "require_columns",
    "snap_to_grid",
    "time_steps",
]

# Length assumed where a source gives none: a typical passenger car (NGSIM I-80 cars are ~4.5 m).
DEFAULT_LENGTH_M = 4.5
# A time this far off the dt grid (in units of dt) is not float rounding but a wrong sampling rate.
GRID_TOLERANCE = 1e-3


# Notes that record a change to the data start with this; ``read(strict=True)`` refuses them.
REPAIR_PREFIX = "repair: "


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


def input_files(path: str | Path, patterns: Sequence[str], *, what: str) -> list[Path]:
    """The file ``path`` itself, or the files in folder ``path`` matching ``patterns`` (sorted)."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if path.is_file():
        return [path]
    found = sorted({f for pattern in patterns for f in path.glob(pattern) if f.is_file()})
    if not found:
        raise DataError(
            f"{path}: no {what} files in this folder (looked for {', '.join(patterns)})"
        )
    return found


def read_table(
    path: Path,
    *,
    header_line: int = 0,
    names: Sequence[str] | None = None,
    sep: str = ",",
    fmt: str,
) -> pd.DataFrame:
    """Read a CSV (or parquet) whose header is on 0-based line ``header_line``.

    Adds ``_row`` (1-based line number in the file, header included, so row 2 is the first data
    row of a file with a header on line 1) and ``_file``. ``names`` reads a file without a header.
    Blank lines are kept (as all-NaN rows) so that line numbers stay true and they are reported.
    """
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
    try:
        frame = pd.read_csv(
            path,
            skiprows=header_line,
            header=None if names is not None else 0,
            names=list(names) if names is not None else None,
            sep=sep,
            skip_blank_lines=False,
            low_memory=False,
        )
    except pd.errors.EmptyDataError:
        raise DataError(f"{path}: empty file (expected a {fmt} table)") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot parse as a {fmt} CSV ({exc})") from None
    if frame.empty:
        raise DataError(f"{path}: no data rows (empty file or nothing left after the header)")
    first_data_line = header_line + (1 if names is not None else 2)
    frame.columns = [c.strip() if isinstance(c, str) else c for c in frame.columns]
    where = pd.DataFrame(
        {"_row": np.arange(len(frame)) + first_data_line, "_file": str(path)}, index=frame.index
    )
    return pd.concat([frame, where], axis=1)


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
        value = np.asarray(times)[int(np.argmax(off))]
        raise DataError(
            f"{file}, row {row}, column {column!r}: time {value!r} is not on the {dt} s grid "
            f"(expected samples every {dt} s)"
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


def leader_values(tracks: pd.DataFrame, column: str, dt: float) -> pd.Series:
    """The leader's ``column`` on each row at the same time; NaN without a leader sample."""
    key = np.round(tracks["t"].to_numpy(dtype=float) / dt).astype(np.int64)
    own = pd.DataFrame(
        {
            "leader_id": tracks["vehicle_id"].to_numpy(),
            "_k": key,
            "_value": tracks[column].to_numpy(dtype=float),
        }
    ).drop_duplicates(["leader_id", "_k"])
    asked = pd.DataFrame({"leader_id": tracks["leader_id"].to_numpy(), "_k": key})
    found = asked.merge(own, on=["leader_id", "_k"], how="left")["_value"]
    return pd.Series(found.to_numpy(), index=tracks.index)


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


def finish(
    tracks: pd.DataFrame,
    *,
    fmt: str,
    source: str | Path,
    dt: float,
    scenes: pd.DataFrame,
    notes: Notes,
    column_names: Mapping[str, str] | None = None,
    extra_flags: pd.DataFrame | None = None,
) -> Trajectories:
    """Validate ``tracks``, flag non-positive gaps and wrap everything in a :class:`Trajectories`."""
    valid = validate_tracks(tracks, source=str(source), dt=dt, column_names=column_names)
    flags = flag_negative_gaps(valid)
    if extra_flags is not None and not extra_flags.empty:
        flags = pd.concat([flags, extra_flags[FLAG_COLUMNS]], ignore_index=True)
    if len(flags):
        kinds = flags.groupby("kind").size()
        notes.assume(
            "flagged (kept, left out of fitting): "
            + ", ".join(f"{n} {kind} sample(s)" for kind, n in kinds.items())
        )
    scenes = scenes.drop_duplicates(["scene_id", "vehicle_id"]).reset_index(drop=True)
    scenes["vehicle_id"] = scenes["vehicle_id"].astype(str)
    return Trajectories(
        tracks=valid,
        scenes=scenes,
        dt=float(dt),
        format=fmt,
        source=str(source),
        flags=flags.reset_index(drop=True),
        notes=tuple(notes.items),
    )


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
