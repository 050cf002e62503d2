"""The closed-loop simulator: it is the model's own transition sampler, fed simulated leaders."""

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.idm import IDM
from bayesdrive.simulation.baselines import CONSTANT_ACCELERATION, ConstantAccelerationParams
from bayesdrive.simulation.rollout import (
    broadcast_params,
    draw_particles,
    rollout,
    rollout_keys,
)
from bayesdrive.simulation.rollout import platoon_scene as make_platoon_scene

DT = 0.1
LENGTH = 4.5


def platoon_scene(head_v, x0, v0, length=LENGTH):
    return make_platoon_scene(head_v, np.asarray(x0), np.asarray(v0), length=length, dt=DT)


def braking_head(speed: float, brake_at_s: float, decel: float, floor: float, steps: int):
    t = np.arange(steps + 1) * DT
    return np.where(t < brake_at_s, speed, np.maximum(floor, speed - decel * (t - brake_at_s)))


# One shape (IDM, rollouts x vehicles x steps) for every IDM test below: one compilation.
ROLLOUTS, PLATOON, HORIZON_STEPS = 4, 5, 120


def test_every_step_is_the_models_transition_sample_with_simulated_leaders():
    key_params, key_run = jax.random.split(jax.random.key(7))
    t = np.arange(HORIZON_STEPS + 1) * DT
    head_v = 12.0 + 2.0 * np.sin(t)
    scene = platoon_scene(head_v, x0=-18.0 * np.arange(1, 6), v0=[11.0, 12.5, 10.0, 13.0, 9.0])
    # Different parameters per rollout and vehicle, drawn from the IDM's prior.
    theta = IDM.prior().sample(key_params, (ROLLOUTS, PLATOON))
    params = IDM.params_type(*(theta[..., i] for i in range(theta.shape[-1])))
    out = rollout(key_run, IDM, params, scene, num_rollouts=ROLLOUTS)
    np.testing.assert_array_equal(out.x[:, :, 0], np.broadcast_to(scene.x0, (ROLLOUTS, PLATOON)))

    # Inputs built here from the SIMULATED leaders (closed loop), not by the simulator.
    x, v = out.x[:, :, :-1], out.v[:, :, :-1]  # (R, N, T): the state before each step
    head_shape = (ROLLOUTS, 1, HORIZON_STEPS)
    lead_x = jnp.concatenate([jnp.broadcast_to(scene.head_x[:-1], head_shape), x[:, :-1]], 1)
    lead_v = jnp.concatenate([jnp.broadcast_to(scene.head_v[:-1], head_shape), v[:, :-1]], 1)
    inputs = CarFollowingInputs(lead_x - x - LENGTH, lead_v, jnp.ones_like(x), jnp.full_like(x, DT))
    keys = jax.vmap(lambda k: rollout_keys(k, HORIZON_STEPS, PLATOON).steps)(
        jax.random.split(key_run, ROLLOUTS)
    )  # (R, T, N), the documented key schedule
    by_step = jax.tree.map(lambda leaf: jnp.broadcast_to(leaf[:, :, None], x.shape), params)

    @jax.jit
    def sample(step_keys):
        # The model's own one-step sampler, vmapped over rollouts, vehicles and steps.
        per_vehicle = jax.vmap(jax.vmap(jax.vmap(IDM.transition_sample)))
        return per_vehicle(step_keys.transpose(0, 2, 1), by_step, EgoState(x, v), inputs)

    expected = sample(keys)
    # float32 positions of up to ~200 m: 1e-4 m is a few ulps.
    np.testing.assert_allclose(out.x[:, :, 1:], expected.x, rtol=0, atol=1e-4)
    np.testing.assert_allclose(out.v[:, :, 1:], expected.v, rtol=0, atol=1e-5)
    # A deliberately wrong variant (each step drawn with the next step's keys) fails that check.
    wrong = sample(jnp.roll(keys, -1, axis=1))
    assert not np.allclose(out.v[:, :, 1:], wrong.v, rtol=0, atol=1e-5)


def test_same_key_is_bit_identical_and_another_key_differs():
    scene = platoon_scene(
        np.full(HORIZON_STEPS + 1, 10.0), -20.0 * np.arange(1, 6), np.full(5, 10.0)
    )
    params = broadcast_params(IDM.defaults(), ROLLOUTS, PLATOON)
    first = rollout(jax.random.key(3), IDM, params, scene, num_rollouts=ROLLOUTS)
    again = rollout(jax.random.key(3), IDM, params, scene, num_rollouts=ROLLOUTS)
    other = rollout(jax.random.key(4), IDM, params, scene, num_rollouts=ROLLOUTS)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first.x, other.x)
    # Rollouts of one call are independent draws, not copies.
    assert not np.array_equal(first.x[0], first.x[1])


def constant_acceleration_run(acc, v0, x0, head_v):
    """Three independent constant-acceleration cars (sigma = 0) over 10 steps, one rollout."""
    scene = platoon_scene(head_v, x0=x0, v0=v0)
    params = ConstantAccelerationParams(
        acc=jnp.asarray([acc], jnp.float32), sigma=jnp.zeros((1, 3), jnp.float32)
    )
    return rollout(jax.random.key(0), CONSTANT_ACCELERATION, params, scene, num_rollouts=1)


def test_collision_is_counted_while_the_bumper_gap_is_not_positive():
    # Head standing at x = 0 (4.5 m long); a constant-velocity follower 5 m behind its rear at
    # 10 m/s closes 1 m per step: gap 5 - t, so steps t = 5..10 are collisions. The cars behind
    # stand still far back and never collide.
    out = constant_acceleration_run(
        [0.0, 0.0, 0.0], v0=[10.0, 0.0, 0.0], x0=[-9.5, -60.0, -90.0], head_v=np.zeros(11)
    )
    np.testing.assert_allclose(out.gap[0, 0], 5.0 - np.arange(11), atol=1e-5)
    np.testing.assert_array_equal(out.collision[0, 0], np.arange(1, 11) >= 5)
    assert not bool(out.collision[0, 1:].any())


def test_hard_braking_counts_realised_decelerations_at_or_below_3():
    # -4 m/s^2 from 10 m/s: 10 hard steps; -2.9 m/s^2: none; -4 m/s^2 from 1 m/s: the speed goes
    # 1 -> 0.6 -> 0.2 -> 0 (clipped), realised -4, -4, -2, then 0: two hard steps.
    out = constant_acceleration_run(
        [-4.0, -2.9, -4.0],
        v0=[10.0, 10.0, 1.0],
        x0=[-50.0, -100.0, -150.0],
        head_v=np.full(11, 30.0),
    )
    np.testing.assert_array_equal(out.hard_braking[0].sum(axis=1), [10, 0, 2])


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
    gaps = np.asarray(gap_fraction) * (2.0 + 1.0 * speed)
    head_v = braking_head(speed, brake_at_s, decel, floor_fraction * speed, HORIZON_STEPS)
    scene = platoon_scene(head_v, x0=-np.cumsum(gaps + LENGTH), v0=np.full(PLATOON, speed))
    params = broadcast_params(IDM.defaults(), ROLLOUTS, PLATOON)
    out = rollout(jax.random.key(seed), IDM, params, scene, num_rollouts=ROLLOUTS)
    assert not bool(out.collision.any())
    assert float(out.gap.min()) > 0.0


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
