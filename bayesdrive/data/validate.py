"""The one validation layer: every reader's table passes :func:`check_tracks` before it becomes a
:class:`~bayesdrive.data.trajectories.Trajectories`.

Readers only translate their format into the schema (SI units, one row per vehicle and time); every
check of content lives here, so each applies to every format alike. A breach either refuses the
data (a :class:`DataError` naming file, row and column, values shown in the file's own units) or is
recorded: a flag (samples kept but left out of fitting), a repair (the data were changed, e.g. rows
sorted) or an interpretation (e.g. the sampling rate found). docs/data.md lists every check, its
threshold, how the threshold was set and what no check can catch.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import DRIVERS, FLAG_COLUMNS, TRACK_COLUMNS
from bayesdrive.data.units import LENGTH_UNITS, SPEED_UNITS

log = logging.getLogger(__name__)

__all__ = [
    "Checked",
    "check_distance_ratio",
    "check_tracks",
    "empty_flags",
    "increment_ratio",
    "leader_values",
    "plain",
    "validate_tracks",
]

# A passenger car is at most ~6 m long; a median length above this in "metres" is feet.
MAX_CAR_LENGTH_M = 8.0
# A US tractor-trailer is up to ~23 m (NGSIM I-80 has 74-76 ft trucks); longer than this is feet.
MAX_VEHICLE_LENGTH_M = 30.0
# The shortest cars are ~2.5 m (a two-seater); a median below this is metres declared as feet.
MIN_MEDIAN_LENGTH_M = 2.5
# Stopped cars in a jam keep 1-4 m bumper to bumper; a median jam spacing (front to front) far above
# 15 m while speeds are below 2 m/s reads as feet passed as metres.
MAX_JAM_SPACING_M = 15.0
JAM_SPEED_MPS = 2.0
# 252 km/h: above every speed in ../shared/data (max 39.5 m/s, OpenACC Vicolungo) and any road
# vehicle's; km/h read as m/s exceed it at highway speeds (115 km/h -> "115 m/s").
MAX_SPEED_MPS = 70.0
# Sum of position increments over sum of speed x dt, set on ../shared/data only (ngsim_i80_chains,
# openacc_vicolungo, ngsim_merge_episodes, interaction_fixture; benchmarks/unit_ratio_bounds.py):
# 1.000-1.004 per data set and per file; per vehicle 0.991-1.006 (640 of the merge episodes' 645
# vehicles; the other five 1.07-1.73, each from one 3-21 m jump of a slot). The lower bound is the
# geometric midpoint of the lowest vehicle (0.991) and km/h read as ft/s (0.911, 10% too fast): 4%
# margin either side; the upper bound mirrors it. A feet/metre mix gives 3.28 or 0.30, km/h read as m/s
# 0.28, mph read as ft/s 1.47.
INCREMENT_RATIO = (0.95, 1.05)
# ENU path length (GNSS) over integrated speed, OpenACC only: 0.995-1.018 per car on
# openacc_vicolungo, and a noisy path only grows, so the bound stays wide; the format's speeds are
# SI, and km/h there give 0.28.
ENU_PATH_RATIO = (0.67, 1.5)
# A ratio within 3% of what a unit mix-up gives is named as that mix-up in the error.
UNIT_MATCH = 0.03
# Slope of gap increments on the relative speed x dt (least squares through 0). 0.81 (OpenACC
# Vicolungo, GNSS gaps), 1.00 (chains, merge episodes); km/h speeds give ~0.25, feet gaps 3.3.
GAP_RATE = (0.5, 2.0)
# The ratio checks need this much expected motion (m) to say anything.
MIN_MOTION_M = 20.0
# A step in which a gap changes by more than this (50 m/s at 10 Hz) is a jump, not motion: the
# gap-rate check leaves it out (gap jumps are flagged or compared with positions elsewhere).
GAP_JUMP_M = 5.0
# A gap column that disagrees with the positions by more than a car length is flagged.
GAP_MISMATCH_M = 5.0
# A time this far off the dt grid (in units of dt) is not float rounding but a wrong sampling rate.
GRID_TOLERANCE = 1e-3


def plain(value: object) -> str:
    """A number as the file would show it (``10.05``, not ``np.float64(10.05)``)."""
    try:
        return f"{float(value):.10g}"
    except (TypeError, ValueError):
        return str(value)


@dataclasses.dataclass(frozen=True)
class Checked:
    """A table that passed :func:`check_tracks`: typed and sorted, with what the checks found.

    ``dt`` may be a multiple of the declared interval (the rate found in the data); ``repairs``
    changed the data, ``findings`` are interpretations; both are to be logged and recorded.
    """

    tracks: pd.DataFrame
    dt: float
    flags: pd.DataFrame
    repairs: tuple[str, ...]
    findings: tuple[str, ...]


def _where(source: str, frame: pd.DataFrame, index, column: str) -> str:
    """'file, row R, column C' for an error message; rows carry their source row when known.

    A ``_file`` column, if present, names each row's own file (readers that merge several files
    into one table set it), so the message names the file the row came from.
    """
    row = frame.loc[index, "_row"] if "_row" in frame.columns else index
    if "_file" in frame.columns and isinstance(frame.loc[index, "_file"], str):
        source = frame.loc[index, "_file"]
    return f"{source}, row {row}, column {column!r}"


def empty_flags() -> pd.DataFrame:
    return pd.DataFrame(
        {c: pd.Series(dtype="object" if c != "t" else "float64") for c in FLAG_COLUMNS}
    )


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


class _Context:
    """Source name, shown column names and unit factors for the messages of one check run."""

    def __init__(self, source, column_names, file_units):
        self.source = source
        self.names = dict(column_names or {})
        self.factors = dict(file_units or {})

    def shown(self, column: str) -> str:
        return self.names.get(column, column)

    def value(self, column: str, si: float) -> str:
        """A value in the file's own units, with the SI figure where they differ."""
        factor = self.factors.get(column, 1.0)
        if factor == 1.0:
            return plain(si)
        return f"{plain(si / factor)} (= {si:.4g} in SI units)"

    def where(self, frame: pd.DataFrame, index, column: str) -> str:
        return _where(self.source, frame, index, self.shown(column))


def check_tracks(
    tracks: pd.DataFrame,
    *,
    source: str,
    dt: float,
    column_names: Mapping[str, str] | None = None,
    file_units: Mapping[str, float] | None = None,
    measured_gap: bool = False,
) -> Checked:
    """Check a schema table (SI units) and return it typed, sorted and with what was found.

    ``column_names`` maps schema columns to the source's own names and ``file_units`` gives the
    factor from the file's unit to SI per schema column, so messages name what the user sees in the
    file. A ``_row`` column gives source row numbers and a ``_file`` column each row's file; both
    are dropped from the result. ``measured_gap`` says the gap column was measured independently of
    the positions (NGSIM ``Space_Headway``, a mapped gap column), so the two are compared.
    """
    ctx = _Context(source, column_names, file_units)
    _check_schema(tracks, ctx, dt)
    repairs: list[str] = []
    findings: list[str] = []

    ordered = tracks.reset_index(drop=True)
    back = ordered.groupby("vehicle_id", sort=False)["t"].diff() < 0
    if back.any():
        first = back.idxmax()
        repairs.append(
            f"{source}: rows of {ordered.loc[back, 'vehicle_id'].nunique()} vehicle(s) are not in "
            f"time order (first: {ctx.where(ordered, first, 't')}, vehicle "
            f"{ordered.loc[first, 'vehicle_id']}); sorted by time"
        )
    ordered = ordered.sort_values(["vehicle_id", "t"], kind="stable").reset_index(drop=True)
    dt = _check_time(ordered, ctx, dt, findings)
    _check_leaders(ordered, ctx)
    _check_plausible(ordered, ctx, dt)

    typed = ordered.drop(columns=[c for c in ordered.columns if c not in TRACK_COLUMNS])
    typed = typed.astype(TRACK_COLUMNS)
    typed["leader_id"] = typed["leader_id"].where(typed["leader_id"].notna(), None)
    flags = [_flag_negative_gaps(typed)]
    if measured_gap:
        flags.append(_flag_gap_mismatch(typed, dt))
    flags = [f for f in flags if len(f)]
    return Checked(
        tracks=typed,
        dt=dt,
        flags=pd.concat(flags, ignore_index=True) if flags else empty_flags(),
        repairs=tuple(repairs),
        findings=tuple(findings),
    )


def validate_tracks(tracks: pd.DataFrame, *, source: str, dt: float) -> pd.DataFrame:
    """:func:`check_tracks` for a table built in code (simulations, tests): the checked table.

    Such a table must need nothing: a repair or a reinterpretation (e.g. of the sampling rate)
    is an error here, since no reader's notes would record it.
    """
    checked = check_tracks(tracks, source=source, dt=dt)
    changed = [*checked.repairs, *checked.findings]
    if changed:
        raise DataError(f"{source}: a table built in code needs no repair, but: {changed[0]}")
    return checked.tracks


def _check_schema(tracks: pd.DataFrame, ctx: _Context, dt: float) -> None:
    source = ctx.source
    if len(tracks) == 0:
        raise DataError(f"{source}: no data rows (empty file or nothing left after the header)")
    missing = [c for c in TRACK_COLUMNS if c not in tracks.columns]
    if missing:
        raise DataError(f"{source}: missing column(s) {', '.join(ctx.shown(c) for c in missing)}")
    if not (np.isfinite(dt) and dt > 0):
        raise DataError(f"{source}: sampling interval must be positive, got {plain(dt)}")
    for column in ("t", "x", "v", "length"):
        bad = tracks[column].isna() | ~np.isfinite(tracks[column].astype(float))
        if bad.any():
            first = bad.idxmax()
            raise DataError(
                f"{ctx.where(tracks, first, column)}: value is NaN or infinite "
                f"({int(bad.sum())} such row(s) in all)"
            )
    for column, what in (("v", "negative speed"), ("length", "non-positive vehicle length")):
        bad = tracks[column] < 0 if column == "v" else tracks[column] <= 0
        if bad.any():
            first = bad.idxmax()
            raise DataError(
                f"{ctx.where(tracks, first, column)}: {what} "
                f"{ctx.value(column, tracks.loc[first, column])}"
            )
    unknown = ~tracks["driver"].isin(DRIVERS)
    if unknown.any():
        first = unknown.idxmax()
        raise DataError(
            f"{ctx.where(tracks, first, 'driver')}: driver must be one of {', '.join(DRIVERS)}, "
            f"got {tracks.loc[first, 'driver']!r}"
        )


def _check_time(ordered: pd.DataFrame, ctx: _Context, dt: float, findings: list[str]) -> float:
    """Duplicates and off-grid steps refuse; the rate found in the steps may replace ``dt``."""
    step = ordered.groupby("vehicle_id", sort=False)["t"].diff()
    duplicate = step == 0
    if duplicate.any():
        first = duplicate.idxmax()
        raise DataError(
            f"{ctx.where(ordered, first, 't')}: duplicate frame for vehicle "
            f"{ordered.loc[first, 'vehicle_id']} at t={plain(ordered.loc[first, 't'])} s"
        )
    ratio = step / dt
    off_grid = step.notna() & (np.abs(ratio - np.round(ratio)) > GRID_TOLERANCE)
    if off_grid.any():
        first = off_grid.idxmax()
        raise DataError(
            f"{ctx.where(ordered, first, 't')}: time step {step[first]:.6g} s is not "
            f"a multiple of the sampling interval {plain(dt)} s"
        )
    multiples = np.round(ratio[step.notna()]).astype(np.int64).to_numpy()
    factor = int(np.gcd.reduce(multiples)) if len(multiples) else 1
    if factor > 1:
        found = round(factor * dt, 9)
        findings.append(
            f"{ctx.source}: every time step is a multiple of {factor} x {plain(dt)} s: the data "
            f"are sampled every {plain(found)} s ({plain(1 / found)} Hz), not at "
            f"{plain(1 / dt)} Hz with missing samples; sampling interval set to {plain(found)} s"
        )
        return found
    return dt


def _check_leaders(ordered: pd.DataFrame, ctx: _Context) -> None:
    leaders = ordered["leader_id"]
    own = leaders.notna() & (leaders.astype(object) == ordered["vehicle_id"].astype(object))
    if own.any():
        first = own.idxmax()
        raise DataError(
            f"{ctx.where(ordered, first, 'leader_id')}: vehicle "
            f"{ordered.loc[first, 'vehicle_id']} is named as its own leader"
        )
    dangling = leaders.notna() & ~leaders.isin(set(ordered["vehicle_id"]))
    if dangling.any():
        first = dangling.idxmax()
        raise DataError(
            f"{ctx.where(ordered, first, 'leader_id')}: leader id "
            f"{ordered.loc[first, 'leader_id']!r} names no vehicle in the data"
        )
    no_gap = leaders.notna() & ordered["gap"].isna()
    if no_gap.any():
        first = no_gap.idxmax()
        raise DataError(f"{ctx.where(ordered, first, 'gap')}: vehicle has a leader but no gap")


def _check_plausible(tracks: pd.DataFrame, ctx: _Context, dt: float) -> None:
    """Units and rates: what no single value shows but the data as a whole do."""
    too_fast = tracks["v"] > MAX_SPEED_MPS
    if too_fast.any():
        first = too_fast.idxmax()
        raise DataError(
            f"{ctx.where(tracks, first, 'v')}: speed {ctx.value('v', tracks.loc[first, 'v'])} "
            f"is above {plain(MAX_SPEED_MPS)} m/s ({plain(MAX_SPEED_MPS * 3.6)} km/h), not "
            "plausible for a road vehicle; is the column in km/h or another unit?"
        )
    _refuse_wrong_length_units(tracks, ctx)
    moved, expected = _position_increments(tracks, dt)
    _refuse_ratio(
        tracks, ctx, moved, expected, INCREMENT_RATIO, ("x", "v"), "positions advance", "the speeds"
    )

    vehicle = tracks.groupby("vehicle_id", sort=False)
    consecutive = _consecutive(tracks, dt)
    step = vehicle["t"].diff()
    relative = leader_values(tracks, "v", dt) - tracks["v"]
    same_leader = consecutive & tracks["leader_id"].notna()
    same_leader &= tracks["leader_id"].eq(vehicle["leader_id"].shift())
    closing = (0.5 * (relative + relative.groupby(tracks["vehicle_id"]).shift()) * step).where(
        same_leader
    )
    gap_change = vehicle["gap"].diff().where(same_leader)
    smooth = (gap_change.abs() <= GAP_JUMP_M) & (closing.abs() <= GAP_JUMP_M)
    _refuse_ratio(
        tracks,
        ctx,
        gap_change.where(smooth),
        closing.where(smooth),
        GAP_RATE,
        ("gap", "v"),
        "gaps change",
        "the relative speeds",
        slope=True,
    )


def _consecutive(tracks: pd.DataFrame, dt: float) -> pd.Series:
    """Rows one ``dt`` after their vehicle's previous row (a row table sorted by vehicle, time)."""
    step = tracks.groupby("vehicle_id", sort=False)["t"].diff()
    return np.abs(step - dt) < 1e-6 * dt


def _position_increments(tracks: pd.DataFrame, dt: float) -> tuple[pd.Series, pd.Series]:
    """Each step's position increment and trapezoid speed x dt; NaN where not comparable."""
    vehicle = tracks.groupby("vehicle_id", sort=False)
    step = vehicle["t"].diff()
    # A change of lane may re-base x (INTERACTION restarts x in each lanelet): not motion.
    lane = tracks["lane_id"].astype("Int64")
    same_lane = (lane == lane.groupby(tracks["vehicle_id"], sort=False).shift()).fillna(True)
    comparable = _consecutive(tracks, dt) & same_lane.astype(bool)
    expected = (0.5 * (tracks["v"] + vehicle["v"].shift()) * step).where(comparable)
    return vehicle["x"].diff().where(comparable), expected


def _ratio(observed, expected, *, slope: bool) -> tuple[float, pd.Series] | None:
    """Sum (or least-squares slope) of ``observed`` over ``expected`` increments and the steps it
    used; None with too few steps or too little motion to say anything."""
    usable = observed.notna() & expected.notna()
    if usable.sum() < 10 or expected[usable].abs().sum() < MIN_MOTION_M:
        return None
    o, e = observed[usable], expected[usable]
    return (float((o * e).sum() / (e * e).sum()) if slope else float(o.sum() / e.sum())), usable


def increment_ratio(tracks: pd.DataFrame, dt: float) -> float | None:
    """Sum of position increments over sum of speed x dt, as the check of :data:`INCREMENT_RATIO`
    computes it on a checked table (sorted by vehicle and time); None without enough motion."""
    found = _ratio(*_position_increments(tracks, dt), slope=False)
    return None if found is None else found[0]


def _refuse_ratio(
    tracks, ctx, observed, expected, bounds, columns, what, against, *, slope=False
) -> None:
    """Refuse when ``observed`` increments are not ``expected`` ones within ``bounds``."""
    found = _ratio(observed, expected, slope=slope)
    if found is None:
        return
    ratio, usable = found
    if bounds[0] <= ratio <= bounds[1]:
        return
    first = usable.idxmax()
    mixups = _unit_mixups(ratio, ctx, columns)
    cause = (
        "; or ".join(mixups)
        if mixups
        else f"columns {ctx.shown(columns[0])!r} and {ctx.shown(columns[1])!r} are not in matching "
        "units (feet and metres? km/h and m/s?) or the time column is scaled wrongly"
    )
    raise DataError(
        f"{ctx.where(tracks, first, columns[0])}: {what} {ratio:.2f} times as much as "
        f"{against} say over {int(usable.sum())} steps (expected {bounds[0]:g} to "
        f"{bounds[1]:g}): {cause}"
    )


def _unit_mixups(ratio: float, ctx: _Context, columns: tuple[str, str]) -> list[str]:
    """The unit mix-ups, of the speeds or of the distances, that give ``ratio`` (distance
    increments over speed x dt) within :data:`UNIT_MATCH`, each as a phrase naming the column."""
    found = []
    distance, speed = columns
    for units, column, quantity, gives in (
        (SPEED_UNITS, speed, "speeds", lambda declared, true: true / declared),
        (LENGTH_UNITS, distance, "distances", lambda declared, true: declared / true),
    ):
        declared = ctx.factors.get(column, 1.0)
        names = [name for name, factor in units.items() if np.isclose(factor, declared)]
        if not names:  # a declared factor that is no named unit (a corrected conversion)
            continue
        for name, factor in units.items():
            mixup = gives(declared, factor)
            if name != names[0] and abs(np.log(ratio / mixup)) < np.log1p(UNIT_MATCH):
                found.append(
                    f"column {ctx.shown(column)!r} looks like {quantity} in {name} read as "
                    f"{names[0]} (that mix-up gives {mixup:.2f})"
                )
    return found


def check_distance_ratio(measured_m: float, integrated_m: float, *, where: str, what: str) -> None:
    """Refuse a distance measured independently of the speeds (an OpenACC ENU path) that is not
    the integrated speed within :data:`ENU_PATH_RATIO`: the speed column is in another unit."""
    if integrated_m < MIN_MOTION_M:
        return
    ratio = measured_m / integrated_m
    if not ENU_PATH_RATIO[0] <= ratio <= ENU_PATH_RATIO[1]:
        raise DataError(
            f"{where}: {what} is {ratio:.2f} times the distance the speeds integrate to "
            f"({measured_m:.0f} m against {integrated_m:.0f} m; expected {ENU_PATH_RATIO[0]:g} to "
            f"{ENU_PATH_RATIO[1]:g}): is the speed in km/h or another unit?"
        )


def _refuse_wrong_length_units(tracks: pd.DataFrame, ctx: _Context) -> None:
    """Refuse lengths or jam spacings that can only be feet read as metres, or the reverse.

    Congested speeds in ft/s (10-30) still look like plausible m/s, so speed alone cannot tell;
    vehicle length and the spacing of stopped cars can.
    """
    hint = (
        "the column-map reader takes the unit (--units / units=); other readers declare theirs, "
        "so the file is not in its format's unit"
    )
    too_long = tracks["length"] > MAX_VEHICLE_LENGTH_M
    median_length = float(tracks["length"].median())
    if median_length > MAX_CAR_LENGTH_M or too_long.any():
        first = too_long.idxmax() if too_long.any() else tracks.index[0]
        raise DataError(
            f"{ctx.where(tracks, first, 'length')}: vehicle lengths (median "
            f"{median_length:.1f} m after conversion) are too long to be metres; are these feet? "
            + hint
        )
    if median_length < MIN_MEDIAN_LENGTH_M:
        raise DataError(
            f"{ctx.where(tracks, tracks.index[0], 'length')}: vehicle lengths (median "
            f"{median_length:.2f} m after conversion) are too short for cars; are metres "
            "declared as feet? " + hint
        )
    jammed = tracks["leader_id"].notna() & (tracks["v"] < JAM_SPEED_MPS)
    if jammed.sum() >= 10:
        spacing = (tracks.loc[jammed, "gap"] + tracks.loc[jammed, "length"]).median()
        if spacing > MAX_JAM_SPACING_M:
            first = jammed.idxmax()
            raise DataError(
                f"{ctx.where(tracks, first, 'gap')}: stopped vehicles keep a median "
                f"spacing of {spacing:.1f} m after conversion, too long for metres; are these "
                "feet? " + hint
            )


def _flag_negative_gaps(tracks: pd.DataFrame) -> pd.DataFrame:
    """Samples whose bumper gap is not positive: physically impossible, so never fitted."""
    bad = tracks["gap"].notna() & (tracks["gap"] <= 0)
    flagged = tracks.loc[bad]
    return _flags(
        flagged,
        "negative_gap",
        [
            f"bumper gap {g:.2f} m to leader {lead}"
            for g, lead in zip(flagged["gap"], flagged["leader_id"], strict=True)
        ],
    )


def _flag_gap_mismatch(tracks: pd.DataFrame, dt: float) -> pd.DataFrame:
    """Samples whose measured gap disagrees with the positions by more than a car length."""
    from_positions = (
        leader_values(tracks, "x", dt) - tracks["x"] - leader_values(tracks, "length", dt)
    )
    bad = (tracks["gap"] - from_positions).abs() > GAP_MISMATCH_M
    flagged = tracks.loc[bad]
    return _flags(
        flagged,
        "gap_mismatch",
        [
            f"gap column {g:.2f} m, positions give {p:.2f} m to leader {lead}"
            for g, p, lead in zip(
                flagged["gap"], from_positions[bad], flagged["leader_id"], strict=True
            )
        ],
    )


def _flags(flagged: pd.DataFrame, kind: str, messages: list[str]) -> pd.DataFrame:
    if flagged.empty:
        return empty_flags()
    # A note, not a warning: the flags travel with the data and every summary counts them.
    log.info("%d sample(s) flagged (%s)", len(flagged), kind)
    return pd.DataFrame(
        {
            "vehicle_id": flagged["vehicle_id"].to_numpy(),
            "t": flagged["t"].to_numpy(),
            "kind": kind,
            "message": messages,
        }
    )
