"""The hidden-effect generator: NGSIM raw files that the real reader reads back exactly."""

from __future__ import annotations

import jax
import numpy as np
import pandas as pd
import pytest

from bayesdrive.criticism.generator import EFFECTS, simulate_traffic, write_ngsim_raw
from bayesdrive.data.readers import read

SMALL = {"num_platoons": 1, "followers": 3, "duration_s": 40.0, "cut_ins": 2}


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    path = tmp_path_factory.mktemp("gen") / "delay.csv"
    traffic, truth = simulate_traffic(
        jax.random.key(4), "reaction_delay", effect_range=(0.3, 0.5), **SMALL
    )
    write_ngsim_raw(traffic, path)
    return path, traffic, truth


def test_file_has_the_ngsim_columns_in_feet(written):
    path, traffic, _ = written
    table = pd.read_csv(path)
    assert list(table.columns) == [
        "Vehicle_ID",
        "Frame_ID",
        "Total_Frames",
        "Global_Time",
        "Local_X",
        "Local_Y",
        "v_Length",
        "v_Width",
        "v_Class",
        "v_Vel",
        "v_Acc",
        "Lane_ID",
        "Preceding",
        "Following",
        "Space_Headway",
        "Time_Headway",
    ]
    first = table[table["Vehicle_ID"] == table["Vehicle_ID"].iloc[0]]
    np.testing.assert_allclose(first["v_Vel"].to_numpy() * 0.3048, traffic.v[0], atol=1e-5)


def test_reader_gets_back_the_simulated_trajectories(written):
    """Positions, speeds and bumper gaps through the real reader: within 1e-5 m (float64 CSV)."""
    path, traffic, truth = written
    traj = read(path, format="ngsim_raw")
    assert traj.flags.empty and truth.collisions == 0
    ids = [f"{path.stem}:{vid}" for vid in 100 + np.arange(len(traffic.length))]
    for row, vid in enumerate(ids):
        rows = traj.vehicle(vid)
        np.testing.assert_allclose(rows["x"], traffic.x[row], atol=1e-5)
        np.testing.assert_allclose(rows["v"], traffic.v[row], atol=1e-5)
        leaders = traffic.leader[row]
        has = leaders >= 0
        assert (rows["leader_id"].notna().to_numpy() == has).all()
        lead = np.maximum(leaders, 0)
        expected_gap = traffic.x[lead, np.arange(len(lead))] - traffic.length[lead] - traffic.x[row]
        np.testing.assert_allclose(rows["gap"].to_numpy()[has], expected_gap[has], atol=1e-5)


def test_cut_ins_change_lane_and_leader(written):
    """Each cut-in vehicle drives in lane 2, then enters lane 1 in front of its target, whose
    leader switches to it at that moment (a cut-in that never finds its gap stays in lane 2)."""
    _, traffic, truth = written
    cutters = np.flatnonzero((traffic.lane[:, 0] == 2) & (traffic.lane[:, -1] == 1))
    assert len(cutters) == truth.cut_ins >= 1
    for c in cutters:
        entry = np.argmax(traffic.lane[c] == 1)
        assert entry > 0 and (traffic.lane[c, entry:] == 1).all()
        target = np.flatnonzero((traffic.leader == c).any(axis=1))
        assert len(target) == 1
        assert traffic.leader[target[0], entry] == c and traffic.leader[target[0], entry - 1] != c


def test_effect_sizes_are_drawn_per_driver_within_the_range(written):
    _, _, truth = written
    parameter, _ = EFFECTS["reaction_delay"]
    sizes = truth.params[parameter].to_numpy()
    assert ((sizes >= 0.3) & (sizes <= 0.5)).all()
    assert len(np.unique(sizes)) == len(sizes)


def test_same_key_same_file_other_key_other_file(tmp_path, written):
    path, _, _ = written
    again, _ = simulate_traffic(
        jax.random.key(4), "reaction_delay", effect_range=(0.3, 0.5), **SMALL
    )
    write_ngsim_raw(again, tmp_path / "again.csv")
    assert (tmp_path / "again.csv").read_bytes() == path.read_bytes()
    other, _ = simulate_traffic(
        jax.random.key(5), "reaction_delay", effect_range=(0.3, 0.5), **SMALL
    )
    assert not np.allclose(other.x, again.x)


def test_unknown_cause_is_refused():
    with pytest.raises(KeyError, match="reaction_delay"):
        simulate_traffic(jax.random.key(0), "fog")
