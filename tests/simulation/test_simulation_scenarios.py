"""Scenario selection: chains in held-out windows, by a fixed rule, on synthetic and real data."""

import numpy as np
import pandas as pd
import pytest

from bayesdrive.data import registry
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.validate import validate_tracks
from bayesdrive.data.views import split_time
from bayesdrive.simulation.scenarios import (
    heldout_episodes,
    merge_scenarios,
    platoon_scenarios,
    scenario_capacity,
    with_history,
)

DT = 0.1
LENGTH = 4.5


def chain_trajectories(
    spans: dict[str, tuple[float, float]], leaders: dict, flags=(), gap_offset: float = 0.0
) -> Trajectories:
    """Vehicles driving 10 m/s in one lane, 20 m apart front to front, present over ``spans``
    (start, end) seconds; ``leaders[v]`` is the leader id, or a function of t giving it. The
    measured gap column is the position gap plus ``gap_offset`` (drifted positions)."""
    rows = []
    for order, (vid, (start, end)) in enumerate(spans.items()):
        for t in np.round(np.arange(start, end, DT), 6):
            lead = leaders.get(vid)
            lead = lead(t) if callable(lead) else lead
            rows.append(
                {
                    "vehicle_id": vid,
                    "t": t,
                    "x": 10.0 * t - 20.0 * order,
                    "v": 10.0,
                    "a": 0.0,
                    "lane_id": 1,
                    "leader_id": lead,
                    "gap": 20.0 - LENGTH + gap_offset if lead is not None else np.nan,
                    "length": LENGTH,
                    "driver": "human",
                }
            )
    tracks = validate_tracks(pd.DataFrame(rows), source="synthetic", dt=DT)
    flag_rows = pd.DataFrame(
        [{"vehicle_id": v, "t": t, "kind": "test", "message": "flagged"} for v, t in flags],
        columns=["vehicle_id", "t", "kind", "message"],
    )
    return Trajectories(
        tracks=tracks,
        scenes=pd.DataFrame({"scene_id": "s", "vehicle_id": list(spans)}),
        dt=DT,
        format="synthetic",
        source="synthetic",
        flags=flag_rows,
    )


FOLLOWS = {"B": "A", "C": "B", "D": "C"}


def start_times(found) -> list[float]:
    return [round(s.t0, 6) for s in found.scenarios]


def test_non_overlapping_windows_from_the_start_of_the_held_out_window():
    # 300 samples each: the held-out window starts at sample 210 (t = 21.0 s); 2 s windows of
    # 20 steps start at 21, 23, 25, 27 (the next would need samples up to 31 s).
    traj = chain_trajectories(dict.fromkeys("ABCD", (0.0, 30.0)), FOLLOWS)
    found = platoon_scenarios(traj, vehicles_per_scenario=3, horizon_s=2.0)
    assert start_times(found) == [21.0, 23.0, 25.0, 27.0]
    assert all(s.vehicle_ids == ("A", "B", "C", "D") for s in found.scenarios)
    first = found.scenarios[0]
    assert first.x.shape == (4, 21) and first.gap.shape == (3, 21)
    np.testing.assert_allclose(first.x[0], 10.0 * (21.0 + DT * np.arange(21)))
    np.testing.assert_allclose(first.gap, 20.0 - LENGTH)
    assert found.num_vehicles == 12


def test_the_window_starts_where_the_latest_simulated_vehicle_is_held_out():
    # D appears at 5 s: 250 samples, held out from sample 175, i.e. t = 22.5 s.
    traj = chain_trajectories(
        {"A": (0.0, 30.0), "B": (0.0, 30.0), "C": (0.0, 30.0), "D": (5.0, 30.0)}, FOLLOWS
    )
    found = platoon_scenarios(traj, vehicles_per_scenario=3, horizon_s=2.0)
    assert start_times(found) == [22.5, 24.5, 26.5]
    for scenario in found.scenarios:
        for vid in scenario.simulated_ids:
            assert scenario.t0 >= split_time(traj.vehicle(vid)["t"].to_numpy())


def test_flagged_samples_and_broken_leader_links_end_windows():
    # C flagged at 24.0 s: the window [23, 25] is skipped; the next starts at 24.1 s.
    traj = chain_trajectories(dict.fromkeys("ABCD", (0.0, 30.0)), FOLLOWS, flags=[("C", 24.0)])
    found = platoon_scenarios(traj, vehicles_per_scenario=3, horizon_s=2.0)
    assert start_times(found) == [21.0, 24.1, 26.1]
    assert found.flagged_samples_skipped == 1

    # D loses its leader during [25.0, 25.5): no window of the chain may contain those samples.
    def d_leader(t):
        return None if 25.0 <= t < 25.5 else "C"

    traj = chain_trajectories(dict.fromkeys("ABCD", (0.0, 30.0)), {**FOLLOWS, "D": d_leader})
    found = platoon_scenarios(traj, vehicles_per_scenario=3, horizon_s=2.0)
    assert start_times(found) == [21.0, 25.5, 27.5]


def test_a_vehicle_is_simulated_in_at_most_one_scenario_at_a_time():
    # Two simulated vehicles per scenario: chains A-B-C and B-C-D share C, so only A-B-C (first
    # by vehicle ids) is taken at each start time; the head may be reused, C may not.
    traj = chain_trajectories(dict.fromkeys("ABCD", (0.0, 30.0)), FOLLOWS)
    found = platoon_scenarios(traj, vehicles_per_scenario=2, horizon_s=2.0)
    assert [s.vehicle_ids for s in found.scenarios] == [("A", "B", "C")] * 4
    assert scenario_capacity(traj, horizon_s=2.0, max_size=5) == [
        {"vehicles_per_scenario": 1, "scenarios": 12, "vehicles": 12},
        {"vehicles_per_scenario": 2, "scenarios": 4, "vehicles": 8},
        {"vehicles_per_scenario": 3, "scenarios": 4, "vehicles": 12},
    ]


def test_followers_are_re_anchored_to_the_measured_gap_at_the_start():
    # Positions put the cars 15.5 m apart bumper to bumper, the measured gap says 18.5 m: each
    # follower moves back 3 m more than the one ahead; speeds and the window are untouched.
    traj = chain_trajectories(dict.fromkeys("ABCD", (0.0, 30.0)), FOLLOWS, gap_offset=3.0)
    found = platoon_scenarios(traj, vehicles_per_scenario=3, horizon_s=2.0)
    first = found.scenarios[0]
    np.testing.assert_allclose(first.anchor_shift, [-3.0, -6.0, -9.0])
    np.testing.assert_allclose(first.x[:-1, 0] - first.x[1:, 0] - LENGTH, 18.5)
    np.testing.assert_allclose(first.x[1] - first.x[1, 0], 10.0 * DT * np.arange(21), atol=1e-9)
    assert found.summary()["anchor_shift_m"] == {"median": 6.0, "max": 9.0}


def test_with_history_takes_each_followers_steps_before_t0_and_drops_scenarios_without():
    """Hand-made chain at 10 m/s, 20 m front to front: a scenario's past holds its followers'
    last 17 steps (history_steps(0.1): 1.5 s and two more) before t0, with their speeds,
    increments, gaps and leader speeds; a follower with a flagged sample there leaves its scenario
    out (counted): the negative control."""
    traj = chain_trajectories(dict.fromkeys("ABC", (0.0, 30.0)), FOLLOWS)
    found = platoon_scenarios(traj, vehicles_per_scenario=2, horizon_s=2.0)
    kept, dropped = with_history(found, traj)
    assert dropped == 0 and len(kept.scenarios) == len(found.scenarios)
    past = kept.scenarios[0].past
    assert past.v.shape == (2, 17)
    np.testing.assert_allclose(past.v, 10.0)
    np.testing.assert_allclose(past.dx, 10.0 * DT, atol=1e-9)
    np.testing.assert_allclose(past.gap, 20.0 - LENGTH)
    np.testing.assert_allclose(past.lead_v, 10.0)

    # A flagged sample of C half a second before t0 breaks its history (not its window).
    t0 = found.scenarios[0].t0
    flagged = chain_trajectories(dict.fromkeys("ABC", (0.0, 30.0)), FOLLOWS, [("C", t0 - 0.5)])
    first_window = platoon_scenarios(flagged, vehicles_per_scenario=2, horizon_s=2.0).first(1)
    assert first_window.scenarios[0].t0 == pytest.approx(t0)
    kept, dropped = with_history(first_window, flagged)
    assert dropped == 1 and kept.scenarios == []


def test_a_horizon_off_the_sampling_grid_is_refused():
    traj = chain_trajectories(dict.fromkeys("AB", (0.0, 30.0)), FOLLOWS)
    with pytest.raises(DataError, match="not a positive multiple"):
        platoon_scenarios(traj, vehicles_per_scenario=1, horizon_s=0.25)


def check_real_platoons(traj: Trajectories, found) -> None:
    """Every scenario satisfies the definition, checked against the raw tracks."""
    simulated_at: dict[str, set[int]] = {}
    for scenario in found.scenarios:
        times = np.round(scenario.t0 + DT * np.arange(scenario.steps + 1), 6)
        for k, vid in enumerate(scenario.vehicle_ids):
            rows = traj.vehicle(vid)
            assert set(times) <= set(np.round(rows["t"], 6)), (scenario.scenario_id, vid)
            if k == 0:
                continue
            assert scenario.t0 >= split_time(rows["t"].to_numpy()) - 1e-9
            at = rows.set_index(np.round(rows["t"], 6)).loc[times]
            assert (at["leader_id"] == scenario.vehicle_ids[k - 1]).all()
            np.testing.assert_allclose(scenario.v[k], at["v"])
            steps = set(np.round(times[1:] / DT).astype(int))
            assert not steps & simulated_at.get(vid, set()), f"{vid} simulated twice"
            simulated_at.setdefault(vid, set()).update(steps)


@pytest.mark.realdata
def test_ngsim_platoons_lie_in_held_out_windows_and_span_several_chain_files(data_dir):
    traj = registry.load("ngsim_i80_chains", data_dir=data_dir)
    found = platoon_scenarios(traj, vehicles_per_scenario=4, horizon_s=5.0)
    assert found.scenarios, "the NGSIM chains allow 4-vehicle platoons over 5 s"
    check_real_platoons(traj, found)
    # Deduplication joins chain files of 6 vehicles into longer platoons: 7-vehicle scenarios
    # (6 simulated) exist, and none fits inside one file.
    longer = platoon_scenarios(traj, vehicles_per_scenario=6, horizon_s=5.0)
    assert longer.scenarios
    check_real_platoons(traj, longer)
    by_scene = traj.scenes.groupby("scene_id")["vehicle_id"].apply(set)
    for scenario in longer.scenarios:
        assert not any(set(scenario.vehicle_ids) <= members for members in by_scene)


@pytest.mark.realdata
def test_openacc_platoons_replay_car_1_and_simulate_the_four_followers(data_dir):
    traj = registry.load("openacc_vicolungo", data_dir=data_dir)
    found = platoon_scenarios(traj, vehicles_per_scenario=4, horizon_s=5.0)
    assert found.scenarios
    check_real_platoons(traj, found)
    assert {s.vehicle_ids[0].rsplit(":", 1)[1] for s in found.scenarios} == {"1"}
    # Integrated-speed positions drift from the measured spacing; scenarios start at the latter.
    for scenario in found.scenarios:
        start_gap = scenario.x[:-1, 0] - scenario.x[1:, 0] - scenario.length[:-1]
        np.testing.assert_allclose(start_gap, scenario.gap[:, 0], atol=1e-9)
    assert not platoon_scenarios(traj, vehicles_per_scenario=5, horizon_s=5.0).scenarios


@pytest.mark.realdata
def test_merge_scenarios_simulate_the_car_just_behind_the_merging_car(data_dir):
    traj = registry.load("ngsim_merge_episodes", data_dir=data_dir)
    held_out = heldout_episodes(traj)
    assert len(held_out) == len(traj.scene_ids) - int(0.7 * len(traj.scene_ids))
    found = merge_scenarios(traj, horizon_s=5.0)
    assert found.scenarios
    lanes = traj.tracks.groupby("vehicle_id")["lane_id"].first()
    for scenario in found.scenarios:
        episode, _ = scenario.scenario_id.split(":", 1)
        (v2,) = scenario.simulated_ids
        assert episode in held_out and v2 in traj.scene_vehicles(episode)
        assert lanes[v2] != lanes[f"{episode}_ego"]
        # At the start the simulated car is behind the merging car (merge point at x = 0).
        assert scenario.x[1, 0] < scenario.merge_x[0, 0] < 0.0
        real = int(scenario.step_mask.sum())
        assert round(1.0 / DT) <= real <= scenario.steps
        assert np.all(scenario.merge_present[0, : real + 1] == 1)
