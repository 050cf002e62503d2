r"""Platoons of simulated drivers behind varied head vehicles, with hidden mechanisms.

**Driver.** The Intelligent Driver Model written from Treiber, Hennecke & Helbing (2000): with
speed :math:`v`, bumper gap :math:`s` and closing speed :math:`\Delta v = v - v_1`,

.. math::

    \dot v = a\Big[1 - (v/v_0)^4 - \big(s^*/s\big)^2\Big], \qquad
    s^* = s_0 + \max\Big(0,\ vT + \frac{v\,\Delta v}{2\sqrt{ab}}\Big),

plus an acceleration error of sd :math:`\sigma`. Without a mechanism the error is white per 0.1 s
sample (one normal draw held for the sample, as a pedal set ten times a second). The equations are
integrated on ``SUBSTEPS`` = 10 sub-steps per sample (speed clipped at 0, positions by the
trapezoid of the speeds, an exact stop inside a sub-step), so the recorded 0.1 s steps are not the
one-step Euler map any fitted model uses.

**Platoons.** Each platoon is a head vehicle, replayed from a random profile (segments of constant
acceleration, 2-6 s each, with occasional hard braking), and ``followers`` simulated drivers;
follower k follows the simulated follower k - 1. ``cut_ins`` vehicles per platoon change into the
lane in the last quarter of the record (inside the held-out window of bayesdrive's 70/30 split, the
fitting window stays ordinary following): each drives in lane 2 at constant speed, enters in front
of a follower (in turn) once MOBIL's safety criterion allows it (neither the new follower nor the
changer brakes harder than ``B_SAFE`` = 4 m/s^2 at entry, at the place in the gap where the harder
braking is least; without it the IDM answers a cut-in with physically impossible braking of 10-70
m/s^2), at a random speed within 1 m/s of the vehicle it then follows, and is driven by the IDM
from then on.

**Mechanisms** (:data:`trafficgen.mechanisms.MECHANISMS`) change the followers' driving (all but
``video_position_noise`` and ``position_smoothing``, which change the recording). Each follower
draws its own size from the range given; heads and cut-in vehicles get none (the recording's
mechanisms excepted: a camera sees every vehicle).

Randomness: one integer seed; each part (heads, drivers, noise, cut-ins, each mechanism, the
recording) draws from its own stream spawned from it by a fixed position, so adding a mechanism
does not change the traffic it is added to.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from trafficgen.mechanisms import MECHANISMS

__all__ = [
    "DRIVER_RANGES",
    "DT",
    "SUBSTEPS",
    "Recording",
    "simulate",
]

DT = 0.1
SUBSTEPS = 10
DRIVER_RANGES = {  # per-follower IDM parameters, uniform on these ranges (congested highway)
    "v0": (28.0, 36.0),  # desired speed, m/s
    "s0": (1.5, 3.0),  # jam distance, m
    "T": (0.9, 1.6),  # time gap, s
    "a": (1.0, 2.0),  # maximum acceleration, m/s^2
    "b": (1.5, 2.5),  # comfortable deceleration, m/s^2
    "sigma": (0.15, 0.35),  # acceleration error sd, m/s^2
}
HEAD_SPEED = (2.0, 24.0)  # m/s: the heads' speeds never leave this range
HEAD_START_SPEED = (8.0, 16.0)
HEAD_TARGET_SPEED = (4.0, 22.0)
HEAD_ACCELERATION = (0.3, 1.5)  # m/s^2 magnitude toward the segment's target speed
HARD_BRAKING = (2.5, 3.5)
HEAD_SEGMENT_S = (2.0, 6.0)
LENGTH_M = (4.2, 5.0)
WARMUP_S = 5.0
CUT_WINDOW = (0.74, 0.92)  # fraction of the record in which cut-ins are attempted
LANDING = np.linspace(0.2, 0.8, 25)  # places in the follower's gap a cut-in considers
CUT_SPEED_GAIN = (-1.0, 1.0)  # m/s relative to the vehicle it will follow
MIN_CUT_GAP = 8.0  # m of bumper gap a cut-in waits for
B_SAFE = 4.0  # m/s^2: MOBIL's safe braking limit for the new follower of a lane change
MIN_GAP = 0.1  # m: the interaction term's floor, so a collision does not divide by zero
STREAMS = ("heads", "drivers", "lengths", "cut_ins", "noise", "recording", *MECHANISMS)
# Mechanisms of the recording, not of the drivers: they act on every vehicle the camera sees.
RECORDING_MECHANISMS = ("video_position_noise", "position_smoothing")
# The smoothing kernel is cut where its weight falls below exp(-SMOOTHING_CUT).
SMOOTHING_CUT = 5.0


class Recording(NamedTuple):
    """What a recording system would write, arrays (vehicle, sample), SI units.

    x: recorded front-bumper position, v: recorded speed, a: recorded acceleration, headway:
    recorded front-to-front distance to the leader (0 without one), leader: row of the vehicle ahead
    or -1, lane: 1 or 2; true_x, true_v: the simulated truth; length, platoon, vehicle_id per
    vehicle; follower: True for the simulated followers (not heads, not cut-ins); params: per
    vehicle driver parameters and mechanism sizes (NaN where not drawn); mechanisms: the hidden
    ones; collisions: samples with a bumper gap <= 0; cut_ins: cut-ins that found their gap.
    """

    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    headway: np.ndarray
    leader: np.ndarray
    lane: np.ndarray
    true_x: np.ndarray
    true_v: np.ndarray
    length: np.ndarray
    platoon: np.ndarray
    vehicle_id: np.ndarray
    follower: np.ndarray
    params: dict[str, np.ndarray]
    mechanisms: tuple[str, ...]
    collisions: int
    cut_ins: int
    dt: float


class _Layout(NamedTuple):
    head: np.ndarray  # bool per vehicle
    cutter: np.ndarray  # bool
    target: np.ndarray  # the follower a cut-in enters in front of, else -1
    platoon: np.ndarray
    head_row: np.ndarray  # row of the vehicle's platoon head


def _layout(platoons: int, followers: int, cut_ins: int) -> _Layout:
    """Per platoon the head then its followers; then every cut-in vehicle."""
    if cut_ins > 2 * followers:
        raise ValueError(f"at most two cut-ins per follower: cut_ins={cut_ins} > 2 x {followers}")
    lane = platoons * (1 + followers)
    n = lane + platoons * cut_ins
    head = np.zeros(n, bool)
    cutter = np.zeros(n, bool)
    target = np.full(n, -1)
    platoon = np.zeros(n, int)
    for p in range(platoons):
        first = p * (1 + followers)
        head[first] = True
        platoon[first : first + 1 + followers] = p
        for c in range(cut_ins):
            row = lane + p * cut_ins + c
            cutter[row] = True
            platoon[row] = p
            target[row] = first + 1 + c % followers
    head_row = np.flatnonzero(head)[platoon]
    return _Layout(head, cutter, target, platoon, head_row)


def _head_accelerations(rng: np.random.Generator, start: np.ndarray, steps: int) -> np.ndarray:
    """(heads, steps) accelerations: segments that each head toward a random target speed, one in
    six by hard braking; the acceleration stops where the target is reached."""
    out = np.zeros((len(start), steps))
    for row, v in enumerate(start):
        k = 0
        while k < steps:
            length = round(rng.uniform(*HEAD_SEGMENT_S) / DT)
            target = rng.uniform(*HEAD_TARGET_SPEED)
            hard = target < v and rng.random() < 1 / 6
            magnitude = rng.uniform(*(HARD_BRAKING if hard else HEAD_ACCELERATION))
            for step in range(k, min(k + length, steps)):
                out[row, step] = np.clip(target - v, -magnitude * DT, magnitude * DT) / DT
                v += out[row, step] * DT
            k += length
    return out


def _idm(v, gap, closing, v0, s0, time_gap, a, b, has_leader):
    """IDM acceleration (module docstring); the interaction term only with a leader."""
    desired = s0 + np.maximum(0.0, v * time_gap + v * closing / (2.0 * np.sqrt(a * b)))
    interaction = np.where(has_leader, (desired / np.maximum(gap, MIN_GAP)) ** 2, 0.0)
    return a * (1.0 - (v / v0) ** 4 - interaction)


def _draw_sizes(
    seed_streams: dict[str, np.random.Generator],
    mechanisms: dict[str, tuple[float, float]],
    follower: np.ndarray,
    n: int,
) -> dict[str, np.ndarray]:
    """Each mechanism's size per vehicle (NaN where it does not act) and its extra draws."""
    params: dict[str, np.ndarray] = {}
    for name, (low, high) in mechanisms.items():
        if name not in MECHANISMS:
            raise KeyError(f"unknown mechanism {name!r}; known: {list(MECHANISMS)}")
        if not 0 <= low <= high:
            raise ValueError(
                f"mechanism {name}: size range must be 0 <= low <= high, got {low, high}"
            )
        rng = seed_streams[name]
        acts = np.ones(n, bool) if name in RECORDING_MECHANISMS else follower
        params[f"{name}.{MECHANISMS[name].parameter}"] = np.where(
            acts, rng.uniform(low, high, n), np.nan
        )
        if name in ("time_gap_drift", "acceleration_drift"):
            params[f"{name}.period_s"] = np.where(acts, rng.uniform(15.0, 40.0, n), np.nan)
            params[f"{name}.phase"] = np.where(acts, rng.uniform(0.0, 2 * np.pi, n), np.nan)
        elif name == "time_gap_switch":
            params[f"{name}.switch_fraction"] = np.where(acts, rng.uniform(0.4, 0.8, n), np.nan)
        elif name == "speed_power_noise":
            params[f"{name}.power"] = np.where(acts, rng.uniform(1.5, 2.5, n), np.nan)
        elif name == "cut_in_relaxation":
            params[f"{name}.relaxation_time_s"] = np.where(acts, rng.uniform(4.0, 10.0, n), np.nan)
        elif name == "leader_acceleration_response":
            params[f"{name}.smoothing_s"] = np.where(acts, rng.uniform(0.2, 0.5, n), np.nan)
        elif name == "approach_braking":
            params[f"{name}.onset_m_s"] = np.where(acts, rng.uniform(0.0, 1.0, n), np.nan)
    return params


def simulate(
    seed: int,
    mechanisms: dict[str, tuple[float, float]] | None = None,
    *,
    platoons: int = 2,
    followers: int = 4,
    duration_s: float = 40.0,
    cut_ins: int = 8,
) -> Recording:
    """Simulate the platoons with ``mechanisms`` (name -> size range) hidden in every follower."""
    mechanisms = dict(mechanisms or {})
    streams = {
        name: np.random.default_rng(child)
        for name, child in zip(
            STREAMS, np.random.SeedSequence(seed).spawn(len(STREAMS)), strict=True
        )
    }
    layout = _layout(platoons, followers, cut_ins)
    n = len(layout.head)
    follower = ~layout.head & ~layout.cutter
    warmup = round(WARMUP_S / DT)
    steps = warmup + round(duration_s / DT)
    h = DT / SUBSTEPS

    drivers = streams["drivers"]
    p = {name: drivers.uniform(low, high, n) for name, (low, high) in DRIVER_RANGES.items()}
    sizes = _draw_sizes(streams, mechanisms, follower, n)

    def size(name: str, extra: str | None = None) -> np.ndarray:
        key = f"{name}.{extra or MECHANISMS[name].parameter}"
        return np.nan_to_num(sizes[key]) if key in sizes else np.zeros(n)

    delay = size("perception_delay")
    pedal_time = size("pedal_noise")
    pedal = pedal_time > 0
    gap_drift = (size("time_gap_drift"), size("time_gap_drift", "period_s"))
    gap_phase = size("time_gap_drift", "phase")
    acc_drift = (size("acceleration_drift"), size("acceleration_drift", "period_s"))
    acc_phase = size("acceleration_drift", "phase")
    switch = size("time_gap_switch")
    switch_time = warmup * DT + duration_s * size("time_gap_switch", "switch_fraction")
    growth, power = size("speed_power_noise"), size("speed_power_noise", "power")
    weight = size("two_leader_anticipation")
    relax, relax_time = size("cut_in_relaxation"), size("cut_in_relaxation", "relaxation_time_s")
    lead_gain = size("leader_acceleration_response")
    lead_smoothing = size("leader_acceleration_response", "smoothing_s")
    approach_gain = size("approach_braking")
    approach_onset = size("approach_braking", "onset_m_s")

    length = streams["lengths"].uniform(*LENGTH_M, n)
    heads = np.flatnonzero(layout.head)
    head_index = np.searchsorted(heads, layout.head_row)
    head_start = streams["heads"].uniform(*HEAD_START_SPEED, len(heads))
    head_acc = _head_accelerations(streams["heads"], head_start, steps)
    cuts = streams["cut_ins"]
    activation = warmup * DT + duration_s * cuts.uniform(*CUT_WINDOW, n)
    cut_gain = cuts.uniform(*CUT_SPEED_GAIN, n)

    # Start: every lane vehicle at its equilibrium gap behind the one ahead.
    v = head_start[head_index]
    x = np.zeros(n)
    for i in np.flatnonzero(follower):
        free = max(1.0 - (v[i] / p["v0"][i]) ** 4, 0.05)
        x[i] = x[i - 1] - length[i - 1] - (p["s0"][i] + v[i] * p["T"][i]) / np.sqrt(free)
    active = ~layout.cutter
    entered = np.full(n, -1)  # sample at which a cut-in entered
    entry_sub = np.zeros(n)  # sub-step from which a vehicle's lane-1 history exists
    cut_time = np.full(n, -np.inf)  # when a vehicle was last cut in front of

    x_hist = np.zeros((steps * SUBSTEPS + 1, n))
    v_hist = np.zeros_like(x_hist)
    leader_hist = np.full((steps + 1, n), -1)
    v_rec = np.zeros((steps + 1, n))
    x_rec = np.zeros((steps + 1, n))
    gap_rec = np.full((steps + 1, n), np.inf)
    noise = streams["noise"]
    pedal_state = noise.standard_normal(n)
    realized_acc = np.zeros(n)  # each vehicle's acceleration over the last sub-step
    perceived_lead_acc = np.zeros(n)  # the leader's acceleration as the driver perceives it
    same_platoon = layout.platoon[None, :] == layout.platoon[:, None]
    rows = np.arange(n)

    def leaders_now() -> np.ndarray:
        ahead = same_platoon & active[None, :] & (x[None, :] > x[:, None])
        distance = np.where(ahead, x[None, :] - x[:, None], np.inf)
        nearest = np.argmin(distance, axis=1)
        return np.where(np.isfinite(distance[rows, nearest]) & active, nearest, -1)

    for k in range(steps + 1):
        t = k * DT
        lead = leaders_now()
        # Cut-ins enter at sample boundaries, in front of their target, when its gap allows.
        waiting = np.flatnonzero(layout.cutter & ~active & (activation <= t))
        for c in waiting:
            target = layout.target[c]
            ahead = lead[target]
            if ahead < 0:
                continue
            free_gap = x[ahead] - length[ahead] - x[target]
            if free_gap <= MIN_CUT_GAP:
                continue
            entry_v = v[ahead] + cut_gain[c]
            # MOBIL's safety criterion (Kesting, Treiber & Helbing 2007): the change waits until
            # some place in the gap lets neither the new follower nor the changer brake harder
            # than B_SAFE; it takes the place where the harder of the two brakes least.
            entry_x = x[target] + length[c] + LANDING * (free_gap - length[c])
            follower_rule = (p[name][target] for name in ("v0", "s0", "T", "a", "b"))
            changer_rule = (p[name][c] for name in ("v0", "s0", "T", "a", "b"))
            gap_behind = entry_x - length[c] - x[target]
            gap_ahead = x[ahead] - length[ahead] - entry_x
            worst = np.minimum(
                _idm(v[target], gap_behind, v[target] - entry_v, *follower_rule, True),
                _idm(entry_v, gap_ahead, entry_v - v[ahead], *changer_rule, True),
            )
            if worst.max() < -B_SAFE:
                continue
            entry_x = entry_x[np.argmax(worst)]
            x[c], v[c] = entry_x, entry_v
            active[c] = True
            entered[c] = k
            entry_sub[c] = k * SUBSTEPS
            cut_time[target] = t
            lead = leaders_now()
        leader_hist[k] = lead
        x_rec[k], v_rec[k] = x, v
        has = lead >= 0
        safe = np.maximum(lead, 0)
        gap_rec[k] = np.where(has, x[safe] - length[safe] - x, np.inf)
        if k == steps:
            break
        lead2 = np.where(has, lead[safe], -1)
        has2 = lead2 >= 0
        white = noise.standard_normal(n)  # held for the sample
        for j in range(SUBSTEPS):
            m = k * SUBSTEPS + j
            time = t + j * h
            # Perceived leader: the current one, its position and speed (and the ego's own
            # position and speed in the gap and closing speed) delay_s ago, linearly interpolated
            # between sub-steps; never from before a cut-in entered (it was in the other lane).
            back = np.maximum(m - delay / h, entry_sub[safe] * has)
            low = np.floor(back).astype(int)
            frac = back - low
            high = np.minimum(low + 1, m)

            def at(series, who, low=low, high=high, frac=frac):
                return (1 - frac) * series[low, who] + frac * series[high, who]

            x_hist[m], v_hist[m] = x, v
            lead_x = np.where(delay > 0, at(x_hist, safe), x[safe])
            ego_x = np.where(delay > 0, at(x_hist, rows), x)
            lead_v = np.where(delay > 0, at(v_hist, safe), v[safe])
            gap = lead_x - length[safe] - ego_x
            closing = np.where(delay > 0, at(v_hist, rows), v) - lead_v
            closing = np.where(
                has2 & (weight > 0),
                (1 - weight) * closing + weight * (v - v[np.maximum(lead2, 0)]),
                closing,
            )
            time_gap = p["T"] * (
                1.0
                + gap_drift[0]
                * np.sin(2 * np.pi * time / np.maximum(gap_drift[1], 1.0) + gap_phase)
            )
            time_gap = np.where(time >= switch_time, time_gap * (1.0 + switch), time_gap)
            max_acc = p["a"] * (
                1.0
                + acc_drift[0]
                * np.sin(2 * np.pi * time / np.maximum(acc_drift[1], 1.0) + acc_phase)
            )
            since_cut = time - cut_time
            shrink = 1.0 - relax * np.exp(
                -np.maximum(since_cut, 0.0) / np.maximum(relax_time, 1e-9)
            )
            shrink = np.where(since_cut >= 0, shrink, 1.0)
            rule = _idm(
                v,
                gap,
                closing,
                p["v0"],
                p["s0"] * shrink,
                time_gap * shrink,
                max_acc,
                p["b"],
                has,
            )
            # The leader's acceleration reaches the driver through a first-order lag (exact
            # exponential smoothing on the sub-steps); without a leader there is none to perceive.
            smoothing = np.exp(-h / np.maximum(lead_smoothing, 1e-9))
            perceived_lead_acc = smoothing * perceived_lead_acc + (1.0 - smoothing) * np.where(
                has, realized_acc[safe], 0.0
            )
            rule = rule + lead_gain * np.where(has, perceived_lead_acc, 0.0)
            # Braking beyond the rule's while closing in faster than the driver's onset speed.
            rule = rule - approach_gain * np.where(
                has, np.maximum(closing - approach_onset, 0.0), 0.0
            )
            sd = p["sigma"] * (1.0 + growth * (v / 10.0) ** power)
            if pedal.any():
                decay = np.exp(-h / np.maximum(pedal_time, 1e-9))
                pedal_state = np.where(
                    pedal,
                    decay * pedal_state + np.sqrt(1 - decay**2) * noise.standard_normal(n),
                    pedal_state,
                )
            acc = rule + sd * np.where(pedal, pedal_state, white)
            # Heads replay their profile; waiting cut-ins cruise in lane 2 (rebuilt afterwards).
            # Heads keep their speed inside HEAD_SPEED by capping the acceleration.
            head = np.clip(
                head_acc[head_index, k], (HEAD_SPEED[0] - v) / h, (HEAD_SPEED[1] - v) / h
            )
            acc = np.where(layout.head, head, acc)
            acc = np.where(active, acc, 0.0)
            v_next = v + acc * h
            stops = v_next < 0
            dx = np.where(stops, v**2 / (2 * np.maximum(-acc, 1e-9)), 0.5 * (v + v_next) * h)
            v_next = np.maximum(v_next, 0.0)
            realized_acc = (v_next - v) / h
            x = x + dx
            v = v_next

    # A cut-in's record before its entry: lane 2, constant speed, no leader; one that never found
    # its gap stays there all along (entering at the end, notionally).
    lane = np.ones((steps + 1, n), int)
    for c in np.flatnonzero(layout.cutter):
        first = entered[c] if entered[c] >= 0 else steps
        before = np.arange(first)
        x_rec[before, c] = x_rec[first, c] - v_rec[first, c] * (first - before) * DT
        v_rec[before, c] = v_rec[first, c]
        lane[before, c] = 2
        leader_hist[before, c] = -1
        if entered[c] < 0:
            lane[first, c] = 2
            leader_hist[first, c] = -1
    gaps = gap_rec[warmup:]
    collisions = int(np.sum(np.isfinite(gaps) & (gaps <= 0)))

    keep = slice(warmup, steps + 1)
    true_x, true_v = x_rec[keep].T, v_rec[keep].T
    leader, lane = leader_hist[keep].T, lane[keep].T
    sd = np.nan_to_num(sizes.get("video_position_noise.position_noise_m", np.zeros(n)))
    recorded_x = true_x + sd[:, None] * streams["recording"].standard_normal(true_x.shape)
    if "position_smoothing" in mechanisms:
        width = sizes["position_smoothing.smoothing_width_s"]
        recorded_x = np.stack([_smoothed(row, w) for row, w in zip(recorded_x, width, strict=True)])
    if any(name in mechanisms for name in RECORDING_MECHANISMS):
        # Speeds differenced from the recorded positions (central, one-sided at the ends), floored
        # at 0 as published speeds are (the noise alone makes a standing vehicle's negative).
        recorded_v = np.maximum(np.gradient(recorded_x, DT, axis=1), 0.0)
    else:
        recorded_v = true_v
    recorded_a = np.gradient(recorded_v, DT, axis=1)
    has = leader >= 0
    safe = np.maximum(leader, 0)
    samples = np.arange(true_x.shape[1])
    headway = np.where(has, recorded_x[safe, samples] - recorded_x, 0.0)
    params = {name: values for name, values in p.items()} | sizes
    return Recording(
        x=recorded_x,
        v=recorded_v,
        a=recorded_a,
        headway=headway,
        leader=leader,
        lane=lane,
        true_x=true_x,
        true_v=true_v,
        length=length,
        platoon=layout.platoon,
        vehicle_id=_vehicle_ids(layout.platoon),
        follower=follower,
        params=params,
        mechanisms=tuple(mechanisms),
        collisions=collisions,
        cut_ins=int((entered >= 0).sum()),
        dt=DT,
    )


def _smoothed(x: np.ndarray, width_s: float) -> np.ndarray:
    """Symmetric exponential moving average of one vehicle's positions: weights exp(-|k| DT / T)
    over the samples within ``SMOOTHING_CUT`` T. Beyond the record's ends the positions are
    continued by reflection through the end point (x(end + k) = 2 x(end) - x(end - k)), so a
    trajectory at constant speed stays as it is there too (a plain renormalised average bends it:
    m/s^2 of false acceleration in the last samples)."""
    reach = min(int(np.ceil(SMOOTHING_CUT * width_s / DT)), x.size - 1)
    weights = np.exp(-np.abs(np.arange(-reach, reach + 1)) * DT / width_s)
    before = 2.0 * x[0] - x[reach:0:-1]
    after = 2.0 * x[-1] - x[-2 : -reach - 2 : -1]
    padded = np.concatenate([before, x, after])
    return np.convolve(padded, weights / weights.sum(), mode="valid")


def _vehicle_ids(platoon: np.ndarray) -> np.ndarray:
    """Ids 100 (platoon + 1) + rank in the platoon (head 0, then followers, then cut-ins)."""
    ids = np.zeros(len(platoon), int)
    for q in np.unique(platoon):
        members = np.flatnonzero(platoon == q)
        ids[members] = 100 * (q + 1) + np.arange(len(members))
    return ids
