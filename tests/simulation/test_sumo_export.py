"""SUMO export: a follower of an exported type, driven by SUMO's own IDM behind a leader that
replays a recorded NGSIM speed profile, moves as bayesdrive's deterministic IDM rollout does.

Set-up: a straight 5 km single-lane road (hand-written plain XML, built by SUMO's netconvert;
speed limit 50 m/s, above every v_des involved), step length 0.1 s (the data's), positions
integrated by ``--step-method.ballistic`` (bayesdrive's trapezoid rule). The leader is vehicle
115 of the chain ``115_124_136_140_146_162`` replaying its recorded speeds through TraCI
(libsumo) ``setSpeed`` with all speed checks off (speed mode 0); the follower is vehicle 124
at its recorded initial gap and speed, of the exported type of vehicle 124 in the committed
``models/ngsim_i80_chains_idm_smc.nc`` (posterior medians). Cars are 4.5 m long (the data README's
assumption for NGSIM); ``minGap`` = d_min (SUMO's IDM adds minGap back to the gap, so both see the
bumper gap); ``stepping`` = 0.1 s, i.e. one IDM Euler step per simulation step, as bayesdrive; SUMO
``sigma`` 0 and ``speedFactor`` 1; bayesdrive's rollout runs with execution noise sigma = 0.

Tolerance: 5 mm in position and 1 mm/s in speed over 25 s. Both integrate the same difference
equation; what remains is bayesdrive's float32 rollout (positions of up to ~250 m: one rounding is
~1.5e-5 m, 250 steps at most ~4e-3 m; measured 4e-5 m and 1.3e-5 m/s). The structural choices
are far outside it, measured on this scene: SUMO's default semi-implicit Euler position update
differs by 0.36 m and 0.037 m/s; ``stepping`` 0.025 s (4 sub-steps holding the leader's speed)
by 0.071 m and 0.025 m/s. Negative control: the same type with accel and decel swapped (a wrong
mapping) must miss the tolerance.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
import numpy as np
import pandas as pd
import pytest

from bayesdrive.drivers.idm import IDM, IDMParams
from bayesdrive.inference.core.output import load_result
from bayesdrive.simulation.rollout import broadcast_params, platoon_scene, rollout
from bayesdrive.simulation.sumo import (
    follow_in_sumo,
    per_vehicle_drivers,
    straight_road,
    sumo_home,
    vtype_distribution,
    write_vtype_distribution,
)

REPO = Path(__file__).resolve().parents[2]
MODEL = REPO / "models" / "ngsim_i80_chains_idm_smc.nc"
CHAIN = "115_124_136_140_146_162.csv"
LENGTH_M = 4.5
DT_S = 0.1
POSITION_TOL_M = 5e-3
SPEED_TOL_MPS = 1e-3


def _sumo_home() -> Path:
    try:
        return sumo_home()
    except RuntimeError as error:
        if os.environ.get("CI"):
            pytest.fail(str(error))
        pytest.skip(str(error))


def _sumo_follower(folder, home, net, vtypes, vtype_id, lead_v, lead_offset, v0):
    """SUMO's follower positions (from its start) and speeds, one per 0.1 s step."""
    followed = follow_in_sumo(
        home,
        net,
        vtypes,
        vtype_id,
        lead_v,
        gap=lead_offset - LENGTH_M,
        v0=v0,
        dt=DT_S,
        leader_length=LENGTH_M,
        folder=folder,
    )
    return followed.x, followed.v


@pytest.mark.realdata
def test_an_exported_type_follows_a_recorded_leader_in_sumo_as_bayesdrives_idm_does(
    data_dir, tmp_path
):
    sumo_home = _sumo_home()
    chain = pd.read_csv(Path(data_dir) / "ngsim_i80_chains" / CHAIN)
    assert (chain.ID1.iloc[0], chain.ID2.iloc[0]) == (115, 124)
    lead_v = chain.v1.to_numpy()
    lead_offset = chain.Y1.iloc[0] - chain.Y2.iloc[0]  # front to front
    v0 = chain.v2.iloc[0]

    tree = load_result(MODEL)
    vtypes = tmp_path / "vtypes.xml"
    xml = vtype_distribution(
        per_vehicle_drivers(tree), distribution_id="ngsim", stepping=DT_S, header="test"
    )
    write_vtype_distribution(vtypes, xml)
    net = straight_road(tmp_path, sumo_home, 5000.0)
    sumo_x, sumo_v = _sumo_follower(
        tmp_path, sumo_home, net, vtypes, "ngsim_vehicle_124", lead_v, lead_offset, v0
    )

    # bayesdrive's side, from the posterior itself rather than from the exported file.
    posterior = tree["posterior"].to_dataset().sel(vehicle="124")
    medians = {name: float(np.median(posterior[name].values)) for name in posterior.data_vars}
    params = broadcast_params(IDMParams(**{**medians, "sigma": 0.0}), 1, 1)
    scene = platoon_scene(
        lead_v, np.array([-lead_offset]), np.array([v0]), length=LENGTH_M, dt=DT_S
    )
    ours = rollout(jax.random.key(0), IDM, params, scene, num_rollouts=1)
    our_x = np.asarray(ours.x[0, 0]) + lead_offset
    our_v = np.asarray(ours.v[0, 0])

    # The scene exercises the model: the follower changes speed by several m/s.
    assert np.ptp(sumo_v) > 3.0
    assert np.max(np.abs(sumo_x - our_x)) < POSITION_TOL_M
    assert np.max(np.abs(sumo_v - our_v)) < SPEED_TOL_MPS

    # Negative control: a wrong mapping (accel and decel swapped) misses the tolerance.
    vtype = next(e for e in xml.getroot().iter("vType") if e.get("id") == "ngsim_vehicle_124")
    accel, decel = vtype.get("accel"), vtype.get("decel")
    vtype.set("accel", decel)
    vtype.set("decel", accel)
    write_vtype_distribution(vtypes, xml)
    wrong_x, _ = _sumo_follower(
        tmp_path, sumo_home, net, vtypes, "ngsim_vehicle_124", lead_v, lead_offset, v0
    )
    assert np.max(np.abs(wrong_x - our_x)) > 10 * POSITION_TOL_M
