"""The shared result layout: build, metadata, summary, ArviZ use, atomic save and round trip."""

from __future__ import annotations

import json

import arviz
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import xarray as xr

from bayesdrive.data.views import SPLIT_RULE
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.fit import ENGINES, fit, summary
from bayesdrive.inference.output import (
    REQUIRED_METADATA,
    build_tree,
    load_result,
    metadata,
    save_result,
)
from bayesdrive.inference.synthetic import simulate_following
from bayesdrive.reports.filter_plots import write_filter_plots

# The shapes and settings of test_inference_smc's recovery fits, so a session compiles once.
PARAMS = ("v_des", "sigma")
PARTICLES = 400
VEHICLES = 20
STEPS = 100


@pytest.fixture(scope="module")
def arrays():
    params = IDM.params_type(*(jnp.full(VEHICLES, s.default) for s in IDM.specs))
    return simulate_following(jax.random.key(21), IDM, params, num_steps=STEPS)


@pytest.fixture(scope="module")
def tree(arrays):
    return fit(
        jax.random.key(5),
        arrays,
        engine="smc",
        params=PARAMS,
        num_particles=PARTICLES,
        fixed={"tau": 1.0, "b_pref": 2.0},
        seed=5,
    )


def test_tree_has_the_shared_layout(tree, arrays):
    assert set(tree.children) == {"posterior", "sample_stats", "log_likelihood", "observed_data"}
    for name in PARAMS:
        assert tree["posterior"][name].dims == ("chain", "draw", "vehicle")
        assert tree["posterior"][name].shape == (1, PARTICLES, VEHICLES)
    assert tree["log_likelihood"]["dx"].dims == ("chain", "draw", "vehicle", "step")
    assert tree["log_likelihood"]["dx"].shape == (1, 200, VEHICLES, STEPS)
    # The scored draws are named by their posterior draw indices.
    assert set(tree["log_likelihood"]["draw"].values) <= set(tree["posterior"]["draw"].values)
    assert tree["sample_stats"]["ess"].dims == ("vehicle", "step")
    assert tree["sample_stats"]["log_evidence"].dims == ("vehicle",)
    np.testing.assert_array_equal(tree["observed_data"]["dx"].values, arrays.dx)
    assert list(tree["posterior"]["vehicle"].values) == list(arrays.vehicle_ids)


def test_metadata_is_complete_and_decodes(tree):
    meta = metadata(tree)
    for key in (*REQUIRED_METADATA, "split_rule", "versions", "created_at", "wall_time_s"):
        assert key in meta, key
    assert meta["params"] == list(PARAMS)
    assert meta["fixed"] == {"d_min": 2.0, "tau": 1.0, "a_max": 3.0, "b_pref": 2.0}
    assert meta["seed"] == 5
    assert meta["split_rule"] == SPLIT_RULE
    assert meta["flagged_samples"] is None  # arrays given directly: the count is unknown
    assert set(meta["versions"]) >= {"bayesdrive", "jax", "numpyro", "arviz"}
    # Raw attributes are netCDF-safe: strings and numbers only.
    assert all(isinstance(v, str | int | float) for v in tree.attrs.values())


def test_summary_reports_each_vehicle_and_parameter(tree):
    result = summary(tree)
    json.dumps(result)  # summary.json must serialise as it is
    assert result["engine"] == "smc" and result["params"] == list(PARAMS)
    assert result["wall_time_s"] > 0 and result["compile_time_s"] >= 0
    first = result["vehicles"]["sim0"]["sigma"]
    draws = tree["posterior"]["sigma"].values[0, :, 0]
    assert first["mean"] == pytest.approx(draws.mean())
    assert first["q05"] < first["mean"] < first["q95"]
    assert (
        set(result["log_evidence"]) == set(result["vehicles"]) == set(tree.posterior.vehicle.values)
    )


def test_arviz_loo_reads_the_log_likelihood_group(tree):
    loo = arviz.loo(tree)
    assert np.isfinite(loo.elpd)
    assert loo.n_data_points == VEHICLES * STEPS


def test_build_tree_refuses_bad_shapes_and_missing_metadata(tree, arrays):
    good = {
        "posterior": {"v_des": np.zeros((1, 4, VEHICLES))},
        "sample_stats": {},
        "log_likelihood": np.zeros((1, 4, VEHICLES, STEPS)),
        "arrays": arrays,
        "metadata": {k: 0 for k in REQUIRED_METADATA} | {"params": ["v_des"]},
    }
    assert isinstance(build_tree(**good), xr.DataTree)
    with pytest.raises(ValueError, match="posterior 'v_des' has shape"):
        build_tree(**(good | {"posterior": {"v_des": np.zeros((1, 4, 2))}}))
    with pytest.raises(ValueError, match="log_likelihood has shape"):
        build_tree(**(good | {"log_likelihood": np.zeros((1, 4, VEHICLES, 63))}))
    with pytest.raises(ValueError, match=r"lacks \['seed'\]"):
        meta = dict(good["metadata"])
        del meta["seed"]
        build_tree(**(good | {"metadata": meta}))


def test_unknown_engine_and_conflicting_parameters_are_refused(arrays):
    with pytest.raises(ValueError, match="unknown engine 'mcmc'"):
        fit(jax.random.key(0), arrays, engine="mcmc")
    with pytest.raises(ValueError, match=r"\['sigma'\] are both inferred and fixed"):
        fit(jax.random.key(0), arrays, params=PARAMS, fixed={"sigma": 0.3})
    with pytest.raises(ValueError, match="no parameter"):
        fit(jax.random.key(0), arrays, params=("v_max",))
    assert {"smc", "pf"} <= set(ENGINES)


def test_a_crash_mid_write_leaves_no_file(tree, tmp_path, monkeypatch):
    target = tmp_path / "result.nc"
    target.write_bytes(b"the previous result")

    def half_write(self, path, **kwargs):
        path.write_bytes(b"\x89HDF half a file")
        raise RuntimeError("disk full")

    monkeypatch.setattr(xr.DataTree, "to_netcdf", half_write)
    with pytest.raises(RuntimeError, match="disk full"):
        save_result(tree, target)
    assert target.read_bytes() == b"the previous result"  # the old file is untouched
    assert [p.name for p in tmp_path.iterdir()] == ["result.nc"]  # no temporary left behind
    with pytest.raises(RuntimeError):
        save_result(tree, tmp_path / "new.nc")
    assert not (tmp_path / "new.nc").exists()


def test_round_trip_through_netcdf(tree, tmp_path):
    pytest.importorskip("h5py", reason="h5netcdf needs h5py to read or write netCDF4 files")
    path = save_result(tree, tmp_path / "result.nc")
    for opened in (xr.open_datatree(path, engine="h5netcdf"), arviz.from_netcdf(path)):
        for group in ("posterior", "sample_stats", "log_likelihood", "observed_data"):
            xr.testing.assert_identical(opened[group].to_dataset(), tree[group].to_dataset())
        assert dict(opened.attrs) == dict(tree.attrs)
    assert metadata(load_result(path)) == metadata(tree)


def test_filter_plots_are_written(tree, tmp_path):
    paths = write_filter_plots(tree, tmp_path)
    assert [p.name for p in paths] == ["ess.png", "unique_particles.png", "convergence.png"]
    for path in paths:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert path.stat().st_size > 10_000  # a drawn figure, not an empty canvas
