"""The flat API (``import bayesdrive as bd``): lazy names, DataFrames in and out, simulation.

Fitting through ``bd.fit`` runs in tests/test_readme.py (the README's Python tour); here the
pieces around it are checked against what they must equal: the file reader, the posterior draws
themselves, and the IDM's closed-form equilibrium.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pandas as pd
import pytest

import bayesdrive as bd
from bayesdrive.data.errors import DataError
from bayesdrive.data.readers.columns import read_columns
from bayesdrive.data.views import follower_arrays
from bayesdrive.inference.core.output import build_tree

ROOT = Path(__file__).resolve().parents[1]
CHAIN = "1_11_24_44_55_54.csv"
PAIR_COLUMNS = {
    "t": "t1",
    "leader_id": "ID1",
    "x_leader": "Y1",
    "v_leader": "v1",
    "follower_id": "ID2",
    "x_follower": "Y2",
    "v_follower": "v2",
}


def test_import_is_cheap_and_every_name_resolves():
    probe = "import sys, bayesdrive; print('jax' in sys.modules, 'pandas' in sys.modules)"
    done = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.stdout.split() == ["False", "False"]
    for name in bd.API:
        assert getattr(bd, name) is not None
        assert name in dir(bd)
    assert set(bd.models) >= {"idm", "cidm"} and bd.get_model("idm").name == "idm"
    with pytest.raises(AttributeError, match="no attribute 'fitt'"):
        bd.fitt  # noqa: B018


@pytest.mark.realdata
def test_a_dataframe_reads_as_the_same_csv_does(data_dir):
    path = data_dir / "ngsim_i80_chains" / CHAIN
    # No mode given: a map naming x_follower is read as pairs.
    from_file = read_columns(path, PAIR_COLUMNS, units="m")
    from_frame = bd.from_dataframe(pd.read_csv(path), PAIR_COLUMNS, units="m")
    assert from_frame.vehicle_ids == from_file.vehicle_ids == ["1", "11"]
    pd.testing.assert_frame_equal(from_frame.tracks, from_file.tracks)
    assert from_frame.source == "dataframe" and from_frame.dt == from_file.dt


@pytest.mark.realdata
def test_load_takes_a_held_out_name_as_bayesdrive_fit_does(holdout_dir, caplog):
    name = "openacc_casale"
    with caplog.at_level("WARNING", logger="bayesdrive.data.registry"):
        traj = bd.load(name, data_dir=holdout_dir)
    assert traj.source == name and traj.vehicle_ids
    assert "held out for evaluation only" in caplog.text and "never choose or tune" in caplog.text
    # The criticism chooses a model, which a held-out set must never decide: still refused.
    with pytest.raises(DataError, match="held out for evaluation only"):
        bd.criticize(name, seed=1, data_dir=holdout_dir)


@pytest.mark.realdata
def test_a_bad_dataframe_value_is_named_by_frame_row_and_column(data_dir):
    frame = pd.read_csv(data_dir / "ngsim_i80_chains" / CHAIN)
    frame["Y2"] = frame["Y2"].astype(object)
    frame.loc[3, "Y2"] = "n/a"
    with pytest.raises(DataError, match=r"mine, row 3, column 'Y2': not a number: 'n/a'"):
        bd.from_dataframe(frame, PAIR_COLUMNS, units="m", name="mine")
    with pytest.raises(DataError, match="mode 'vehicles' or 'pairs'"):
        bd.from_dataframe(frame, PAIR_COLUMNS, units="m", mode="wide")
    with pytest.raises(DataError, match=r"unknown DataFrame option\(s\) \['patterns'\]"):
        bd.from_dataframe(frame, PAIR_COLUMNS, units="m", patterns=("*.csv",))


# Two followers with different safe time headways; every other IDM parameter fixed.
TAU = {"11": 1.5, "24": 2.5}
FIXED = {"v_des": 30.0, "d_min": 2.0, "a_max": 3.0, "b_pref": 2.0, "sigma": 0.02}


def _posterior(data_dir, num_draws: int = 40):
    """A result tree as `fit` writes it, with known draws: tau spread around TAU per vehicle."""
    traj = bd.load(data_dir / "ngsim_i80_chains" / CHAIN)
    arrays = follower_arrays(traj, window="fit", vehicle_ids=list(TAU))
    rng = np.random.default_rng(7)
    tau = np.stack([rng.normal(TAU[v], 0.05, num_draws) for v in arrays.vehicle_ids], axis=-1)
    return build_tree(
        posterior={"tau": tau[None]},
        sample_stats={},
        log_likelihood=np.zeros((1, num_draws, *arrays.mask.shape)),
        arrays=arrays,
        metadata={
            "engine": "test",
            "model": "idm",
            "params": ["tau"],
            "fixed": FIXED,
            "seed": 0,
            "data_source": traj.source,
            "window": "fit",
            "num_particles": num_draws,
            "flagged_samples": 0,
        },
    )


@pytest.mark.realdata
def test_summary_is_one_row_per_vehicle_and_parameter_with_units(data_dir):
    tree = _posterior(data_dir)
    table = bd.summary(tree)
    assert list(table.index) == [("11", "tau"), ("24", "tau")]
    assert list(table.columns) == ["unit", "mean", "sd", "q05", "q95"]
    assert set(table["unit"]) == {"s"}
    draws = tree["posterior"]["tau"]
    for vehicle in TAU:
        values = draws.sel(vehicle=vehicle).values.ravel()
        row = table.loc[(vehicle, "tau")]
        assert row["mean"] == pytest.approx(values.mean())
        assert row["q95"] == pytest.approx(np.quantile(values, 0.95))


@pytest.mark.realdata
def test_followers_keep_their_own_equilibrium_gap_behind_a_steady_leader(data_dir):
    """Started at the IDM's equilibrium gap (d_min + v tau) / sqrt(1 - (v / v_des)^4) behind a
    leader at a constant 10 m/s, each follower stays there (noise sd 0.02 m/s^2: tolerance
    0.5 m after 30 s, over 64 rollouts, seed fixed); the follower with the longer headway sits
    10 m further back, so each follower drew its own vehicle's posterior (negative control:
    swapping the vehicles' order puts each 10 m off its gap)."""
    tree = _posterior(data_dir)
    speed = 10.0
    root = np.sqrt(1 - (speed / FIXED["v_des"]) ** 4)
    equilibrium = {v: (FIXED["d_min"] + speed * tau) / root for v, tau in TAU.items()}
    leader = np.full(301, speed)

    def final_gaps(order):
        sim = bd.posterior_predictive(
            jax.random.key(3),
            tree,
            leader,
            dt=0.1,
            gap=[equilibrium[v] for v in TAU],
            speed=speed,
            vehicles=order,
            num_rollouts=64,
        )
        assert sim["gap"].dims == ("rollout", "vehicle", "time")
        assert sim["time"].values[-1] == pytest.approx(30.0)
        assert not sim["collision"].any()
        return sim["gap"].isel(time=-1).mean("rollout").values

    same = final_gaps(list(TAU))
    assert same == pytest.approx([equilibrium[v] for v in TAU], abs=0.5)
    swapped = final_gaps(list(TAU)[::-1])
    assert np.all(np.abs(swapped - [equilibrium[v] for v in TAU]) > 5.0)


@pytest.mark.realdata
def test_posterior_predictive_refuses_what_it_cannot_simulate(data_dir):
    tree = _posterior(data_dir)
    with pytest.raises(KeyError, match=r"no posterior draws for vehicle\(s\) \['99'\]"):
        bd.posterior_predictive(
            jax.random.key(0), tree, [10.0, 10.0], dt=0.1, gap=5.0, vehicles=["99"]
        )
    with pytest.raises(ValueError, match="bumper gap must be positive"):
        bd.posterior_predictive(jax.random.key(0), tree, [10.0, 10.0], dt=0.1, gap=0.0)
