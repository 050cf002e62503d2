"""Derived views of a :class:`Trajectories`: the fitting/held-out split and the padded per-step
arrays the engines and the simulator consume.

The split rule (recorded in every result's metadata as :data:`SPLIT_RULE`): each vehicle's own time
axis is cut once; the first ``FIT_FRACTION`` of its samples form the fitting window and the rest the
later held-out window. Deduplicated vehicles are split once, so no evaluation ever scores on data a
fit has seen, whichever chain a copy came from.
"""

from __future__ import annotations

import logging
import math
from typing import Literal, NamedTuple

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories

__all__ = [
    "FIT_FRACTION",
    "HISTORY_SECONDS",
    "SPLIT_RULE",
    "AheadArrays",
    "FollowerArrays",
    "MergeArrays",
    "ScoredWindows",
    "follower_arrays",
    "full_history_mask",
    "history_steps",
    "leader_follower_pairs",
    "pooled_series",
    "scored_series",
    "split_time",
]

log = logging.getLogger(__name__)

FIT_FRACTION = 0.7
SPLIT_RULE = (
    f"per vehicle, on its own time axis: first {FIT_FRACTION:.0%} of samples = fitting window, "
    f"the rest = held-out window"
)
# Pad step counts up to a multiple of this, so JAX compiles once per bucket, not per vehicle length.
LENGTH_BUCKET = 64
# The longest reaction delay the models consider (the delay prior's upper bound) sets the history
# a model may read behind each step.
HISTORY_SECONDS = 1.5


def history_steps(dt: float) -> int:
    """K: how many past steps a model may read at sampling interval dt: a history of
    :data:`HISTORY_SECONDS`, and two steps more, so that a model remembering its previous two
    steps (autocorrelated noise) can wrap one that reads the whole history (a reaction delay)."""
    return math.ceil(HISTORY_SECONDS / dt - 1e-9) + 2


def full_history_mask(mask: np.ndarray, history: int) -> np.ndarray:
    """The usable steps of ``mask`` (N, T) with ``history`` usable steps before them (bool): the
    steps every model scores, with or without memory, so comparisons are like for like."""
    usable = np.asarray(mask) > 0
    kept = usable.copy()
    for k in range(1, history + 1):
        kept[:, k:] &= usable[:, :-k]
        kept[:, :k] = False
    return kept


Window = Literal["fit", "heldout", "all"]


class MergeArrays(NamedTuple):
    """The merge scene beside each step of :class:`FollowerArrays`, for merging models (C-IDM).

    Distances are front-bumper distances to the merge point along each car's own lane (m,
    negative once past it); K merge-lane slots per step, padded slots with ``merge_present`` 0.
    ego_to_merge: (N, T). merge_to_merge, merge_v, merge_length, merge_present: (N, T, K).
    The field order is that of the trailing fields of ``bayesdrive.drivers.cidm.MergeInputs``.
    """

    ego_to_merge: np.ndarray
    merge_to_merge: np.ndarray
    merge_v: np.ndarray
    merge_length: np.ndarray
    merge_present: np.ndarray


class AheadArrays(NamedTuple):
    """What lies ahead of the leader, beside each step of :class:`FollowerArrays` (N, T).

    lead_acc: the leader's acceleration, backward difference of its observed speed (m/s^2; 0
        where the leader has no previous sample).
    gap2: bumper gap to the leader plus the leader's bumper gap to its own leader (m).
    lead2_v: speed of the second vehicle ahead (m/s).
    has_leader2: 1.0 where a second vehicle ahead is known, else 0.0 (gap2, lead2_v then padded).
    lead_age: how many samples before this one the current leader has been the leader without a
        break (0 on the sample a leader cuts in or appears; a model with a delay perceives a new
        leader from its entry on).
    """

    lead_acc: np.ndarray
    gap2: np.ndarray
    lead2_v: np.ndarray
    has_leader2: np.ndarray
    lead_age: np.ndarray


class ScoredWindows(NamedTuple):
    """Which steps a model comparison scores (N, T): ``fit`` and ``heldout`` are the usable steps
    of the fitting and the held-out window that have a full :data:`HISTORY_SECONDS` of usable
    steps before them, so every model, with or without memory, is scored on the same steps."""

    fit: np.ndarray
    heldout: np.ndarray


class FollowerArrays(NamedTuple):
    """The one per-vehicle series: per-step arrays of N vehicles, padded to T steps (numpy,
    float64; engines cast). Every driver model builds its inputs from it (``model.inputs_at``).

    Step t scores the transition from sample t to sample t+1 of vehicle n. ``mask[n, t]`` is 1
    where that transition is real and usable (both samples present, one dt apart, no flagged
    sample, inside the chosen window), else 0; padded entries hold harmless finite values.
    ``dx`` is the position increment x[t+1] - x[t], computed in float64 before any cast.
    The scene parts a model may read beyond its leader are None where the data have none:
    ``merge`` the merge scene (merging models), ``ahead`` the second vehicle ahead and the
    leader's acceleration (filled from trajectories), ``windows`` the scored fitting and held-out
    steps of a model comparison (:func:`scored_series`).
    """

    vehicle_ids: tuple[str, ...]
    v: np.ndarray
    next_v: np.ndarray
    dx: np.ndarray
    gap: np.ndarray
    lead_v: np.ndarray
    has_leader: np.ndarray
    mask: np.ndarray
    t: np.ndarray
    dt: float
    merge: MergeArrays | None = None
    ahead: AheadArrays | None = None
    windows: ScoredWindows | None = None

    @property
    def num_steps(self) -> np.ndarray:
        return self.mask.sum(axis=1).astype(int)

    @property
    def history(self) -> int:
        """Steps of history a model may read behind each step (:func:`history_steps`)."""
        return history_steps(self.dt)

    @property
    def full_history_mask(self) -> np.ndarray:
        """:func:`full_history_mask` of these series."""
        return full_history_mask(self.mask, self.history)

    def subset(self, rows) -> FollowerArrays:
        """The same series restricted to some vehicle rows (an index array or slice)."""
        index = np.arange(len(self.vehicle_ids))[rows]

        def pick(value):
            if isinstance(value, np.ndarray):
                return value[index]
            if isinstance(value, tuple) and value and isinstance(value[0], np.ndarray):
                return type(value)(*(a[index] for a in value))
            return value

        picked = {name: pick(value) for name, value in self._asdict().items()}
        picked["vehicle_ids"] = tuple(self.vehicle_ids[i] for i in index)
        return self._replace(**picked)


def split_time(times: np.ndarray) -> float:
    """The first time of the held-out window for a vehicle sampled at ``times``."""
    ordered = np.sort(np.asarray(times))
    return float(ordered[int(np.floor(FIT_FRACTION * len(ordered)))])


def leader_follower_pairs(traj: Trajectories, *, include_flagged: bool = False) -> pd.DataFrame:
    """Distinct (follower, leader) pairs with sample counts; flagged pairs left out by default."""
    rows = traj.tracks[traj.tracks["leader_id"].notna()]
    pairs = (
        rows.groupby(["vehicle_id", "leader_id"], sort=True)["t"]
        .agg(samples="size", t_start="min", t_end="max")
        .reset_index()
        .rename(columns={"vehicle_id": "follower_id"})
    )
    flagged = set(traj.flags["vehicle_id"])
    pairs["flagged"] = pairs["follower_id"].isin(flagged)
    return pairs if include_flagged else pairs[~pairs["flagged"]].reset_index(drop=True)


def follower_arrays(
    traj: Trajectories,
    *,
    window: Window = "fit",
    vehicle_ids: list[str] | None = None,
    require_leader: bool = True,
    bucket: int = LENGTH_BUCKET,
) -> FollowerArrays:
    """Padded per-step arrays for fitting or scoring, one row per vehicle.

    With ``require_leader`` (the default) only steps with a leader are used, because the free-road
    term alone leaves d_min, tau and b_pref unidentified. Flagged samples are masked out; how many
    steps that removes is logged.
    """
    tracks = traj.tracks
    ids = list(vehicle_ids) if vehicle_ids is not None else traj.vehicle_ids
    # A dict, not a MultiIndex lookup: the speeds are read sample by sample below.
    speed_of = dict(
        zip(zip(tracks["vehicle_id"], tracks["t"], strict=True), tracks["v"], strict=True)
    )
    flagged = set(zip(traj.flags["vehicle_id"], np.round(traj.flags["t"], 6), strict=True))

    per_vehicle = []
    dropped_flagged = 0
    for vid in ids:
        rows = traj.vehicle(vid)
        t = rows["t"].to_numpy()
        x = rows["x"].to_numpy(dtype=np.float64)
        v = rows["v"].to_numpy(dtype=np.float64)
        gap = rows["gap"].to_numpy(dtype=np.float64)
        leader = rows["leader_id"].to_numpy()
        has_leader = np.array([lead is not None and lead == lead for lead in leader])
        lead_v = np.array(
            [
                speed_of.get((lead, tt), np.nan) if has else np.nan
                for lead, tt, has in zip(leader, t, has_leader, strict=True)
            ]
        )
        consecutive = np.isclose(np.diff(t), traj.dt)
        usable = consecutive & np.isfinite(lead_v[:-1]) | (consecutive & ~has_leader[:-1])
        if require_leader:
            usable &= has_leader[:-1]
        bad = np.array([(vid, round(tt, 6)) in flagged for tt in t])
        touched = bad[:-1] | bad[1:]
        dropped_flagged += int((usable & touched).sum())
        usable &= ~touched
        cut = split_time(t)
        if window == "fit":
            usable &= t[1:] < cut
        elif window == "heldout":
            usable &= t[:-1] >= cut
        per_vehicle.append(
            (vid, t[:-1], v[:-1], v[1:], np.diff(x), gap[:-1], lead_v[:-1], has_leader[:-1], usable)
        )
    if dropped_flagged:
        log.info(
            "%d step(s) touching flagged samples left out of the %s window", dropped_flagged, window
        )
    kept = [p for p in per_vehicle if p[-1].any()]
    if not kept:
        raise DataError(f"{traj.source}: no usable car-following steps in the {window!r} window")
    left_out = [p[0] for p in per_vehicle if not p[-1].any()]
    if left_out:
        log.warning(
            "%d of %d vehicle(s) have no usable step in the %s window (one dt apart, unflagged%s) "
            "and are left out: %s",
            len(left_out),
            len(per_vehicle),
            window,
            ", with a leader" if require_leader else "",
            ", ".join(left_out),
        )

    longest = max(len(p[1]) for p in kept)
    width = int(np.ceil(longest / bucket) * bucket)

    def stack(index: int, fill: float) -> np.ndarray:
        out = np.full((len(kept), width), fill, dtype=np.float64)
        for row, p in enumerate(kept):
            values = np.asarray(p[index], dtype=np.float64)
            out[row, : len(values)] = np.where(np.isfinite(values), values, fill)
        return out

    arrays = FollowerArrays(
        vehicle_ids=tuple(p[0] for p in kept),
        t=stack(1, 0.0),
        v=stack(2, 1.0),
        next_v=stack(3, 1.0),
        dx=stack(4, 0.1),
        gap=stack(5, 10.0),
        lead_v=stack(6, 1.0),
        has_leader=stack(7, 0.0),
        mask=stack(8, 0.0),
        dt=float(traj.dt),
    )
    return arrays._replace(ahead=_ahead_arrays(traj, arrays))


def _second_vehicle_and_leader_acc(traj: Trajectories) -> pd.DataFrame:
    """Per sample: the second vehicle ahead (gap2, lead2_v) and the leader's acceleration."""
    tracks = traj.tracks
    frame = np.round(tracks["t"].to_numpy() / traj.dt).astype(np.int64)
    own = pd.DataFrame(
        {
            "vehicle_id": tracks["vehicle_id"].to_numpy(),
            "frame": frame,
            "v": tracks["v"].to_numpy(dtype=np.float64),
            "gap": tracks["gap"].to_numpy(dtype=np.float64),
            "leader_id": tracks["leader_id"].to_numpy(),
        }
    )
    previous = own[["vehicle_id", "frame", "v"]].assign(frame=own["frame"] + 1)
    own = own.merge(
        previous.rename(columns={"v": "v_before"}), on=["vehicle_id", "frame"], how="left"
    )
    leader_rows = own.rename(
        columns={
            "vehicle_id": "leader_id",
            "v": "lead_v",
            "gap": "lead_gap",
            "leader_id": "lead2_id",
            "v_before": "lead_v_before",
        }
    )
    joined = own[["vehicle_id", "frame", "gap", "leader_id"]].merge(
        leader_rows, on=["leader_id", "frame"], how="left"
    )
    lead_acc = (joined["lead_v"] - joined["lead_v_before"]) / traj.dt
    second = leader_rows[["leader_id", "frame", "lead_v"]].rename(
        columns={"leader_id": "lead2_id", "lead_v": "lead2_v"}
    )
    joined = joined.merge(second, on=["lead2_id", "frame"], how="left")
    has2 = joined["lead2_v"].notna() & joined["lead_gap"].notna() & joined["gap"].notna()
    # Runs of consecutive frames with the same leader; the age counts samples into the run.
    ordered = joined.sort_values(["vehicle_id", "frame"])
    same_vehicle = ordered["vehicle_id"].eq(ordered["vehicle_id"].shift())
    same_leader = (
        ordered["leader_id"].eq(ordered["leader_id"].shift()) & ordered["leader_id"].notna()
    )
    consecutive = ordered["frame"].diff().eq(1)
    run = (~(same_vehicle & same_leader & consecutive)).cumsum()
    lead_age = ordered.groupby(run).cumcount().reindex(joined.index)
    return pd.DataFrame(
        {
            "vehicle_id": joined["vehicle_id"],
            "frame": joined["frame"],
            "lead_acc": lead_acc,
            "gap2": np.where(has2, joined["gap"] + joined["lead_gap"], np.nan),
            "lead2_v": np.where(has2, joined["lead2_v"], np.nan),
            "has_leader2": has2.astype(float),
            "lead_age": lead_age.astype(float),
        }
    )


def _ahead_arrays(traj: Trajectories, arrays: FollowerArrays) -> AheadArrays:
    """The scene ahead of each step of ``arrays``, read from ``traj`` (padding as documented)."""
    dt = arrays.dt
    extras = _second_vehicle_and_leader_acc(traj).set_index(["vehicle_id", "frame"])
    shape = arrays.mask.shape
    out = {name: np.zeros(shape) for name in AheadArrays._fields}
    no_lead_acc = 0
    for row, vid in enumerate(arrays.vehicle_ids):
        frames = np.round(traj.vehicle(vid)["t"].to_numpy()[:-1] / dt).astype(np.int64)
        rows = extras.iloc[extras.index.get_indexer([(vid, f) for f in frames])]
        n = len(frames)
        lead_acc = rows["lead_acc"].to_numpy()
        no_lead_acc += int((~np.isfinite(lead_acc) & (arrays.mask[row, :n] > 0)).sum())
        out["lead_acc"][row, :n] = np.nan_to_num(lead_acc, nan=0.0)
        known = rows["has_leader2"].to_numpy() > 0
        out["gap2"][row, :n] = np.where(known, rows["gap2"], 100.0)
        out["lead2_v"][row, :n] = np.where(known, rows["lead2_v"], 1.0)
        out["has_leader2"][row, :n] = known
        out["lead_age"][row, :n] = rows["lead_age"].to_numpy()
    if no_lead_acc:
        log.info(
            "%d usable step(s) have no previous leader sample; their leader acceleration is "
            "taken as 0",
            no_lead_acc,
        )
    return AheadArrays(**out)


def scored_series(traj: Trajectories, *, vehicle_ids: list[str] | None = None) -> FollowerArrays:
    """Every usable step (``mask``: the ``window="all"`` view) with the steps a model comparison
    scores in each window (``windows``, see :class:`ScoredWindows`).

    The first :func:`history_steps` steps of every vehicle and of every stretch after a gap in the
    data are left out of scoring for every model alike (how many steps that removes is logged);
    vehicles without a scored step in both windows are left out, and the count is logged.
    """
    views = {
        name: follower_arrays(traj, window=name, vehicle_ids=vehicle_ids)
        for name in ("all", "fit", "heldout")
    }
    every = views["all"]
    shape = every.mask.shape

    def window_mask(name: str) -> np.ndarray:
        arrays = views[name]
        out = np.zeros(shape)
        row_of = {vid: i for i, vid in enumerate(arrays.vehicle_ids)}
        for row, vid in enumerate(every.vehicle_ids):
            if vid in row_of:
                width = min(shape[1], arrays.mask.shape[1])
                out[row, :width] = arrays.mask[row_of[vid], :width]
        return out

    full_history = every.full_history_mask
    lost = int((every.mask > 0).sum() - full_history.sum())
    if lost:
        log.info(
            "%d step(s) without a full %.1f s history left out of scoring (all models alike)",
            lost,
            every.history * every.dt,
        )
    windows = ScoredWindows(
        fit=window_mask("fit") * full_history, heldout=window_mask("heldout") * full_history
    )
    keep = (windows.fit.sum(axis=1) > 0) & (windows.heldout.sum(axis=1) > 0)
    if not keep.any():
        raise DataError(
            f"{traj.source}: no vehicle has scored steps in both the fitting and the held-out "
            "window (each needs a leader and a full history)"
        )
    if not keep.all():
        log.warning(
            "%d vehicle(s) without scored steps in both windows left out: %s",
            int((~keep).sum()),
            [vid for vid, k in zip(every.vehicle_ids, keep, strict=True) if not k],
        )
    return every._replace(windows=windows).subset(np.flatnonzero(keep))


def pooled_series(
    arrays: FollowerArrays, name: str, *, bucket: int = LENGTH_BUCKET
) -> FollowerArrays:
    """All usable steps of every row as one row named ``name`` (complete pooling: one parameter
    set for all of them). Exact for models whose one-step density depends on the current step
    only, as every base model's does; steps keep their order, row after row."""
    usable = arrays.mask > 0
    count = int(usable.sum())
    if count == 0:
        raise DataError("no usable step to pool")
    width = int(np.ceil(count / bucket) * bucket)

    def pool(values: np.ndarray) -> np.ndarray:
        picked = values[usable]
        pad = np.repeat(picked[-1:], width - count, axis=0)
        return np.concatenate([picked, pad])[None]

    def pool_part(part):
        return None if part is None else type(part)(*map(pool, part))

    mask = np.zeros((1, width))
    mask[0, :count] = 1.0
    return arrays._replace(
        vehicle_ids=(name,),
        **{
            f: pool(getattr(arrays, f))
            for f in ("v", "next_v", "dx", "gap", "lead_v", "has_leader", "t")
        },
        mask=mask,
        merge=pool_part(arrays.merge),
        ahead=pool_part(arrays.ahead),
        windows=None,
    )
