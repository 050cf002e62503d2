"""SUMO export without SUMO: which drivers are written, with which attributes, from which draws."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import jax
import numpy as np
import pytest
import xarray as xr
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.drivers.gipps import GIPPS
from bayesdrive.inference.core.output import load_result, set_metadata
from bayesdrive.simulation.sumo import (
    per_vehicle_drivers,
    population_drivers,
    vtype_distribution,
)

MODEL = Path(__file__).resolve().parents[2] / "models" / "ngsim_i80_chains_idm_smc.nc"
runner = CliRunner()


def _export(tmp_path: Path, *options: str) -> tuple[int, ET.Element | None, str]:
    out = tmp_path / "vtypes.xml"
    out.unlink(missing_ok=True)
    done = runner.invoke(
        app, ["export", "sumo", str(MODEL), "--out", str(out), "--stepping", "0.1", *options]
    )
    root = ET.parse(out).getroot() if out.exists() else None
    return done.exit_code, root, done.output


def test_one_type_per_vehicle_carries_its_posterior_medians_under_sumos_names(tmp_path):
    code, root, output = _export(tmp_path)
    assert code == 0
    # Execution noise has no SUMO carrier: one line says so, naming the parameter.
    assert "sigma (sd of Gaussian execution noise on the acceleration" in " ".join(output.split())
    posterior = load_result(MODEL)["posterior"].to_dataset()
    vtypes = {v.get("id"): v for v in root.iter("vType")}
    assert len(vtypes) == posterior.sizes["vehicle"]
    vehicle = str(posterior["vehicle"].values[7])
    vtype = vtypes[f"ngsim_i80_chains_idm_smc_vehicle_{vehicle}"]
    median = {n: float(np.median(posterior[n].sel(vehicle=vehicle))) for n in posterior.data_vars}
    expected = {
        "maxSpeed": median["v_des"],
        "desiredMaxSpeed": median["v_des"],
        "minGap": median["d_min"],
        "tau": median["tau"],
        "accel": median["a_max"],
        "decel": median["b_pref"],
        "delta": 4.0,
        "stepping": 0.1,
        "sigma": 0.0,
        "speedFactor": 1.0,
        "speedDev": 0.0,
    }
    for attribute, value in expected.items():
        np.testing.assert_allclose(float(vtype.get(attribute)), value, rtol=1e-6, err_msg=attribute)
    assert vtype.get("carFollowModel") == "IDM"
    params = {p.get("key"): p.get("value") for p in vtype.iter("param")}
    np.testing.assert_allclose(float(params["bayesdrive.sigma"]), median["sigma"], rtol=1e-6)


def test_posterior_draws_repeat_with_their_seed_and_change_with_another(tmp_path):
    def drawn(seed: str) -> list[dict]:
        code, root, _ = _export(tmp_path, "--draws", "5", "--seed", seed)
        assert code == 0
        return [dict(v.attrib) for v in root.iter("vType")]

    first = drawn("3")
    assert len(first) == 5
    assert first == drawn("3")
    assert first != drawn("4")


def test_bad_requests_exit_2_with_a_message_and_write_nothing(tmp_path):
    code, root, output = _export(tmp_path, "--draws", "5")
    assert (code, root) == (2, None) and "--seed" in output
    code, root, output = _export(tmp_path, "--population", "--draws", "5", "--seed", "1")
    assert (code, root) == (2, None) and "no population distribution" in output


def test_population_drivers_are_rows_of_the_population_new_driver_draws():
    tree = load_result(MODEL)
    params = ["v_des", "tau", "sigma"]  # a fit of these three; the others stay at their defaults
    rows = np.array([[20.0 + d, 1.0 + d / 10, 0.3] for d in range(8)]).reshape(2, 4, 3)
    stats = xr.Dataset(
        {"population_new_driver": (("chain", "draw", "param"), rows)},
        coords={"param": params},
    )
    tree["sample_stats"] = xr.DataTree(stats)
    drivers = population_drivers(jax.random.key(0), tree, 6)
    assert len(drivers) == 6
    flat = rows.reshape(-1, 3)
    for driver in drivers:
        drawn = [driver.params[name] for name in params]
        assert any(np.allclose(drawn, row) for row in flat), drawn
    assert drivers != population_drivers(jax.random.key(1), tree, 6)


@pytest.mark.parametrize(
    ("model", "named"),
    [
        ("idm+autocorrelated_noise", "noise_time_s has no SUMO carrier"),
        ("idm+reaction_delay", "reaction_time has no SUMO carrier"),
        ("idm+drifting_parameters", "tau_drift has no SUMO carrier"),
        ("idm+state_correction", "corr_speed has no SUMO carrier"),
    ],
)
def test_a_driver_parameter_sumo_cannot_carry_is_refused_by_name(model, named):
    tree = load_result(MODEL)
    set_metadata(tree, model=model)
    with pytest.raises(ValueError, match=named):
        per_vehicle_drivers(tree)


def test_a_gipps_driver_becomes_a_krauss_type_with_its_reaction_time_as_tau():
    # A Gipps fit of v_des, d_min and a_max (the IDM result's draws stand in for them); the
    # other Gipps parameters stay at the model's defaults, as in a fit that held them fixed.
    tree = load_result(MODEL)
    set_metadata(tree, model="gipps", params=["v_des", "d_min", "a_max"], fixed={})
    driver = per_vehicle_drivers(tree)[3]
    xml = vtype_distribution([driver], distribution_id="g", stepping=0.1, header="test")
    vtype = next(xml.getroot().iter("vType"))
    posterior = tree["posterior"].to_dataset()
    vehicle = str(posterior["vehicle"].values[3])
    median = {n: float(np.median(posterior[n].sel(vehicle=vehicle))) for n in posterior.data_vars}
    defaults = {spec.name: spec.default for spec in GIPPS.specs}
    expected = {
        "maxSpeed": median["v_des"],
        "desiredMaxSpeed": median["v_des"],
        "minGap": median["d_min"],
        "accel": median["a_max"],
        "decel": defaults["b_max"],
        "tau": 0.1,
        "sigma": 0.0,
    }
    assert vtype.get("carFollowModel") == "Krauss"
    for attribute, value in expected.items():
        np.testing.assert_allclose(float(vtype.get(attribute)), value, rtol=1e-6, err_msg=attribute)
    assert vtype.get("delta") is None and vtype.get("stepping") is None
    params = {
        p.get("key"): float(p.get("value"))
        for p in vtype.iter("param")
        if "source" not in p.get("key")
    }
    assert params == pytest.approx(
        {"bayesdrive.b_lead": defaults["b_lead"], "bayesdrive.sigma": defaults["sigma"]}
    )
