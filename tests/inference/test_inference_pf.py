"""The pf engine is the paper's Algorithm 1: grid particles, weight, resample every step, dither
by one grid step, epochs pooled."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import Array

from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.core.likelihood import fixed_params, step_inputs, step_loglik
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following
from bayesdrive.inference.engines import pf

PARAMS = ("v_des", "tau", "sigma")
PARTICLES = 256
STEPS = 64


class PointPrior(NamedTuple):
    """Every particle starts at one value, so moves can be counted from a known start."""

    value: Array

    def logpdf(self, theta):
        return jnp.where(jnp.all(theta == self.value), 0.0, -jnp.inf)

    def sample(self, key, shape=()):
        del key
        return jnp.broadcast_to(self.value, (*shape, self.value.shape[0]))


START = jnp.array([20.0, 1.5, 0.5])  # on the grid: 40 * 0.5, 15 * 0.1, 5 * 0.1


@pytest.fixture(scope="module")
def arrays():
    params = IDM.params_type(*(jnp.full(3, s.default) for s in IDM.specs))
    return simulate_following(jax.random.key(8), IDM, params, num_steps=STEPS)


def run(arrays, seed=1, **options):
    return pf.run(
        jax.random.key(seed),
        arrays,
        model=IDM,
        params=PARAMS,
        num_particles=PARTICLES,
        **options,
    )


def grid_index(result) -> np.ndarray:
    """Posterior values as grid indices (particle, vehicle, param), checked to be whole numbers."""
    grid = pf.make_grid(IDM, PARAMS)
    values = np.stack([result.posterior[n][0] for n in PARAMS], axis=-1)
    index = (values - grid.first) / grid.step
    assert np.allclose(index, np.round(index), atol=1e-9)
    return np.round(index).astype(int)


def test_grid_holds_the_multiples_of_each_step_inside_the_bounds():
    grid = pf.make_grid(IDM, ("v_des", "sigma"))
    assert grid.values(np.array([0, 0])).tolist() == [5.0, 0.1]  # sigma's bound 0.02 -> 0.1
    assert grid.values(grid.size - 1).tolist() == [45.0, 2.0]
    assert grid.size.tolist() == [81, 20]
    with pytest.raises(ValueError, match="must be positive"):
        pf.make_grid(IDM, ("v_des",), steps={"v_des": -1.0})
    with pytest.raises(ValueError, match="fewer than 2 points"):
        pf.make_grid(IDM, ("tau",), steps={"tau": 10.0})


def test_particles_stay_on_the_grid_inside_the_bounds(arrays):
    index = grid_index(run(arrays))
    grid = pf.make_grid(IDM, PARAMS)
    assert index.min() >= 0
    assert np.all(index <= grid.size - 1)


@pytest.mark.parametrize("live_steps", [0, 1, 3])
def test_dithering_moves_at_most_one_grid_step_per_step(arrays, live_steps):
    mask = np.zeros_like(arrays.mask)
    mask[:, 10 : 10 + live_steps] = 1.0
    result = run(arrays._replace(mask=mask), prior=PointPrior(START))
    grid = pf.make_grid(IDM, PARAMS)
    moved = np.abs(grid_index(result) - np.round((np.asarray(START) - grid.first) / grid.step))
    assert moved.max() == live_steps  # every live step dithers, by one grid step at most


def test_every_live_step_resamples_and_masked_steps_do_not(arrays):
    mask = arrays.mask.copy()
    mask[:, 30:40] = 0.0
    result = run(arrays._replace(mask=mask))
    unique = result.sample_stats["unique_particles"][1]
    live = mask > 0
    assert np.array_equal(result.sample_stats["resampled"][1], live)
    # Systematic resampling on unequal weights keeps fewer than N distinct ancestors every time.
    assert np.all(unique[live] < PARTICLES) and np.all(unique[live] >= 1)
    assert np.all(np.isnan(unique[~live]))


def test_epochs_pool_the_final_particles_of_all_vehicles(arrays):
    mask = arrays.mask.copy()
    mask[0] = 0.0  # vehicle 0 has no data: only pooling can move its particles off the start
    data = arrays._replace(mask=mask)
    grid = pf.make_grid(IDM, PARAMS)
    start_index = np.round((np.asarray(START) - grid.first) / grid.step)
    one = grid_index(run(data, prior=PointPrior(START), epochs=1))
    two = grid_index(run(data, prior=PointPrior(START), epochs=2))
    assert np.all(one[:, 0] == start_index)
    assert np.any(two[:, 0] != start_index)
    stats = run(data, prior=PointPrior(START), epochs=2).sample_stats
    assert stats["epoch_log_evidence"][1].shape == (2, 3)


def test_log_evidence_is_the_sum_of_log_mean_weights(arrays):
    # From a point prior all particles are equal at the first live step, so its mean weight is the
    # one-step density of START itself.
    mask = np.zeros_like(arrays.mask)
    mask[:, 5] = 1.0
    result = run(arrays._replace(mask=mask), prior=PointPrior(START))
    series = step_inputs(arrays._replace(mask=mask), IDM)
    expected = [
        float(
            step_loglik(
                IDM,
                PARAMS,
                fixed_params(IDM, None),
                START,
                jax.tree.map(lambda a, i=i: a[i, 5], series),
            )
        )
        for i in range(3)
    ]
    # Two compiled programs round one step's density differently in float32: the residual of a
    # position increment of about 2.5 m carries an ulp of about 2e-7 m, magnified by the Gaussian
    # exponent (1e-3 nats here); a wrong evidence is off by whole nats (log N, a missed step).
    assert np.allclose(result.sample_stats["log_evidence"][1], expected, rtol=1e-4, atol=1e-3)


def test_pf_same_seed_is_bit_identical_and_seeds_differ(arrays):
    first, again, other = run(arrays, seed=3), run(arrays, seed=3), run(arrays, seed=4)
    for name in PARAMS:
        assert np.array_equal(first.posterior[name], again.posterior[name])
        assert not np.array_equal(first.posterior[name], other.posterior[name])


def test_pf_masked_steps_contribute_nothing(arrays):
    mask = arrays.mask.copy()
    mask[:, 20:30] = 0.0
    clean = arrays._replace(mask=mask)
    garbage = clean._replace(dx=np.where(mask > 0, arrays.dx, -50.0))
    a, b = run(clean, seed=6), run(garbage, seed=6)
    for name in PARAMS:
        assert np.array_equal(a.posterior[name], b.posterior[name])


def test_dither_steps_are_uniform_and_independent():
    # 30000 particles x 6 parameters; tolerance 5 binomial standard errors.
    steps = np.asarray(pf.dither_steps(jax.random.key(17), (30_000, 6)))
    assert set(np.unique(steps)) == {-1, 0, 1}
    for column in steps.T:
        share = np.bincount(column + 1, minlength=3) / len(column)
        assert np.all(np.abs(share - 1 / 3) < 5 * np.sqrt((1 / 3) * (2 / 3) / len(column)))
    pairs = np.bincount(3 * (steps[:, 0] + 1) + steps[:, 5] + 1, minlength=9) / len(steps)
    assert np.all(np.abs(pairs - 1 / 9) < 5 * np.sqrt((1 / 9) * (8 / 9) / len(steps)))


def test_results_do_not_depend_on_chunking_or_order(arrays):
    # Vehicles are sorted by series length and chunked; each keeps its own random stream.
    mask = arrays.mask.copy()
    mask[1, 40:] = 0.0  # different lengths, so sorting reorders the vehicles
    data = arrays._replace(mask=mask)
    together, alone = run(data, seed=9), run(data, seed=9, vehicle_chunk=1)
    for name in PARAMS:
        assert np.array_equal(together.posterior[name], alone.posterior[name])
