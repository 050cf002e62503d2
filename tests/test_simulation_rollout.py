"""The closed-loop simulator: it is the model's own transition sampler, fed simulated leaders."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.idm import IDM
from bayesdrive.simulation.baselines import CONSTANT_ACCELERATION, ConstantAccelerationParams
from bayesdrive.simulation.rollout import (
    SceneArrays,
    broadcast_params,
    draw_particles,
    rollout,
    rollout_keys,
)

DT = 0.1
LENGTH = 4.5


def platoon_scene(head_v: np.ndarray, x0: np.ndarray, v0: np.ndarray, length=LENGTH):
    """A platoon behind a head driving ``head_v`` (T + 1,), starting at x = 0."""
    head_v = np.asarray(head_v, np.float64)
    steps = len(head_v) - 1
    head_x = np.concatenate([[0.0], np.cumsum(0.5 * (head_v[1:] + head_v[:-1]) * DT)])
    n = len(x0)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    return SceneArrays(
        head_x=f32(head_x),
        head_v=f32(head_v),
        head_present=jnp.ones(steps + 1),
        x0=f32(x0),
        v0=f32(v0),
        lead_length=jnp.full(n, length, jnp.float32),
        road_end=jnp.full(n, jnp.inf, jnp.float32),
        step_mask=jnp.ones(steps),
        merge_x=jnp.zeros((0, steps + 1)),
        merge_v=jnp.zeros((0, steps + 1)),
        merge_present=jnp.zeros((0, steps + 1)),
        merge_length=jnp.zeros(0),
        dt=jnp.float32(DT),
    )


def braking_head(speed: float, brake_at_s: float, decel: float, floor: float, steps: int):
    t = np.arange(steps + 1) * DT
    return np.where(t < brake_at_s, speed, np.maximum(floor, speed - decel * (t - brake_at_s)))


def test_every_step_is_the_models_transition_sample_with_simulated_leaders():
    num_rollouts, num_vehicles, steps = 3, 4, 20
    key_params, key_run = jax.random.split(jax.random.key(7))
    head_v = 12.0 + 2.0 * np.sin(np.arange(steps + 1) * DT)
    scene = platoon_scene(head_v, x0=-18.0 * np.arange(1, 5), v0=[11.0, 12.5, 10.0, 13.0])
    # Different parameters per rollout and vehicle, drawn from the IDM's prior.
    theta = IDM.prior().sample(key_params, (num_rollouts, num_vehicles))
    params = IDM.params_type(*(theta[..., i] for i in range(theta.shape[-1])))
    out = rollout(key_run, IDM, params, scene, num_rollouts=num_rollouts)

    np.testing.assert_array_equal(out.x[:, :, 0], np.broadcast_to(scene.x0, (3, 4)))

    # Inputs built here from the SIMULATED leaders (closed loop), not by the simulator.
    x, v = out.x[:, :, :-1], out.v[:, :, :-1]  # (R, N, T): the state before each step
    lead_x = jnp.concatenate([jnp.broadcast_to(scene.head_x[:-1], (3, 1, steps)), x[:, :-1]], 1)
    lead_v = jnp.concatenate([jnp.broadcast_to(scene.head_v[:-1], (3, 1, steps)), v[:, :-1]], 1)
    inputs = CarFollowingInputs(lead_x - x - LENGTH, lead_v, jnp.ones_like(x), jnp.full_like(x, DT))
    keys = jax.vmap(lambda k: rollout_keys(k, steps, num_vehicles).steps)(
        jax.random.split(key_run, num_rollouts)
    )  # (R, T, N)
    by_step = jax.tree.map(lambda leaf: jnp.broadcast_to(leaf[:, :, None], x.shape), params)

    def sample(step_keys):
        # vmap over rollouts, vehicles and steps of the model's own one-step sampler.
        per_vehicle = jax.vmap(jax.vmap(jax.vmap(IDM.transition_sample)))
        return per_vehicle(step_keys.transpose(0, 2, 1), by_step, EgoState(x, v), inputs)

    expected = sample(keys)
    np.testing.assert_allclose(out.x[:, :, 1:], expected.x, rtol=0, atol=1e-5)
    np.testing.assert_allclose(out.v[:, :, 1:], expected.v, rtol=0, atol=1e-5)
    # A deliberately wrong variant (each step drawn with the next step's keys) fails that check.
    wrong = sample(jnp.roll(keys, -1, axis=1))
    assert not np.allclose(out.v[:, :, 1:], wrong.v, rtol=0, atol=1e-5)


def test_same_key_is_bit_identical_and_another_key_differs():
    scene = platoon_scene(np.full(31, 10.0), x0=[-20.0, -40.0], v0=[10.0, 10.0])
    params = broadcast_params(IDM.defaults(), 5, 2)
    first = rollout(jax.random.key(3), IDM, params, scene, num_rollouts=5)
    again = rollout(jax.random.key(3), IDM, params, scene, num_rollouts=5)
    other = rollout(jax.random.key(4), IDM, params, scene, num_rollouts=5)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first.x, other.x)
    # Rollouts of one call are independent draws, not copies.
    assert not np.array_equal(first.x[0], first.x[1])


def test_collision_is_counted_while_the_bumper_gap_is_not_positive():
    # Head standing at x = 0 (4.5 m long); a constant-velocity follower 5 m behind its rear at
    # 10 m/s closes 1 m per step: gap 5 - t, so steps t = 5..10 are collisions.
    steps = 10
    scene = platoon_scene(np.zeros(steps + 1), x0=[-9.5], v0=[10.0])
    params = broadcast_params(ConstantAccelerationParams(acc=0.0, sigma=0.0), 1, 1)
    out = rollout(jax.random.key(0), CONSTANT_ACCELERATION, params, scene, num_rollouts=1)
    np.testing.assert_allclose(out.gap[0, 0], 5.0 - np.arange(steps + 1), atol=1e-5)
    expected = np.arange(1, steps + 1) >= 5
    np.testing.assert_array_equal(out.collision[0, 0], expected)


@pytest.mark.parametrize(
    ("acc", "v0", "expected"), [(-4.0, 10.0, 10), (-2.9, 10.0, 0), (-4.0, 1.0, 2)]
)
def test_hard_braking_counts_realised_decelerations_at_or_below_3(acc, v0, expected):
    # From 1 m/s at -4 m/s^2 the speed goes 1 -> 0.6 -> 0.2 -> 0 (clipped): realised -4, -4, -2,
    # then 0, so two hard-braking steps; the third step's -2 m/s^2 is not hard braking.
    scene = platoon_scene(np.full(11, 30.0), x0=[-50.0], v0=[v0])
    params = broadcast_params(ConstantAccelerationParams(acc=acc, sigma=0.0), 1, 1)
    out = rollout(jax.random.key(0), CONSTANT_ACCELERATION, params, scene, num_rollouts=1)
    assert int(out.hard_braking.sum()) == expected


PLATOON = 5
HORIZON_STEPS = 120


@settings(max_examples=40, deadline=None)
@given(
    speed=st.floats(0.0, 30.0),
    gap_fraction=st.lists(st.floats(0.5, 3.0), min_size=PLATOON, max_size=PLATOON),
    brake_at_s=st.floats(0.0, 6.0),
    decel=st.floats(0.5, 9.0),
    floor_fraction=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31 - 1),
)
def test_idm_platoon_at_default_parameters_never_collides(
    speed, gap_fraction, brake_at_s, decel, floor_fraction, seed
):
    # Initial gaps from half to three times the IDM's static desired gap d_min + v tau (defaults:
    # 2 m + 1 s * v); the head brakes at up to 9 m/s^2 (an emergency stop) to any lower speed.
    # Execution noise at the default sigma = 0.3 m/s^2; seed drawn by hypothesis.
    desired = 2.0 + 1.0 * speed
    gaps = np.asarray(gap_fraction) * desired
    x0 = -np.cumsum(gaps + LENGTH)
    head_v = braking_head(speed, brake_at_s, decel, floor_fraction * speed, HORIZON_STEPS)
    scene = platoon_scene(head_v, x0=x0, v0=np.full(PLATOON, speed))
    params = broadcast_params(IDM.defaults(), 4, PLATOON)
    out = rollout(jax.random.key(seed), IDM, params, scene, num_rollouts=4)
    assert not bool(out.collision.any())
    assert float(out.gap.min()) > 0.0


def test_constant_velocity_platoon_collides_when_the_head_stops():
    # The same kind of scene as the property above: what the IDM avoids, constant velocity hits.
    head_v = braking_head(20.0, 1.0, 6.0, 0.0, HORIZON_STEPS)
    scene = platoon_scene(
        head_v, x0=-np.cumsum(np.full(PLATOON, 22.0 + LENGTH)), v0=np.full(5, 20.0)
    )
    params = broadcast_params(ConstantAccelerationParams(acc=0.0, sigma=0.0), 1, PLATOON)
    out = rollout(jax.random.key(0), CONSTANT_ACCELERATION, params, scene, num_rollouts=1)
    assert bool(out.collision[0, 0].any())


def test_draw_particles_takes_each_vehicles_own_particles():
    # Vehicle n's particles all have v_des in [10 n, 10 n + 1): any mix-up shows.
    num_vehicles, num_particles = 3, 50
    rng = np.random.default_rng(0)
    v_des = 10.0 * np.arange(1, num_vehicles + 1)[:, None] + rng.uniform(0, 1, (3, num_particles))
    particles = v_des[..., None]
    params = draw_particles(jax.random.key(1), IDM, ("v_des",), particles, num_rollouts=200)
    assert params.v_des.shape == (200, num_vehicles)
    drawn = np.asarray(params.v_des)
    for n in range(num_vehicles):
        assert np.all(np.isin(drawn[:, n], particles[n, :, 0].astype(np.float32)))
    # 200 uniform draws from 50 particles reach most of them (P(a particle is missed) = 1.8%).
    assert len(np.unique(drawn[:, 0])) > 40
    np.testing.assert_array_equal(params.tau, np.full((200, num_vehicles), IDM.spec("tau").default))
