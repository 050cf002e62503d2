"""The Optimal Velocity Model pinned against Bando et al.'s dimensionless optimal velocity by hand,
its scene generation against the inverse of that function, and its parameters recovered by smc from
OVM followers of the independent generator (``trafficgen.ovm``), with a negative control."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.ovm import OVM
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.engines import smc
from bayesdrive.simulation.generate import equilibrium_gap
from trafficgen.ovm import ovm_platoon

DT = 0.1
# v_max = 2 and s_c = 1 are Bando et al.'s dimensionless units: V(b) = tanh(b - 2) + tanh 2.
BANDO = OVM.params_type(kappa=1.0, v_max=2.0, s_c=1.0, sigma=0.3)
TANH_1, TANH_2 = 0.7615941559557649, 0.9640275800758169
ACC_TOL = 1e-5


def acceleration(v, gap, has_leader=1.0, params=BANDO):
    inputs = CarFollowingInputs(*(jnp.asarray(x) for x in (gap, 0.0, has_leader, DT)))
    return float(OVM.mean_acceleration(params, EgoState(jnp.asarray(0.0), jnp.asarray(v)), inputs))


def test_the_optimal_velocity_is_bandos_function_in_its_own_units():
    # V(2) = tanh 0 + tanh 2; V(3) = tanh 1 + tanh 2; kappa scales the relaxation.
    assert acceleration(0.5, 2.0) == pytest.approx(TANH_2 - 0.5, abs=ACC_TOL)
    assert acceleration(0.5, 3.0) == pytest.approx(TANH_1 + TANH_2 - 0.5, abs=ACC_TOL)
    assert acceleration(0.0, 0.0) == pytest.approx(0.0, abs=ACC_TOL)  # V(0) = 0
    doubled = BANDO._replace(kappa=2.0)
    assert acceleration(0.5, 3.0, params=doubled) == pytest.approx(
        2 * (TANH_1 + TANH_2 - 0.5), abs=ACC_TOL
    )


def test_free_road_relaxes_to_the_limit_of_the_optimal_velocity():
    # V(infinity) = 1 + tanh 2; the gap, NaN without a leader, is not read.
    assert acceleration(0.5, float("nan"), has_leader=0.0) == pytest.approx(
        1.0 + TANH_2 - 0.5, abs=ACC_TOL
    )


def test_ovm_is_registered_with_its_declarations():
    assert get_model("ovm") is OVM
    assert (OVM.desired_speed_param, OVM.execution_noise_param) == ("v_max", "sigma")
    assert OVM.scene is None and OVM.observed_exactly


def test_scene_generation_starts_platoons_at_the_ovm_equilibrium_gap():
    # V(s) = v solved by hand in Bando's units: v = tanh 2 at b = 2; in metres, x s_c = 7.5 m.
    params = jax.tree.map(lambda x: jnp.full(3, x), BANDO._replace(s_c=7.5, sigma=0.0))
    gaps = np.asarray(equilibrium_gap(OVM, params, jnp.asarray(TANH_2), DT))
    np.testing.assert_allclose(gaps, 15.0, atol=1e-3)


# --- recovery: OVM followers of the independent generator (sub-stepped, its own code) ---

TRUTH = {"kappa": 0.8, "v_max": 24.0, "s_c": 8.0, "sigma": 0.2}
# The generator integrates ten sub-steps per sample and the model is the one-step Euler map, which
# shrinks the fitted kappa by about kappa dt / 2 (4%): medians within 5% of the truth.
RELATIVE_TOL = 0.05


def as_arrays(seed: int, inflection: float) -> FollowerArrays:
    """Two OVM followers of the truth behind one head, 50 s, as the one series representation."""
    platoon = ovm_platoon(
        seed, **{n: [v, v] for n, v in TRUTH.items()}, duration_s=50.0, inflection=inflection
    )
    x, v, length = platoon.x, platoon.v, platoon.length
    gap = x[:-1, :-1] - length[:-1, None] - x[1:, :-1]
    shape = gap.shape
    return FollowerArrays(
        vehicle_ids=("ovm1", "ovm2"),
        v=v[1:, :-1],
        next_v=v[1:, 1:],
        dx=np.diff(x[1:], axis=1),
        gap=gap,
        lead_v=v[:-1, :-1],
        has_leader=np.ones(shape),
        mask=np.ones(shape),
        t=np.broadcast_to(np.arange(shape[1]) * platoon.dt, shape).copy(),
        dt=platoon.dt,
    )


def fitted_medians(inflection: float) -> dict[str, np.ndarray]:
    # Seeds: generator 21, smc key 22; 400 particles as the Gipps recovery test.
    result = smc.run(
        jax.random.key(22), as_arrays(21, inflection), model=OVM, params=tuple(TRUTH),
        num_particles=400,
    )  # fmt: skip
    return {n: np.median(np.asarray(result.posterior[n][0]), axis=0) for n in TRUTH}


def test_smc_recovers_the_parameters_of_generated_ovm_followers():
    for name, median in fitted_medians(2.0).items():
        assert np.all(np.abs(median - TRUTH[name]) <= RELATIVE_TOL * TRUTH[name]), (name, median)


def test_recovery_fails_when_the_generator_uses_another_optimal_velocity():
    # Negative control: an inflection of 1.5 instead of Bando's 2 is another law; the fitted gap
    # scale then misses its truth by far more than the tolerance.
    median = fitted_medians(1.5)["s_c"]
    assert np.all(np.abs(median - TRUTH["s_c"]) > RELATIVE_TOL * TRUTH["s_c"]), median
