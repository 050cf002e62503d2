"""NGSIM I-80 car-following chains (``ngsim_i80_chains``): one CSV per chain of 6 vehicles.

Units (:data:`UNITS`): m, m/s, m/s^2, 10 Hz. Columns: ``t1``, then ``IDi, Yi, vi, ai`` for
i = 1..6, vehicle 1 leading, vehicle i+1 following vehicle i in the same lane. ``Y`` is a
longitudinal position, ``Y_lead - Y`` is FRONT-to-front. The files carry no vehicle lengths:
:data:`ASSUMED_LENGTH_M` (4.5 m, an NGSIM I-80 passenger car) is assumed and noted, so the bumper
gap is ``Y_leader - Y - 4.5``; non-positive gaps are flagged, not fitted.

Deduplication. The 75 chains overlap: a vehicle appears in several files as time-shifted copies,
and every file restarts ``t1`` and ``Y`` at 0. For every pair of copies of a vehicle the reader
finds the time shift at which their speed sequences agree exactly (to the 4-decimal rounding) over
their overlap, and the position offset as the mean difference of ``Y`` over it; a copy whose
positions then disagree beyond rounding is refused. Shifts and offsets are per file (all vehicles of
a file share them; checked). Files linked by shared vehicles form connected components; each
component gets one time axis and one position axis (those of its first file), and every vehicle
exists once: the union of its copies' samples. Copies that never overlap in time cannot be aligned;
if they sit in different components the vehicle keeps one id and its samples in each component, and
components are placed in disjoint time windows (component c at ``c * stride`` seconds, see notes)
so that such a vehicle's track has a time hole and an x jump between components rather than two
clashing copies. The scenes table (one scene per file) carries the component id in a ``component``
column. A vehicle's leader per row is taken from whichever chain gives one at that time;
conflicting leaders are an error.

Reading one file works too (no deduplication needed; scene id = file stem).
"""

from __future__ import annotations

import collections
import itertools
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.lib.stride_tricks import sliding_window_view

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers._common import (
    Notes,
    finish,
    gaps_from_positions,
    input_files,
    integer_ids,
    make_tracks,
    merge_copies,
    numeric_columns,
    read_table,
    require_columns,
    snap_to_grid,
    sort_rows,
    time_steps,
)
from bayesdrive.data.trajectories import Trajectories

__all__ = ["ASSUMED_LENGTH_M", "DT", "UNITS", "CopyMatch", "align_copies", "read_ngsim_chains"]

log = logging.getLogger(__name__)

FORMAT = "ngsim_chains"
DT = 0.1
UNITS = {"t1": "s", "Y": "m (front to front between vehicles)", "v": "m/s", "a": "m/s^2"}
ASSUMED_LENGTH_M = 4.5
# Copies sharing fewer samples than this are not matched: a short run of equal speeds (a stopped
# car) could match by chance. Real overlaps here are 10 or more samples.
MIN_OVERLAP = 5
# Speeds and accelerations are written with 4 decimals: copies of one sample agree to this.
VALUE_TOL = 1e-4
# Y is written with 4 decimals, so two aligned copies differ by rounding (< 1e-4) plus the error of
# the mean offset; anything larger is a copy that does not match.
POSITION_TOL = 1e-3
# Components are placed in windows this long (rounded up when a component lasts longer).
COMPONENT_STRIDE_S = 1000.0


@dataclass
class _Slot:
    file: int
    vehicle: str
    steps: np.ndarray  # local step numbers of this file
    y: np.ndarray
    v: np.ndarray
    a: np.ndarray
    rows: np.ndarray
    leader: str | None


@dataclass
class CopyMatch:
    """Copy B of a vehicle aligned on copy A: B's local step j is A's step j + shift."""

    shift: int
    offset: float  # Y_A = Y_B + offset over the overlap
    overlap: int
    y_residual: float


def read_ngsim_chains(path: str | Path, *, length: float = ASSUMED_LENGTH_M) -> Trajectories:
    """Read one chain CSV or the folder of chains, deduplicated onto common axes per component."""
    files = input_files(path, ["*.csv"], what="NGSIM chain")
    notes = Notes(log)
    notes.assume(
        f"no vehicle lengths in the chain files: every vehicle assumed {length} m long "
        "(gap = Y_leader - Y - length)"
    )
    slots: list[_Slot] = []
    for index, file in enumerate(files):
        slots.extend(_read_chain(file, index, notes))
    stems = [f.stem for f in files]

    file_edges = _match_all(slots, stems)
    component_of, time_offset, y_offset = _components(file_edges, len(files), stems)
    n_components = max(component_of) + 1

    # Component c occupies [c * stride, c * stride + span): disjoint windows.
    spans = collections.defaultdict(int)
    for slot in slots:
        c = component_of[slot.file]
        spans[c] = max(spans[c], int(slot.steps[-1] + time_offset[slot.file]) + 1)
    stride = round(COMPONENT_STRIDE_S / DT)
    while max(spans.values()) + round(10 / DT) > stride:
        stride *= 2

    parts = []
    for slot in slots:
        c = component_of[slot.file]
        steps = slot.steps + time_offset[slot.file] + c * stride
        parts.append(
            pd.DataFrame(
                {
                    "vehicle_id": slot.vehicle,
                    "_k": steps,
                    "x": slot.y + y_offset[slot.file],
                    "v": slot.v,
                    "a": slot.a,
                    "leader_id": slot.leader,
                    "_row": slot.rows,
                    "_file": str(files[slot.file]),
                    "_component": c,
                }
            )
        )
    copies = pd.concat(parts, ignore_index=True)
    merged = merge_copies(
        copies,
        tolerances={"x": POSITION_TOL, "v": VALUE_TOL, "a": VALUE_TOL},
        notes=notes,
        what="chains",
    )

    tracks = make_tracks(
        vehicle_id=merged["vehicle_id"].to_numpy(),
        t=time_steps(merged["_k"].to_numpy(), DT),
        x=merged["x"].to_numpy(),
        v=merged["v"].to_numpy(),
        a=merged["a"].to_numpy(),
        leader_id=merged["leader_id"].to_numpy(),
        length=float(length),
        row=merged["_row"].to_numpy(),
        file=merged["_file"].to_numpy(),
    )
    tracks["gap"] = gaps_from_positions(tracks, DT)
    no_leader_sample = tracks["leader_id"].notna() & tracks["gap"].isna()
    if no_leader_sample.any():  # cannot happen for well-formed chains: the leader is on the row
        first = tracks[no_leader_sample].iloc[0]
        raise DataError(
            f"{first['_file']}, row {first['_row']}: leader {first['leader_id']} has no sample "
            f"at t={first['t']}"
        )

    component_names = [f"c{c:02d}" for c in range(n_components)]
    scenes = pd.DataFrame(
        {
            "scene_id": [stems[s.file] for s in slots],
            "vehicle_id": [s.vehicle for s in slots],
            "component": [component_names[component_of[s.file]] for s in slots],
        }
    )
    if len(files) > 1:
        _note_components(notes, copies, component_of, n_components, stride, slots)
    return finish(tracks, fmt=FORMAT, source=path, dt=DT, scenes=scenes, notes=notes)


def _read_chain(path: Path, index: int, notes: Notes) -> list[_Slot]:
    frame = read_table(
        path,
        fmt="NGSIM chain",
        notes=notes,
        text_columns=lambda name: re.fullmatch(r"ID\d+", name) is not None,
    )
    n = 0
    while f"ID{n + 1}" in frame.columns:
        n += 1
    expected = ["t1"] + [f"{c}{i}" for i in range(1, max(n, 1) + 1) for c in ("ID", "Y", "v", "a")]
    require_columns(frame, expected, source=path, fmt="NGSIM chain (t1, IDi, Yi, vi, ai)")
    id_columns = [f"ID{i}" for i in range(1, n + 1)]
    numeric_columns(frame, [c for c in expected if c not in id_columns])
    frame = sort_rows(frame, ["t1"], notes=notes, path=path, what="time")
    steps = snap_to_grid(frame["t1"], DT, frame, column="t1")
    slots = []
    previous = None
    seen = set()
    for i in range(1, n + 1):
        ids = integer_ids(frame, f"ID{i}")
        changed = ids != ids[0]
        if changed.any():
            row = frame["_row"].iloc[int(np.argmax(changed))]
            raise DataError(
                f"{path}, row {row}, column 'ID{i}': vehicle id changes within the file "
                f"({ids[0]} then {ids[int(np.argmax(changed))]}); a chain slot holds one vehicle"
            )
        vehicle = ids[0]
        if vehicle in seen:
            raise DataError(f"{path}, row 2, column 'ID{i}': vehicle {vehicle} occurs twice")
        seen.add(vehicle)
        slots.append(
            _Slot(
                file=index,
                vehicle=vehicle,
                steps=steps,
                y=frame[f"Y{i}"].to_numpy(),
                v=frame[f"v{i}"].to_numpy(),
                a=frame[f"a{i}"].to_numpy(),
                rows=frame["_row"].to_numpy(),
                leader=previous,
            )
        )
        previous = vehicle
    return slots


def align_copies(
    v_a: np.ndarray, y_a: np.ndarray, v_b: np.ndarray, y_b: np.ndarray
) -> CopyMatch | None:
    """Align copy B of a vehicle on copy A by matching speeds exactly; None if they never overlap.

    Both copies are contiguous 10 Hz series starting at their file's step 0. Returns the step
    shift (B's step j is A's step j + shift), the position offset ``mean(Y_A - Y_B)`` over the
    overlap and the largest position residual. Raises ``_Ambiguous`` if several shifts match.
    """
    n_a, n_b = len(v_a), len(v_b)
    m = min(MIN_OVERLAP, n_a, n_b)
    candidates = set()
    # An overlap either starts inside A (B's first samples are in A) or inside B.
    windows_a = sliding_window_view(v_a, m)
    hits = np.nonzero(np.all(np.abs(windows_a - v_b[:m]) <= VALUE_TOL, axis=1))[0]
    candidates.update(int(j) for j in hits)
    windows_b = sliding_window_view(v_b, m)
    hits = np.nonzero(np.all(np.abs(windows_b - v_a[:m]) <= VALUE_TOL, axis=1))[0]
    candidates.update(-int(j) for j in hits)
    verified = []
    for shift in sorted(candidates):
        a0, a1 = max(0, shift), min(n_a, n_b + shift)
        if np.all(np.abs(v_a[a0:a1] - v_b[a0 - shift : a1 - shift]) <= VALUE_TOL):
            verified.append((shift, a0, a1))
    if not verified:
        return None
    if len(verified) > 1:
        raise _Ambiguous([s for s, _, _ in verified])
    shift, a0, a1 = verified[0]
    diff = y_a[a0:a1] - y_b[a0 - shift : a1 - shift]
    offset = float(diff.mean())
    return CopyMatch(shift, offset, a1 - a0, float(np.abs(diff - offset).max()))


class _Ambiguous(Exception):
    def __init__(self, shifts: list[int]) -> None:
        super().__init__(shifts)
        self.shifts = shifts


def _match_all(slots: list[_Slot], stems: list[str]) -> dict[tuple[int, int], list]:
    """Per pair of files (a < b): the alignments implied by their shared vehicles."""
    by_vehicle = collections.defaultdict(list)
    for slot in slots:
        by_vehicle[slot.vehicle].append(slot)
    edges: dict[tuple[int, int], list] = collections.defaultdict(list)
    for vehicle, copies in by_vehicle.items():
        for first, second in itertools.combinations(copies, 2):
            a, b = (first, second) if first.file < second.file else (second, first)
            try:
                match = align_copies(a.v, a.y, b.v, b.y)
            except _Ambiguous as exc:
                log.warning(
                    "vehicle %s: copies in %s and %s match at several shifts %s; not used to align",
                    vehicle,
                    stems[a.file],
                    stems[b.file],
                    exc.shifts,
                )
                continue
            if match is None:
                continue
            if match.y_residual > POSITION_TOL:
                raise DataError(
                    f"vehicle {vehicle}: its copies in {stems[a.file]} and {stems[b.file]} have "
                    f"equal speeds over {match.overlap} samples but positions differ by up to "
                    f"{match.y_residual:.4g} m after aligning: copy does not match, refused"
                )
            edges[(a.file, b.file)].append((vehicle, match))
    for (a, b), matches in edges.items():
        shifts = {m.shift for _, m in matches}
        offsets = [m.offset for _, m in matches]
        if len(shifts) > 1 or max(offsets) - min(offsets) > POSITION_TOL:
            raise DataError(
                f"{stems[a]} and {stems[b]}: shared vehicles imply different alignments "
                f"(shifts {sorted(shifts)}, position offsets {min(offsets):.4f}.."
                f"{max(offsets):.4f} m): the files do not share one time and position axis"
            )
    return edges


def _components(
    edges: dict[tuple[int, int], list], n_files: int, stems: list[str]
) -> tuple[list[int], list[int], list[float]]:
    """Component per file and each file's time/position offset on its component's axes."""
    neighbours = collections.defaultdict(list)
    for (a, b), matches in edges.items():
        shift = matches[0][1].shift
        offset = float(np.mean([m.offset for _, m in matches]))
        # File b's step j is file a's step j + shift; Y_a = Y_b + offset.
        neighbours[a].append((b, shift, offset))
        neighbours[b].append((a, -shift, -offset))
    component = [-1] * n_files
    time_offset = [0] * n_files
    y_offset = [0.0] * n_files
    count = 0
    for root in range(n_files):
        if component[root] >= 0:
            continue
        component[root] = count
        queue = [root]
        members = [root]
        while queue:
            u = queue.pop()
            for w, shift, offset in neighbours[u]:
                if component[w] < 0:
                    component[w] = count
                    time_offset[w] = time_offset[u] + shift
                    y_offset[w] = y_offset[u] + offset
                    queue.append(w)
                    members.append(w)
        start = min(time_offset[m] for m in members)  # component time starts at 0
        for m in members:
            time_offset[m] -= start
        count += 1
    # Every link, not only the spanning tree, must agree (a cycle of files must close).
    for (a, b), matches in edges.items():
        shift = matches[0][1].shift
        offset = float(np.mean([m.offset for _, m in matches]))
        if (
            time_offset[b] - time_offset[a] != shift
            or abs(y_offset[b] - y_offset[a] - offset) > POSITION_TOL
        ):
            raise DataError(
                f"{stems[a]} and {stems[b]}: alignment through other files disagrees with their "
                "direct alignment (a cycle of chains does not close)"
            )
    return component, time_offset, y_offset


def _note_components(
    notes: Notes,
    copies: pd.DataFrame,
    component_of: list[int],
    n_components: int,
    stride: int,
    slots: list[_Slot],
) -> None:
    notes.assume(
        f"{len(slots)} vehicle slots in {len(component_of)} files hold "
        f"{copies['vehicle_id'].nunique()} distinct vehicles; files linked by shared vehicles form "
        f"{n_components} components (scenes.component), each with one time and position axis; "
        f"component c starts at t = c * {stride * DT:g} s"
    )
    spread = copies.groupby("vehicle_id")["_component"].nunique()
    split = sorted(spread[spread > 1].index, key=int)
    if split:
        notes.assume(
            f"{len(split)} vehicle(s) ({', '.join(split)}) have copies that never overlap in time "
            "in different components, so those copies cannot be aligned: each such vehicle keeps "
            "one id with a time hole and an x jump between its components' windows"
        )
