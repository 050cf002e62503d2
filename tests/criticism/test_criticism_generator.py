"""The independent hidden-effect generator (trafficgen): its IDM, its mechanisms, its NGSIM files
read back through bayesdrive's reader, and its independence from bayesdrive."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bayesdrive.data.readers import read
from bayesdrive.drivers.extensions import CAUSES, NO_CAUSE
from trafficgen import MECHANISMS, NULL, generate, right_verdicts, simulate, write_ngsim_raw
from trafficgen.ngsim import COLUMNS
from trafficgen.simulate import _idm

SMALL = {"platoons": 1, "followers": 3, "duration_s": 30.0, "cut_ins": 6}


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    path = tmp_path_factory.mktemp("gen") / "plain.csv"
    return path, generate(4, path, None, **SMALL)


def test_idm_rule_from_the_equations():
    """Known values: free road a (1 - (v/v0)^4); zero at the equilibrium gap; the approach term."""
    v0, s0, time_gap, a, b = 30.0, 2.0, 1.5, 1.0, 2.0
    free = _idm(10.0, 50.0, 0.0, v0, s0, time_gap, a, b, has_leader=False)
    assert free == pytest.approx(1.0 - (10 / 30) ** 4)
    equilibrium = (s0 + 10.0 * time_gap) / np.sqrt(1.0 - (10 / 30) ** 4)
    assert _idm(10.0, equilibrium, 0.0, v0, s0, time_gap, a, b, True) == pytest.approx(
        0.0, abs=1e-12
    )
    # closing at 2 m/s on a 20 m gap: s* = 2 + 15 + 10 * 2 / (2 sqrt(2)) = 24.0711
    expected = 1.0 - (10 / 30) ** 4 - ((2 + 15 + 20 / (2 * np.sqrt(2))) / 20.0) ** 2
    assert _idm(10.0, 20.0, 2.0, v0, s0, time_gap, a, b, True) == pytest.approx(expected)


def test_file_columns_and_reader_round_trip(plain):
    """Positions, speeds and bumper gaps through the real reader within 1e-5 m (6 decimals in
    feet); no flags, no collisions, cut-ins change lane once and become their target's leader."""
    path, rec = plain
    assert tuple(pd.read_csv(path, nrows=1).columns) == COLUMNS
    traj = read(path, format="ngsim_raw")
    assert traj.flags.empty and rec.collisions == 0 and rec.cut_ins >= 1
    for row, vid in enumerate(rec.vehicle_id):
        rows = traj.vehicle(f"plain:{vid}")
        np.testing.assert_allclose(rows["x"], rec.true_x[row], atol=1e-5)
        np.testing.assert_allclose(rows["v"], rec.true_v[row], atol=1e-5)
        has = rec.leader[row] >= 0
        assert (rows["leader_id"].notna().to_numpy() == has).all()
        lead = np.maximum(rec.leader[row], 0)
        gap = rec.true_x[lead, np.arange(len(lead))] - rec.length[lead] - rec.true_x[row]
        np.testing.assert_allclose(rows["gap"].to_numpy()[has], gap[has], atol=1e-5)
    for c in np.flatnonzero((rec.lane[:, 0] == 2) & (rec.lane[:, -1] == 1)):
        entry = np.argmax(rec.lane[c] == 1)
        target = np.flatnonzero((rec.leader == c).any(axis=1))
        assert len(target) == 1 and rec.leader[target[0], entry] == c
        assert rec.leader[target[0], entry - 1] != c


def test_sub_steps_make_speeds_and_positions_consistent(plain):
    """Speeds never negative; each 0.1 s position increment is the integral of a speed that moves
    between the sample's end speeds (sub-steps), so it differs from their trapezoid by at most half
    the speed change times dt (plus 0.2 mm where the speed turns round inside the sample), and it
    is not exactly the trapezoid (the one-step map a fitted model uses) wherever the acceleration
    changes inside a sample."""
    _, rec = plain
    assert (rec.true_v >= 0).all()
    dx = np.diff(rec.true_x, axis=1)
    dv = np.abs(np.diff(rec.true_v, axis=1))
    departure = np.abs(dx - 0.5 * (rec.true_v[:, 1:] + rec.true_v[:, :-1]) * rec.dt)
    assert (departure <= 0.5 * dv * rec.dt + 2e-4).all()
    assert np.median(departure[rec.follower]) > 1e-7


def test_video_noise_speeds_are_differences_of_the_noisy_positions(tmp_path):
    mechanism = {"video_position_noise": (0.02, 0.03)}
    rec = simulate(5, mechanism, **SMALL)
    central = (rec.x[:, 2:] - rec.x[:, :-2]) / (2 * rec.dt)
    np.testing.assert_allclose(rec.v[:, 1:-1], np.maximum(central, 0.0))
    errors = rec.x - rec.true_x
    drawn = rec.params["video_position_noise.position_noise_m"]
    # ~300 samples per vehicle: the sample sd is within 15% of the drawn sd (4 standard errors).
    np.testing.assert_allclose(errors.std(axis=1), drawn, rtol=0.15)
    traj = read(write_ngsim_raw(rec, tmp_path / "video.csv"), format="ngsim_raw")
    first = traj.vehicle(f"video:{rec.vehicle_id[1]}")
    np.testing.assert_allclose(first["v"], rec.v[1], atol=1e-5)


def test_position_smoothing_averages_the_recorded_positions_and_leaves_the_drivers(tmp_path):
    """The recording's smoothing: the same traffic as without it; every vehicle (a camera sees all)
    draws its width; inside the record each position is the exponentially weighted mean of the
    true ones within five widths (summed here term by term); speeds are differences of the
    smoothed positions; the recorded jerk falls well below the unsmoothed record's."""
    base = simulate(7, None, **SMALL)
    rec = simulate(7, {"position_smoothing": (0.2, 0.4)}, **SMALL)
    np.testing.assert_array_equal(rec.true_x, base.true_x)
    width = rec.params["position_smoothing.smoothing_width_s"]
    assert ((width >= 0.2) & (width <= 0.4)).all()
    for row in (0, 2):
        reach = int(np.ceil(5 * width[row] / rec.dt))
        for t in (reach, 150, rec.x.shape[1] - 1 - reach):
            terms = [
                (np.exp(-abs(k) * rec.dt / width[row]), rec.true_x[row, t + k])
                for k in range(-reach, reach + 1)
            ]
            mean = sum(w * x for w, x in terms) / sum(w for w, _ in terms)
            assert rec.x[row, t] == pytest.approx(mean, abs=1e-9)
    central = (rec.x[:, 2:] - rec.x[:, :-2]) / (2 * rec.dt)
    np.testing.assert_allclose(rec.v[:, 1:-1], np.maximum(central, 0.0))
    jerk = np.diff(rec.a[rec.follower], axis=1).std()
    assert jerk < 0.5 * np.diff(base.a[base.follower], axis=1).std()
    # At the ends too: no false braking or acceleration where the average runs out of record.
    assert np.abs(rec.a[rec.follower]).max() < 1.5 * np.abs(base.a[base.follower]).max()
    traj = read(write_ngsim_raw(rec, tmp_path / "smoothed.csv"), format="ngsim_raw")
    np.testing.assert_allclose(
        traj.vehicle(f"smoothed:{rec.vehicle_id[1]}")["v"], rec.v[1], atol=1e-5
    )


def test_mechanism_sizes_per_driver_and_streams_apart():
    """Each follower draws its own size in the range; heads and cut-ins none; adding a mechanism
    leaves the head vehicles' trajectories unchanged (their own random stream)."""
    base = simulate(6, None, **SMALL)
    rec = simulate(6, {"perception_delay": (0.3, 0.5)}, **SMALL)
    sizes = rec.params["perception_delay.delay_s"]
    assert np.isnan(sizes[~rec.follower]).all()
    inside = sizes[rec.follower]
    assert ((inside >= 0.3) & (inside <= 0.5)).all() and len(np.unique(inside)) == len(inside)
    heads = rec.vehicle_id % 100 == 0
    np.testing.assert_array_equal(rec.true_x[heads], base.true_x[heads])
    assert not np.allclose(rec.true_x[rec.follower], base.true_x[rec.follower])


def _whole_record_pairs(rec):
    """(follower, leader) row pairs of the followers that keep one leader for the whole record."""
    for i in np.flatnonzero(rec.follower):
        lead = rec.leader[i]
        if (lead == lead[0]).all() and lead[0] >= 0:
            yield i, lead[0]


def test_perception_delay_lags_the_response():
    """Followers' accelerations respond to their leader's later with a delay than without one:
    the lag of the peak cross-correlation grows (negative control: no mechanism)."""

    def response_lag(rec):
        acc = np.gradient(rec.true_v, rec.dt, axis=1)
        lags = []
        for i, lead in _whole_record_pairs(rec):
            own, ahead = acc[i] - acc[i].mean(), acc[lead] - acc[lead].mean()
            corr = [np.dot(own[k:], ahead[: len(ahead) - k]) for k in range(30)]
            lags.append(int(np.argmax(corr)))
        return np.mean(lags)

    scenario = {"platoons": 2, "followers": 4, "duration_s": 40.0, "cut_ins": 0}
    plain_lag = response_lag(simulate(7, None, **scenario))
    delayed_lag = response_lag(simulate(7, {"perception_delay": (0.6, 0.8)}, **scenario))
    assert delayed_lag > plain_lag + 2  # steps of 0.1 s


def test_leader_acceleration_response_follows_the_leader_sooner():
    """Followers that add a share of their leader's (smoothed) acceleration accelerate with it
    within a step: the correlation of a follower's acceleration with its leader's one sample
    earlier, averaged over whole-record leaders, rises by more than 0.1 with gains of 0.7-0.8
    (seed 7; negative control: the same traffic without the mechanism, whose IDM answers the
    leader only through the gap and closing speed, later). No collision either way."""

    def lag1_correlation(rec):
        acc = np.gradient(rec.true_v, rec.dt, axis=1)
        pairs = _whole_record_pairs(rec)
        return np.mean([np.corrcoef(acc[i, 1:], acc[lead, :-1])[0, 1] for i, lead in pairs])

    scenario = {"platoons": 2, "followers": 4, "duration_s": 40.0, "cut_ins": 0}
    plain = simulate(7, None, **scenario)
    responding = simulate(7, {"leader_acceleration_response": (0.7, 0.8)}, **scenario)
    smoothing = responding.params["leader_acceleration_response.smoothing_s"][responding.follower]
    assert ((smoothing >= 0.2) & (smoothing <= 0.5)).all()
    assert plain.collisions == responding.collisions == 0
    assert lag1_correlation(responding) > lag1_correlation(plain) + 0.1


def test_same_seed_same_file_other_seed_other_traffic(tmp_path, plain):
    path, rec = plain
    generate(4, tmp_path / "plain.csv", None, **SMALL)
    assert (tmp_path / "plain.csv").read_bytes() == path.read_bytes()
    assert not np.allclose(simulate(5, None, **SMALL).true_x, rec.true_x)


def test_bad_arguments_are_refused():
    with pytest.raises(KeyError, match="perception_delay"):
        simulate(0, {"fog": (0.1, 0.2)})
    with pytest.raises(ValueError, match="pedal_noise"):
        simulate(0, {"pedal_noise": (0.5, 0.1)})
    with pytest.raises(ValueError, match="cut_ins"):
        simulate(0, None, followers=1, cut_ins=3)


def test_verdict_table_names_bayesdrive_causes():
    """Every right verdict is a cause criticize can name; every extension has a mechanism."""
    named = {v for m in MECHANISMS.values() for v in m.verdicts}
    assert named <= set(CAUSES)
    assert named == set(CAUSES)
    assert right_verdicts(()) == (NULL,) == (NO_CAUSE,)
    assert right_verdicts(("perception_delay", "pedal_noise")) == (
        "reaction_delay",
        "autocorrelated_noise",
    )


def test_generator_imports_nothing_from_bayesdrive():
    code = (
        "import sys, trafficgen; trafficgen.simulate(1, {'pedal_noise': (0.2, 0.3)}, "
        "platoons=1, followers=1, duration_s=2.0, cut_ins=0); "
        "sys.exit(any(m.split('.')[0] in ('bayesdrive', 'jax') for m in sys.modules))"
    )
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
