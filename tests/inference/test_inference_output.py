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
from bayesdrive.inference.core.output import (
    REQUIRED_METADATA,
    build_tree,
    load_result,
    metadata,
    save_result,
)
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following
from bayesdrive.inference.fit import ENGINES, fit, summary
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


def fit_smc(arrays, **options):
    return fit(
        jax.random.key(5),
        arrays,
        engine="smc",
        params=PARAMS,
        num_particles=PARTICLES,
        fixed={"tau": 1.0, "b_pref": 2.0},
        seed=5,
        sequential=True,  # the per-step statistics are part of the layout checked here
        **options,
    )


@pytest.fixture(scope="module")
def tree(arrays):
    return fit_smc(arrays)


def test_tree_has_the_shared_layout(tree, arrays):
    assert set(tree.children) == {"posterior", "sample_stats", "log_likelihood", "observed_data"}
    for name in PARAMS:
        assert tree["posterior"][name].dims == ("chain", "draw", "vehicle")
        assert tree["posterior"][name].shape == (1, PARTICLES, VEHICLES)
        assert tree["posterior"][name].attrs["units"] == IDM.spec(name).unit
        assert tree["posterior"][name].attrs["long_name"] == IDM.spec(name).doc
    for group in ("posterior", "sample_stats"):
        assert tree[group].attrs["inference_library"] == "bayesdrive"
    assert tree["sample_stats"]["particle_ess"].dims == ("vehicle", "step")
    assert "ess" not in tree["sample_stats"]  # ArviZ's name, not the filters' statistic
    assert tree["sample_stats"]["log_evidence"].dims == ("vehicle",)
    np.testing.assert_array_equal(tree["observed_data"]["dx"].values, arrays.dx)
    assert list(tree["posterior"]["vehicle"].values) == list(arrays.vehicle_ids)


def _small_tree(arrays, scores, posterior, **options):
    """A two-vehicle tree of ``arrays``' first two rows with holes in their masks (the layout
    under test, no engine): vehicle a usable on steps 0-29, vehicle b on every step but 40."""
    mask = np.ones((2, STEPS))
    mask[0, 30:] = 0
    mask[1, 40] = 0
    small = arrays._replace(
        vehicle_ids=("a", "b"),
        mask=mask,
        **{n: getattr(arrays, n)[:2] for n in ("v", "next_v", "dx", "gap", "lead_v", "t")},
        has_leader=arrays.has_leader[:2],
    )
    meta = {k: 0 for k in REQUIRED_METADATA} | {"params": list(posterior)}
    built = build_tree(
        posterior=posterior,
        sample_stats={},
        log_likelihood=scores,
        arrays=small,
        metadata=meta,
        **options,
    )
    return small, built


def test_log_likelihood_holds_the_steps_with_a_full_history_and_every_draw(arrays):
    """Steps without a full history (1.5 s at dt = 0.1 s plus two steps: 17 usable steps before
    them) are left out for every model, as masked steps are (not scored as 0), and every
    posterior draw is scored: the obs coordinates name each kept (vehicle, step), and its value
    is the padded score there."""
    assert float(arrays.dt) == pytest.approx(0.1)
    scores = np.random.default_rng(3).normal(size=(2, 5, 2, STEPS))
    small, built = _small_tree(arrays, scores, {"v_des": np.zeros((2, 5, 2))})
    log_lik = built["log_likelihood"]["dx"]
    assert log_lik.dims == ("chain", "draw", "obs") and log_lik.dtype == np.float32
    # Counted by hand: a scores 17-29; b scores 17-39, and 58-99 after its hole at step 40.
    steps_a, steps_b = list(range(17, 30)), [*range(17, 40), *range(58, STEPS)]
    assert log_lik.shape == (2, 5, len(steps_a) + len(steps_b))
    assert list(log_lik["vehicle"].values) == ["a"] * len(steps_a) + ["b"] * len(steps_b)
    assert list(log_lik["step"].values) == steps_a + steps_b
    rows = [0] * len(steps_a) + [1] * len(steps_b)
    np.testing.assert_array_equal(log_lik["t"].values, small.t[rows, steps_a + steps_b])
    np.testing.assert_allclose(log_lik.values, scores[:, :, rows, steps_a + steps_b], rtol=1e-6)
    assert metadata(built)["num_draws"] == 10 and metadata(built)["num_chains"] == 2


def test_psis_loo_metadata_names_copied_draws_and_constant_observations(arrays):
    """Distinct draws with varying scores are reliable; copies among draws that are not Markov
    chains, and an observation scored the same under every draw, are named (seed 4)."""
    rng = np.random.default_rng(4)
    scores = rng.normal(size=(1, 50, 2, STEPS))
    distinct = {"v_des": rng.uniform(20.0, 30.0, size=(1, 50, 2))}
    assert metadata(_small_tree(arrays, scores, distinct)[1])["psis_loo"] == {
        "reliable": True,
        "problems": [],
    }

    copied = {"v_des": distinct["v_des"].copy()}
    copied["v_des"][0, 25:, 1] = copied["v_des"][0, :25, 1]  # vehicle b: 25 draws, each twice
    verdict = metadata(_small_tree(arrays, scores, copied)[1])["psis_loo"]
    assert not verdict["reliable"] and "criticize" in verdict["instead"]
    (problem,) = verdict["problems"]
    assert "1 vehicle(s) hold copies" in problem and "fewest distinct: 25, vehicle b" in problem
    # The same repeats in a Markov chain are rejections, which PSIS's relative efficiency handles.
    markov = _small_tree(arrays, scores, copied, markov_chains=True)[1]
    assert metadata(markov)["psis_loo"]["reliable"]

    flat = scores.copy()
    flat[:, :, 1, 20:23] = -1.5  # three observations of vehicle b, the same under every draw
    verdict = metadata(_small_tree(arrays, flat, distinct)[1])["psis_loo"]
    assert verdict["problems"] == [
        "3 observation(s) score the same under every draw (vehicles b): PSIS cannot fit their "
        "tail and arviz.loo raises"
    ]


def test_a_fit_without_pointwise_scores_has_the_same_draws_and_no_log_likelihood(
    tree, arrays, tmp_path
):
    slim = fit_smc(arrays, pointwise=False)
    assert "log_likelihood" in tree.children  # the default keeps the group
    assert "log_likelihood" not in slim.children
    for name in PARAMS:
        np.testing.assert_array_equal(
            slim["posterior"][name].values, tree["posterior"][name].values
        )
    psis = metadata(slim)["psis_loo"]
    assert not psis["reliable"] and "pointwise=False" in psis["problems"][0]
    save_result(slim, tmp_path / "slim.nc")
    assert "log_likelihood" not in load_result(tmp_path / "slim.nc").children


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


def test_arviz_loo_reads_the_log_likelihood_group(tree, arrays):
    loo = arviz.loo(tree, pointwise=True)
    assert np.isfinite(loo.elpd)
    # The usable steps with 17 usable steps before them (1.5 s at 0.1 s, plus two).
    mask = np.asarray(arrays.mask) > 0
    scored = sum(mask[n, j - 17 : j + 1].all() for n, j in np.argwhere(mask) if j >= 17)
    assert loo.n_data_points == scored
    assert np.isfinite(loo.pareto_k.values).all()


def test_build_tree_refuses_bad_shapes_and_missing_metadata(tree, arrays):
    good = {
        "posterior": {"v_des": np.zeros((1, 4, VEHICLES))},
        "sample_stats": {},
        "log_likelihood": np.zeros((1, 4, VEHICLES, STEPS)),
        "specs": IDM.specs,
        "arrays": arrays,
        "metadata": {k: 0 for k in REQUIRED_METADATA} | {"params": ["v_des"]},
    }
    assert isinstance(build_tree(**good), xr.DataTree)
    with pytest.raises(ValueError, match="posterior 'v_des' has shape"):
        build_tree(**(good | {"posterior": {"v_des": np.zeros((1, 4, 2))}}))
    with pytest.raises(ValueError, match="log_likelihood has shape"):
        build_tree(**(good | {"log_likelihood": np.zeros((1, 4, VEHICLES, 63))}))
    with pytest.raises(ValueError, match="every posterior draw"):  # a thinned set is refused
        build_tree(**(good | {"log_likelihood": np.zeros((1, 2, VEHICLES, STEPS))}))
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
    with pytest.raises(ValueError, match="'smc' is sized by its particles"):
        fit(jax.random.key(0), arrays, draws=100)
    with pytest.raises(ValueError, match="'lm' has no chains option"):
        fit(jax.random.key(0), arrays, engine="lm", chains=4)
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


def test_results_of_the_older_layout_are_converted_on_loading(tree, tmp_path, caplog):
    """Before: log_likelihood padded to (vehicle, step) with zeros, thinned draws, ``ess``."""
    pytest.importorskip("h5py", reason="h5netcdf needs h5py to read or write netCDF4 files")
    scored = tree["log_likelihood"]["dx"]
    rows = [
        list(tree["observed_data"]["vehicle"].values).index(v) for v in scored["vehicle"].values
    ]
    draws = np.arange(0, PARTICLES, 4)
    padded = np.zeros((1, len(draws), VEHICLES, STEPS))
    padded[:, :, rows, scored["step"].values] = scored.values[:, draws]
    old = tree.copy()
    old["log_likelihood"] = xr.DataTree(
        xr.Dataset(
            {"dx": (("chain", "draw", "vehicle", "step"), padded)},
            coords={"chain": [0], "draw": draws},
        )
    )
    old["sample_stats"] = xr.DataTree(
        tree["sample_stats"].to_dataset().rename({"particle_ess": "ess"})
    )
    path = save_result(old, tmp_path / "old.nc")
    with caplog.at_level("WARNING"):
        loaded = load_result(path)
    assert (
        "older result layout" in caplog.text and "scores 100 of the posterior's 400" in caplog.text
    )
    np.testing.assert_array_equal(
        loaded["log_likelihood"]["dx"].values, tree["log_likelihood"]["dx"].values[:, draws]
    )
    assert "particle_ess" in loaded["sample_stats"] and "ess" not in loaded["sample_stats"]
    assert np.isfinite(arviz.loo(loaded).elpd)

    # Flat on every usable step, as saved before only steps with a full history were kept.
    mask = tree["observed_data"]["mask"].values > 0
    vehicle, step = np.nonzero(mask)
    every = padded[:, :, vehicle, step].astype(np.float32)
    every[:, :, step < 17] = np.nan  # steps without a full history: left out when converted
    flat = old.copy()
    flat["log_likelihood"] = xr.DataTree(
        xr.Dataset(
            {"dx": (("chain", "draw", "obs"), every)},
            coords={
                "chain": [0],
                "draw": draws,
                "vehicle": ("obs", tree["observed_data"]["vehicle"].values[vehicle]),
                "step": ("obs", step),
            },
        )
    )
    caplog.clear()
    with caplog.at_level("WARNING"):
        loaded = load_result(save_result(flat, tmp_path / "flat.nc"))
    assert f"cut to the {scored.sizes['obs']} of its {len(step)} steps" in caplog.text
    np.testing.assert_array_equal(
        loaded["log_likelihood"]["dx"].values, tree["log_likelihood"]["dx"].values[:, draws]
    )

    # A slim posterior-only file (the committed model cards) loads as it was written.
    slim = save_result(
        xr.DataTree.from_dict({"posterior": tree["posterior"].to_dataset()}), tmp_path / "slim.nc"
    )
    assert list(load_result(slim).children) == ["posterior"]


def test_filter_plots_are_written(tree, tmp_path):
    paths = write_filter_plots(tree, tmp_path)
    assert [p.name for p in paths] == ["ess.png", "unique_particles.png", "convergence.png"]
    for path in paths:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert path.stat().st_size > 10_000  # a drawn figure, not an empty canvas
