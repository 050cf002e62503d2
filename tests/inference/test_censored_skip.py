"""The likelihood computes the censored classes' probabilities only where they are needed, for
the extensions as for the base models, and no density changes: a model scored step by step gets
them on its usable censored steps alone, a model with a state filter on a series with a censored
step.

Real NGSIM I-80 series: vehicle 210 has no censored step; vehicle 252 of the same chain has steps
at the collision-free ceiling (its reconstructed gap shrinks to about 1 m and below); 210 with
one step edited to end in a stop gives a stop. Each model (two extensions scored step by step,
two with a state filter) scores every series three ways: as the likelihood chooses, with the
class probabilities always computed and with them skipped; the two scored step by step are also
scored one step at a time, as pf and smc's sequential pass score them. Tolerance rtol 1e-4 and
1e-3 nats (float32 rounding of one density computed in two compiled programs,
:data:`TOLERANCE`); no randomness. Negative control: skipping on a series with a censored step
changes its density by more than 1 nat.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.data.readers import read
from bayesdrive.data.views import FollowerArrays, scored_series
from bayesdrive.drivers.base import EgoState
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.likelihood import StepInputs, step_inputs, step_loglik
from tests.compiled import step_logpdfs

CHAIN = "ngsim_i80_chains/202_210_213_222_234_252.csv"
CLEAN, AT_CEILING = "210", "252"
# Step of the clean series edited to end in a stop (mid-series, usable).
STOP_AT = 100
# Two compiled programs round one density differently: an ulp of a position increment of about
# 1 m is about 1e-4 of its sd (0.5 sigma dt^2, about 2 mm), and the Gaussian exponent magnifies it.
TOLERANCE = {"rtol": 1e-4, "atol": 1e-3}
# model -> (the extension switched on, whether its likelihood censors at the physical limits: the
# measurement-noise filter reads a step at a limit as a moving one and censors stops alone, but
# its declaration is its base model's, so a step at a limit still turns the skip off).
CASES = {
    "idm+autocorrelated_noise": ({"noise_time_s": 1.0}, True),
    "idm+reaction_delay": ({"reaction_time": 0.7}, True),
    "idm+drifting_parameters": ({"tau_drift": 0.05}, True),
    "idm+measurement_noise": ({"sigma_obs": 0.05}, False),
}
# Added by the skipping densities of the marked model, so the branch taken shows in the values.
MARK = 1000.0


@pytest.fixture(scope="module")
def chain(data_dir) -> FollowerArrays:
    return scored_series(read(data_dir / CHAIN))


def one_vehicle(arrays: FollowerArrays, model, vehicle: str) -> StepInputs:
    row = arrays.vehicle_ids.index(vehicle)
    return jax.tree.map(lambda a: a[row], step_inputs(arrays, model))


def with_a_stop(arrays: FollowerArrays) -> FollowerArrays:
    """The clean vehicle braking to a stop from 0.5 m/s at one step (a stop within the floor)."""
    row = arrays.vehicle_ids.index(CLEAN)
    assert arrays.mask[row, STOP_AT] > 0 and arrays.next_v[row, STOP_AT] > 1.0
    v, next_v, dx = (values.copy() for values in (arrays.v, arrays.next_v, arrays.dx))
    v[row, STOP_AT], next_v[row, STOP_AT] = 0.5, 0.0
    dx[row, STOP_AT] = 0.5 * 0.5 * arrays.dt
    return arrays._replace(v=v, next_v=next_v, dx=dx)


def marked(model):
    """``model`` whose densities add :data:`MARK` when told that no step is censored."""
    scores = model.filter if model.filter is not None else model.transition_logpdf

    def scores_marked(*args, may_be_censored: bool = True):
        mark = jnp.where(may_be_censored, 0.0, MARK)
        return scores(*args, may_be_censored=may_be_censored) + mark

    if model.filter is not None:
        return model._replace(filter=scores_marked)
    return model._replace(transition_logpdf=scores_marked)


@pytest.mark.realdata
@pytest.mark.parametrize("name", list(CASES))
def test_the_skip_changes_no_series_density_and_is_taken_only_off_censored_steps(chain, name):
    extension, censors_limits = CASES[name]
    model = get_model(name)
    params = model.defaults()._replace(**{k: jnp.asarray(v) for k, v in extension.items()})

    @jax.jit
    def scored(steps):
        chosen = step_logpdfs(model, params, steps)
        full = step_logpdfs(model, params, steps, may_be_censored=True)
        skipped = step_logpdfs(model, params, steps, may_be_censored=False)
        branch = step_logpdfs(marked(model), params, steps) - chosen
        if model.filter is not None:  # scored as a whole series only
            return chosen, full, skipped, branch, None
        # What engines that score one step at a time get (pf, smc's sequential pass): each
        # step's own check.
        theta = jnp.stack(params)
        one_by_one = jax.vmap(lambda step: step_loglik(model, model.param_names, None, theta, step))
        return chosen, full, skipped, branch, one_by_one(steps)

    series = {
        "clean": one_vehicle(chain, model, CLEAN),
        "ceiling": one_vehicle(chain, model, AT_CEILING),
        "stop": one_vehicle(with_a_stop(chain), model, CLEAN),
    }
    for kind, steps in series.items():
        chosen, full, skipped, branch, one_by_one = scored(steps)
        chosen, full, skipped, branch = map(np.asarray, (chosen, full, skipped, branch))
        usable = np.asarray(steps.mask) > 0
        assert np.all(np.isfinite(full[usable])), kind
        # Masked steps are zeroed by every caller; padding reads as a stop.
        np.testing.assert_allclose(chosen[usable], full[usable], **TOLERANCE, err_msg=kind)
        if one_by_one is not None:
            masked = np.where(usable, full, 0.0)
            np.testing.assert_allclose(one_by_one, masked, **TOLERANCE, err_msg=kind)
        if model.filter is not None:
            # The skip is taken exactly on the series without a censored step.
            expected = MARK if kind == "clean" else 0.0
            censored_usable = kind != "clean"
        else:
            # Step by step: the classes on the usable censored steps alone.
            flags = jax.vmap(model.censored)(
                EgoState(jnp.zeros_like(steps.v), steps.v),
                EgoState(steps.dx, steps.next_v),
                steps.inputs,
            )
            censored = usable & np.asarray(flags)
            # The edited stop is usable; the ceiling's steps lack the history some models need.
            censored_usable = bool(censored.any())
            assert censored_usable or kind != "stop", kind
            expected = np.where(censored, 0.0, MARK)
            branch = np.where(usable, branch, expected)
        np.testing.assert_allclose(branch, expected, **TOLERANCE, err_msg=kind)
        # Where a filter scores the series, every step it returns; step by step, the usable ones.
        compared = slice(None) if model.filter is not None else usable
        if kind == "stop" or (kind == "ceiling" and censors_limits and censored_usable):
            # Negative control: the skip forced on a censored series is wrong.
            assert np.nanmax(np.abs(skipped - full)[compared]) > 1.0, kind
        else:
            np.testing.assert_allclose(skipped[compared], full[compared], **TOLERANCE, err_msg=kind)
