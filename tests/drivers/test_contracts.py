"""Engines, extensions and the simulator read what a driver model declares (its observation, scene,
noise sd and desired speed), never its name, a function's identity or a parameter's name: a model
that spells its parameters differently, or reads its inputs through another function, is handled
by what it declares."""

from __future__ import annotations

from types import SimpleNamespace
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import xarray as xr
from jax import Array

from bayesdrive.data.errors import DataError
from bayesdrive.drivers.base import EgoState, car_following_at
from bayesdrive.drivers.execution_noise import execution_noise_model
from bayesdrive.drivers.extensions import EXTENSIONS, compose
from bayesdrive.drivers.extensions.autocorrelated_noise import NoiseMemoryInputs, NoiseMemoryState
from bayesdrive.drivers.extensions.inputs import inputs_at as extended_inputs_at
from bayesdrive.drivers.idm import IDM, idm_acceleration
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.likelihood import StepInputs, check_model
from bayesdrive.inference.core.output import set_metadata
from bayesdrive.inference.engines import pmmh
from bayesdrive.simulation.evaluation import _posterior_policy
from bayesdrive.simulation.generate import desired_speed_name
from bayesdrive.simulation.posterior import posterior_predictive
from tests.compiled import step_logpdfs


class RenamedParams(NamedTuple):
    """The IDM's parameters under other names: desired speed v0, execution-noise sd eta."""

    v0: Array
    d_min: Array
    tau: Array
    a_max: Array
    b_pref: Array
    eta: Array


def _renamed_mean(params, state, inputs):
    idm = IDM.params_type(params.v0, params.d_min, params.tau, params.a_max, params.b_pref, 0.0)
    return idm_acceleration(idm, state.v, inputs.gap, inputs.lead_v, inputs.has_leader)


RENAMED_SPECS = (
    IDM.specs[0]._replace(name="v0"),
    *IDM.specs[1:5],
    IDM.specs[5]._replace(name="eta"),
)
RENAMED = execution_noise_model("renamed_idm", RenamedParams, RENAMED_SPECS, _renamed_mean)
VALUES = (24.0, 2.5, 1.2, 1.4, 2.0, 0.35)


def test_the_declarations_name_the_renamed_parameters():
    assert (RENAMED.execution_noise_param, RENAMED.desired_speed_param) == ("eta", "v0")
    assert desired_speed_name(RENAMED) == "v0"
    with pytest.raises(ValueError, match="marks no desired-speed parameter"):
        desired_speed_name(
            IDM._replace(specs=tuple(s._replace(desired_speed=False) for s in IDM.specs))
        )


def steps() -> StepInputs:
    """Six steps of one vehicle, behind a leader (arbitrary numbers: both models score the same)."""
    v = jnp.asarray([10.0, 10.3, 10.1, 9.8, 9.9, 10.2])
    next_v = jnp.concatenate([v[1:], jnp.asarray([10.0])])
    dx = 0.5 * (v + next_v) * 0.1 + jnp.asarray([0.002, -0.001, 0.0, 0.003, -0.002, 0.001])
    ones = jnp.ones_like(v)
    series = SimpleNamespace(
        gap=jnp.asarray([20.0, 19.8, 19.9, 20.2, 20.0, 19.7]),
        lead_v=jnp.full_like(v, 10.0),
        has_leader=ones,
        dt=jnp.full_like(v, 0.1),
    )
    inputs = jax.vmap(lambda j: car_following_at(series, j, 0))(jnp.arange(6))
    return StepInputs(v=v, next_v=next_v, dx=dx, mask=ones, inputs=inputs)


def renamed_and_idm(cause: str):
    """``cause`` over the renamed model and over the IDM, with the same parameter values."""
    renamed, idm = EXTENSIONS[cause](RENAMED).model, EXTENSIONS[cause](IDM).model
    extra = [s.default + 0.1 * (s.upper - s.lower) for s in idm.specs[len(IDM.specs) :]]
    values = tuple(map(jnp.asarray, (*VALUES, *extra)))
    return renamed, renamed.params_type(*values), idm, idm.params_type(*values)


def test_speed_dependent_noise_scales_the_declared_noise_sd():
    renamed, ours, idm, theirs = renamed_and_idm("speed_dependent_noise")
    state = EgoState(jnp.zeros(()), jnp.asarray(12.0))
    slope = float(theirs.noise_speed_slope)
    expected = 0.35 * (1 + 12.0 * slope) / (1 + 10.0 * slope)
    assert float(renamed.noise_sd(ours, state)) == pytest.approx(expected)
    data = steps()
    np.testing.assert_allclose(
        step_logpdfs(renamed, ours, data), step_logpdfs(idm, theirs, data), rtol=1e-6
    )


def test_autocorrelated_noise_scales_the_declared_noise_sd():
    renamed, ours, idm, theirs = renamed_and_idm("autocorrelated_noise")
    data = steps()
    now = jax.tree.map(lambda leaf: leaf[1], data.inputs)
    before = jax.tree.map(lambda leaf: leaf[0], data.inputs)
    inputs = NoiseMemoryInputs(now, before, data.v[0], data.dx[0], before, data.v[0], data.dx[0])
    state = NoiseMemoryState(
        jnp.zeros(()), data.v[1], jnp.asarray(0.1), jnp.asarray(-0.05), jnp.asarray(2.0)
    )
    following = EgoState(data.dx[1], data.next_v[1])
    got = renamed.transition_logpdf(ours, state, following, inputs)
    want = idm.transition_logpdf(theirs, state, following, inputs)
    assert np.isfinite(float(got)) and float(got) == pytest.approx(float(want), rel=1e-6)


@pytest.mark.parametrize("cause", ["measurement_noise", "video_noise"])
def test_observation_models_filter_with_the_declared_noise_sd(cause):
    renamed, ours, idm, theirs = renamed_and_idm(cause)
    assert renamed.observation == idm.observation == cause
    data = steps()
    got = np.asarray(renamed.filter(ours, data))
    np.testing.assert_allclose(got, np.asarray(idm.filter(theirs, data)), rtol=1e-6)
    assert np.all(np.isfinite(got))


# --- scene: the Cooperative IDM and everything built on it need merge scenes ---


def result_of(model_name: str) -> xr.DataTree:
    tree = xr.DataTree()
    set_metadata(tree, model=model_name)
    return tree


def test_a_noise_extension_of_the_cidm_keeps_its_declared_scene():
    assert get_model("cidm+autocorrelated_noise").scene == "merge"
    assert get_model("cidm+measurement_noise").scene == "merge"
    assert get_model("idm+autocorrelated_noise").scene is None


def test_followers_behind_a_replayed_leader_refuse_a_model_that_needs_a_scene():
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="reads the merge scene"):
        posterior_predictive(
            key, result_of("cidm+autocorrelated_noise"), [10.0, 10.0], dt=0.1, gap=20.0
        )
    # Negative control: the same extension of the IDM passes the check (and then misses the
    # posterior's parameter list, which this bare result lacks).
    with pytest.raises(KeyError, match="params"):
        posterior_predictive(
            key, result_of("idm+autocorrelated_noise"), [10.0, 10.0], dt=0.1, gap=20.0
        )


def test_evaluation_refuses_platoons_for_a_model_that_needs_merge_scenes():
    platoons = SimpleNamespace(kind="platoon")
    name = "cidm+autocorrelated_noise"
    with pytest.raises(DataError, match="needs merge scenes, not platoon scenes"):
        _posterior_policy(result_of(name), name, None, platoons, None)


def test_extensions_read_the_declared_scene_not_the_inputs_function():
    def own_inputs_at(series, j, history):  # the same inputs, through another function
        return extended_inputs_at(series, j, history).car_following

    reading_otherwise = IDM._replace(name="idm_own_inputs", inputs_at=own_inputs_at)
    assert compose(reading_otherwise, ("reaction_delay",)).scene is None
    declaring_a_scene = IDM._replace(name="idm_merge", scene="merge")
    with pytest.raises(ValueError, match="reads more, the merge scene"):
        compose(declaring_a_scene, ("reaction_delay",))


# --- observation: exactly, or through an observation model ---


def test_engines_read_the_declared_observation():
    observed_otherwise = IDM._replace(name="idm_observed", observation="some_observation_model")
    with pytest.raises(NotImplementedError, match="observed with noise"):
        check_model(observed_otherwise, "smc")
    pmmh.check_model(observed_otherwise)
    check_model(IDM, "smc")
    with pytest.raises(ValueError, match="observes them exactly"):
        pmmh.check_model(IDM)
