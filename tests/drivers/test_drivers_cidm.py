"""The Cooperative IDM's yield rule: c = 0 never yields, c = 1 yields to whoever arrives first, the
threshold sits at TTM_other = c TTM_ego, and yielding never beats the IDM towards the real leader."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.cidm import CIDM, MergeInputs, cidm_acceleration, yield_target
from bayesdrive.drivers.execution_noise import acceleration_ceiling, noisy_step
from bayesdrive.drivers.idm import IDM, idm_acceleration

DT = 0.1
LENGTH = 4.5


def merge_inputs(gap, lead_v, ego_to_merge, merge_to_merge, merge_v, present=None):
    """One step's inputs with a leader; the merge-lane arrays have shape (..., K)."""
    merge_to_merge = np.asarray(merge_to_merge, dtype=float)
    present = np.ones_like(merge_to_merge) if present is None else present

    def f(values):
        return jnp.asarray(values, dtype=float)

    return MergeInputs(
        gap=f(gap),
        lead_v=f(lead_v),
        has_leader=jnp.ones_like(f(gap)),
        dt=jnp.full(np.shape(gap), DT, dtype=float),
        ego_to_merge=f(ego_to_merge),
        merge_to_merge=f(merge_to_merge),
        merge_v=f(merge_v),
        merge_length=jnp.full(merge_to_merge.shape, LENGTH, dtype=float),
        merge_present=f(present),
    )


def with_c(c, params=None):
    base = CIDM.defaults() if params is None else params
    return base._replace(c=jnp.asarray(c, dtype=float))


def random_scenes(rng, n, k):
    """n random merge scenes with k merge-lane slots, some padded, some past the merge point."""
    ego_v = np.where(rng.random(n) < 0.1, 0.0, rng.uniform(0.5, 30.0, n))
    merge_v = np.where(rng.random((n, k)) < 0.1, 0.0, rng.uniform(0.5, 30.0, (n, k)))
    return ego_v, merge_inputs(
        gap=rng.uniform(3.0, 80.0, n),
        lead_v=rng.uniform(0.0, 30.0, n),
        ego_to_merge=rng.uniform(-20.0, 200.0, n),
        merge_to_merge=rng.uniform(-20.0, 200.0, (n, k)),
        merge_v=merge_v,
        present=(rng.random((n, k)) < 0.8).astype(float),
    )


def cidm_accelerations(params, v, inputs):
    """CIDM acceleration of many scenes (one parameter set, or one per scene)."""
    params_axis = 0 if np.ndim(params.c) else None
    return np.asarray(
        jax.jit(jax.vmap(cidm_acceleration, in_axes=(params_axis, 0, 0)))(
            params, jnp.asarray(v, dtype=float), inputs
        )
    )


def leader_accelerations(params, v, inputs):
    """The IDM towards the real leader only, for the same scenes."""
    return np.asarray(
        jax.jit(idm_acceleration)(
            params, jnp.asarray(v, dtype=float), inputs.gap, inputs.lead_v, inputs.has_leader
        )
    )


def test_c_zero_never_yields():
    # 3000 random scenes (numpy seed 1), 3 merge-lane slots each.
    rng = np.random.default_rng(1)
    v, inputs = random_scenes(rng, 3000, 3)
    params = with_c(0.0)
    # Equal up to float32 rounding of separate kernels; a yield would move a value by far more.
    np.testing.assert_allclose(
        cidm_accelerations(params, v, inputs),
        leader_accelerations(params, v, inputs),
        rtol=1e-6,
        atol=1e-5,
    )


def test_never_accelerates_harder_than_the_idm_towards_the_real_leader():
    # 3000 random scenes (numpy seed 2) with c ~ U[0, 1] drawn per scene.
    rng = np.random.default_rng(2)
    n = 3000
    v, inputs = random_scenes(rng, n, 3)
    defaults = CIDM.defaults()
    params = jax.tree.map(lambda p: jnp.full(n, p), defaults)._replace(
        c=jnp.asarray(rng.uniform(0.0, 1.0, n), dtype=float)
    )
    cidm = cidm_accelerations(params, v, inputs)
    leader = leader_accelerations(defaults, v, inputs)
    # Computed in separate float32 kernels, equal values may differ by float32 rounding: the
    # subtraction in the IDM leaves ~1e-6 relative to its largest term (tolerance 1e-6 + 1e-5).
    assert np.all(cidm <= leader + 1e-6 * np.abs(leader) + 1e-5)
    assert np.mean(cidm < leader - 0.1) > 0.05, "the scenes should include real yields"


def test_c_one_yields_to_every_vehicle_that_arrives_first():
    # 3000 random scenes with ONE merge-lane vehicle (numpy seed 3). Oracle, in float64: the ego
    # yields iff both are before the merge point and the other's TTM is the smaller; then it takes
    # the smaller of the IDM towards the projected vehicle and towards its leader.
    rng = np.random.default_rng(3)
    n = 3000
    v, inputs = random_scenes(rng, n, 1)
    params = with_c(1.0)
    d_ego = np.asarray(inputs.ego_to_merge, np.float64)
    d_other = np.asarray(inputs.merge_to_merge[:, 0], np.float64)
    v_other = np.asarray(inputs.merge_v[:, 0], np.float64)
    with np.errstate(divide="ignore"):
        ttm_ego = np.where(v > 0, d_ego / v, np.inf)
        ttm_other = np.where(v_other > 0, d_other / v_other, np.inf)
    first = (
        (np.asarray(inputs.merge_present[:, 0]) > 0)
        & (d_ego >= 0)
        & (d_other >= 0)
        & (ttm_other < ttm_ego)
    )
    # float32 cannot order near-ties the way float64 does: leave out TTMs within 0.1 %.
    clear = ~np.isclose(ttm_other, ttm_ego, rtol=1e-3, atol=0.0)
    projected = idm_acceleration(
        params,
        jnp.asarray(v, dtype=float),
        inputs.ego_to_merge - inputs.merge_to_merge[:, 0] - LENGTH,
        inputs.merge_v[:, 0],
        1.0,
    )
    leader = leader_accelerations(params, v, inputs)
    expected = np.where(first, np.minimum(np.asarray(projected), leader), leader)
    got = cidm_accelerations(params, v, inputs)
    np.testing.assert_allclose(got[clear], expected[clear], rtol=1e-6, atol=1e-6)
    assert np.sum(first & clear & (np.asarray(projected) < leader)) > 100, "too few real yields"


# Ego 100 m before the merge point at 10 m/s: TTM_ego = 10 s; its leader is 200 m ahead. The
# merge-lane vehicle drives at 10 m/s too and is placed so that TTM_other = c TTM_ego (1 +- 1 %).
LEADER_GAP = 200.0


@pytest.mark.parametrize("c", [0.25, 0.5, 0.8])
def test_yield_threshold_sits_at_c_times_the_ego_ttm(c):
    ttm_ego, speed = 10.0, 10.0
    yields = []
    for factor in (0.99, 1.01):
        inputs = merge_inputs(
            gap=LEADER_GAP,
            lead_v=10.0,
            ego_to_merge=ttm_ego * speed,
            merge_to_merge=[factor * c * ttm_ego * speed],
            merge_v=[speed],
        )
        decision, _ = yield_target(jnp.asarray(c), jnp.asarray(speed), inputs)
        yields.append(bool(decision))
        # The decision shows in the acceleration: the projected vehicle is closer than the leader.
        params = with_c(c)
        a_cidm = float(cidm_acceleration(params, jnp.asarray(speed), inputs))
        a_leader = float(leader_accelerations(params, speed, inputs))
        assert (a_cidm < a_leader) == decision
    assert yields == [True, False]


def test_the_ego_considers_the_vehicle_whose_ttm_is_closest_to_its_own():
    # TTM_ego = 10 s, c = 0.5. Vehicle A arrives at 2 s (< 5 s: would be yielded to), vehicle B at
    # 9 s (arrives first but not early enough). B's TTM is the closest, so the ego does not yield;
    # with B's slot padded out, A is the closest and the ego yields.
    inputs = merge_inputs(
        gap=60.0, lead_v=10.0, ego_to_merge=100.0, merge_to_merge=[20.0, 90.0], merge_v=[10.0, 10.0]
    )
    decision, chosen = yield_target(jnp.asarray(0.5), jnp.asarray(10.0), inputs)
    assert (bool(decision), int(chosen)) == (False, 1)
    only_a = inputs._replace(merge_present=jnp.asarray([1.0, 0.0]))
    decision, chosen = yield_target(jnp.asarray(0.5), jnp.asarray(10.0), only_a)
    assert (bool(decision), int(chosen)) == (True, 0)


@pytest.mark.parametrize(
    ("ego_to_merge", "merge_to_merge"),
    [(-5.0, 30.0), (100.0, -1.0)],
    ids=["ego-past-merge", "other-past-merge"],
)
def test_nobody_past_the_merge_point_takes_part(ego_to_merge, merge_to_merge):
    inputs = merge_inputs(
        gap=60.0,
        lead_v=10.0,
        ego_to_merge=ego_to_merge,
        merge_to_merge=[merge_to_merge],
        merge_v=[25.0],
    )
    decision, _ = yield_target(jnp.asarray(1.0), jnp.asarray(10.0), inputs)
    assert not bool(decision)


def test_without_merging_vehicles_the_cidm_is_the_idm():
    # 1000 random scenes (numpy seed 4): slots all padded out, random c. Mean, density and the
    # sampled step (same key) must equal the IDM's exactly.
    rng = np.random.default_rng(4)
    n = 1000
    v, inputs = random_scenes(rng, n, 3)
    inputs = inputs._replace(merge_present=jnp.zeros_like(inputs.merge_present))
    idm_params = IDM.defaults()
    cidm_params = jax.tree.map(lambda p: jnp.full(n, p), CIDM.defaults())._replace(
        c=jnp.asarray(rng.uniform(0.0, 1.0, n), dtype=float)
    )
    states = EgoState(jnp.zeros(n), jnp.asarray(v, dtype=float))
    next_states = EgoState(
        jnp.asarray(v * DT + rng.normal(0.0, 0.01, n), dtype=float),
        jnp.asarray(np.where(rng.random(n) < 0.1, 0.0, v + 0.1), dtype=float),
    )
    keys = jax.random.split(jax.random.key(4), n)

    # Separate float32 kernels may round the mean acceleration an ulp apart (rtol 1e-6), and the
    # predicted increment (~3 m) by an ulp of 2.4e-7 m = 1.6e-4 of the 1.5 mm sd, which moves a
    # log-density at |z| <= 10 by <= 2e-3 nats (atol) and one far in the tails by rtol 1e-4.
    cidm_mean = jax.jit(jax.vmap(CIDM.mean_acceleration))(cidm_params, states, inputs)
    idm_mean = jax.jit(jax.vmap(IDM.mean_acceleration, in_axes=(None, 0, 0)))(
        idm_params, states, inputs.car_following
    )
    np.testing.assert_allclose(np.asarray(cidm_mean), np.asarray(idm_mean), rtol=1e-6, atol=1e-6)
    cidm_logp = jax.jit(jax.vmap(CIDM.transition_logpdf))(cidm_params, states, next_states, inputs)
    idm_logp = jax.jit(jax.vmap(IDM.transition_logpdf, in_axes=(None, 0, 0, 0)))(
        idm_params, states, next_states, inputs.car_following
    )
    np.testing.assert_allclose(np.asarray(cidm_logp), np.asarray(idm_logp), rtol=1e-4, atol=2e-3)

    cidm_step = jax.jit(jax.vmap(CIDM.transition_sample))(keys, cidm_params, states, inputs)
    idm_step = jax.jit(jax.vmap(IDM.transition_sample, in_axes=(0, None, 0, 0)))(
        keys, idm_params, states, inputs.car_following
    )
    for got, expected in zip(cidm_step, idm_step, strict=True):
        np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-6, atol=1e-6)


def test_yielding_moves_the_noise_and_the_density_with_the_cidm_mean():
    # A yielding scene: the sampled step is the IDM's noise around the CIDM mean (same key), and the
    # density peaks at the CIDM's predicted increment, not at the IDM-towards-leader one.
    params = with_c(1.0)
    inputs = merge_inputs(
        gap=LEADER_GAP, lead_v=10.0, ego_to_merge=100.0, merge_to_merge=[80.0], merge_v=[10.0]
    )
    state = EgoState(jnp.zeros(()), jnp.asarray(10.0))
    a_cidm = cidm_acceleration(params, state.v, inputs)
    a_leader = leader_accelerations(params, 10.0, inputs)
    assert float(a_cidm) < float(a_leader) - 0.5

    key = jax.random.key(9)
    sampled = CIDM.transition_sample(key, params, state, inputs)
    ceiling = acceleration_ceiling(state.v, inputs)
    expected = noisy_step(key, state, a_cidm, params.sigma, DT, ceiling)
    assert float(sampled.x) == float(expected.x) and float(sampled.v) == float(expected.v)

    def logp(acc):
        next_state = EgoState(state.v * DT + 0.5 * acc * DT**2, state.v + acc * DT)
        return float(CIDM.transition_logpdf(params, state, next_state, inputs))

    assert logp(a_cidm) > logp(a_leader) + 10.0


def test_stopped_vehicles_give_finite_values_and_gradients():
    # TTM = inf for a stopped ego and stopped merge-lane vehicles: no NaN in values or gradients.
    inputs = merge_inputs(
        gap=5.0, lead_v=0.0, ego_to_merge=20.0, merge_to_merge=[10.0, 15.0], merge_v=[0.0, 3.0]
    )
    for v in (0.0, 5.0):
        for c in (0.0, 0.5, 1.0):
            params = with_c(c)
            state = EgoState(jnp.zeros(()), jnp.asarray(v))
            value, grads = jax.value_and_grad(
                lambda p, state=state: CIDM.mean_acceleration(p, state, inputs)
            )(params)
            assert np.isfinite(float(value))
            assert all(np.isfinite(float(g)) for g in grads)


def test_car_following_inputs_are_refused_with_a_clear_error():
    inputs = CarFollowingInputs(jnp.asarray(20.0), jnp.asarray(10.0), jnp.asarray(1.0), DT)
    with pytest.raises(TypeError, match="MergeInputs"):
        CIDM.mean_acceleration(CIDM.defaults(), EgoState(0.0, 10.0), inputs)
