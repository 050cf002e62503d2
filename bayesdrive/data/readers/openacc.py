"""JRC OpenACC platoon recordings (Vicolungo, Casale, ZalaZone, ...) and OpenACC-like extracts.

Units (:data:`UNITS`): SI; ``Time`` in s at 10 Hz, ``Speed<i>`` (Doppler) in m/s, ``E/N/U<i>`` in
m (local ENU plane), ``IVS<i>`` in m, the BUMPER-to-bumper gap between car i and car i+1.

Layout: a few metadata rows (``Date``, ``Vehicle_order``, ``Number_of_vehicles``, ``ACC``,
``Distance_setting``; their number varies, possibly none) and then the header row starting with
``Time``; per vehicle ``Speed<i>`` plus position columns, then ``IVS<i>`` and ``Driver<i>``.
Vehicle 1 leads; vehicle i+1 follows vehicle i. Files may lack vehicles (ZalaZone: ``Speed3``
absent), their IVS or their Driver columns.

What the reader makes of it:

- ``t``: Time minus the first timestamp, rounded onto the 0.1 s grid (the column carries float
  noise such as ``208970.39999997``); a time off the grid or a rate other than 10 Hz is an error.
- ``x``: the trapezoid integral of the Doppler speed, NOT the ENU path (the ENU path disagrees
  with the integrated speed by centimetres per step; the difference is recorded in the notes as a
  consistency check). To put a platoon on one axis each follower's integration constant is set so
  that ``x_i - x_{i+1} - length_i = IVS_i`` holds in the median over the samples where both cars
  and ``IVS_i`` are present. (Not at the first sample only: in ``JRC-VC_260219_part3`` IVS4 jumps
  by 62 m around t = 5 s, so anchoring on t = 0 would misplace car 5 by 60 m for the whole
  recording.) Each car's x is its own integrated speed, so the identity drifts by the integration
  error (median and maximum drift in the notes); ``gap`` is always the measured ``IVS_i``.
- Flags: a step where IVS changes more than :data:`GAP_JUMP_M` beyond what the two speeds allow
  within 0.1 s (a 50 m/s discrepancy: a GNSS artefact, not motion) flags both samples
  (kind ``gap_jump``); non-positive IVS is flagged as ``negative_gap`` like everywhere.
  A car whose predecessor is absent is placed by the straight-line ENU distance to the nearest
  present car ahead (noted), or on its own axis if there is no ENU either (noted).
- ``leader_id``: car i for car i+1 wherever both are present and ``IVS_i`` is a number.
- ``driver``: ``Driver<i>`` per row (``Human`` -> human, ``ACC`` -> acc). Without the column:
  ``ACC`` metadata 0 -> human for all; 1 -> acc for the followers and unknown for the leader;
  otherwise unknown (noted).
- ``length``: from the folder's ``*veh_specifications.csv`` if it has a length column, or from
  ``lengths={model name: metres}``; otherwise 4.5 m assumed (noted). The published JRC
  specification files list power, fuel and top speed but no length.
- Missing values (NaN policy): a row without ``Time`` is an error. A car's samples without
  ``Speed<i>`` mean the car was not measured then: they are left out (a logged repair, counted per
  file in the notes: leading, trailing and interior samples). A missing ``IVS_i`` while both cars
  are present removes the leader link for that sample (logged, counted). Missing ENU values only
  affect the consistency check.
- One scene per file (scene id = file path relative to the folder read, without suffix); vehicle
  ids ``"<scene>:<i>"``.
"""

from __future__ import annotations

import csv
import logging
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers._common import (
    DEFAULT_LENGTH_M,
    FileFormat,
    Notes,
    finish_parts,
    integrate_speed,
    make_tracks,
    numeric_columns,
    open_text,
    read_table,
    require_regular_file,
    snap_to_grid,
    sort_rows,
    time_steps,
)
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.validate import check_distance_ratio

__all__ = ["DT", "UNITS", "enu_consistency", "read_openacc"]

log = logging.getLogger(__name__)

FORMAT = "openacc"
DT = 0.1
UNITS = {
    "Time": "s",
    "Speed": "m/s (Doppler)",
    "E/N/U": "m (local ENU plane)",
    "IVS": "m (bumper to bumper, car i to car i+1)",
}
EXPECTED = (
    "Time, Speed1, [Lat1, Lon1, Alt1, E1, N1, U1, ...], ..., IVS1..IVS(n-1), Driver1..Driver(n)"
)
# Column names in messages (the row names the car: row of Speed<i> of car i).
SCHEMA_NAMES = {"t": "Time", "v": "Speed<i>", "x": "Speed<i> (integrated)", "gap": "IVS<i-1>"}
# x is integrated speed placed by IVS itself: not independent of it, so the gap is not measured.
FILE_FORMAT = FileFormat(FORMAT, DT, SCHEMA_NAMES, measured_gap=False)
# Metadata rows are few; the header must appear this early.
MAX_METADATA_ROWS = 50
DRIVERS = {"human": "human", "acc": "acc"}
# IVS may not change by more than this per step beyond the integrated relative speed: 5 m in 0.1 s
# would be 50 m/s of unexplained relative motion.
GAP_JUMP_M = 5.0


def read_openacc(path: str | Path, *, lengths: Mapping[str, float] | None = None) -> Trajectories:
    """Read one OpenACC CSV, or every CSV in a folder (recursively), one scene per file."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    notes = Notes(log)
    if not path.is_dir():
        require_regular_file(path)
        files, root = [path], path.parent
    else:
        candidates = sorted(
            f for f in path.rglob("*.csv") if f.is_file() and "specification" not in f.name.lower()
        )
        files = [f for f in candidates if _header_line(f) is not None]
        root = path
        if not files:
            raise DataError(
                f"{path}: no OpenACC files in this folder (CSV files whose header row starts with "
                f"'Time' followed by Speed1, ...)"
            )
        skipped = [f.relative_to(path).as_posix() for f in candidates if f not in files]
        if skipped:
            notes.assume(
                f"{len(skipped)} CSV file(s) without an OpenACC header row ('Time', Speed1, ...) "
                f"in the first {MAX_METADATA_ROWS} lines skipped: {', '.join(skipped)}",
                warn=True,
            )
    notes.assume(
        "OpenACC: x = trapezoid integral of the Doppler speed (not ENU), followers placed so "
        "that x_i - x_(i+1) - length_i = IVS_i in the median over their common samples; "
        "gap = IVS (measured)"
    )
    parts = []
    specs = set()
    for file in files:
        scene = file.relative_to(root).with_suffix("").as_posix()
        spec, spec_lengths = _spec_lengths(file.parent, notes)
        specs.update([spec] if spec else [])
        parts.append(_read_file(file, scene, {**spec_lengths, **(lengths or {})}, notes))
    jumps = [f for _, _, f in parts if f is not None and len(f)]
    return finish_parts(
        parts,
        FILE_FORMAT,
        path,
        notes,
        extra_flags=pd.concat(jumps, ignore_index=True) if jumps else None,
        extra_inputs=specs,
    )


def _header_line(path: Path) -> int | None:
    """0-based line of the header row (first field ``Time``), or None."""
    try:
        with open_text(path) as handle:
            for index, row in enumerate(csv.reader(handle)):
                if row and row[0].strip() == "Time":
                    return index
                if index >= MAX_METADATA_ROWS:
                    return None
    except (OSError, DataError):
        return None
    return None


def _metadata(path: Path, header_line: int) -> dict[str, list[str]]:
    with open_text(path) as handle:
        rows = [row for _, row in zip(range(header_line), csv.reader(handle), strict=False)]
    meta = {}
    for row in rows:
        if row and row[0].strip():
            meta[row[0].strip()] = [c.strip() for c in row[1:] if c.strip()]
    return meta


def _normalise_name(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


def _spec_lengths(folder: Path, notes: Notes) -> tuple[Path | None, dict[str, float]]:
    """The ``*veh_specifications.csv`` read and its vehicle lengths, if it has a length column."""
    specs = sorted(f for f in folder.glob("*[Ss]pecifications.csv") if f.is_file())
    if not specs:
        return None, {}
    table = read_table(specs[0], fmt="OpenACC vehicle specifications", notes=notes)
    columns = [c for c in table.columns if c not in ("_row", "_file")]
    length_columns = [c for c in columns if "length" in str(c).lower()]
    if not length_columns:
        notes.assume(
            f"{specs[0].name} lists no vehicle length (columns: {', '.join(map(str, columns))})"
        )
        return specs[0], {}
    column = length_columns[0]
    numeric_columns(table, [column], allow_nan=[column])
    factor = 0.001 if "mm" in column.lower() else 1.0
    return specs[0], {
        str(name): float(value) * factor
        for name, value in zip(table[columns[0]], table[column], strict=True)
        if pd.notna(value)
    }


def _length_of(name: str | None, lengths: Mapping[str, float]) -> float | None:
    if name is None:
        return None
    wanted = _normalise_name(name)
    for key, value in lengths.items():
        if _normalise_name(key) == wanted:
            return float(value)
    return None


def _read_file(
    path: Path, scene: str, lengths: Mapping[str, float], notes: Notes
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame | None]:
    header = _header_line(path)
    if header is None:
        raise DataError(
            f"{path}: not an OpenACC file: no header row starting with 'Time' in the first "
            f"{MAX_METADATA_ROWS} lines. Expected columns: {EXPECTED}"
        )
    meta = _metadata(path, header)
    frame = read_table(path, header_line=header, fmt="OpenACC", notes=notes)
    numbers = sorted(
        int(m.group(1)) for c in frame.columns if (m := re.fullmatch(r"Speed(\d+)", str(c)))
    )
    if not numbers:
        raise DataError(
            f"{path}, row {header + 1}: not an OpenACC file: no Speed1, Speed2, ... columns. "
            f"Expected columns: {EXPECTED}"
        )
    numeric_columns(frame, ["Time"])
    frame = sort_rows(frame, ["Time"], notes=notes, path=path, what="time")
    # The rate is found from the steps by the validation layer (a 5 Hz file is not 10 Hz with holes).
    steps = snap_to_grid(frame["Time"].to_numpy() - frame["Time"].iloc[0], DT, frame, column="Time")
    position_columns = [
        c for c in frame.columns if re.fullmatch(r"(E|N|U|IVS|Lat|Lon|Alt|VE|VN|VU)\d+", str(c))
    ]
    numeric_columns(
        frame, [f"Speed{i}" for i in numbers] + position_columns, allow_nan=frame.columns
    )

    order = meta.get("Vehicle_order", [])
    names = {i: order[i - 1] if i - 1 < len(order) else None for i in numbers}
    acc_setting = (meta.get("ACC") or [None])[0]
    ids = {i: f"{scene}:{i}" for i in numbers}
    present = {i: frame[f"Speed{i}"].notna().to_numpy() for i in numbers}
    t = time_steps(steps, DT)
    rows = frame["_row"].to_numpy()

    _note_missing_speeds(path, numbers, present, notes)

    length = {i: _length_of(names[i], lengths) for i in numbers}
    unknown = [names[i] or f"vehicle {i}" for i in numbers if length[i] is None]
    if unknown:
        notes.assume(
            f"{path.name}: no length known for {', '.join(unknown)}: assumed {DEFAULT_LENGTH_M} m"
        )
    length = {i: DEFAULT_LENGTH_M if value is None else value for i, value in length.items()}

    # Positions: integrate speed per car, then anchor each car on the platoon.
    x = {}
    for i in numbers:
        x[i] = np.full(len(frame), np.nan)
        mask = present[i]
        x[i][mask] = integrate_speed(t[mask], frame.loc[mask, f"Speed{i}"].to_numpy())
    enu = {
        i: (frame[f"E{i}"].to_numpy(), frame[f"N{i}"].to_numpy())
        for i in numbers
        if f"E{i}" in frame.columns and f"N{i}" in frame.columns
    }
    anchored: list[int] = []
    drift = []
    for i in numbers:
        if not present[i].any():
            continue
        ivs = f"IVS{i - 1}"
        if anchored and (i - 1) in anchored and ivs in frame.columns:
            both = present[i] & present[i - 1] & frame[ivs].notna().to_numpy()
            if both.any():
                implied = x[i - 1] - x[i] - length[i - 1] - frame[ivs].to_numpy()
                x[i] += np.median(implied[both])
                drift.append(np.abs(implied[both] - np.median(implied[both])))
                anchored.append(i)
                continue
        if anchored:
            _place_by_enu(path, i, anchored, x, present, enu, notes)
        anchored.append(i)

    if drift:
        d = np.concatenate(drift)
        notes.assume(
            f"{path.name}: x_leader - x - length_leader departs from the measured IVS by "
            f"median {np.median(d):.2f} m, max {d.max():.2f} m (integration drift; gap = IVS)"
        )
    check = enu_consistency_from(t, frame, numbers, present)
    if check is not None and len(check):
        for row in check.itertuples():
            check_distance_ratio(
                row.enu_path_m,
                row.integrated_m,
                where=f"{path}, column 'Speed{row.vehicle}'",
                what=f"the ENU path (E{row.vehicle}, N{row.vehicle})",
            )
        worst = check.loc[check["difference_m"].abs().idxmax()]
        notes.assume(
            f"{path.name}: ENU path vs integrated speed differ by up to "
            f"{worst['difference_m']:.1f} m over {worst['integrated_m']:.0f} m (vehicle "
            f"{int(worst['vehicle'])})"
        )

    parts = []
    flags = []
    for i in numbers:
        mask = present[i]
        if not mask.any():
            continue
        leader = np.full(len(frame), None, dtype=object)
        gap = np.full(len(frame), np.nan)
        ivs = f"IVS{i - 1}"
        if (i - 1) in present and ivs in frame.columns:
            measured = frame[ivs].to_numpy()
            link = mask & present[i - 1] & np.isfinite(measured)
            lost = mask & present[i - 1] & ~np.isfinite(measured)
            if lost.any():
                notes.repair(
                    f"{path.name}: {int(lost.sum())} sample(s) of vehicle {i} have no {ivs} "
                    "although both cars are present; leader link left out there"
                )
            leader[link] = ids[i - 1]
            gap[link] = measured[link]
            flags.append(_gap_jumps(frame, i, link, t, ids[i]))
        elif (i - 1) in present:
            notes.repair(
                f"{path.name}: no {ivs} column although vehicles {i - 1} and {i} are present; "
                f"vehicle {i} has no leader"
            )
        parts.append(
            make_tracks(
                vehicle_id=ids[i],
                t=t[mask],
                x=x[i][mask],
                v=frame.loc[mask, f"Speed{i}"].to_numpy(),
                leader_id=leader[mask],
                gap=gap[mask],
                length=length[i],
                driver=_drivers(path, frame, i, numbers, acc_setting, notes)[mask],
                row=rows[mask],
                file=str(path),
            )
        )
    tracks = pd.concat(parts, ignore_index=True)
    scenes = pd.DataFrame({"scene_id": scene, "vehicle_id": pd.unique(tracks["vehicle_id"])})
    return tracks, scenes, pd.concat(flags, ignore_index=True) if flags else None


def _gap_jumps(
    frame: pd.DataFrame, i: int, link: np.ndarray, t: np.ndarray, vehicle: str
) -> pd.DataFrame:
    """Samples where IVS_(i-1) jumps by more than the two cars' speeds allow (both ends flagged)."""
    ivs = frame[f"IVS{i - 1}"].to_numpy()
    closing = (frame[f"Speed{i - 1}"] - frame[f"Speed{i}"]).to_numpy()
    expected = 0.5 * (closing[1:] + closing[:-1]) * np.diff(t)
    residual = np.diff(ivs) - expected
    jump = link[1:] & link[:-1] & (np.abs(residual) > GAP_JUMP_M)
    where = np.zeros(len(frame), dtype=bool)
    where[1:] |= jump
    where[:-1] |= jump
    worst = np.zeros(len(frame))
    worst[1:] = np.where(jump, residual, 0.0)
    worst[:-1] = np.where(jump & (np.abs(residual) > np.abs(worst[:-1])), residual, worst[:-1])
    return pd.DataFrame(
        {
            "vehicle_id": vehicle,
            "t": t[where],
            "kind": "gap_jump",
            "message": [
                f"IVS{i - 1} changes {r:+.1f} m more than the speeds allow in one step"
                for r in worst[where]
            ],
        }
    )


def _note_missing_speeds(
    path: Path, numbers: list[int], present: dict[int, np.ndarray], notes: Notes
) -> None:
    for i in numbers:
        mask = present[i]
        missing = int((~mask).sum())
        if not missing:
            continue
        if not mask.any():
            notes.repair(f"{path.name}: vehicle {i} has no speed at all; left out")
            continue
        first, last = int(np.argmax(mask)), len(mask) - int(np.argmax(mask[::-1])) - 1
        leading, trailing = first, len(mask) - 1 - last
        notes.repair(
            f"{path.name}: vehicle {i} not measured in {missing} sample(s) (Speed{i} empty: "
            f"{leading} leading, {trailing} trailing, {missing - leading - trailing} interior); "
            "those samples left out"
        )


def _place_by_enu(
    path: Path,
    i: int,
    anchored: list[int],
    x: dict[int, np.ndarray],
    present: dict[int, np.ndarray],
    enu: dict[int, tuple[np.ndarray, np.ndarray]],
    notes: Notes,
) -> None:
    """Anchor car i, whose predecessor is absent, by the ENU distance to a car ahead."""
    for j in sorted(anchored, reverse=True):
        if i in enu and j in enu:
            e_i, n_i = enu[i]
            e_j, n_j = enu[j]
            usable = present[i] & present[j] & np.isfinite(e_i + n_i + e_j + n_j)
            if usable.any():
                k = int(np.argmax(usable))
                distance = float(np.hypot(e_j[k] - e_i[k], n_j[k] - n_i[k]))
                x[i] += x[j][k] - distance - x[i][k]
                notes.assume(
                    f"{path.name}: vehicle {i} has no measured gap to the car ahead; placed on the "
                    f"platoon axis by its straight-line ENU distance to vehicle {j} "
                    "(approximate; it has no leader)",
                    warn=True,
                )
                return
    notes.assume(
        f"{path.name}: vehicle {i} cannot be placed relative to the platoon (no IVS, no ENU); "
        "its x is its own integrated distance from 0 (it has no leader)",
        warn=True,
    )


def _drivers(
    path: Path,
    frame: pd.DataFrame,
    i: int,
    numbers: list[int],
    acc_setting: str | None,
    notes: Notes,
) -> np.ndarray:
    column = f"Driver{i}"
    if column in frame.columns:
        text = frame[column].astype("string").str.strip().str.lower()
        mapped = text.map(DRIVERS)
        bad = mapped.isna() & text.notna()
        if bad.any():
            first = int(np.argmax(bad.to_numpy()))
            raise DataError(
                f"{path}, row {frame['_row'].iloc[first]}, column {column!r}: driver must be "
                f"Human or ACC, got {frame[column].iloc[first]!r}"
            )
        blank = text.isna() & frame[f"Speed{i}"].notna()
        if blank.any():
            notes.repair(
                f"{path.name}: {int(blank.sum())} sample(s) with an empty {column}; driver "
                "'unknown' there"
            )
        return mapped.fillna("unknown").to_numpy(dtype=object)
    if acc_setting == "0":
        driver = "human"
    elif acc_setting == "1":
        driver = "unknown" if i == min(numbers) else "acc"
    else:
        driver = "unknown"
    notes.assume(
        f"{path.name}: no Driver<i> column for some vehicles; their driver follows the ACC "
        f"metadata ({acc_setting!r}): 0 -> human; 1 -> acc for followers, unknown for the "
        "leader; otherwise unknown"
    )
    return np.full(len(frame), driver, dtype=object)


def enu_consistency_from(
    t: np.ndarray, frame: pd.DataFrame, numbers: list[int], present: dict[int, np.ndarray]
) -> pd.DataFrame | None:
    """Per car: ENU path length vs integrated speed over the samples where both are known."""
    rows = []
    for i in numbers:
        if f"E{i}" not in frame.columns or f"N{i}" not in frame.columns:
            continue
        e, n = frame[f"E{i}"].to_numpy(), frame[f"N{i}"].to_numpy()
        ok = present[i] & np.isfinite(e) & np.isfinite(n)
        if ok.sum() < 2:
            continue
        step_ok = ok[1:] & ok[:-1]
        path_steps = np.hypot(np.diff(e), np.diff(n))[step_ok]
        speed = frame[f"Speed{i}"].to_numpy()
        speed_steps = (0.5 * (speed[1:] + speed[:-1]) * np.diff(t))[step_ok]
        rows.append(
            {
                "vehicle": i,
                "enu_path_m": float(path_steps.sum()),
                "integrated_m": float(speed_steps.sum()),
                "difference_m": float(path_steps.sum() - speed_steps.sum()),
            }
        )
    return pd.DataFrame(rows) if rows else None


def enu_consistency(path: str | Path) -> pd.DataFrame:
    """ENU path length vs integrated Doppler speed per car of one OpenACC file (a check only)."""
    path = Path(path)
    header = _header_line(path)
    if header is None:
        raise DataError(f"{path}: not an OpenACC file (no header row starting with 'Time')")
    frame = read_table(path, header_line=header, fmt="OpenACC", notes=Notes(log))
    numbers = sorted(
        int(m.group(1)) for c in frame.columns if (m := re.fullmatch(r"Speed(\d+)", str(c)))
    )
    numeric_columns(frame, ["Time"])
    numeric_columns(
        frame,
        [c for c in frame.columns if re.fullmatch(r"(Speed|E|N)\d+", str(c))],
        allow_nan=frame.columns,
    )
    t = frame["Time"].to_numpy() - frame["Time"].iloc[0]
    present = {i: frame[f"Speed{i}"].notna().to_numpy() for i in numbers}
    result = enu_consistency_from(t, frame, numbers, present)
    if result is None:
        raise DataError(f"{path}: no E<i>/N<i> columns to check against")
    return result
