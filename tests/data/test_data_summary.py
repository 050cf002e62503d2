"""data info figures: recorded duration counts each clock once and never the gaps between files."""

import pandas as pd
import pytest

from bayesdrive.data.trajectories import FLAG_COLUMNS, Trajectories, recorded_duration, summary


def _tracks(rows):
    frame = pd.DataFrame(rows, columns=["vehicle_id", "t"])
    return frame.assign(
        x=0.0,
        v=1.0,
        a=float("nan"),
        lane_id=pd.NA,
        leader_id=None,
        gap=float("nan"),
        length=4.5,
        driver="unknown",
    )


def test_duration_sums_independent_clocks_and_unions_shared_ones():
    dt = 0.1
    rows = [("a", k * dt) for k in range(11)]  # scene 1: 0.0-1.0 s
    rows += [("b", k * dt) for k in range(5, 21)]  # scene 1 too, overlapping a: up to 2.0 s
    rows += [("c", k * dt) for k in range(31)]  # scene 2 restarts its clock: 0.0-3.0 s
    rows += [("d", 100 + k * dt) for k in range(11)] + [("d", 200 + k * dt) for k in range(11)]
    scenes = pd.DataFrame(
        {"scene_id": ["s1", "s1", "s2", "s3"], "vehicle_id": ["a", "b", "c", "d"]}
    )
    traj = Trajectories(_tracks(rows), scenes, dt=dt, format="test", source="memory")
    # s1: union of a and b = 2.0 s; s2: 3.0 s; s3: two runs of 1.0 s with a hole between them.
    assert recorded_duration(traj) == pytest.approx(2.0 + 3.0 + 2.0)


@pytest.mark.realdata
def test_merge_episode_duration_matches_provenance(data_dir):
    from bayesdrive.data.readers import read

    info = summary(read(data_dir / "ngsim_merge_episodes"))
    # PROVENANCE.txt: 4877 rows at 10 Hz in 98 episodes; each episode spans (rows - 1) * 0.1 s.
    assert info["scenes"] == 98
    assert info["duration_s"] == pytest.approx((4877 - 98) * 0.1)


def test_first_seconds_counts_from_each_scenes_earliest_sample():
    dt = 0.1
    rows = [("a", k * dt) for k in range(31)]  # scene 1 starts at 0 s
    rows += [("b", 1.0 + k * dt) for k in range(31)]  # joins scene 1 at 1 s
    rows += [("c", 50.0 + k * dt) for k in range(31)]  # scene 2 starts at 50 s
    rows += [("d", 10.0 + k * dt) for k in range(5)]  # scene 1 again, only after the span
    scenes = pd.DataFrame(
        {"scene_id": ["s1", "s1", "s2", "s1"], "vehicle_id": ["a", "b", "c", "d"]}
    )
    no_flags = pd.DataFrame({c: pd.Series(dtype="str") for c in FLAG_COLUMNS}).astype({"t": float})
    traj = Trajectories(
        _tracks(rows), scenes, dt=dt, format="test", source="memory", flags=no_flags
    )
    cropped = traj.first_seconds(1.5)
    ends = cropped.tracks.groupby("vehicle_id")["t"].agg(["min", "max"])
    assert ends.loc["a", "max"] == pytest.approx(1.4)
    assert ends.loc["b", "min"] == pytest.approx(1.0) and ends.loc["b", "max"] == pytest.approx(1.4)
    assert ends.loc["c", "min"] == pytest.approx(50.0) and ends.loc["c", "max"] == pytest.approx(
        51.4
    )
    assert "d" not in ends.index and "d" not in set(cropped.scenes["vehicle_id"])
    with pytest.raises(ValueError, match="positive"):
        traj.first_seconds(0.0)


def test_every_keeps_common_instants_moves_flags_and_notes_it():
    dt = 0.1
    rows = [("a", k * dt) for k in range(21)] + [("b", 0.3 + k * dt) for k in range(15)]
    scenes = pd.DataFrame({"scene_id": ["s1", "s1"], "vehicle_id": ["a", "b"]})
    flags = pd.DataFrame(
        {
            "vehicle_id": ["a", "b", "b"],
            "t": [0.7, 1.0, 1.7],  # dropped instant; kept instant; past b's last kept sample
            "kind": ["negative_gap"] * 3,
            "message": ["m"] * 3,
        }
    )
    traj = Trajectories(_tracks(rows), scenes, dt=dt, format="test", source="memory", flags=flags)
    reduced = traj.every(5)
    assert reduced.dt == pytest.approx(0.5)
    times = reduced.tracks.groupby("vehicle_id")["t"].apply(list)
    assert times["a"] == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])
    assert times["b"] == pytest.approx([0.5, 1.0, 1.5])  # the instants a keeps too
    # The flag at 0.7 s moves to a's next kept instant (1.0 s), so the 0.5-1.0 s step stays out.
    assert list(zip(reduced.flags["vehicle_id"], reduced.flags["t"].round(6), strict=True)) == [
        ("a", 1.0),
        ("b", 1.0),
    ]
    assert "one sample in 5 kept" in reduced.notes[-1]
    assert traj.every(1) is traj
    with pytest.raises(ValueError, match="whole number"):
        traj.every(2.5)
    off_grid = Trajectories(
        _tracks([("a", 0.0), ("a", 0.15)]), scenes[:1], dt=dt, format="test", source="memory"
    )
    with pytest.raises(ValueError, match=r"vehicle a: sample at t = 0\.15"):
        off_grid.every(2)
