"""A corpus of bad and edge-case inputs across every reader, each with its expected outcome class.

Outcome classes: ``refuse`` (a one-line :class:`DataError` naming the file, and row and column
where there is one, with the words that say what is wrong), ``repair`` (read, with the change in
``Trajectories.repairs`` and logged), ``note`` (read unchanged, the interpretation noted and logged)
and ``accept`` (read exactly: the figures put into the file come back). The files are built in
``tmp_path`` by the builders in ``tests/bad_inputs``; the expected figures are the builders' inputs.
Issue classes (the first word of each case id): units, rate, ids, frames, self_leader, gap_check,
traceback, misleading, valid_refused, silent_drop, message.
"""

from __future__ import annotations

import logging
import os
import re
from collections import Counter

import numpy as np
import pandas as pd
import pytest
from bad_inputs import (
    FT,
    OPENACC_META,
    VEHICLE_MAP,
    chain_table,
    highd_tables,
    interaction_table,
    merge_table,
    ngsim_table,
    openacc_table,
    osm_text,
    vehicles_table,
    write_chain,
    write_highd,
    write_interaction,
    write_merge,
    write_ngsim,
    write_openacc,
    write_vehicles,
)

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers import detect_format, read
from bayesdrive.data.views import follower_arrays

CASES = []


def case(cls: str):
    def register(fn):
        CASES.append(pytest.param(fn, id=f"{cls}-{fn.__name__}"))
        return fn

    return register


def refuses(pattern: str, call, *, file=None) -> str:
    """The call raises a one-line DataError matching ``pattern`` (and naming ``file``)."""
    with pytest.raises(DataError) as err:
        call()
    message = str(err.value)
    assert re.search(pattern, message), message
    assert "\n" not in message and "np.float64" not in message, message
    if file is not None:
        assert str(file) in message, message
    return message


def repaired(traj, pattern: str) -> None:
    assert any(re.search(pattern, r) for r in traj.repairs), traj.repairs


def noted(traj, pattern: str) -> None:
    assert any(re.search(pattern, n) for n in traj.notes), traj.notes


def columns(path, **kw):
    return read(path, format="columns", columns={**VEHICLE_MAP, "length": "len"}, dt=0.1, **kw)


# --- units: position increments vs speed x dt, plausible speeds and lengths ---------------------


@case("units")
def ngsim_metres_declared_as_feet(tmp_path):
    table = ngsim_table()
    for column in ("Local_Y", "v_Vel", "v_Length", "Space_Headway"):
        table[column] *= FT  # metres written where NGSIM declares feet
    path = write_ngsim(tmp_path, table)
    refuses(
        r"row 2, column 'v_Length'.*too short for cars; are metres declared as feet",
        lambda: read(path),
        file=path,
    )


def _ngsim_speeds_scaled(tmp_path, factor: float, pattern: str) -> None:
    """The file's speeds multiplied by ``factor`` (another unit), positions kept in feet."""
    table = ngsim_table()
    table["v_Vel"] *= factor
    path = write_ngsim(tmp_path, table)
    refuses(pattern, lambda: read(path), file=path)


@case("units")
def ngsim_speed_column_in_metres_positions_in_feet(tmp_path):
    _ngsim_speeds_scaled(
        tmp_path,
        FT,
        r"column 'Local_Y'.*positions advance 3\.28 times.*"
        r"column 'v_Vel' looks like speeds in m/s read as ft/s",
    )


@case("units")
def ngsim_speed_in_kmh_read_as_feet_per_second(tmp_path):
    _ngsim_speeds_scaled(
        tmp_path,
        FT * 3.6,  # the same speeds written in km/h: 10% above ft/s, below 70 m/s
        r"row 3, column 'Local_Y': positions advance 0\.91 times as much as the speeds say.*"
        r"column 'v_Vel' looks like speeds in km/h read as ft/s",
    )


@case("units")
def columns_speed_in_mph_declared_feet(tmp_path):
    table = vehicles_table()
    table["pos"] /= FT
    table["speed"] /= 0.44704  # positions in feet, speeds in mph; lengths in feet
    table["len"] /= FT
    path = write_vehicles(tmp_path, table)
    refuses(
        r"positions advance 1\.47 times.*column 'speed' looks like speeds in mph read as ft/s",
        lambda: columns(path, units="ft"),
    )


@case("units")
def ngsim_noisy_speeds_accepted_negative_control(tmp_path):
    """Measurement noise of 2 ft/s on every speed (seed 36) is no unit error."""
    table = ngsim_table()
    noise = np.random.default_rng(36).normal(0.0, 2.0, len(table))
    table["v_Vel"] = np.abs(table["v_Vel"] + noise)
    traj = read(write_ngsim(tmp_path, table))
    np.testing.assert_allclose(traj.tracks["v"].sort_values(), (table["v_Vel"] * FT).sort_values())


@case("units")
def openacc_speed_in_kmh_at_highway_speed(tmp_path):
    table = openacc_table(speed_factor=3.6).drop(columns=["E1", "N1", "E2", "N2"])  # no ENU
    path = write_openacc(tmp_path / "run.csv", table)
    message = refuses(r"row 7, column 'Speed<i>': speed 90 is above 70 m/s", lambda: read(path))
    assert "km/h" in message


@case("units")
def openacc_speed_in_kmh_caught_by_the_enu_path_first(tmp_path):
    path = write_openacc(tmp_path / "run.csv", openacc_table(speed_factor=3.6))
    refuses(
        r"column 'Speed1': the ENU path \(E1, N1\) is 0\.28 times", lambda: read(path), file=path
    )


@case("units")
def openacc_speed_in_kmh_at_town_speed(tmp_path):
    table = openacc_table()
    for column in ("Speed1", "Speed2"):
        table[column] = (table[column] - 15.0) * 3.6  # 10 +- 3 m/s written as km/h (< 70)
    # IVS measured in metres, as the true speeds move the cars.
    v1, v2 = table["Speed1"].to_numpy() / 3.6, table["Speed2"].to_numpy() / 3.6
    table["IVS1"] = 30.0 + np.r_[0, np.cumsum(0.05 * ((v1 - v2)[1:] + (v1 - v2)[:-1]))]
    path = write_openacc(tmp_path / "run.csv", table)
    refuses(r"gaps change 0\.2\d times as much as the relative speeds say", lambda: read(path))


@case("units")
def openacc_kmh_without_a_gap_caught_by_the_enu_path(tmp_path):
    table = openacc_table().drop(columns=["IVS1"])
    for column in ("Speed1", "Speed2"):
        table[column] = (table[column] - 15.0) * 3.6  # 10 m/s as 36 "m/s"; E/N are metres
    table["E1"] = table["E1"] * (10.0 / 25.0)
    table["E2"] = table["E2"] * (10.0 / 25.0)
    path = write_openacc(tmp_path / "run.csv", table)
    refuses(
        r"column 'Speed1': the ENU path \(E1, N1\) is 0\.\d+ times the distance", lambda: read(path)
    )


@case("units")
def chains_written_in_feet(tmp_path):
    table = chain_table(base=0.5, amplitude=0.3)  # a jam, in metres
    for i in (1, 2, 3):
        table[f"Y{i}"] /= FT
        table[f"v{i}"] /= FT
    path = write_chain(tmp_path, table)
    refuses(
        r"stopped vehicles keep a median spacing of 49\.\d m.*are these feet", lambda: read(path)
    )


@case("units")
def columns_declared_feet_but_metres(tmp_path):
    path = write_vehicles(tmp_path, vehicles_table())
    refuses(r"too short for cars; are metres declared as feet", lambda: columns(path, units="ft"))


@case("units")
def columns_positions_feet_speeds_metres(tmp_path):
    table = vehicles_table()
    table["pos"] /= FT
    path = write_vehicles(tmp_path, table)
    refuses(r"column 'pos'.*positions advance 3\.28 times", lambda: columns(path))


@case("units")
def highd_lengths_in_feet(tmp_path):
    tracks, meta, recording = highd_tables(width=(15.0, 16.0))
    path = write_highd(tmp_path, tracks, meta, recording)
    refuses(r"column 'width'.*too long to be metres; are these feet", lambda: read(path))


@case("units")
def merge_distances_in_feet(tmp_path):
    table = merge_table()
    for column in ("ego_dist_to_accel_lane_end_m", "d_V3_m", "d_V5_m"):
        table[column] /= FT
    path = write_merge(tmp_path, table)
    refuses(r"positions advance 3\.28 times as much as the speeds", lambda: read(path))


@case("units")
def columns_valid_metres_accepted_negative_control(tmp_path):
    table = vehicles_table()
    traj = columns(write_vehicles(tmp_path, table))
    np.testing.assert_allclose(traj.vehicle("b")["x"], table.loc[table["car"] == "b", "pos"])
    assert traj.flags.empty and not traj.repairs


def _pairs_table(n: int = 100, follower=2, leader=1):
    table = vehicles_table(n)
    lead, follow = (table[table["car"] == c].reset_index(drop=True) for c in ("a", "b"))
    return pd.DataFrame(
        {
            "t": lead["time"],
            "fid": follower,
            "lid": leader,
            "xf": follow["pos"],
            "vf": follow["speed"],
            "xl": lead["pos"],
            "vl": lead["speed"],
        }
    )


PAIR_MAP = {
    "t": "t",
    "follower_id": "fid",
    "leader_id": "lid",
    "x_follower": "xf",
    "v_follower": "vf",
    "x_leader": "xl",
    "v_leader": "vl",
}


def _pairs(path, **kw):
    return read(path, format="columns", mode="pairs", columns=PAIR_MAP, dt=0.1, **kw)


@case("units")
def wide_matrices_positions_in_feet_speeds_in_metres(tmp_path):
    table = _pairs_table()
    quantities = {"x_leader": "xl", "v_leader": "vl", "x_follower": "xf", "v_follower": "vf"}
    for key, column in quantities.items():
        values = table[column] / (FT if key.startswith("x") else 1.0)
        values.to_frame().to_csv(tmp_path / f"{key}.csv", index=False, header=False)
    files = {key: f"{key}.csv" for key in quantities}
    call = lambda: read(tmp_path, format="columns", mode="wide", files=files, dt=0.1)  # noqa: E731
    refuses(r"positions advance 3\.28 times as much as the speeds say", call)


@case("ids")
def pairs_17_digit_ids(tmp_path):
    path = tmp_path / "pairs.csv"
    _pairs_table(follower=ID_17[1], leader=ID_17[0]).to_csv(path, index=False)
    traj = _pairs(path)
    assert sorted(traj.vehicle_ids) == [str(i) for i in ID_17]
    assert traj.vehicle(str(ID_17[1]))["leader_id"].eq(str(ID_17[0])).all()


@case("misleading")
def pairs_shuffled_rows_sorted(tmp_path):
    table = _pairs_table()
    path = tmp_path / "pairs.csv"
    table.sample(frac=1.0, random_state=6).to_csv(path, index=False)
    traj = _pairs(path)
    repaired(traj, r"rows of a pair are not in time order")
    np.testing.assert_allclose(traj.vehicle("2")["x"], table["xf"])


# --- rate: a 5 Hz file is not 10 Hz with holes ---------------------------------------------------


@case("rate")
def ngsim_5hz(tmp_path):
    traj = read(write_ngsim(tmp_path, ngsim_table(frame_step=2)))
    assert traj.dt == pytest.approx(0.2)
    noted(traj, r"sampled every 0\.2 s \(5 Hz\)")
    assert follower_arrays(traj, window="all").mask.sum() == 99  # every step usable


@case("rate")
def openacc_5hz(tmp_path):
    traj = read(write_openacc(tmp_path / "run.csv", openacc_table(n=150, dt=0.2)))
    assert traj.dt == pytest.approx(0.2)
    noted(traj, r"sampled every 0\.2 s")


@case("rate")
def chains_5hz(tmp_path):
    traj = read(write_chain(tmp_path, chain_table(dt=0.2)))
    assert traj.dt == pytest.approx(0.2)


@case("rate")
def columns_5hz_declared_10hz(tmp_path):
    traj = columns(write_vehicles(tmp_path, vehicles_table(dt=0.2)))
    assert traj.dt == pytest.approx(0.2)
    noted(traj, r"not at 10 Hz with missing samples")


@case("rate")
def ngsim_10hz_with_holes_stays_10hz(tmp_path):
    table = ngsim_table()
    table = table[~table["Frame_ID"].isin([110, 111, 150])]
    traj = read(write_ngsim(tmp_path, table))
    assert traj.dt == pytest.approx(0.1)
    assert not any("sampled every" in n for n in traj.notes)


@case("rate")
def ngsim_20hz_refused(tmp_path):
    table = ngsim_table()
    table["Frame_ID"] = table["Frame_ID"] * 0.5 + 50  # half frames: 20 Hz
    path = write_ngsim(tmp_path, table)
    refuses(r"column 'Frame_ID'.* is not a whole number", lambda: read(path))


# --- ids kept as exact strings -----------------------------------------------------------------

ID_17 = (12345678901234567, 12345678901234568)
ID_30 = ("123456789012345678901234567890", "123456789012345678901234567891")


@case("ids")
def ngsim_17_digit_ids_stay_distinct(tmp_path):
    traj = read(write_ngsim(tmp_path, ngsim_table(ids=ID_17)))
    stem = "trajectories-0400-0415"
    assert traj.vehicle_ids == [f"{stem}:{i}" for i in ID_17]
    assert traj.vehicle(f"{stem}:{ID_17[1]}")["leader_id"].eq(f"{stem}:{ID_17[0]}").all()


@case("ids")
def ngsim_30_digit_ids(tmp_path):
    traj = read(write_ngsim(tmp_path, ngsim_table(ids=ID_30)))
    assert [v.split(":")[1] for v in traj.vehicle_ids] == list(ID_30)


@case("ids")
def chains_17_digit_ids(tmp_path):
    traj = read(write_chain(tmp_path, chain_table(ids=(*ID_17, 12345678901234569))))
    assert sorted(traj.vehicle_ids) == [
        "12345678901234567",
        "12345678901234568",
        "12345678901234569",
    ]


@case("ids")
def highd_17_digit_ids(tmp_path):
    traj = read(write_highd(tmp_path, *highd_tables(ids=ID_17)))
    assert traj.vehicle_ids == [f"07:{i}" for i in ID_17]


@case("ids")
def interaction_30_digit_ids(tmp_path):
    traj = read(write_interaction(tmp_path, interaction_table(ids=ID_30)))
    assert {v.split(":")[1] for v in traj.vehicle_ids} == set(ID_30)


@case("ids")
def columns_17_digit_numeric_ids(tmp_path):
    table = vehicles_table(ids=ID_17)
    table["lead"] = table["lead"].replace("", 0)
    traj = columns(write_vehicles(tmp_path, table))
    assert sorted(traj.vehicle_ids) == [str(i) for i in ID_17]


@case("ids")
def columns_ids_written_as_floats_match(tmp_path):
    table = vehicles_table(ids=(7, 8))
    table["lead"] = table["lead"].replace("", np.nan).astype(float)  # 7.0 for vehicle 7
    traj = columns(write_vehicles(tmp_path, table))
    assert traj.vehicle("8")["leader_id"].eq("7").all()


@case("ids")
def ngsim_fractional_id_refused(tmp_path):
    table = ngsim_table()
    table["Vehicle_ID"] = table["Vehicle_ID"].astype(object)
    table.loc[5, "Vehicle_ID"] = "1.5"
    path = write_ngsim(tmp_path, table)
    refuses(
        r"row 7, column 'Vehicle_ID': id is not a whole number: '1\.5'",
        lambda: read(path),
        file=path,
    )


# --- frames: whole numbers only -------------------------------------------------------------------


@case("frames")
def ngsim_fractional_frame(tmp_path):
    table = ngsim_table()
    table["Frame_ID"] = table["Frame_ID"].astype(float)
    table.loc[3, "Frame_ID"] = 103.5
    path = write_ngsim(tmp_path, table)
    refuses(
        r"row 5, column 'Frame_ID': 103\.5 is not a whole number", lambda: read(path), file=path
    )


@case("frames")
def ngsim_frame_beyond_int64(tmp_path):
    table = ngsim_table()
    table["Frame_ID"] = table["Frame_ID"].astype(object)
    table.loc[3, "Frame_ID"] = "99999999999999999999"  # > 2**63: int64 would wrap to -9.2e18
    path = write_ngsim(tmp_path, table)
    message = refuses(
        r"row 5, column 'Frame_ID': 1e\+20 is out of range", lambda: read(path), file=path
    )
    assert "duplicate" not in message


@case("frames")
def merge_episode_number_out_of_range(tmp_path):
    table = merge_table()
    table["episode"] = table["episode"].astype(float)
    table.loc[10:, "episode"] = 4e15
    path = write_merge(tmp_path, table)
    refuses(r"row 12, column 'episode': 4e\+15 is out of range", lambda: read(path))


@case("frames")
def highd_fractional_frame(tmp_path):
    tracks, meta, recording = highd_tables()
    tracks["frame"] = tracks["frame"].astype(float)
    tracks.loc[4, "frame"] = 5.5
    path = write_highd(tmp_path, tracks, meta, recording)
    refuses(r"row 6, column 'frame': 5\.5 is not a whole number", lambda: read(path))


@case("frames")
def columns_fractional_frame_number(tmp_path):
    table = vehicles_table()
    table["time"] = np.round(table["time"] * 10).astype(float)
    table.loc[2, "time"] = 2.5
    path = write_vehicles(tmp_path, table)
    refuses(r"row 4, column 'time'.*not on the 0\.1 s grid", lambda: columns(path, time_factor=0.1))


@case("frames")
def ngsim_fractional_lane(tmp_path):
    table = ngsim_table()
    table["Lane_ID"] = table["Lane_ID"].astype(float)
    table.loc[8, "Lane_ID"] = 2.5
    path = write_ngsim(tmp_path, table)
    refuses(r"row 10, column 'Lane_ID': 2\.5 is not a whole number", lambda: read(path))


@case("frames")
def interaction_timestamp_off_grid(tmp_path):
    table = interaction_table()
    table.loc[3, "timestamp_ms"] = 450
    path = write_interaction(tmp_path, table)
    refuses(r"row 5, column 'timestamp_ms'.*not on the 0\.1 s grid", lambda: read(path))


@case("frames")
def merge_fractional_episode(tmp_path):
    table = merge_table()
    table["episode"] = table["episode"].astype(float)
    table.loc[10, "episode"] = 4.5
    path = write_merge(tmp_path, table)
    refuses(r"row 12, column 'episode': 4\.5 is not a whole number", lambda: read(path))


@case("ids")
def highd_empty_preceding_id(tmp_path):
    tracks, meta, recording = highd_tables()
    tracks["precedingId"] = tracks["precedingId"].astype(object)
    tracks.loc[7, "precedingId"] = None
    path = write_highd(tmp_path, tracks, meta, recording)
    refuses(r"row 9, column 'precedingId': id is empty", lambda: read(path))


# --- self-leader -----------------------------------------------------------------------------------


@case("self_leader")
def ngsim_own_leader(tmp_path):
    table = ngsim_table()
    table.loc[table["Vehicle_ID"] == 2, "Preceding"] = 2
    path = write_ngsim(tmp_path, table)
    refuses(
        r"column 'Preceding': vehicle \S+:2 is named as its own leader",
        lambda: read(path),
        file=path,
    )


@case("self_leader")
def columns_own_leader(tmp_path):
    table = vehicles_table()
    table.loc[table["car"] == "b", "lead"] = "b"
    path = write_vehicles(tmp_path, table)
    refuses(r"vehicle b is named as its own leader", lambda: columns(path))


@case("self_leader")
def highd_own_leader(tmp_path):
    tracks, meta, recording = highd_tables()
    tracks.loc[tracks["id"] == 2, "precedingId"] = 2
    path = write_highd(tmp_path, tracks, meta, recording)
    refuses(r"column 'precedingId': vehicle 07:2 is named as its own leader", lambda: read(path))


# --- gaps checked against positions ------------------------------------------------------------


@case("gap_check")
def ngsim_follower_inside_leader_while_headway_says_otherwise(tmp_path):
    table = ngsim_table()
    late = (table["Vehicle_ID"] == 2) & table["Frame_ID"].between(150, 199)
    table.loc[late, "Space_Headway"] += 100.0  # 5 s in which the headway column disagrees
    traj = read(write_ngsim(tmp_path, table))
    flagged = traj.flags[traj.flags["kind"] == "gap_mismatch"]
    assert len(flagged) == 50 and flagged["t"].min() == pytest.approx(15.0)
    assert "gap column" in flagged["message"].iloc[0]
    noted(traj, r"50 gap_mismatch sample")


@case("gap_check")
def ngsim_small_headway_noise_not_flagged(tmp_path):
    table = ngsim_table()
    table.loc[table["Vehicle_ID"] == 2, "Space_Headway"] += 3.0  # 0.9 m: within a car length
    traj = read(write_ngsim(tmp_path, table))
    assert traj.flags.empty


@case("gap_check")
def columns_gap_column_contradicts_positions(tmp_path):
    table = vehicles_table()
    follower = table["car"] == "b"
    table["gap"] = np.nan
    table.loc[follower, "gap"] = 15.5
    table.loc[follower & (table["time"] >= 5.0), "gap"] = 40.0
    path = write_vehicles(tmp_path, table)
    traj = read(
        path, format="columns", columns={**VEHICLE_MAP, "length": "len", "gap": "gap"}, dt=0.1
    )
    assert set(traj.flags["kind"]) == {"gap_mismatch"}
    assert traj.flags["t"].min() == pytest.approx(5.0)


@case("gap_check")
def openacc_gap_not_compared_with_derived_positions(tmp_path):
    traj = read(write_openacc(tmp_path / "run.csv", openacc_table()))
    assert traj.flags.empty


@case("gap_check")
def columns_gap_column_agreeing_with_positions_accepted(tmp_path):
    table = vehicles_table()
    leader = table.loc[table["car"] == "a", "pos"].to_numpy()
    follower = table["car"] == "b"
    table["gap"] = np.nan
    table.loc[follower, "gap"] = leader - table.loc[follower, "pos"].to_numpy() - 4.5
    mapping = {**VEHICLE_MAP, "length": "len", "gap": "gap"}
    traj = read(write_vehicles(tmp_path, table), format="columns", columns=mapping, dt=0.1)
    assert traj.flags.empty
    np.testing.assert_allclose(traj.vehicle("b")["gap"], table.loc[follower, "gap"])


# --- tracebacks ---------------------------------------------------------------------------------


def _openacc_with_spec(tmp_path, spec: bytes):
    write_openacc(tmp_path / "run.csv", openacc_table())
    (tmp_path / "Test_veh_specifications.csv").write_bytes(spec)
    return tmp_path


@case("traceback")
def openacc_spec_length_dash(tmp_path):
    folder = _openacc_with_spec(tmp_path, b"Model,Length(m)\nFord(S-Max),4.8\nKIA(Niro),-\n")
    refuses(
        r"specifications\.csv, row 3, column 'Length\(m\)': not a number: '-'", lambda: read(folder)
    )


@case("traceback")
def openacc_spec_not_utf8(tmp_path):
    folder = _openacc_with_spec(
        tmp_path, b"Model,Length(m)\nFord(S-Max),4.8\nKIA(Niro\xff\xfe),4.4\n"
    )
    refuses(r"specifications\.csv: cannot parse", lambda: read(folder))


@case("traceback")
def openacc_spec_with_lengths_used(tmp_path):
    folder = _openacc_with_spec(tmp_path, b"Model,Length(m)\nFord(S-Max),4.8\nKIA(Niro),4.4\n")
    traj = read(folder)
    assert traj.vehicle("run:1")["length"].eq(4.8).all()
    assert str(tmp_path / "Test_veh_specifications.csv") in traj.inputs


@case("traceback")
def interaction_way_to_missing_node(tmp_path):
    path = write_interaction(tmp_path, interaction_table(), osm_text(extra_way_ref=99))
    refuses(r"map\.osm: way 11 refers to node 99, which is not in the map", lambda: read(path))


@case("traceback")
def interaction_node_without_lat(tmp_path):
    path = write_interaction(tmp_path, interaction_table(), osm_text(drop_lat=3))
    refuses(r"map\.osm: node 3: lat is missing", lambda: read(path))


@case("traceback")
def interaction_map_not_xml(tmp_path):
    path = write_interaction(tmp_path, interaction_table(), "<osm><node id='1'\n")
    refuses(r"map\.osm: cannot read the lanelet2 map", lambda: read(path))


@case("traceback")
def interaction_node_lat_not_a_number(tmp_path):
    osm = osm_text(drop_lat=3).replace('<node id="3" lon="0">', '<node id="3" lat="north" lon="0">')
    path = write_interaction(tmp_path, interaction_table(), osm)
    refuses(r"node 3: lat is not a number: 'north'", lambda: read(path))


def _fifo(path):
    if not hasattr(os, "mkfifo"):
        pytest.skip("no named pipes on this platform")
    os.mkfifo(path)
    return path


@case("traceback")
def named_pipe_as_the_path(tmp_path):
    pipe = _fifo(tmp_path / "trajectories.csv")
    refuses(r"not a regular file", lambda: read(pipe), file=pipe)


@case("traceback")
def named_pipe_with_a_format(tmp_path):
    pipe = _fifo(tmp_path / "trajectories.csv")
    refuses(r"not a regular file", lambda: read(pipe, format="ngsim_raw"), file=pipe)


@case("traceback")
def named_pipe_in_an_openacc_folder(tmp_path):
    write_openacc(tmp_path / "run.csv", openacc_table())
    _fifo(tmp_path / "stuck.csv")
    traj = read(tmp_path, format="openacc")
    assert traj.scene_ids == ["run"]


@case("traceback")
def named_pipe_as_the_map(tmp_path):
    write_interaction(tmp_path, interaction_table())
    (tmp_path / "map.osm").unlink()
    pipe = _fifo(tmp_path / "map.osm")
    refuses(
        r"map\.osm: not a regular file",
        lambda: read(tmp_path / "vehicle_tracks_001.csv", format="interaction", map_path=pipe),
    )


# --- misleading errors -------------------------------------------------------------------------


def _shuffled(table: pd.DataFrame, seed: int) -> pd.DataFrame:
    return table.sample(frac=1.0, random_state=seed)


@case("misleading")
def ngsim_shuffled_rows_sorted(tmp_path):
    table = ngsim_table()
    traj = read(write_ngsim(tmp_path, _shuffled(table, 1)))
    repaired(traj, r"not in time order.*sorted by time")
    expected = table[table["Vehicle_ID"] == 2]
    np.testing.assert_allclose(
        traj.vehicle("trajectories-0400-0415:2")["x"], expected["Local_Y"] * FT
    )


@case("misleading")
def openacc_shuffled_rows_sorted(tmp_path):
    table = openacc_table()
    traj = read(write_openacc(tmp_path / "run.csv", _shuffled(table, 2)))
    repaired(traj, r"run\.csv: rows are not in time order")
    np.testing.assert_allclose(traj.vehicle("run:2")["gap"], table["IVS1"])
    np.testing.assert_allclose(traj.vehicle("run:2")["v"], table["Speed2"])


@case("misleading")
def chains_shuffled_rows_sorted(tmp_path):
    table = chain_table()
    traj = read(write_chain(tmp_path, _shuffled(table, 3)))
    repaired(traj, r"rows are not in time order")
    np.testing.assert_allclose(traj.vehicle("12")["v"], table["v2"])


@case("misleading")
def merge_shuffled_rows_sorted(tmp_path):
    table = merge_table(episodes=(4, 5))
    traj = read(write_merge(tmp_path, _shuffled(table, 4)))
    repaired(traj, r"not in episode and time order")
    np.testing.assert_allclose(
        traj.vehicle("ep5_ego")["v"], table.loc[table["episode"] == 5, "ego_v_mps"]
    )


@case("misleading")
def columns_shuffled_rows_sorted(tmp_path):
    table = vehicles_table()
    traj = columns(write_vehicles(tmp_path, _shuffled(table, 5)))
    repaired(traj, r"not in time order")
    np.testing.assert_allclose(traj.vehicle("a")["x"], table.loc[table["car"] == "a", "pos"])


@case("misleading")
def interaction_track_far_from_every_lanelet(tmp_path):
    table = interaction_table()
    table.loc[table["track_id"] == 2, "y"] += 500.0  # a map of another place, for one track
    path = write_interaction(tmp_path, table)
    message = refuses(
        r"row 42, columns 'x', 'y': track 2 lies 500 m from every lanelet of map\.osm",
        lambda: read(path),
        file=path,
    )
    assert "times as much" not in message


@case("misleading")
def ngsim_trailing_comma_on_data_rows(tmp_path):
    table = ngsim_table()
    path = write_ngsim(tmp_path, table)
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0]] + [line + "," for line in lines[1:]]) + "\n")
    traj = read(path)
    noted(traj, r"trailing delimiter")
    np.testing.assert_allclose(
        traj.vehicle("trajectories-0400-0415:1")["v"],
        table.loc[table["Vehicle_ID"] == 1, "v_Vel"] * FT,
    )


@case("misleading")
def ngsim_extra_field_names_the_row(tmp_path):
    path = write_ngsim(tmp_path, ngsim_table())
    lines = path.read_text().splitlines()
    lines[1:] = [line + "," for line in lines[1:]]
    lines[4] = lines[4] + "7"
    path.write_text("\n".join(lines) + "\n")
    refuses(r"row 5: 17 fields but the header has 16", lambda: read(path), file=path)


@case("misleading")
def chains_trailing_comma_on_every_line(tmp_path):
    table = chain_table()
    path = write_chain(tmp_path, table)
    path.write_text("\n".join(line + "," for line in path.read_text().splitlines()) + "\n")
    traj = read(path)
    np.testing.assert_allclose(traj.vehicle("11")["v"], table["v1"])


@case("misleading")
def ngsim_blank_line_then_trailing_commas(tmp_path):
    table = ngsim_table()
    path = write_ngsim(tmp_path, table)
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0], ""] + [line + "," for line in lines[1:]]) + "\n")
    traj = read(path)
    noted(traj, r"trailing delimiter")
    np.testing.assert_allclose(
        traj.vehicle("trajectories-0400-0415:2")["gap"],
        (table.loc[table["Vehicle_ID"] == 2, "Space_Headway"] - 15.0) * FT,
    )


@case("valid_refused")
def interaction_vehicle_crossing_into_the_next_lanelet(tmp_path):
    """x restarts in each lanelet (documented): the jump is not read as a unit error."""
    nodes = [(1, 0, 0), (2, 100, 0), (3, 0, 3.5), (4, 100, 3.5), (5, 200, 0), (6, 200, 3.5)]
    second = (
        '  <way id="12"><nd ref="2"/><nd ref="5"/></way>\n'
        '  <way id="13"><nd ref="4"/><nd ref="6"/></way>\n'
        '  <relation id="21"><member type="way" ref="13" role="left"/>'
        '<member type="way" ref="12" role="right"/><tag k="type" v="lanelet"/></relation>\n'
    )
    osm = osm_text(nodes=nodes).replace("</osm>", second + "</osm>")
    table = interaction_table(n=120)  # 10 m/s from x = 60-80 m: both cars pass x = 100 m
    traj = read(write_interaction(tmp_path, table, osm))
    assert set(traj.tracks["lane_id"]) == {20, 21}
    np.testing.assert_allclose(
        traj.vehicle("vehicle_tracks_001:1")["v"], table.loc[table["track_id"] == 1, "vx"]
    )


# --- valid files that were refused -------------------------------------------------------------


@case("valid_refused")
def ngsim_with_bom(tmp_path):
    table = ngsim_table()
    traj = read(write_ngsim(tmp_path, table, encoding="utf-8-sig"))
    assert len(traj.tracks) == len(table)


@case("valid_refused")
def openacc_with_bom_and_crlf(tmp_path):
    table = openacc_table()
    traj = read(write_openacc(tmp_path / "run.csv", table, newline="\r\n", bom=True))
    np.testing.assert_allclose(traj.vehicle("run:1")["v"], table["Speed1"])


@case("valid_refused")
def chains_with_bom(tmp_path):
    traj = read(write_chain(tmp_path, chain_table(), encoding="utf-8-sig"))
    assert sorted(traj.vehicle_ids) == ["11", "12", "13"]


@case("valid_refused")
def ngsim_tab_separated(tmp_path):
    table = ngsim_table()
    path = write_ngsim(tmp_path, table, name="trajectories.tsv", sep="\t")
    assert detect_format(path)[0] == "ngsim_raw"
    traj = read(path)
    np.testing.assert_allclose(traj.tracks["length"].unique() / FT, [15.0, 14.0])


@case("valid_refused")
def columns_tab_separated(tmp_path):
    table = vehicles_table()
    traj = columns(write_vehicles(tmp_path, table, sep="\t"))
    np.testing.assert_allclose(traj.vehicle("b")["v"], table.loc[table["car"] == "b", "speed"])


@case("valid_refused")
def chains_tab_separated(tmp_path):
    traj = read(write_chain(tmp_path, chain_table(), sep="\t"), format="ngsim_chains")
    assert len(traj.tracks) == 240


@case("valid_refused")
def ngsim_dat_extension(tmp_path):
    path = write_ngsim(tmp_path, ngsim_table(), name="trajectories-0400-0415.dat")
    assert detect_format(path)[0] == "ngsim_raw"
    assert len(read(path).tracks) == 200


@case("valid_refused")
def chains_dat_extension(tmp_path):
    path = write_chain(tmp_path, chain_table(), name="11_12_13.dat")
    assert detect_format(path)[0] == "ngsim_chains"
    assert len(read(path).tracks) == 240


@case("valid_refused")
def openacc_dat_extension(tmp_path):
    path = write_openacc(tmp_path / "run.dat", openacc_table())
    assert detect_format(path)[0] == "openacc"
    assert len(read(path).tracks) == 600


@case("valid_refused")
def ngsim_blank_lines(tmp_path):
    path = write_ngsim(tmp_path, ngsim_table())
    lines = path.read_text().splitlines()
    lines.insert(5, "")
    path.write_text("\n".join(lines) + "\n\n")
    traj = read(path)
    assert len(traj.tracks) == 200
    noted(traj, r"blank line\(s\) skipped \(line\(s\) 6")
    assert not traj.repairs


@case("valid_refused")
def openacc_blank_line(tmp_path):
    path = write_openacc(tmp_path / "run.csv", openacc_table())
    lines = path.read_text().splitlines()
    lines.insert(20, "")
    path.write_text("\n".join(lines) + "\n")
    assert len(read(path).tracks) == 600


@case("valid_refused")
def merge_blank_line(tmp_path):
    path = write_merge(tmp_path, merge_table())
    lines = path.read_text().splitlines()
    lines.insert(3, "")
    path.write_text("\n".join(lines) + "\n")
    traj = read(path)
    assert len(traj.vehicle("ep4_ego")) == 60


@case("valid_refused")
def openacc_zalazone_file_on_its_own(tmp_path):
    table = openacc_table().rename(columns={"Speed2": "Speed5", "E2": "E5", "N2": "N5"})
    table = table.drop(columns=["IVS1", "Driver1", "Driver2"])
    meta = ["Date,8,10,2019,", "Vehicle_order,SMART,BMW,AUDI,TESLA,MAZDA,", "ACC,1,"]
    folder = tmp_path / "dynamic"
    folder.mkdir()
    path = write_openacc(folder / "dynamic_part26.csv", table, meta=meta, newline="\r\n")
    assert detect_format(path)[0] == "openacc"
    traj = read(path)
    assert traj.vehicle_ids == ["dynamic_part26:1", "dynamic_part26:5"]
    np.testing.assert_allclose(traj.vehicle("dynamic_part26:5")["v"], table["Speed5"])


@case("valid_refused")
def openacc_many_metadata_rows_without_date(tmp_path):
    meta = [*OPENACC_META[1:], *(f"Comment,{i}" for i in range(15))]  # header on line 20
    path = write_openacc(tmp_path / "run.csv", openacc_table(), meta=meta)
    assert detect_format(path)[0] == "openacc"


# --- silent drops -----------------------------------------------------------------------------------


@case("silent_drop")
def openacc_folder_csv_with_wrong_header_is_noted(tmp_path):
    write_openacc(tmp_path / "run.csv", openacc_table())
    (tmp_path / "other.csv").write_text("time,Speed1\n0,1\n")
    traj = read(tmp_path, format="openacc")
    noted(traj, r"1 CSV file\(s\) without an OpenACC header row.*skipped: other\.csv")


@case("silent_drop")
def openacc_folder_nested_wrong_header_is_noted(tmp_path, caplog):
    write_openacc(tmp_path / "run.csv", openacc_table())
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "log.csv").write_text("a,b\n1,2\n")
    with caplog.at_level(logging.WARNING):
        read(tmp_path, format="openacc")
    assert "sub/log.csv" in caplog.text


@case("silent_drop")
def follower_arrays_names_vehicles_left_out(tmp_path, caplog):
    table = ngsim_table(ids=(1, 2, 3))
    traj = read(write_ngsim(tmp_path, table))
    with caplog.at_level(logging.WARNING):
        arrays = follower_arrays(traj, window="all")
    assert len(arrays.vehicle_ids) == 2
    assert "1 of 3 vehicle(s)" in caplog.text and "trajectories-0400-0415:1" in caplog.text


@case("silent_drop")
def follower_arrays_requested_vehicle_without_leader(tmp_path, caplog):
    traj = read(write_ngsim(tmp_path, ngsim_table()))
    with caplog.at_level(logging.WARNING):
        arrays = follower_arrays(traj, window="fit", vehicle_ids=traj.vehicle_ids)
    assert arrays.vehicle_ids == ("trajectories-0400-0415:2",)
    assert "left out: trajectories-0400-0415:1" in caplog.text


@case("silent_drop")
def openacc_missing_speed_samples_are_a_repair(tmp_path):
    table = openacc_table()
    table.loc[290:, ["Speed2", "E2", "IVS1"]] = np.nan
    traj = read(write_openacc(tmp_path / "run.csv", table))
    repaired(traj, r"vehicle 2 not measured in 10 sample")


# --- messages -----------------------------------------------------------------------------------


@case("message")
def negative_speed_in_file_units(tmp_path):
    table = ngsim_table()
    table.loc[7, "v_Vel"] = -10.05
    path = write_ngsim(tmp_path, table)
    message = refuses(
        r"row 9, column 'v_Vel': negative speed -10\.05 \(= -3\.063 in SI", lambda: read(path)
    )
    assert "np." not in message


@case("message")
def missing_leader_suggests_existing_option(tmp_path):
    table = ngsim_table()
    table = table[~((table["Vehicle_ID"] == 1) & (table["Frame_ID"] == 120))]
    path = write_ngsim(tmp_path, table)
    message = refuses(r"leader 1 has no row at frame 120", lambda: read(path))
    assert "missing_leaders='drop'" in message and "--missing" not in message
    traj = read(path, missing_leaders="drop")
    repaired(traj, r"1 row\(s\) name a leader that is not in the file")


@case("message")
def off_grid_time_plain_number(tmp_path):
    table = openacc_table()
    table.loc[10, "Time"] = 4001.05
    path = write_openacc(tmp_path / "run.csv", table)
    refuses(r"row 17, column 'Time': time 4001\.05 is not on the 0\.1 s grid", lambda: read(path))


@case("message")
def too_fast_message_shows_file_value(tmp_path):
    table = ngsim_table()
    table.loc[3, "v_Vel"] = 300.0
    path = write_ngsim(tmp_path, table)
    refuses(
        r"row 5, column 'v_Vel': speed 300 \(= 91\.44 in SI units\) is above 70 m/s",
        lambda: read(path),
    )


def test_the_corpus_covers_every_class():
    classes = Counter(p.id.split("-")[0] for p in CASES)
    assert len(CASES) >= 80, classes
    assert min(classes.values()) >= 3, classes


@pytest.mark.parametrize("run", CASES)
def test_bad_input(run, tmp_path, caplog):
    if "caplog" in run.__code__.co_varnames[: run.__code__.co_argcount]:
        run(tmp_path, caplog)
    else:
        run(tmp_path)
