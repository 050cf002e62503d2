"""The one simulator: a driver model's closed-loop step and rollout, for every caller.

Every simulation in bayesdrive runs here: the platoon and merge rollouts of ``evaluate``, the
paper's tables and scene generation (:mod:`bayesdrive.simulation.rollout` builds their scenes),
the held-out forecasts of the criticism and the calibration
(:mod:`bayesdrive.simulation.follower_rollout`: one follower behind its replayed leader), the
posterior predictive, and the synthetic data of SBC and the coverage studies
(:mod:`bayesdrive.inference.diagnostics.synthetic_followers`). It lives beside the driver models, below both the
engines and the simulation, because the engines' synthetic data need it too; it knows no engine.

**The step** (:func:`step`): the model's inputs at step ``j`` of a buffer of the one series
(``model.inputs_at``), then its stochastic move (``model.transition_sample``) from the state with
``x = 0``: states are kept relative to the current step, as the engines score them, so a recorded
increment carries no float32 position round-off. Positions are accumulated beside it.

**One rollout** (:func:`rollout`): a replayed head (and, in merge scenes, a replayed merge lane)
and ``N`` simulated vehicles behind it, front to back; vehicle ``k`` follows the *simulated*
vehicle ``k - 1`` (the head for ``k = 0``): ``gap = x_leader - x - length_leader``. Each step the
simulated vehicles' speeds, gaps, leader speeds, the scene ahead (second vehicle ahead, the
leader's acceleration and age) and the distance to the merge point are written into the buffer,
whose first ``K = history_steps(dt)`` steps hold the past before the start.

**Two starts** (:data:`STARTS`):

* ``stationary``: for a scene without history (scene generation, synthetic data). The state is
  the model's ``initial_sample`` at the observed position and speed (an AR residual drawn from its
  stationary law, a drifting parameter at its fitted value) and the past repeats the first step.
* ``filtered``: for forecasting from a window of observed data. The past is the data's
  (``SceneArrays.past``), so a reaction delay perceives what the driver saw, and the model's extra
  state is the one its observed history implies (``model.lift``: the autocorrelated noise recovers
  its last residual), per posterior draw. That is exact filtering for a model whose state is
  observed exactly. A model with a hidden state (a drifting parameter: ``model.filter``) starts
  from the law its state filter gives at t0 (``model.filtered_start``): the caller, who holds the
  window's whole observed history, runs the filter per posterior draw and hands the laws in
  (``laws``; the held-out windows of :mod:`bayesdrive.simulation.follower_rollout` do), and each
  rollout draws its hidden state from its law with its ``init`` keys. Without laws, or for a model
  without a ``filtered_start`` (an observation model), the filtered start is refused
  (:func:`check_start`).

**Keys** (:func:`rollout_keys`): the key splits into one key per rollout; a rollout key splits
into ``init`` (one key per vehicle for ``initial_sample``) and ``steps`` (one key per step, each
split into one per vehicle). The same key gives bit-identical rollouts.

**Events**, per rollout, vehicle and step t = 1 .. T (after the t-th transition):
collision: bumper gap to the leader <= 0 (vehicle lengths included);
hard braking: realised acceleration (v_t - v_{t-1}) / dt <= :data:`HARD_BRAKING_MPS2`;
off road: the vehicle's front passed the end of its lane (``road_end``; +inf on the main lane).
Steps past the end of a scene (``step_mask`` = 0, merge episodes) count nothing.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from bayesdrive.data.views import AheadArrays, MergeArrays, history_steps
from bayesdrive.drivers.base import DriverModel, EgoState, Series

__all__ = [
    "FILTERED",
    "HARD_BRAKING_MPS2",
    "STARTS",
    "STATIONARY",
    "Rollout",
    "RolloutKeys",
    "SceneArrays",
    "check_start",
    "forecast_start",
    "platoon_scene",
    "rollout",
    "rollout_keys",
    "rollout_scenes",
    "step",
]

# The paper's hard-braking threshold.
HARD_BRAKING_MPS2 = -3.0
STATIONARY = "stationary"
FILTERED = "filtered"
STARTS = (STATIONARY, FILTERED)
# What a scene writes where no second vehicle ahead is known (the data views' placeholders).
NO_GAP2, NO_LEAD2_V = 100.0, 1.0


class SceneArrays(NamedTuple):
    """What the simulator needs of one scene (float32; positions from the scene's origin).

    head_x, head_v, head_present: (T + 1,) the replayed leader of the first simulated vehicle
        (head_present = 0 where it is absent: the first vehicle then drives on free road).
    head_gap, head_lead_v, head_has_leader: (T + 1,) the replayed head's own bumper gap to its
        leader and that leader's speed: the first vehicle's second vehicle ahead (head_has_leader
        = 0: none known).
    x0, v0: (N,) observed state of the simulated vehicles at t0, front to back.
    lead_length: (N,) length of each simulated vehicle's leader.
    road_end: (N,) position where each simulated vehicle's lane ends (+inf: it does not).
    step_mask: (T,) 1 for real steps, 0 for padding past the end of the scene.
    merge_x, merge_v, merge_present: (K, T + 1) replayed merge-lane vehicles (K = 0: none).
    merge_length: (K,) their lengths.
    dt: () step length (s).
    past: the simulated vehicles' observed series over the ``history_steps(dt)`` steps before t0
        (:class:`~bayesdrive.drivers.base.Series`, fields (N, K), ``ahead`` included, ``merge``
        None), what the ``filtered`` start reads; None where the data hold no history.
    """

    head_x: Array
    head_v: Array
    head_present: Array
    head_gap: Array
    head_lead_v: Array
    head_has_leader: Array
    x0: Array
    v0: Array
    lead_length: Array
    road_end: Array
    step_mask: Array
    merge_x: Array
    merge_v: Array
    merge_present: Array
    merge_length: Array
    dt: Array
    past: Series | None = None


class Rollout(NamedTuple):
    """Simulated trajectories and events, leading axes (rollout, vehicle).

    x, v, gap: (R, N, T + 1) position (from the scene's origin), speed and bumper gap to the
        leader; index 0 is the initial state. dx: (R, N, T) each step's position increment, as the
        step made it (no position round-off). collision, hard_braking, off_road: (R, N, T)
        booleans for steps 1..T.
    """

    x: Array
    v: Array
    gap: Array
    dx: Array
    collision: Array
    hard_braking: Array
    off_road: Array


class RolloutKeys(NamedTuple):
    """The keys of one rollout: init (N,) and steps (T, N)."""

    init: Array
    steps: Array


def rollout_keys(key: Array, num_steps: int, num_vehicles: int) -> RolloutKeys:
    """The documented key schedule of one rollout (module docstring)."""
    key_init, key_steps = jax.random.split(key)
    per_step = jax.random.split(key_steps, num_steps)
    return RolloutKeys(
        init=jax.random.split(key_init, num_vehicles),
        steps=jax.vmap(lambda k: jax.random.split(k, num_vehicles))(per_step),
    )


def forecast_start(model: DriverModel, *, whole_history: bool = False) -> str:
    """The start a forecast of ``model`` takes: ``filtered`` where its state can be filtered from
    the observed history, else ``stationary`` (callers record which start they used). A hidden
    state is filtered only by a caller that holds each window's ``whole_history`` (module
    docstring)."""
    if not model.observed_exactly:
        return STATIONARY
    if model.filter is None:
        return FILTERED
    return FILTERED if whole_history and model.filtered_start is not None else STATIONARY


def check_start(
    model: DriverModel, start: str, has_past: bool, *, whole_history: bool = False
) -> None:
    """Refuse a start this simulator cannot give ``model`` on a scene (module docstring);
    ``whole_history``: the caller hands in the filtered laws of a hidden state."""
    if start not in STARTS:
        raise ValueError(f"unknown start {start!r}; the starts are {list(STARTS)}")
    if start != FILTERED:
        return
    if forecast_start(model, whole_history=whole_history) != FILTERED:
        if not model.observed_exactly:
            why = f"it is observed through {model.observation}, which the simulator does not filter"
        elif model.filtered_start is None:
            why = "it has a hidden state and brings no filtered start"
        else:
            why = (
                "its hidden state is filtered over each window's whole history, and no filtered "
                "laws were handed in (held-out follower windows hand them in)"
            )
        raise ValueError(
            f"the {FILTERED!r} start cannot start {model.name!r} from the observed history: "
            f"{why}; use start={STATIONARY!r}"
        )
    if not has_past:
        raise ValueError(
            f"the {FILTERED!r} start reads the observed history before t0; this scene holds "
            f"none: use start={STATIONARY!r}"
        )


def platoon_scene(head_v: Array, x0: Array, v0: Array, *, length: float, dt: float) -> SceneArrays:
    """A synthetic platoon: the head starts at x = 0 and drives the speeds ``head_v`` (T + 1,)
    (positions by the trapezoid rule); the simulated vehicles start at ``x0`` with speeds ``v0``
    (front to back); every car is ``length`` metres long; no history, no second vehicle ahead of
    the head. For synthetic data, tests and speed benchmarks (it vmaps over platoons)."""
    head_v = jnp.asarray(head_v, jnp.float32)
    steps, num_vehicles = head_v.shape[0] - 1, jnp.shape(x0)[0]
    travelled = jnp.cumsum(0.5 * (head_v[1:] + head_v[:-1]) * dt)
    none = jnp.zeros(steps + 1, jnp.float32)
    no_merge_lane = jnp.zeros((0, steps + 1), jnp.float32)
    return SceneArrays(
        head_x=jnp.concatenate([none[:1], travelled]),
        head_v=head_v,
        head_present=jnp.ones(steps + 1, jnp.float32),
        head_gap=none,
        head_lead_v=none,
        head_has_leader=none,
        x0=jnp.asarray(x0, jnp.float32),
        v0=jnp.asarray(v0, jnp.float32),
        lead_length=jnp.full(num_vehicles, length, jnp.float32),
        road_end=jnp.full(num_vehicles, jnp.inf, jnp.float32),
        step_mask=jnp.ones(steps, jnp.float32),
        merge_x=no_merge_lane,
        merge_v=no_merge_lane,
        merge_present=no_merge_lane,
        merge_length=jnp.zeros(0, jnp.float32),
        dt=jnp.asarray(dt, jnp.float32),
    )


def step(
    key: Array, model: DriverModel, params: Any, state: Any, series: Series, j: Array, history: int
) -> Any:
    """One vehicle's closed-loop step: ``model``'s inputs at step ``j`` of ``series`` (the buffer
    the caller writes), then its stochastic move from ``state`` taken at ``x = 0``."""
    inputs = model.inputs_at(series, j, history)
    return model.transition_sample(key, params, state._replace(x=jnp.zeros_like(state.v)), inputs)


def _from_leaders(head: Array, followers: Array) -> Array:
    """Each simulated vehicle's leader's values: the head's for the first, vehicle k-1's for
    vehicle k; for one step (head (), followers (N,)) or a path (head (T + 1,), followers
    (N, T + 1))."""
    return jnp.concatenate([jnp.asarray(head)[None], followers[:-1]])


def _start_buffer(scene: SceneArrays, past: int) -> Series:
    """The simulated vehicles' series (N, past + T + 1): the scene's past (zeros without one),
    then the steps to be written; the replayed merge lane is known in advance (its past repeats
    its first step)."""
    num_vehicles, length = scene.x0.shape[0], scene.head_x.shape[0]
    zeros = jnp.zeros((num_vehicles, length), jnp.float32)
    ahead = AheadArrays(zeros, zeros, zeros, zeros, zeros)
    columns = Series(*(zeros for _ in range(7)), dt=jnp.broadcast_to(scene.dt, zeros.shape))
    columns = columns._replace(ahead=ahead)
    if scene.past is None:
        before = jax.tree.map(lambda a: jnp.zeros((num_vehicles, past), jnp.float32), columns)
    else:
        given = scene.past._replace(merge=None)
        if given.ahead is None:  # data without the scene ahead: none known, no leader acceleration
            given = given._replace(
                ahead=AheadArrays(*(jnp.zeros_like(given.v) for _ in AheadArrays._fields))
            )
        before = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), given)
    buffer = jax.tree.map(lambda a, b: jnp.concatenate([a, b], axis=1), before, columns)
    if scene.merge_x.shape[0] > 0:

        def per_vehicle(values: Array) -> Array:
            values = jnp.concatenate([jnp.repeat(values[:1], past, axis=0), values])
            return jnp.broadcast_to(values, (num_vehicles, *values.shape))

        # Distances to the merge point (x = 0) are measured from the front bumper.
        merge_x = scene.merge_x.T
        merge = MergeArrays(
            ego_to_merge=jnp.zeros((num_vehicles, past + length), jnp.float32),
            merge_to_merge=per_vehicle(-merge_x),
            merge_v=per_vehicle(scene.merge_v.T),
            merge_length=per_vehicle(jnp.broadcast_to(scene.merge_length, merge_x.shape)),
            merge_present=per_vehicle(scene.merge_present.T),
        )
        buffer = buffer._replace(merge=merge)
    return buffer


def _written(
    buffer: Series, scene: SceneArrays, t: Array, x: Array, v: Array, past: int, fresh: bool
) -> Series:
    """``buffer`` with every simulated vehicle's step t (at index ``past + t``) written: its speed,
    the *simulated* gap to its leader and the leader's speed, the second vehicle ahead, the
    leader's acceleration and age, and (in merge scenes) its distance to the merge point.
    ``fresh``: step t starts a scene without history (the past then repeats it)."""
    i = past + t
    gap = _from_leaders(scene.head_x[t], x) - x - scene.lead_length
    lead_v = _from_leaders(scene.head_v[t], v)
    has_leader = _from_leaders(scene.head_present[t], jnp.ones_like(x))
    has_leader2 = _from_leaders(scene.head_has_leader[t], has_leader) * has_leader
    earlier = lead_v if fresh else buffer.lead_v[:, i - 1]
    # Leaders never change in a scene; a replayed head that appears starts a new leader.
    kept_leader = (buffer.has_leader[:, i - 1] > 0) & (has_leader > 0) & (not fresh)
    lead_age = jnp.where(kept_leader, buffer.ahead.lead_age[:, i - 1] + 1.0, 0.0)
    column = {"v": v, "gap": gap, "lead_v": lead_v, "has_leader": has_leader}
    ahead = {
        "lead_acc": (lead_v - earlier) / scene.dt,
        "gap2": jnp.where(has_leader2 > 0, gap + _from_leaders(scene.head_gap[t], gap), NO_GAP2),
        "lead2_v": jnp.where(
            has_leader2 > 0, _from_leaders(scene.head_lead_v[t], lead_v), NO_LEAD2_V
        ),
        "has_leader2": has_leader2,
        "lead_age": lead_age,
    }
    # A fresh start writes its first step over the whole past as well.
    at = slice(0, i + 1) if fresh else i

    def put(a: Array, c: Array) -> Array:
        return a.at[:, at].set(c[:, None] if fresh else c)

    buffer = buffer._replace(
        **{k: put(getattr(buffer, k), c) for k, c in column.items()},
        ahead=buffer.ahead._replace(
            **{k: put(getattr(buffer.ahead, k), c) for k, c in ahead.items()}
        ),
    )
    if fresh:
        buffer = buffer._replace(dx=put(buffer.dx, v * scene.dt))
    if buffer.merge is not None:
        merge = buffer.merge._replace(ego_to_merge=put(buffer.merge.ego_to_merge, -x))
        buffer = buffer._replace(merge=merge)
    return buffer


def _one_rollout(
    key: Array,
    model: DriverModel,
    params: Any,
    scene: SceneArrays,
    laws: Any,
    history: int,
    past: int,
    start: str,
) -> Rollout:
    num_steps = scene.step_mask.shape[0]
    num_vehicles = scene.x0.shape[0]
    keys = rollout_keys(key, num_steps, num_vehicles)
    stationary = start == STATIONARY
    buffer = _written(_start_buffer(scene, past), scene, 0, scene.x0, scene.v0, past, stationary)
    here = EgoState(x=jnp.zeros_like(scene.v0), v=scene.v0)
    if stationary:
        state = jax.vmap(model.initial_sample)(keys.init, params, here)
    elif laws is not None:  # a hidden state, filtered by the caller over the whole history
        state = jax.vmap(model.filtered_start.draw)(keys.init, params, here, laws)
    else:
        inputs = jax.vmap(lambda row: model.inputs_at(row, past, history))(buffer)
        state = jax.vmap(model.lift)(params, here, inputs)

    def advance(carry, scan_in):
        state, x, buffer = carry
        t, step_keys = scan_in
        moved = jax.vmap(lambda k, p, s, row: step(k, model, p, s, row, past + t, history))(
            step_keys, params, state, buffer
        )
        buffer = buffer._replace(dx=buffer.dx.at[:, past + t].set(moved.x))
        x = x + moved.x
        buffer = _written(buffer, scene, t + 1, x, moved.v, past, False)
        return (moved, x, buffer), (x, moved.v, moved.x)

    scan_in = (jnp.arange(num_steps), keys.steps)
    _, (xs, vs, dxs) = jax.lax.scan(advance, (state, scene.x0, buffer), scan_in)
    x = jnp.concatenate([scene.x0[:, None], xs.T], axis=1)
    v = jnp.concatenate([scene.v0[:, None], vs.T], axis=1)
    gap = _from_leaders(scene.head_x, x) - x - scene.lead_length[:, None]
    has_leader = _from_leaders(scene.head_present, jnp.ones_like(x)) > 0
    real = scene.step_mask[None, :] > 0
    acceleration = jnp.diff(v, axis=1) / scene.dt
    return Rollout(
        x=x,
        v=v,
        gap=gap,
        dx=dxs.T,
        collision=(gap[:, 1:] <= 0) & has_leader[:, 1:] & real,
        hard_braking=(acceleration <= HARD_BRAKING_MPS2) & real,
        off_road=(x[:, 1:] > scene.road_end[:, None]) & real,
    )


def _static_arguments(
    model: DriverModel,
    dt: float,
    start: str,
    scene: SceneArrays,
    num_rollouts: int,
    has_laws: bool = False,
) -> dict[str, Any]:
    """The compiled rollouts' static arguments, after the start's check: the history a model
    reads and the buffer's past (steps before t0)."""
    check_start(model, start, scene.past is not None, whole_history=has_laws)
    past = history_steps(dt)
    history = past if model.reads_history else 0
    return {"num_rollouts": num_rollouts, "history": history, "past": past, "start": start}


def _scene_rollouts(key, model, params, scene, num_rollouts, history, past, start, laws=None):
    keys = jax.random.split(key, num_rollouts)
    return jax.vmap(_one_rollout, in_axes=(0, None, 0, None, 0, None, None, None))(
        keys, model, params, scene, laws, history, past, start
    )


_STATIC = ("model", "num_rollouts", "history", "past", "start")
_rollouts = jax.jit(_scene_rollouts, static_argnames=_STATIC)


@partial(jax.jit, static_argnames=_STATIC)
def _rollouts_per_scene(keys, model, params, scenes, laws, num_rollouts, history, past, start):
    def one_scene(key, scene_params, scene, scene_laws):
        return _scene_rollouts(
            key, model, scene_params, scene, num_rollouts, history, past, start, scene_laws
        )

    return jax.vmap(one_scene)(keys, params, scenes, laws)


def rollout(
    key: Array,
    model: DriverModel,
    params: Any,
    scene: SceneArrays,
    *,
    num_rollouts: int,
    start: str = STATIONARY,
    dt: float | None = None,
) -> Rollout:
    """``num_rollouts`` closed-loop rollouts of ``model`` through ``scene`` from ``start``.

    ``params`` is the model's parameter NamedTuple with every leaf shaped (num_rollouts, N): one
    parameter set per rollout and simulated vehicle. Keys follow :func:`rollout_keys` after one
    split per rollout. ``dt`` (the scene's step as a Python number) is needed where ``scene`` is
    traced (inside ``jit``): it sets the buffer's past and the history a model reads.
    """
    step_s = float(scene.dt) if dt is None else dt
    static = _static_arguments(model, step_s, start, scene, num_rollouts)
    return _rollouts(key, model, params, scene, **static)


def rollout_scenes(
    keys: Array,
    model: DriverModel,
    params: Any,
    scenes: SceneArrays,
    *,
    num_rollouts: int,
    start: str,
    dt: float,
    laws: Any = None,
) -> Rollout:
    """:func:`rollout` of each of a batch of scenes of one shape (every leaf of ``scenes`` with a
    leading scene axis S), scene s with ``keys[s]`` and ``params`` leaves (S, R, N); the result's
    leaves lead with (S, R, N). ``laws``: for the ``filtered`` start of a model with a hidden
    state, its filter's laws at t0 (``model.filtered_start.law``; leaves (S, R, N), like
    ``params``)."""
    static = _static_arguments(model, dt, start, scenes, num_rollouts, laws is not None)
    return _rollouts_per_scene(keys, model, params, scenes, laws, **static)
