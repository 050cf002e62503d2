"""Derived views of a :class:`Trajectories`: the fitting/held-out split and the padded per-step
arrays the engines and the simulator consume.

The split rule (recorded in every result's metadata as :data:`SPLIT_RULE`): each vehicle's own time
axis is cut once; the first ``FIT_FRACTION`` of its samples form the fitting window and the rest the
later held-out window. Deduplicated vehicles are split once, so no evaluation ever scores on data a
fit has seen, whichever chain a copy came from.
"""

from __future__ import annotations

import logging
from typing import Literal, NamedTuple

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories

__all__ = [
    "FIT_FRACTION",
    "SPLIT_RULE",
    "FollowerArrays",
    "MergeArrays",
    "follower_arrays",
    "leader_follower_pairs",
    "pooled_series",
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


class FollowerArrays(NamedTuple):
    """Per-step arrays of N vehicles, padded to T steps (numpy, float64; engines cast).

    Step t scores the transition from sample t to sample t+1 of vehicle n. ``mask[n, t]`` is 1
    where that transition is real and usable (both samples present, one dt apart, no flagged
    sample, inside the chosen window), else 0; padded entries hold harmless finite values.
    ``dx`` is the position increment x[t+1] - x[t], computed in float64 before any cast.
    ``merge`` holds the merge scene for merging models (None for plain car following).
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

    @property
    def num_steps(self) -> np.ndarray:
        return self.mask.sum(axis=1).astype(int)


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
    speed_of = tracks.set_index(["vehicle_id", "t"])["v"]
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

    return FollowerArrays(
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

    merge = None if arrays.merge is None else MergeArrays(*map(pool, arrays.merge))
    mask = np.zeros((1, width))
    mask[0, :count] = 1.0
    return arrays._replace(
        vehicle_ids=(name,),
        **{
            f: pool(getattr(arrays, f))
            for f in ("v", "next_v", "dx", "gap", "lead_v", "has_leader", "t")
        },
        mask=mask,
        merge=merge,
    )
