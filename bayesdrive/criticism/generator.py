r"""Hidden-effect data: platoons driven by the base IDM plus one effect, written as NGSIM raw files.

The criticism is tested the way it is meant to be used: data with a known misfit go through the
real reader, and ``criticize`` must name the cause. :func:`simulate_traffic` simulates
``num_platoons`` platoons closed-loop, each a replayed head vehicle with a random speed profile
and ``followers`` simulated followers (follower k follows the *simulated* follower k-1); every
follower draws its own IDM parameters (:data:`DRIVER_RANGES`) and, unless the cause is "none",
its own value of the effect's parameter (the effect size, uniform on a range: :data:`EFFECTS` gives
realistic defaults). Followers are driven by the extension model of the cause
(:func:`bayesdrive.drivers.extensions.extend`) through its own ``transition_sample``, with inputs
read by :func:`~bayesdrive.drivers.extensions.inputs.inputs_at` from the simulated history,
the same function that reads data.

**Cut-ins.** In every platoon ``cut_ins`` vehicles change into the lane: each appears in front of a
follower (the followers in turn, up to two each) at a random fraction of its gap, slightly faster
than the vehicle ahead, and is simulated from then on like any follower (before that it drives at
constant speed in lane 2). Cut-ins happen in the held-out window (:data:`CUT_WINDOW`), where the
over-reaction to them (the cause ``cut_in_overreaction``) is scored; a vehicle that cuts in there
has no fitting window of its own and drops out of the fits. Every data set has them, effect or
not, so the null data test that extension too.

Positions are simulated in float32 from a local origin over a few kilometres (~1e-4 m resolution);
the written positions are the float64 running sums of the simulated increments, so the position
increments a reader recovers are the simulated ones to ~1e-6 m.

:func:`write_ngsim_raw` writes the US DOT NGSIM column set (feet, ft/s, ft/s^2, 10 Hz frames,
``Space_Headway`` front to front, ``Preceding``/``Following`` ids, 0 for none); :func:`generate`
does both and returns the ground truth.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from jax import Array

from bayesdrive.data.atomic import write_atomic
from bayesdrive.data.units import FOOT_M
from bayesdrive.data.views import AheadArrays
from bayesdrive.drivers.base import EgoState, Series, fill_params
from bayesdrive.drivers.extensions import NO_CAUSE, extend
from bayesdrive.drivers.extensions.inputs import history_steps, inputs_at
from bayesdrive.drivers.idm import IDM

__all__ = [
    "DETECTION_SCENARIO",
    "DETECTION_SIZES",
    "DRIVER_RANGES",
    "EFFECTS",
    "GroundTruth",
    "SimulatedTraffic",
    "generate",
    "simulate_traffic",
    "write_ngsim_raw",
]

DT = 0.1
# Per-follower IDM parameters, uniform on these ranges (congested-highway drivers).
DRIVER_RANGES = {
    "v_des": (28.0, 36.0),
    "d_min": (1.5, 3.0),
    "tau": (0.9, 1.6),
    "a_max": (1.0, 2.0),
    "b_pref": (1.5, 2.5),
    "sigma": (0.15, 0.35),
}
# cause -> (the extension parameter that carries the effect, its default realistic range).
EFFECTS: dict[str, tuple[str, tuple[float, float]]] = {
    "reaction_delay": ("reaction_time", (0.3, 0.7)),
    "autocorrelated_noise": ("rho", (0.6, 0.9)),
    "speed_dependent_noise": ("noise_speed_slope", (0.08, 0.2)),
    "second_leader_anticipation": ("anticipation", (0.4, 0.7)),
    "cut_in_overreaction": ("coolness", (0.9, 1.0)),
    "drifting_parameters": ("tau_drift", (0.05, 0.15)),
    "measurement_noise": ("sigma_obs", (0.005, 0.03)),
}
HEAD_SPEED = (5.0, 22.0)  # m/s bounds of the replayed head vehicles
HEAD_START_SPEED = (8.0, 16.0)
HEAD_ACCELERATION = (-2.0, 1.5)  # m/s^2 range of each head segment
HEAD_SEGMENT_S = (2.0, 6.0)
LENGTH_M = (4.2, 5.0)
WIDTH_M = 1.8
WARMUP_S = 5.0  # simulated before the written record starts, so the history is filled
CUT_FRACTION = (0.35, 0.6)  # the cut-in lands at this fraction of the follower's free gap
CUT_SPEED_GAIN = (0.0, 2.0)  # m/s faster than the vehicle it will follow
MIN_CUT_GAP = 8.0  # m: a cut-in waits for at least this bumper gap
# Fraction of the record in which cut-ins happen: inside the held-out window of the split rule
# (after 70% of each vehicle's samples), where the gain is measured; the fitting window stays
# free of them so the base parameters are learnt from ordinary following.
CUT_WINDOW = (0.74, 0.92)
# The scenario of the detection study (benchmarks/bench_detection.py) and of the CI tests that run
# the effect sizes it detects: small enough for CI, the same in both so the table applies.
DETECTION_SCENARIO = {"num_platoons": 2, "followers": 4, "duration_s": 40.0, "cut_ins": 8}
# Effect sizes of the detection study: ranges of each effect's parameter, drawn per driver.
DETECTION_SIZES: dict[str, dict[str, tuple[float, float]]] = {
    "reaction_delay": {"small": (0.1, 0.2), "medium": (0.2, 0.4), "large": (0.4, 0.7)},
    "autocorrelated_noise": {"small": (0.2, 0.4), "medium": (0.4, 0.6), "large": (0.6, 0.9)},
    # "xlarge" (inside the prior) tested whether size was what kept "large" below 0.95 with 4
    # fixed moves per tempering stage: it was not (18 of 20 against 16 of 20); the sampler was
    # (bayesdrive.inference.tempering, "How many moves").
    "speed_dependent_noise": {
        "small": (0.02, 0.05),
        "medium": (0.05, 0.1),
        "large": (0.1, 0.2),
        "xlarge": (0.2, 0.3),
    },
    "second_leader_anticipation": {
        "small": (0.1, 0.3),
        "medium": (0.3, 0.5),
        "large": (0.5, 0.8),
    },
    "cut_in_overreaction": {"small": (0.3, 0.6), "medium": (0.6, 0.9), "large": (0.9, 1.0)},
    "drifting_parameters": {"small": (0.01, 0.03), "medium": (0.03, 0.06), "large": (0.06, 0.12)},
    "measurement_noise": {
        "small": (0.0005, 0.001),
        "medium": (0.001, 0.003),
        "large": (0.003, 0.01),
    },
}


class SimulatedTraffic(NamedTuple):
    """Simulated samples after the warm-up (numpy, SI): arrays (vehicle, sample).

    x: front-bumper position (m), recorded_x: the position as recorded (x plus the measurement
    noise of the cause ``measurement_noise``, else x), v: speed (m/s), leader: index of the vehicle
    ahead in lane 1 or
    -1, lane: 1 or 2 (cut-in vehicles before their cut-in), length (vehicle,) in m, platoon
    (vehicle,), simulated (vehicle,): True for model-driven vehicles, collisions: steps with a
    bumper gap <= 0, cut_ins: cut-ins that found their gap (the others stay in lane 2).
    """

    x: np.ndarray
    recorded_x: np.ndarray
    v: np.ndarray
    leader: np.ndarray
    lane: np.ndarray
    length: np.ndarray
    platoon: np.ndarray
    simulated: np.ndarray
    dt: float
    collisions: int
    cut_ins: int


class GroundTruth(NamedTuple):
    """What was hidden: the cause, its parameter and every simulated vehicle's parameters."""

    cause: str
    effect_parameter: str | None
    effect_range: tuple[float, float] | None
    params: pd.DataFrame  # one row per simulated vehicle: Vehicle_ID and every model parameter
    collisions: int
    cut_ins: int


class _Layout(NamedTuple):
    is_head: np.ndarray
    is_cutter: np.ndarray
    cut_target: np.ndarray  # the follower a cut-in vehicle enters in front of, else -1
    platoon: np.ndarray
    rank: np.ndarray  # position in the platoon at the start (head 0); cut-in vehicles -1


def _layout(num_platoons: int, followers: int, cut_ins: int) -> _Layout:
    """Vehicle order: per platoon the head then its followers, then all cut-in vehicles.

    Cut-ins go in front of the followers in turn (follower 1, 2, ..., then around again), so a
    platoon can have up to two per follower.
    """
    if cut_ins > 2 * followers:
        raise ValueError(f"at most two cut-ins per follower: {cut_ins} > 2 x {followers}")
    lane_vehicles = num_platoons * (1 + followers)
    n = lane_vehicles + num_platoons * cut_ins
    is_head = np.zeros(n, bool)
    is_cutter = np.zeros(n, bool)
    cut_target = np.full(n, -1)
    platoon = np.zeros(n, int)
    rank = np.full(n, -1)
    for p in range(num_platoons):
        head = p * (1 + followers)
        is_head[head] = True
        platoon[head : head + followers + 1] = p
        rank[head : head + followers + 1] = np.arange(followers + 1)
        for c in range(cut_ins):
            cutter = lane_vehicles + p * cut_ins + c
            is_cutter[cutter] = True
            platoon[cutter] = p
            cut_target[cutter] = head + 1 + c % followers
    return _Layout(is_head, is_cutter, cut_target, platoon, rank)


def _head_profile(key: Array, num_heads: int, num_steps: int, dt: float) -> Array:
    """(heads, steps + 1) speeds: piecewise-constant random accelerations, speeds kept in range."""
    key_start, key_acc, key_len = jax.random.split(key, 3)
    num_segments = int(num_steps * dt / HEAD_SEGMENT_S[0]) + 1
    accelerations = jax.random.uniform(
        key_acc, (num_heads, num_segments), minval=HEAD_ACCELERATION[0], maxval=HEAD_ACCELERATION[1]
    )
    lengths = jax.random.uniform(
        key_len, (num_heads, num_segments), minval=HEAD_SEGMENT_S[0], maxval=HEAD_SEGMENT_S[1]
    )
    ends = jnp.cumsum(lengths, axis=1)
    times = jnp.arange(num_steps) * dt
    segment = jax.vmap(lambda e: jnp.searchsorted(e, times, side="right"))(ends)
    acc = jnp.take_along_axis(accelerations, segment, axis=1)
    start = jax.random.uniform(
        key_start, (num_heads,), minval=HEAD_START_SPEED[0], maxval=HEAD_START_SPEED[1]
    )

    def step(v, a):
        v = jnp.clip(v + a * dt, *HEAD_SPEED)
        return v, v

    _, speeds = jax.lax.scan(step, start, acc.T)
    return jnp.concatenate([start[None, :], speeds], axis=0).T


def _equilibrium_gap(params, v: Array) -> Array:
    """The IDM's steady-state bumper gap at speed v (no relative speed)."""
    free = jnp.maximum(1.0 - (v / params.v_des) ** 4, 0.05)
    return (params.d_min + v * params.tau) / jnp.sqrt(free)


def _draw_params(key: Array, model, cause: str, effect_range, n: int):
    """Per-vehicle parameters: IDM ranges, the effect parameter on its range, defaults elsewhere."""
    ranges = dict(DRIVER_RANGES)
    if cause != NO_CAUSE:
        ranges[EFFECTS[cause][0]] = effect_range
    names = tuple(ranges)
    keys = jax.random.split(key, len(names))
    columns = [
        jax.random.uniform(k, (n,), minval=ranges[name][0], maxval=ranges[name][1])
        for k, name in zip(keys, names, strict=True)
    ]
    return fill_params(model, names, jnp.stack(columns, axis=-1))


class _Scene(NamedTuple):
    """Everything the closed loop reads, per vehicle (see :func:`_layout` for the order)."""

    params: Any
    length: Array
    activation: Array
    cut_fraction: Array
    cut_gain: Array
    is_head: Array
    is_cutter: Array
    cut_target: Array
    platoon: Array
    head_rows: Array
    head_v: Array
    x0: Array
    v0: Array


@functools.partial(jax.jit, static_argnames=("extended", "dt", "num_steps"))
def _closed_loop(
    scene: _Scene, key_steps: Array, key_init: Array, *, extended, dt: float, num_steps: int
):
    """Scan every vehicle over ``num_steps``: heads replay, cut-ins wait, followers follow."""
    model = extended.model
    history = history_steps(dt)
    n = scene.x0.shape[0]
    initial_states = jax.vmap(lambda p, x, v: model.initial_sample(key_init, p, EgoState(x, v)))(
        scene.params, scene.x0, scene.v0
    )

    def leaders(x, active):
        """The nearest vehicle ahead in the lane (same platoon, on the road), else -1."""
        ahead = (
            (scene.platoon[None, :] == scene.platoon[:, None])
            & active[None, :]
            & (x[None, :] > x[:, None])
        )
        distance = jnp.where(ahead, x[None, :] - x[:, None], jnp.inf)
        has = jnp.isfinite(distance.min(axis=1)) & active & ~scene.is_head
        return jnp.where(has, jnp.argmin(distance, axis=1), -1)

    def step(carry, s):
        x, v, active, states, buf = carry
        time = s * dt
        # Cut-ins: a waiting vehicle enters in front of its target once the gap allows it.
        lead_now = leaders(x, active)
        target = jnp.maximum(scene.cut_target, 0)
        target_lead = jnp.maximum(lead_now[target], 0)
        target_gap = x[target_lead] - scene.length[target_lead] - x[target]
        activating = (
            scene.is_cutter & ~active & (time >= scene.activation) & (target_gap > MIN_CUT_GAP)
        )
        entry_x = x[target] + scene.cut_fraction * (target_gap - scene.length) + scene.length
        entry_v = v[target_lead] + scene.cut_gain
        x = jnp.where(activating, entry_x, x)
        v = jnp.where(activating, entry_v, v)
        active = active | activating
        fresh = jax.vmap(lambda p, xx, vv: model.initial_sample(key_init, p, EgoState(xx, vv)))(
            scene.params, x, v
        )
        states = jax.tree.map(lambda new, old: jnp.where(activating, new, old), fresh, states)
        buf = buf._replace(v=buf.v.at[:, s].set(v))

        lead = leaders(x, active)
        has = lead >= 0
        safe = jnp.maximum(lead, 0)
        gap = jnp.where(has, x[safe] - scene.length[safe] - x, 100.0)
        lead_v = jnp.where(has, v[safe], 1.0)
        previous = jnp.maximum(s - 1, 0)
        lead_acc = jnp.where(
            has & (s > 0) & ~activating[safe], (v[safe] - buf.v[safe, previous]) / dt, 0.0
        )
        lead2 = jnp.where(has, lead[safe], -1)
        has2 = lead2 >= 0
        gap2 = jnp.where(has2, gap + gap[safe], 100.0)
        lead2_v = jnp.where(has2, v[jnp.maximum(lead2, 0)], 1.0)

        def written(part, column):
            return part._replace(**{k: getattr(part, k).at[:, s].set(c) for k, c in column.items()})

        buf = written(buf, {"gap": gap, "lead_v": lead_v, "has_leader": has.astype(x.dtype)})
        ahead = {
            "lead_acc": lead_acc,
            "gap2": gap2,
            "lead2_v": lead2_v,
            "has_leader2": has2.astype(x.dtype),
        }
        buf = buf._replace(ahead=written(buf.ahead, ahead))

        inputs = jax.vmap(lambda row: inputs_at(row, s, history))(buf)
        keys = jax.random.split(jax.random.fold_in(key_steps, s), n)
        moved = jax.vmap(model.transition_sample)(
            keys, scene.params, states._replace(x=jnp.zeros_like(x)), inputs
        )
        drives = active & ~scene.is_head & has
        head_next = scene.head_v[scene.head_rows, s + 1]
        next_v = jnp.where(drives, moved.v, jnp.where(scene.is_head, head_next, v))
        dx = jnp.where(drives, moved.x, 0.5 * (v + next_v) * dt)
        states = jax.tree.map(lambda new, old: jnp.where(drives, new, old), moved, states)
        buf = buf._replace(dx=buf.dx.at[:, s].set(dx))
        return (x + dx, next_v, active, states, buf), (lead, active, gap, x)

    zeros = jnp.zeros((n, num_steps + 1), scene.x0.dtype)
    buffers = Series(
        *(zeros for _ in range(len(Series._fields) - 3)),
        dt=jnp.full_like(zeros, dt),
        ahead=AheadArrays(*(zeros for _ in AheadArrays._fields)),
    )
    start = (scene.x0, scene.v0, ~scene.is_cutter, initial_states, buffers)
    (_, v_end, _, _, buf), (lead, active, gap, x_sim) = jax.lax.scan(
        step, start, jnp.arange(num_steps)
    )
    return v_end, buf, lead, active, gap, x_sim


def simulate_traffic(
    key: Array,
    cause: str,
    *,
    effect_range: tuple[float, float] | None = None,
    num_platoons: int = 4,
    followers: int = 5,
    duration_s: float = 60.0,
    cut_ins: int = 5,
    dt: float = DT,
) -> tuple[SimulatedTraffic, GroundTruth]:
    """Simulate the platoons with ``cause`` hidden in every follower (module docstring)."""
    if cause != NO_CAUSE and cause not in EFFECTS:
        raise KeyError(f"no generator for cause {cause!r}; known: {[NO_CAUSE, *EFFECTS]}")
    if effect_range is None and cause != NO_CAUSE:
        effect_range = EFFECTS[cause][1]
    extended = extend(cause, IDM)
    model = extended.model
    layout = _layout(num_platoons, followers, cut_ins)
    n = len(layout.is_head)
    warmup = round(WARMUP_S / dt)
    num_steps = warmup + round(duration_s / dt)

    keys = jax.random.split(key, 7)
    key_heads, key_params, key_len, key_cut, key_steps, key_init, key_noise = keys
    params = _draw_params(key_params, model, cause, effect_range, n)
    heads = np.flatnonzero(layout.is_head)
    head_v = _head_profile(key_heads, len(heads), num_steps, dt)
    length = jax.random.uniform(key_len, (n,), minval=LENGTH_M[0], maxval=LENGTH_M[1])
    key_time, key_frac, key_gain = jax.random.split(key_cut, 3)
    activation = warmup * dt + duration_s * jax.random.uniform(
        key_time, (n,), minval=CUT_WINDOW[0], maxval=CUT_WINDOW[1]
    )
    activation = jnp.where(jnp.asarray(layout.is_cutter), activation, -1.0)
    cut_fraction = jax.random.uniform(
        key_frac, (n,), minval=CUT_FRACTION[0], maxval=CUT_FRACTION[1]
    )
    cut_gain = jax.random.uniform(
        key_gain, (n,), minval=CUT_SPEED_GAIN[0], maxval=CUT_SPEED_GAIN[1]
    )

    # Initial platoon: every follower at its equilibrium gap behind the one ahead.
    head_of = np.array([heads[layout.platoon[i]] for i in range(n)])
    v0 = head_v[np.searchsorted(heads, head_of), 0]
    x0 = np.zeros(n, np.float32)
    gaps0 = np.asarray(_equilibrium_gap(params, v0))
    for i in np.flatnonzero(layout.rank >= 1):  # in platoon order, so the one ahead is placed
        x0[i] = x0[i - 1] - float(length[i - 1]) - gaps0[i]
    x0 = jnp.asarray(x0)
    v0 = jnp.asarray(v0)

    scene = _Scene(
        params=params,
        length=length,
        activation=activation,
        cut_fraction=cut_fraction,
        cut_gain=cut_gain,
        is_head=jnp.asarray(layout.is_head),
        is_cutter=jnp.asarray(layout.is_cutter),
        cut_target=jnp.asarray(layout.cut_target),
        platoon=jnp.asarray(layout.platoon),
        head_rows=jnp.asarray(
            np.searchsorted(heads, np.where(layout.is_head, np.arange(n), heads[0]))
        ),
        head_v=head_v,
        x0=x0,
        v0=v0,
    )
    v_end, buf, lead, active, gap, x_sim = _closed_loop(
        scene, key_steps, key_init, extended=extended, dt=dt, num_steps=num_steps
    )

    dx = np.asarray(buf.dx[:, :num_steps], np.float64)
    v = np.asarray(buf.v, np.float64)
    v[:, num_steps] = np.asarray(v_end)
    x = np.concatenate(
        [np.asarray(x0, np.float64)[:, None], np.asarray(x0)[:, None] + np.cumsum(dx, axis=1)],
        axis=1,
    )
    lead = np.asarray(lead).T  # scan stacks steps first
    active = np.asarray(active).T
    lead = np.concatenate([lead, lead[:, -1:]], axis=1)
    active = np.concatenate([active, active[:, -1:]], axis=1)
    gap = np.asarray(gap).T
    collisions = int(np.sum((lead[:, :-1] >= 0) & (gap <= 0)))

    # Cut-in vehicles drive at constant speed in lane 2 until they enter: back-fill that stretch.
    lane = np.ones_like(lead)
    for c in np.flatnonzero(layout.is_cutter):
        entered = np.flatnonzero(active[c])
        # A cut-in that never finds its gap stays in lane 2, without leader, all along.
        first = entered[0] if len(entered) else active.shape[1] - 1
        # It entered at a simulated position: rebuild its record from there.
        entry = float(np.asarray(x_sim)[min(first, num_steps - 1), c])
        x[c, first:] = (
            entry + np.concatenate([[0.0], np.cumsum(dx[c, first:])])[: x.shape[1] - first]
        )
        before = np.arange(first)
        x[c, before] = x[c, first] - v[c, first] * (first - before) * dt
        v[c, before] = v[c, first]
        lane[c, before] = 2
    cut_ins_done = int(active[layout.is_cutter, -1].sum())
    keep = slice(warmup, num_steps + 1)
    recorded_x = x[:, keep]
    if cause == "measurement_noise":
        # Recorded positions carry white noise; speeds and gaps (headways) stay exact.
        noise_sd = np.asarray(params.sigma_obs, np.float64)[:, None]
        recorded_x = recorded_x + noise_sd * np.asarray(
            jax.random.normal(key_noise, recorded_x.shape), np.float64
        )
    traffic = SimulatedTraffic(
        x=x[:, keep],
        recorded_x=recorded_x,
        v=v[:, keep],
        leader=lead[:, keep],
        lane=lane[:, keep],
        length=np.asarray(length, np.float64),
        platoon=layout.platoon,
        simulated=~layout.is_head,
        dt=dt,
        collisions=collisions,
        cut_ins=cut_ins_done,
    )
    table = pd.DataFrame({name: np.asarray(getattr(params, name)) for name in model.param_names})
    table.insert(0, "Vehicle_ID", _vehicle_ids(layout.platoon))
    truth = GroundTruth(
        cause=cause,
        effect_parameter=EFFECTS[cause][0] if cause != NO_CAUSE else None,
        effect_range=tuple(effect_range) if effect_range is not None else None,
        params=table[~layout.is_head].reset_index(drop=True),
        collisions=collisions,
        cut_ins=cut_ins_done,
    )
    return traffic, truth


def _vehicle_ids(platoon: np.ndarray) -> np.ndarray:
    """NGSIM ids: 100 * (platoon + 1) + the vehicle's rank within its platoon."""
    ranks = np.zeros(len(platoon), int)
    for p in np.unique(platoon):
        members = np.flatnonzero(platoon == p)
        ranks[members] = np.arange(len(members))
    return 100 * (platoon + 1) + ranks


def write_ngsim_raw(traffic: SimulatedTraffic, path: str | Path) -> Path:
    """Write ``traffic`` as an NGSIM raw CSV (US DOT columns, feet; platoons apart in time).

    ``Local_Y`` is the recorded position; ``Space_Headway`` (front to front) comes from the true
    positions, as a ranging sensor would measure it.
    """
    ids = _vehicle_ids(traffic.platoon)
    n, samples = traffic.x.shape
    gap_frames = 100  # 10 s of silence between platoons keeps them apart on the frame clock
    first_frame = 1 + traffic.platoon * (samples + gap_frames)
    rows = []
    for i in range(n):
        frames = first_frame[i] + np.arange(samples)
        lead = traffic.leader[i]
        has = lead >= 0
        safe = np.maximum(lead, 0)
        headway = np.where(has, traffic.x[safe, np.arange(samples)] - traffic.x[i], 0.0)
        follower = np.zeros(samples, int)
        for j in range(n):
            follower = np.where(traffic.leader[j] == i, ids[j], follower)
        v = traffic.v[i]
        acc = np.append(np.diff(v) / traffic.dt, 0.0)
        rows.append(
            pd.DataFrame(
                {
                    "Vehicle_ID": ids[i],
                    "Frame_ID": frames,
                    "Total_Frames": samples,
                    "Global_Time": 1_113_433_135_300 + frames * 100,
                    "Local_X": np.where(traffic.lane[i] == 1, 6.0, 18.0),
                    "Local_Y": traffic.recorded_x[i] / FOOT_M,
                    "v_Length": traffic.length[i] / FOOT_M,
                    "v_Width": WIDTH_M / FOOT_M,
                    "v_Class": 2,
                    "v_Vel": v / FOOT_M,
                    "v_Acc": acc / FOOT_M,
                    "Lane_ID": traffic.lane[i],
                    "Preceding": np.where(has, ids[safe], 0),
                    "Following": follower,
                    "Space_Headway": headway / FOOT_M,
                    "Time_Headway": np.where(
                        has, np.where(v > 0.01, headway / np.maximum(v, 0.01), 9999.99), 0.0
                    ),
                }
            )
        )
    table = pd.concat(rows, ignore_index=True)
    path = Path(path)
    write_atomic(path, lambda tmp: table.to_csv(tmp, index=False, float_format="%.6f"))
    return path


def generate(
    key: Array,
    path: str | Path,
    cause: str,
    *,
    effect_range: tuple[float, float] | None = None,
    num_platoons: int = 4,
    followers: int = 5,
    duration_s: float = 60.0,
    cut_ins: int = 5,
) -> GroundTruth:
    """Simulate traffic with ``cause`` hidden (module docstring) and write it as NGSIM raw CSV."""
    traffic, truth = simulate_traffic(
        key,
        cause,
        effect_range=effect_range,
        num_platoons=num_platoons,
        followers=followers,
        duration_s=duration_s,
        cut_ins=cut_ins,
    )
    write_ngsim_raw(traffic, path)
    return truth
