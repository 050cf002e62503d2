"""The video-noise model's Kalman filter against an exact oracle, and what it recovers from data
made by the independent generator.

Oracle: on LINEAR car-following (``tests/inference/test_latent.py``: Gaussian execution and position noise,
a rule linear in gap and speed) the extended Kalman filter is exact, so its log-likelihood must
equal the numpy float64 Kalman filter on absolute positions of that file, started as the model
says (speed sd ``INITIAL_SPEED_SD`` around the recorded one). Tolerance ``ORACLE_TOL`` nats covers
float32 arithmetic over 50 steps; the negative control (the oracle started from the exact recorded
speed, as the latent engine's particles are) misses by more.

Generator: ``trafficgen`` (its own sub-stepped IDM, no bayesdrive code) writes an NGSIM file with
video-style noise (white noise on positions, speeds and gaps differenced from them); seed 480001,
size "large" (3-10 cm), 2 followers, 40 s. At the generator's own parameters, the log-likelihood's
maximum over a grid of ``sigma_obs`` must lie within ``PROFILE_TOL`` (relative) of the true noise
sd, and over ``sigma`` within the same of the true execution noise. Negative control: the
exact-state IDM, which reads the differenced speeds as true, puts its ``sigma`` maximum at more
than twice the truth (the noise absorbed as acceleration noise).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_latent import (
    LINEAR,
    NUM_STEPS,
    TRUTH,
    follower_arrays_of,
    kalman_loglik,
    simulate_linear,
)

from bayesdrive.data.readers import read
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import get_model
from bayesdrive.drivers.video_noise import INITIAL_SPEED_SD, with_video_noise
from bayesdrive.inference.core.likelihood import step_inputs
from tests.compiled import step_logpdfs
from trafficgen import generate
from trafficgen.mechanisms import MECHANISMS

VIDEO_LINEAR = with_video_noise(LINEAR)
ORACLE_TOL = 0.05
GENERATOR_SEED = 480001
PROFILE_TOL = 0.25
GRID = np.exp(np.linspace(np.log(0.2), np.log(5.0), 41))  # multiples of the truth


@pytest.fixture(scope="module")
def linear_series():
    return simulate_linear(NUM_STEPS)


def video_loglik(model, series, mask) -> float:
    steps = jax.tree.map(lambda a: a[0], step_inputs(follower_arrays_of(series, mask), model))
    params = model.params_type(*(jnp.asarray(TRUTH[name]) for name in model.param_names))
    logp = step_logpdfs(model, params, steps)
    return float(jnp.sum(jnp.where(steps.mask > 0, logp, 0.0)))


@pytest.mark.parametrize("holes", [False, True])
def test_filter_matches_the_kalman_oracle(linear_series, holes):
    mask = np.ones(NUM_STEPS)
    if holes:
        mask[[12, 30, 31]] = 0.0  # a segment ends at each hole and restarts after it
        mask[-6:] = 0.0  # trailing padding
    exact = kalman_loglik(linear_series, mask, initial_speed_sd=INITIAL_SPEED_SD)
    assert video_loglik(VIDEO_LINEAR, linear_series, mask) == pytest.approx(exact, abs=ORACLE_TOL)
    # Negative control: starting from the recorded speed exactly is another likelihood.
    exact_start = kalman_loglik(linear_series, mask)
    assert abs(exact_start - exact) > 10 * ORACLE_TOL


def test_registry_names_and_refusals():
    model = get_model("video_noise+idm")
    assert model is with_video_noise(IDM)
    assert model.name == "idm+video_noise"
    assert model.param_names == (*IDM.param_names, "sigma_obs")
    for name, words in [
        ("idm+measurement_noise+video_noise", "both 'observation' extensions"),
        ("idm+autocorrelated_noise+video_noise", "video_noise does not compose"),
        ("idm+video_noise+video_noise", "named twice"),
    ]:
        with pytest.raises(KeyError, match=words):
            get_model(name)


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / "video.csv"
    recording = generate(
        GENERATOR_SEED,
        path,
        {"video_position_noise": MECHANISMS["video_position_noise"].sizes["large"]},
        platoons=1,
        followers=2,
        duration_s=40.0,
        cut_ins=0,
    )
    return recording, follower_arrays(read(path, format="ngsim_raw"), window="all")


# trafficgen's names of the IDM's parameters
GENERATOR_NAMES = {"v_des": "v0", "d_min": "s0", "tau": "T", "a_max": "a", "b_pref": "b"}
GENERATOR_NAMES |= {"sigma": "sigma", "sigma_obs": "video_position_noise.position_noise_m"}


def profile_argmax(model, arrays, truth: dict[str, float], name: str) -> float:
    """The grid value of ``name`` (other parameters at ``truth``) with the highest likelihood."""
    steps = step_inputs(arrays, model)

    def total(value):
        params = model.params_type(
            *(jnp.asarray(value if n == name else truth[n]) for n in model.param_names)
        )
        logp = jax.vmap(lambda s: step_logpdfs(model, params, s))(steps)
        return jnp.sum(jnp.where(steps.mask > 0, logp, 0.0))

    values = truth[name] * GRID
    return float(values[int(jnp.argmax(jax.vmap(total)(jnp.asarray(values))))])


def test_generator_noise_and_execution_noise_are_recovered(generated):
    recording, arrays = generated
    model = with_video_noise(IDM)
    rows = {str(v): i for i, v in enumerate(recording.vehicle_id) if recording.follower[i]}
    checked = 0
    for index, vehicle in enumerate(arrays.vehicle_ids):
        row = rows.get(str(vehicle).split(":")[-1])
        if row is None:
            continue
        one = arrays.subset([index])
        truth = {n: float(recording.params[GENERATOR_NAMES[n]][row]) for n in model.param_names}
        for name in ("sigma_obs", "sigma"):
            best = profile_argmax(model, one, truth, name)
            assert abs(best / truth[name] - 1) < PROFILE_TOL, (vehicle, name, best, truth[name])
        # Negative control: the exact-state IDM takes the differenced speeds as true.
        exact_best = profile_argmax(IDM, one, truth, "sigma")
        assert exact_best > 2 * truth["sigma"], (vehicle, exact_best, truth["sigma"])
        checked += 1
    assert checked == 2
