"""US DOT NGSIM trajectory files (I-80, US-101, Lankershim, Peachtree) as published.

Units (:data:`UNITS`): feet, ft/s and ft/s^2, sampled at 10 Hz; converted to SI with 0.3048 m/ft.

- ``x`` is ``Local_Y``, the longitudinal position of the FRONT centre of the vehicle (ft).
- ``t`` is ``Frame_ID * 0.1 s`` (frames are 1/10 s; files of one period share the frame clock).
- ``v``/``a`` are ``v_Vel``/``v_Acc``; ``length`` is ``v_Length``; ``lane_id`` is ``Lane_ID``.
- The leader is ``Preceding`` per row (0 means none), so a lane change changes the leader.
- ``Space_Headway`` is FRONT-to-front, so the bumper gap is ``Space_Headway * 0.3048`` minus the
  leader's length (taken from the leader's own row at the same frame).
- A ``Preceding`` id that names no vehicle of the file at that frame is an error naming file, row
  and column; ``missing_leaders="drop"`` instead removes the link (leader None, logged, noted).
- One scene per file (scene id = file stem); vehicle ids are ``"<stem>:<Vehicle_ID>"`` so files of
  different periods never collide. ``driver`` is ``"unknown"``.

Column names are matched case-insensitively (the data.transportation.gov CSV writes ``v_length``).
The original whitespace-separated ``trajectories-*.txt`` files without a header are read too, with
the documented 18-column order (:data:`TXT_COLUMNS`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers._common import (
    FileFormat,
    Notes,
    finish_parts,
    input_files,
    integer_column,
    integer_ids,
    leader_values,
    make_tracks,
    numeric_columns,
    open_text,
    read_table,
    require_columns,
    time_steps,
)
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.units import FOOT_M

__all__ = ["COLUMNS", "DT", "REQUIRED", "TXT_COLUMNS", "UNITS", "read_ngsim_raw"]

log = logging.getLogger(__name__)

FORMAT = "ngsim_raw"
DT = 0.1
UNITS = {
    "Local_Y": "ft (front centre of the vehicle)",
    "v_Length": "ft",
    "v_Vel": "ft/s",
    "v_Acc": "ft/s^2",
    "Space_Headway": "ft (front to front)",
    "Frame_ID": "1/10 s",
}
# The published column set; REQUIRED is what the reader uses.
COLUMNS = [
    "Vehicle_ID",
    "Frame_ID",
    "Total_Frames",
    "Global_Time",
    "Local_X",
    "Local_Y",
    "v_Length",
    "v_Width",
    "v_Class",
    "v_Vel",
    "v_Acc",
    "Lane_ID",
    "Preceding",
    "Following",
    "Space_Headway",
    "Time_Headway",
]
REQUIRED = [
    "Vehicle_ID",
    "Frame_ID",
    "Local_Y",
    "v_Length",
    "v_Vel",
    "v_Acc",
    "Lane_ID",
    "Preceding",
    "Space_Headway",
]
# The headerless text release: the published columns with the global coordinates after Local_Y.
TXT_COLUMNS = [*COLUMNS[:6], "Global_X", "Global_Y", *COLUMNS[6:]]
SCHEMA_NAMES = {
    "vehicle_id": "Vehicle_ID",
    "t": "Frame_ID",
    "x": "Local_Y",
    "v": "v_Vel",
    "a": "v_Acc",
    "lane_id": "Lane_ID",
    "leader_id": "Preceding",
    "gap": "Space_Headway",
    "length": "v_Length",
}
# Every length-based schema column is feet in the file (for messages in the file's own units).
FILE_UNITS = dict.fromkeys(("x", "v", "a", "gap", "length"), FOOT_M)
FILE_FORMAT = FileFormat(FORMAT, DT, SCHEMA_NAMES, FILE_UNITS, measured_gap=True)
ID_COLUMNS = ("Vehicle_ID", "Preceding", "Following")


def read_ngsim_raw(
    path: str | Path, *, missing_leaders: Literal["error", "drop"] = "error"
) -> Trajectories:
    """Read one NGSIM file, or every ``*.csv``/``*.txt`` in a folder, into SI trajectories."""
    if missing_leaders not in ("error", "drop"):
        raise DataError(f"missing_leaders must be 'error' or 'drop', got {missing_leaders!r}")
    files = input_files(path, ["*.csv", "*.txt", "*.dat", "*.tsv"], what="NGSIM")
    notes = Notes(log)
    notes.assume(
        "NGSIM: feet converted with 0.3048 m/ft; x = Local_Y (front of vehicle); "
        "gap = Space_Headway (front to front) - leader length; t = Frame_ID * 0.1 s"
    )
    parts = [_read_file(f, missing_leaders=missing_leaders, notes=notes) for f in files]
    return finish_parts(parts, FILE_FORMAT, path, notes)


def _load(path: Path, notes: Notes) -> pd.DataFrame:
    with open_text(path) as handle:
        first = handle.readline()
    if not first.strip():
        raise DataError(f"{path}: empty file (expected an NGSIM table)")
    if "," not in first and "\t" not in first:
        tokens = first.split()
        if tokens and _is_number(tokens[0]):
            return read_table(
                path,
                names=TXT_COLUMNS,
                sep=r"\s+",
                fmt="NGSIM",
                notes=notes,
                text_columns=ID_COLUMNS,
            )
        return read_table(path, sep=r"\s+", fmt="NGSIM", notes=notes, text_columns=ID_COLUMNS)
    return read_table(path, fmt="NGSIM", notes=notes, text_columns=ID_COLUMNS)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_file(
    path: Path, *, missing_leaders: str, notes: Notes
) -> tuple[pd.DataFrame, pd.DataFrame]:
    frame = _load(path, notes)
    by_lower = {str(c).lower(): c for c in frame.columns}
    frame = frame.rename(
        columns={by_lower[c.lower()]: c for c in TXT_COLUMNS if c.lower() in by_lower}
    )
    require_columns(frame, REQUIRED, source=path, fmt="NGSIM")
    # Every published column present is checked: a damaged cell anywhere means a damaged file,
    # even in a column this reader does not use. Ids stay exact text, never floats.
    ids = {c: integer_ids(frame, c) for c in ID_COLUMNS if c in frame.columns}
    numeric_columns(frame, [c for c in TXT_COLUMNS if c in frame.columns and c not in ids])
    scene = path.stem
    frames = integer_column(frame, "Frame_ID")
    preceding = pd.Series(ids["Preceding"])
    no_leader = preceding == "0"
    tracks = make_tracks(
        vehicle_id=(scene + ":" + pd.Series(ids["Vehicle_ID"])).to_numpy(),
        t=time_steps(frames, DT),
        x=frame["Local_Y"].to_numpy() * FOOT_M,
        v=frame["v_Vel"].to_numpy() * FOOT_M,
        a=frame["v_Acc"].to_numpy() * FOOT_M,
        lane_id=integer_column(frame, "Lane_ID"),
        leader_id=(scene + ":" + preceding).where(~no_leader, None).to_numpy(),
        length=frame["v_Length"].to_numpy() * FOOT_M,
        row=frame["_row"].to_numpy(),
        file=str(path),
    )
    # The leader must be in the file at the same frame: its length gives the bumper gap.
    leader_length = leader_values(tracks, "length", DT).to_numpy()
    has_leader = tracks["leader_id"].notna().to_numpy()
    missing = has_leader & np.isnan(leader_length)
    if missing.any():
        first = int(np.argmax(missing))
        message = (
            f"{path}, row {frame['_row'].iloc[first]}, column 'Preceding': leader "
            f"{preceding.iloc[first]} has no row at frame {frames[first]} "
            f"in this file ({int(missing.sum())} such row(s))"
        )
        if missing_leaders == "error":
            raise DataError(
                message + "; in Python, read(path, missing_leaders='drop') drops these links "
                "(logged); otherwise add the leader's rows"
            )
        notes.repair(
            f"{path.name}: {int(missing.sum())} row(s) name a leader that is not in the file at "
            "that frame; leader set to None there (missing_leaders='drop')"
        )
        tracks.loc[missing, "leader_id"] = None
    tracks["gap"] = frame["Space_Headway"].to_numpy() * FOOT_M - leader_length
    tracks.loc[tracks["leader_id"].isna(), "gap"] = np.nan
    scenes = pd.DataFrame({"scene_id": scene, "vehicle_id": pd.unique(tracks["vehicle_id"])})
    return tracks, scenes
