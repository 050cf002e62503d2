"""Scene generation: preset draws, steady starts, the desired-speed sweep and the CLI."""

import json

import jax
import numpy as np
import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.cli.simulate_cmd import PRESET_DIR
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.idm import equilibrium_gap as idm_equilibrium_gap
from bayesdrive.simulation.generate import (
    Preset,
    draw_preset,
    equilibrium_gap,
    generate_scenes,
    load_preset,
    pair_sweep,
)


def test_preset_draws_follow_the_truncated_normals():
    # seed 0, 200 x 50 draws: mean within 3 standard errors; a 1-sd-wide normal at mean 1 keeps
    # only positive values after truncation.
    preset = Preset("t", "idm", "", {"v_des": 20.0, "sigma": 1.0}, {"v_des": 2.0, "sigma": 1.0})
    params = draw_preset(jax.random.key(0), IDM, preset, 200, 50)
    v_des = np.asarray(params.v_des)
    assert v_des.shape == (200, 50)
    assert abs(v_des.mean() - 20.0) < 3 * 2.0 / np.sqrt(v_des.size)
    assert np.asarray(params.sigma).min() > 0
    # parameters the preset does not name stay at the model's defaults
    assert np.all(np.asarray(params.tau) == float(IDM.defaults().tau))
    assert np.asarray(params.tau).shape == (200, 50)


def test_noise_free_followers_start_in_equilibrium():
    # sigma ~ 0: every follower starts at the IDM equilibrium gap for the common speed, so its
    # first-step acceleration is zero (to float32 rounding); the free-road first car accelerates.
    defaults = IDM.defaults()._replace(sigma=1e-6)
    params = jax.tree.map(lambda leaf: np.full((1, 4), float(leaf), np.float32), defaults)
    result = generate_scenes(jax.random.key(1), IDM, params, num_steps=10, dt=0.1)
    first_step_change = np.diff(np.asarray(result.v)[0, :, :2], axis=1)[:, 0]
    assert first_step_change[0] > 0.05  # 3 m/s^2 x (1 - 0.8^4) x 0.1 s = 0.18 m/s
    np.testing.assert_allclose(first_step_change[1:], 0.0, atol=1e-4)
    assert not np.asarray(result.collision).any()


def test_the_searched_equilibrium_gap_is_the_idms_closed_form():
    # The generator bisects on the model's rule; the IDM's closed form checks it (v 24, 10, 0).
    params = jax.tree.map(lambda leaf: np.full(3, float(leaf), np.float32), IDM.defaults())
    for v in (24.0, 10.0, 0.0):
        searched = np.asarray(equilibrium_gap(IDM, params, np.float32(v), 0.1))
        np.testing.assert_allclose(searched, idm_equilibrium_gap(params, v), rtol=1e-5)


def test_slower_desired_speed_opens_the_gap():
    base = IDM.defaults()._replace(sigma=0.05)
    sweep = pair_sweep(
        jax.random.key(2), IDM, base, np.array([-6.0, 0.0, 6.0]), duration_s=40.0, dt=0.1
    )
    final_gap = np.asarray(sweep.gap)[:, 1, -1]
    assert final_gap[0] > final_gap[1] > 0
    assert final_gap[2] > 0
    # a faster follower ends near the leader's speed, not its own desired speed
    assert np.asarray(sweep.v)[2, 1, -50:].mean() < float(base.v_des) + 3.0


def test_paper_presets_load_as_printed():
    congested = load_preset(PRESET_DIR / "paper_congested.json")
    freeflow = load_preset(PRESET_DIR / "paper_freeflow.json")
    assert congested.means["b_pref"] == 9.0 and freeflow.means["tau"] == 5.0
    assert set(congested.means) == set(IDM.param_names)


@pytest.mark.parametrize("preset", ["paper_congested"])
def test_simulate_command_writes_scenes_figures_and_summary(tmp_path, preset):
    runner = CliRunner()
    args = ["simulate", preset, "--vehicles", "4", "--duration", "5", "--scenes", "3"]
    first = runner.invoke(app, [*args, "--seed", "3", "--out", str(tmp_path / "a"), "--json", "-"])
    assert first.exit_code == 0, first.output
    summary = json.loads(first.stdout)
    assert summary["seed"] == 3 and summary["vehicles"] == 4 and summary["scenes"] == 3
    for name in summary["files"]:
        assert (tmp_path / "a" / name).stat().st_size > 0
    again = runner.invoke(app, [*args, "--seed", "3", "--out", str(tmp_path / "b"), "--json", "-"])
    assert json.loads(again.stdout)["speed_mps"] == summary["speed_mps"]

    missing = runner.invoke(app, ["simulate", "no_such", "--seed", "1", "--out", str(tmp_path)])
    assert missing.exit_code == 2 and "paper_congested" in missing.output
