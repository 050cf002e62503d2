"""Write a :class:`~trafficgen.simulate.Recording` as a US DOT NGSIM raw CSV.

The published column set, in feet, ft/s and ft/s^2, 10 Hz frames: ``Local_Y`` is the front of the
vehicle, ``Space_Headway`` front to front, ``Preceding``/``Following`` vehicle ids (0: none),
``Lane_ID`` 1 or 2. Platoons are written 10 s apart on the frame clock so they never meet. The file
is written to a temporary name beside the target and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from trafficgen.simulate import Recording

__all__ = ["COLUMNS", "FOOT_M", "write_ngsim_raw"]

FOOT_M = 0.3048  # international foot
WIDTH_M = 1.8
COLUMNS = (
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
)
PLATOON_SPACING_FRAMES = 100


def write_ngsim_raw(recording: Recording, path: str | Path) -> Path:
    """Write ``recording`` to ``path`` (module docstring); returns the path."""
    path = Path(path)
    n, samples = recording.x.shape
    ids = recording.vehicle_id
    frame0 = 1 + recording.platoon * (samples + PLATOON_SPACING_FRAMES)
    has = recording.leader >= 0
    preceding = np.where(has, ids[np.maximum(recording.leader, 0)], 0)
    following = np.zeros((n, samples), int)
    for j in range(n):
        ahead = recording.leader[j]
        following[ahead[ahead >= 0], np.flatnonzero(ahead >= 0)] = ids[j]
    speed = recording.v
    time_headway = np.where(
        has, np.where(speed > 0.01, recording.headway / np.maximum(speed, 0.01), 9999.99), 0.0
    )
    frames = frame0[:, None] + np.arange(samples)[None, :]
    columns = [
        np.repeat(ids, samples),
        frames.ravel(),
        np.full(n * samples, samples),
        1_113_433_135_300 + frames.ravel() * 100,
        np.where(recording.lane == 1, 6.0, 18.0).ravel(),
        (recording.x / FOOT_M).ravel(),
        np.repeat(recording.length / FOOT_M, samples),
        np.full(n * samples, WIDTH_M / FOOT_M),
        np.full(n * samples, 2),
        (speed / FOOT_M).ravel(),
        (recording.a / FOOT_M).ravel(),
        recording.lane.ravel(),
        preceding.ravel(),
        following.ravel(),
        (recording.headway / FOOT_M).ravel(),
        time_headway.ravel(),
    ]
    integer = {
        "Vehicle_ID",
        "Frame_ID",
        "Total_Frames",
        "Global_Time",
        "v_Class",
        "Lane_ID",
        "Preceding",
        "Following",
    }
    formats = ["%d" if name in integer else "%.6f" for name in COLUMNS]
    table = np.column_stack([np.asarray(c, np.float64) for c in columns])
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "w") as out:
            np.savetxt(
                out, table, fmt=formats, delimiter=",", header=",".join(COLUMNS), comments=""
            )
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path
