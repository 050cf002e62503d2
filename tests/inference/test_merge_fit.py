"""Fitting a merging model: the cooperating car's steps with the merge scene beside them, scored
by the C-IDM's exact density, and complete pooling of many short stays into one series."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.data import registry
from bayesdrive.data.views import pooled_series
from bayesdrive.drivers.cidm import CIDM, yield_target
from bayesdrive.inference.core.likelihood import fixed_params, series_loglik, step_inputs
from bayesdrive.inference.core.output import metadata
from bayesdrive.inference.fit import first_vehicles, fit
from bayesdrive.simulation.scenarios import (
    MERGE_FIT_STAY_S,
    fitting_episodes,
    heldout_episodes,
    merge_follower_arrays,
    merge_scenarios,
)

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def stays(data_dir):
    traj = registry.load("ngsim_merge_episodes", data_dir=data_dir)
    assert not set(fitting_episodes(traj)) & set(heldout_episodes(traj))
    scenarios = merge_scenarios(traj, horizon_s=MERGE_FIT_STAY_S, episodes="fit")
    return merge_follower_arrays(scenarios)


def _loglik(arrays, c: float) -> np.ndarray:
    """Per-step log-density of every row at the model's defaults with cooperation ``c``."""
    params = fixed_params(CIDM, {"c": c})
    series = step_inputs(arrays, CIDM)
    return np.asarray(jax.vmap(lambda s: series_loglik(CIDM, (), params, jnp.zeros(0), s))(series))


def test_stays_carry_the_merge_scene_and_cooperation_changes_the_likelihood(stays):
    assert stays.merge is not None
    assert stays.merge.merge_to_merge.shape == (*stays.mask.shape, 2)
    assert (stays.mask.sum(axis=1) > 0).all()  # stays without a usable step are left out
    # The merging car is ahead of the cooperating car (V2 is the car just behind it).
    usable = stays.mask > 0
    present = stays.merge.merge_present[..., 0] > 0
    ahead = stays.merge.ego_to_merge > stays.merge.merge_to_merge[..., 0]
    assert ahead[usable & present].all()
    never, always = _loglik(stays, 0.0), _loglik(stays, 1.0)
    changed = np.abs(never - always) > 1e-6
    # Only steps where a fully cooperative driver yields can score differently (not all of them:
    # yielding takes the smaller of two accelerations), and on real merges many do.
    series = step_inputs(stays, CIDM)
    yields = np.asarray(jax.vmap(jax.vmap(lambda s: yield_target(1.0, s.v, s.inputs)[0]))(series))
    assert not (changed & ~yields)[usable].any()
    assert changed[usable].mean() > 0.05


def test_pooling_keeps_every_usable_step_and_its_density(stays):
    pooled = pooled_series(stays, "all stays")
    assert pooled.vehicle_ids == ("all stays",)
    assert pooled.mask.sum() == stays.mask.sum()
    total_by_row = _loglik(stays, 0.5).sum()
    np.testing.assert_allclose(_loglik(pooled, 0.5).sum(), total_by_row, rtol=1e-5)


def test_cidm_fit_learns_cooperation_from_merge_stays(stays):
    seed = 5
    tree = fit(
        jax.random.key(seed),
        first_vehicles(stays, 3),
        model=CIDM,
        engine="smc",
        num_particles=64,
        seed=seed,
        source="ngsim_merge_episodes",
        replicates=2,
    )
    c = tree["posterior"]["c"].values
    assert c.shape == (2, 64, 3) and ((c >= 0) & (c <= 1)).all()
    assert metadata(tree)["data_source"] == "ngsim_merge_episodes"
