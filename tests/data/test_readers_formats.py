"""Each reader on small synthetic files written in its public format (no real data needed)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers import detect_format, read
from bayesdrive.data.readers.columns import read_columns
from bayesdrive.data.readers.ngsim_chains import align_copies

# --- NGSIM chains ----------------------------------------------------------------------------


def chain_file(folder, ids, start, steps):
    """A chain file cut from one common 'truth': car i at 100 - 15 i + integral of its speed."""
    t_all = np.arange(400) * 0.1
    rows = {"t1": np.round(np.arange(steps) * 0.1, 1)}
    speed = {i: 8.0 + 0.5 * np.sin(t_all / 3 + i) for i in ids}
    y = {
        i: 1000.0 - 15.0 * i + np.r_[0, np.cumsum(0.05 * (v[1:] + v[:-1]))]
        for i, v in speed.items()
    }
    origin = y[ids[-1]][start]  # every file restarts Y at 0 for its last car
    window = slice(start, start + steps)
    for slot, vehicle in enumerate(ids, start=1):
        rows[f"ID{slot}"] = vehicle
        rows[f"Y{slot}"] = np.round(y[vehicle][window] - origin, 4)
        rows[f"v{slot}"] = np.round(speed[vehicle][window], 4)
        rows[f"a{slot}"] = np.round(np.gradient(speed[vehicle])[window] / 0.1, 4)
    path = folder / f"{'_'.join(map(str, ids))}.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def test_chains_are_deduplicated_on_common_axes(tmp_path):
    # File B starts 30 steps after file A and shares cars 2 and 3; every file restarts t1 and Y.
    a = chain_file(tmp_path, [1, 2, 3], start=0, steps=100)
    b = chain_file(tmp_path, [2, 3, 4], start=30, steps=100)
    traj = read(tmp_path)
    assert traj.format == "ngsim_chains"
    assert sorted(traj.vehicle_ids) == ["1", "2", "3", "4"]
    assert len(traj.scene_ids) == 2
    assert set(traj.scenes["component"]) == {"c00"}
    car2 = traj.vehicle("2")
    assert len(car2) == 130  # union of 100 + 100 samples overlapping by 70
    assert np.allclose(np.diff(car2["t"]), 0.1)
    # Car 2 has a leader in file A (car 1) but not in file B, where it leads: the union keeps it.
    assert car2["leader_id"].iloc[:100].eq("1").all()
    assert car2["leader_id"].iloc[100:].isna().all()
    car4 = traj.vehicle("4")
    assert car4["leader_id"].eq("3").all()
    assert car4["t"].iloc[0] == pytest.approx(3.0)
    # Gaps live on one position axis: x_leader - x - 4.5 over both files.
    both = car4.merge(traj.vehicle("3"), on="t", suffixes=("", "_lead"))
    assert np.allclose(both["gap"], both["x_lead"] - both["x"] - 4.5)
    assert any("chains: merged 140 samples" in n for n in traj.notes)
    assert read(a).vehicle_ids == ["1", "2", "3"]  # one file reads too
    del b


def test_chain_copy_with_matching_speeds_but_other_positions_is_refused(tmp_path):
    chain_file(tmp_path, [1, 2, 3], start=0, steps=100)
    path = chain_file(tmp_path, [2, 3, 4], start=30, steps=100)
    table = pd.read_csv(path)
    table["Y1"] += np.linspace(0, 2, len(table))  # car 2's copy drifts by 2 m
    table.to_csv(path, index=False)
    with pytest.raises(DataError, match=r"vehicle 2: its copies .* positions differ .*refused"):
        read(tmp_path)


def test_align_copies_finds_the_shift_and_offset():
    v = np.round(8 + np.sin(np.arange(200) / 7), 4)
    y = np.round(np.cumsum(v) * 0.1, 4)
    match = align_copies(v[:120], y[:120], v[50:170], y[50:170] - y[50] + 3.0)
    assert match.shift == 50
    assert match.overlap == 70
    assert match.offset == pytest.approx(y[50] - 3.0, abs=1e-4)
    assert match.y_residual < 1e-4
    assert align_copies(v[:60], y[:60], v[100:160], y[100:160]) is None


def test_chain_slot_id_changing_is_named(tmp_path):
    path = chain_file(tmp_path, [1, 2], start=0, steps=20)
    table = pd.read_csv(path)
    table.loc[5, "ID2"] = 9
    table.to_csv(path, index=False)
    with pytest.raises(DataError, match=r"row 7, column 'ID2': vehicle id changes"):
        read(path)


# --- OpenACC -----------------------------------------------------------------------------------


def openacc_file(path, *, metadata_rows=3, n=300, trailing_nan=0, drivers=True):
    t = 4000.0 + np.arange(n) * 0.1 + 1e-9 * np.sin(np.arange(n))  # float noise in Time
    v1 = 25 + np.sin(np.arange(n) / 20)
    v2 = 25 + np.sin(np.arange(n) / 20 - 0.3)
    gap = 30 + np.r_[0, np.cumsum(0.05 * ((v1 - v2)[1:] + (v1 - v2)[:-1]))]
    table = pd.DataFrame(
        {
            "Time": t,
            "Speed1": v1,
            "E1": np.cumsum(v1) * 0.1,
            "N1": 0.0,
            "Speed2": v2,
            "E2": np.cumsum(v2) * 0.1 - 34.5,
            "N2": 0.0,
            "IVS1": gap,
        }
    )
    if drivers:
        table["Driver1"] = "Human"
        table["Driver2"] = "ACC"
    if trailing_nan:
        table.loc[n - trailing_nan :, ["Speed2", "E2", "IVS1"]] = np.nan
    meta = [
        "Date,5,3,2019",
        "Vehicle_order,Ford(S-Max),KIA(Niro)",
        "Number_of_vehicles,2",
        "ACC,1",
        "Distance_setting,min",
    ][:metadata_rows]
    path.write_text("\n".join(meta) + ("\n" if meta else "") + table.to_csv(index=False))
    return table


def test_openacc_positions_gaps_drivers_and_time(tmp_path):
    path = tmp_path / "platoon_part1.csv"
    table = openacc_file(path, metadata_rows=3)
    assert detect_format(path)[0] == "openacc"
    traj = read(path)
    lead = traj.vehicle("platoon_part1:1")
    follower = traj.vehicle("platoon_part1:2")
    assert lead["t"].iloc[0] == 0.0 and lead["t"].iloc[-1] == pytest.approx(29.9)
    assert list(lead["driver"].unique()) == ["human"]
    assert list(follower["driver"].unique()) == ["acc"]
    # x is the integrated Doppler speed (trapezoid), from 0 for the leader.
    expected = np.r_[0, np.cumsum(0.05 * (table["Speed1"][1:].to_numpy() + table["Speed1"][:-1]))]
    np.testing.assert_allclose(lead["x"], expected, atol=1e-6)
    # gap is the measured IVS; the follower is placed so that the identity holds (4.5 m assumed).
    np.testing.assert_allclose(follower["gap"], table["IVS1"])
    np.testing.assert_allclose(lead["x"].to_numpy() - follower["x"] - 4.5, table["IVS1"], atol=1e-6)
    assert follower["leader_id"].eq("platoon_part1:1").all()
    assert any("no length known for Ford(S-Max), KIA(Niro)" in n for n in traj.notes)


def test_openacc_lengths_given_by_model_name(tmp_path):
    path = tmp_path / "platoon.csv"
    table = openacc_file(path, metadata_rows=2)
    traj = read(path, lengths={"Ford (S-Max)": 4.8})
    lead, follower = traj.vehicle("platoon:1"), traj.vehicle("platoon:2")
    assert lead["length"].eq(4.8).all() and follower["length"].eq(4.5).all()
    np.testing.assert_allclose(lead["x"].to_numpy() - follower["x"] - 4.8, table["IVS1"], atol=1e-6)
    assert any("no length known for KIA(Niro)" in n for n in traj.notes)


def test_openacc_trailing_missing_values_are_a_logged_repair(tmp_path, caplog):
    path = tmp_path / "rec.csv"
    openacc_file(path, metadata_rows=5, trailing_nan=7)
    traj = read(path)
    assert len(traj.vehicle("rec:2")) == 293
    assert len(traj.vehicle("rec:1")) == 300
    assert any(
        n.startswith("repair: rec.csv: vehicle 2 not measured in 7 sample(s)") and "7 trailing" in n
        for n in traj.notes
    )
    assert "not measured" in caplog.text
    with pytest.raises(DataError, match="strict mode refuses data that needed"):
        read(path, strict=True)


def test_openacc_without_metadata_or_driver_columns(tmp_path):
    path = tmp_path / "extract.csv"
    openacc_file(path, metadata_rows=0, drivers=False)
    traj = read(path)
    assert set(traj.tracks["driver"]) == {"unknown"}
    assert any("no Driver<i> column" in n for n in traj.notes)


def test_openacc_bad_driver_and_bad_time_are_named(tmp_path):
    path = tmp_path / "bad.csv"
    table = openacc_file(path, metadata_rows=5)
    lines = path.read_text().splitlines()
    lines[5 + 1 + 10] = lines[5 + 1 + 10].replace("ACC", "Robot")
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"row 17, column 'Driver2': driver must be Human or ACC"):
        read(path)
    table.loc[20, "Time"] += 0.04
    path.write_text("Date,1,1,2020\n" + table.to_csv(index=False))
    with pytest.raises(DataError, match=r"row 23, column 'Time'.*not on the 0.1 s grid"):
        read(path)


# --- highD -------------------------------------------------------------------------------------


def highd_recording(folder, *, break_leader=False):
    frames = np.arange(1, 51)
    rows = []
    # Rightwards (direction 2): car 1 leads car 2 in lane 5; leftwards (direction 1): car 3.
    for car, x0, vx, lane, width, preceding in (
        (1, 100.0, 30.0, 5, 4.0, 0),
        (2, 60.0, 30.0, 5, 5.0, 1),
        (3, 400.0, -25.0, 2, 4.5, 0),
    ):
        for f in frames:
            rows.append(
                {
                    "frame": f,
                    "id": car,
                    "x": x0 + vx * f / 25,
                    "y": 10.0,
                    "width": width,
                    "height": 1.9,
                    "xVelocity": vx,
                    "yVelocity": 0.0,
                    "xAcceleration": 0.5 if vx > 0 else -0.5,
                    "yAcceleration": 0.0,
                    "dhw": (100.0 - 60.0 - 5.0) if preceding else 0.0,
                    "precedingId": preceding,
                    "laneId": lane,
                }
            )
    tracks = pd.DataFrame(rows)
    if break_leader:
        tracks = tracks[~((tracks["id"] == 1) & (tracks["frame"] == 7))]
    tracks.to_csv(folder / "07_tracks.csv", index=False)
    pd.DataFrame(
        {"id": [1, 2, 3], "width": [4.0, 5.0, 4.5], "height": 1.9, "drivingDirection": [2, 2, 1]}
    ).to_csv(folder / "07_tracksMeta.csv", index=False)
    pd.DataFrame({"id": [7], "frameRate": [25]}).to_csv(
        folder / "07_recordingMeta.csv", index=False
    )


def test_highd_directions_front_positions_and_gaps(tmp_path):
    highd_recording(tmp_path)
    assert detect_format(tmp_path)[0] == "highd"
    traj = read(tmp_path)
    assert traj.dt == pytest.approx(0.04)
    car1, car2, car3 = (traj.vehicle(f"07:{i}") for i in (1, 2, 3))
    assert car1["x"].iloc[0] == pytest.approx(100.0 + 30 / 25 + 4.0)  # left edge + length
    assert car2["gap"].iloc[0] == pytest.approx(100.0 - (60.0 + 5.0))  # rear(1) - front(2)
    assert car2["leader_id"].eq("07:1").all() and car2["length"].eq(5.0).all()
    # Leftwards: speed and acceleration turn positive along the driving direction, x increases.
    assert car3["v"].eq(25.0).all() and car3["a"].eq(0.5).all()
    assert car3["x"].iloc[0] == pytest.approx(-(400.0 - 25 / 25))
    assert np.all(np.diff(car3["x"]) > 0)
    assert car1["t"].iloc[0] == pytest.approx(0.04)
    assert any("median |dhw - bumper gap| = 0.00" in n for n in traj.notes)


def test_highd_leader_missing_at_a_frame_is_named(tmp_path):
    highd_recording(tmp_path, break_leader=True)
    with pytest.raises(DataError, match=r"07_tracks.csv, row \d+, column 'precedingId'.*frame 7"):
        read(tmp_path / "07_tracks.csv")


def test_highd_missing_companion_file(tmp_path):
    highd_recording(tmp_path)
    (tmp_path / "07_tracksMeta.csv").unlink()
    with pytest.raises(DataError, match=r"companion file 07_tracksMeta\.csv is missing"):
        read(tmp_path, format="highd")


# --- INTERACTION -------------------------------------------------------------------------------

OSM = """<?xml version="1.0"?>
<osm version="0.6" generator="test">
  <node id="1" lat="0" lon="0"><tag k="local_x" v="0"/><tag k="local_y" v="0"/></node>
  <node id="2" lat="0" lon="0"><tag k="local_x" v="200"/><tag k="local_y" v="0"/></node>
  <node id="3" lat="0" lon="0"><tag k="local_x" v="0"/><tag k="local_y" v="3.5"/></node>
  <node id="4" lat="0" lon="0"><tag k="local_x" v="200"/><tag k="local_y" v="3.5"/></node>
  <node id="5" lat="0" lon="0"><tag k="local_x" v="0"/><tag k="local_y" v="7"/></node>
  <node id="6" lat="0" lon="0"><tag k="local_x" v="200"/><tag k="local_y" v="7"/></node>
  <way id="10"><nd ref="1"/><nd ref="2"/></way>
  <way id="11"><nd ref="3"/><nd ref="4"/></way>
  <way id="12"><nd ref="5"/><nd ref="6"/></way>
  <relation id="20"><member type="way" ref="11" role="left"/>
    <member type="way" ref="10" role="right"/><tag k="type" v="lanelet"/></relation>
  <relation id="21"><member type="way" ref="11" role="left"/>
    <member type="way" ref="12" role="right"/><tag k="type" v="lanelet"/></relation>
</osm>
"""


def test_interaction_lanes_leaders_and_gaps(tmp_path):
    (tmp_path / "map.osm").write_text(OSM)
    rows = []
    for k in range(10):
        for track, x, y, vx, psi, length in (
            (1, 50.0 + k, 1.75, 10.0, 0.0, 4.0),  # eastbound lanelet 20, behind car 2
            (2, 70.0 + k, 1.9, 10.0, 0.0, 5.0),
            (3, 150.0 - k, 5.25, -10.0, np.pi, 4.0),  # westbound lanelet 21 (left bound south)
        ):
            rows.append(
                {
                    "track_id": track,
                    "frame_id": k + 1,
                    "timestamp_ms": 100 * (k + 1),
                    "agent_type": "car",
                    "x": x,
                    "y": y,
                    "vx": vx,
                    "vy": 0.0,
                    "psi_rad": psi,
                    "length": length,
                    "width": 1.8,
                }
            )
    pd.DataFrame(rows).to_csv(tmp_path / "vehicle_tracks_001.csv", index=False)
    assert detect_format(tmp_path)[0] == "interaction"
    traj = read(tmp_path)
    car1, car2, car3 = (traj.vehicle(f"vehicle_tracks_001:{i}") for i in (1, 2, 3))
    assert car1["lane_id"].eq(20).all() and car3["lane_id"].eq(21).all()
    assert car1["leader_id"].eq("vehicle_tracks_001:2").all()
    assert car1["gap"].iloc[0] == pytest.approx((70.0 - 2.5) - (50.0 + 2.0))
    assert car1["x"].iloc[0] == pytest.approx(52.0)  # centre + half length, along lanelet 20
    assert car3["x"].iloc[0] == pytest.approx(200.0 - 150.0 + 2.0)  # lanelet 21 runs west
    assert np.all(np.diff(car3["x"]) > 0)
    assert car2["leader_id"].isna().all() and car3["v"].eq(10.0).all()


# --- merge episodes ----------------------------------------------------------------------------


def test_merge_episodes_sentinels_slots_and_leaders(tmp_path):
    n = 6
    table = pd.DataFrame(
        {
            "episode": 4,
            "t_s": np.round(np.arange(n) * 0.1, 1),
            "ego_v_mps": 12.0,
            "ego_a_mps2": 0.3,
            "ego_dist_to_accel_lane_end_m": 150.0 - 1.2 * np.arange(n),
            "d_V1_m": [-40.0, -40.1, -40.2, -20.0, -20.1, -20.2],  # a different car from step 3
            "dv_V1_mps": -1.0,
            "d_V2_m": -15.0,
            "dv_V2_mps": 0.0,
            "d_V3_m": 10.0,
            "dv_V3_mps": 0.5,
            "d_V4_m": 100.0,  # sentinel: no V4
            "dv_V4_mps": 30.0,
            "d_V5_m": [100.0, 100.0, 25.0, 24.9, 24.8, 24.7],
            "dv_V5_mps": [30.0, 30.0, -1.0, -1.0, -1.0, -1.0],
            "action": 2,
        }
    )
    path = tmp_path / "dataset_with_episode_ids.csv"
    table.to_csv(path, index=False)
    assert detect_format(tmp_path)[0] == "merge_episodes"
    traj = read(tmp_path)
    assert traj.scene_ids == ["ep4"]
    assert "ep4_V4" not in traj.vehicle_ids
    assert len(traj.vehicle("ep4_V1")) == 3 and len(traj.vehicle("ep4_V1_b")) == 3
    ego = traj.vehicle("ep4_ego")
    assert ego["x"].iloc[0] == pytest.approx(-150.0) and ego["lane_id"].eq(0).all()
    assert ego["leader_id"].iloc[:2].isna().all()
    assert ego["gap"].iloc[2] == pytest.approx(25.0 - 4.5)
    v2 = traj.vehicle("ep4_V2")
    assert v2["leader_id"].eq("ep4_V3").all() and v2["gap"].iloc[0] == pytest.approx(25.0 - 4.5)
    assert traj.vehicle("ep4_V3")["v"].iloc[0] == pytest.approx(12.5)
    assert list(traj.vehicle("ep4_V1_b")["leader_id"].unique()) == ["ep4_V2"]
    assert any("1 slot re-assignment" in n for n in traj.notes)


# --- columns -----------------------------------------------------------------------------------


def test_columns_vehicles_with_front_headway_and_centre_positions(tmp_path):
    rows = [
        {"car": c, "time_ms": 100 * k, "pos": p + 2.0 * k, "speed": 20.0, "lead": lead, "h": h}
        for c, p, lead, h in (("A", 100.0, "", np.nan), ("B", 80.0, "A", 20.0))
        for k in range(5)
    ]
    path = tmp_path / "cars.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    columns = {
        "vehicle_id": "car",
        "t": "time_ms",
        "x": "pos",
        "v": "speed",
        "leader_id": "lead",
        "gap": "h",
    }
    traj = read_columns(path, columns, headway="front", time_factor=0.001, position="centre")
    b = traj.vehicle("B")
    assert b["gap"].iloc[0] == pytest.approx(20.0 - 4.5)  # front-to-front minus leader length
    assert b["x"].iloc[0] == pytest.approx(80.0 + 2.25)  # centre -> front
    assert traj.dt == pytest.approx(0.1)
    assert any("dt = 0.1" in n for n in traj.notes)
    with pytest.raises(DataError, match="column map for mode 'vehicles': missing v"):
        read_columns(path, {"vehicle_id": "car", "t": "time_ms", "x": "pos"})
    with pytest.raises(DataError, match=r"missing column\(s\) nope"):
        read_columns(path, {**columns, "v": "nope"})


def test_columns_pairs_merge_a_car_shared_by_two_pairs(tmp_path):
    # Pair 1: car 2 follows car 1; pair 2: car 3 follows car 2. Feet, bumper spacing.
    t = np.round(np.arange(5) * 0.1, 1)
    x1, x2, x3 = 300.0 + 50 * t, 240.0 + 50 * t, 180.0 + 50 * t
    for name, (xf, xl) in {
        "pair_f2_l1": (x2, x1),
        "pair_f3_l2": (x3, x2),
    }.items():
        pd.DataFrame(
            {
                "t": t,
                "x_f": xf,
                "v_f": 50.0,
                "x_l": xl,
                "v_l": 50.0,
                "len_l": 15.0,
                "spacing": xl - xf - 15.0,
            }
        ).to_csv(tmp_path / f"{name}.csv", index=False)
    columns = {
        "t": "t",
        "x_follower": "x_f",
        "v_follower": "v_f",
        "x_leader": "x_l",
        "v_leader": "v_l",
        "length_leader": "len_l",
        "gap": "spacing",
    }
    pattern = r"f(?P<follower>\d+)_l(?P<leader>\d+)$"
    traj = read_columns(tmp_path, columns, mode="pairs", units="ft", id_pattern=pattern, dt=0.1)
    assert sorted(traj.vehicle_ids) == ["1", "2", "3"]
    car2 = traj.vehicle("2")
    assert len(car2) == 5 and car2["leader_id"].eq("1").all()
    assert car2["length"].iloc[0] == pytest.approx(15.0 * 0.3048)  # known from pair 2
    assert traj.vehicle("3")["length"].iloc[0] == pytest.approx(4.5)  # never a leader: assumed
    assert car2["gap"].iloc[0] == pytest.approx(45.0 * 0.3048)
    assert sorted(traj.scenes.query("vehicle_id == '2'")["scene_id"]) == [
        "pair_f2_l1",
        "pair_f3_l2",
    ]
    # A copy that disagrees is refused, naming both files.
    broken = pd.read_csv(tmp_path / "pair_f3_l2.csv")
    broken["x_l"] += 1.0
    broken.to_csv(tmp_path / "pair_f3_l2.csv", index=False)
    with pytest.raises(DataError, match=r"vehicle 2: copies of one sample disagree.*pair_f2_l1"):
        read_columns(tmp_path, columns, mode="pairs", units="ft", id_pattern=pattern, dt=0.1)


def test_columns_wide_matrices(tmp_path):
    steps, pairs = 20, 3
    t = np.arange(steps)[:, None] * 0.1
    lead = 200.0 + 40.0 * t + np.arange(pairs) * 10
    follow = lead - 60.0
    files = {}
    for key, matrix in {
        "x_leader": lead,
        "v_leader": np.full_like(lead, 40.0),
        "x_follower": follow,
        "v_follower": np.full_like(lead, 40.0),
    }.items():
        files[key] = f"{key}.csv"
        np.savetxt(tmp_path / files[key], matrix, delimiter=",", fmt="%.4f")
    traj = read_columns(tmp_path, mode="wide", files=files, units="ft", dt=0.1)
    assert len(traj.vehicle_ids) == 6 and len(traj.scene_ids) == 3
    follower = traj.vehicle("pair2:follower")
    assert follower["leader_id"].eq("pair2:leader").all()
    assert follower["gap"].iloc[0] == pytest.approx(60.0 * 0.3048 - 4.5)
    with pytest.raises(DataError, match="mode 'wide' has no time column; pass dt="):
        read_columns(tmp_path, mode="wide", files=files, units="ft")
    np.savetxt(tmp_path / "x_leader.csv", lead[:-1], delimiter=",", fmt="%.4f")
    with pytest.raises(DataError, match="wide matrices differ in shape"):
        read_columns(tmp_path, mode="wide", files=files, units="ft", dt=0.1)


def test_columns_numeric_leader_ids_with_blanks_mean_no_leader(tmp_path):
    path = tmp_path / "cars.csv"
    path.write_text("id,t,x,v,lead\n1,0.0,50,10,\n1,0.1,51,10,\n2,0.0,30,10,1\n2,0.1,31,10,1\n")
    traj = read_columns(
        path, {"vehicle_id": "id", "t": "t", "x": "x", "v": "v", "leader_id": "lead"}, dt=0.1
    )
    assert traj.vehicle("1")["leader_id"].isna().all()
    assert traj.vehicle("2")["gap"].iloc[0] == pytest.approx(50 - 30 - 4.5)
    path.write_text("id,t,x,v\n1,0.0,50,10\n,0.1,51,10\n")
    with pytest.raises(DataError, match=r"row 3, column 'id': vehicle id is empty"):
        read_columns(path, {"vehicle_id": "id", "t": "t", "x": "x", "v": "v"}, dt=0.1)
