"""Readers on small temporary files: NGSIM raw as the main vehicle for bad inputs, the format
detection and strict mode of ``read``, and property tests (round trip, NaN injection)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers import FORMATS, detect_format, read
from bayesdrive.data.readers.columns import read_columns
from bayesdrive.data.readers.ngsim_raw import COLUMNS, read_ngsim_raw
from bayesdrive.data.units import FOOT_M

FT = FOOT_M


def ngsim_table(n_frames: int = 6, *, lane_change: bool = False) -> pd.DataFrame:
    """Two cars in lane 2, car 2 following car 1 (feet, ft/s); optionally a third car."""
    rows = []
    for vehicle, y0, length, preceding in ((1, 300.0, 15.0, 0), (2, 250.0, 14.0, 1)):
        for k in range(n_frames):
            y = y0 + 40.0 * 0.1 * k
            rows.append(
                {
                    "Vehicle_ID": vehicle,
                    "Frame_ID": 100 + k,
                    "Total_Frames": n_frames,
                    "Global_Time": 1_113_433_135_300 + 100 * k,
                    "Local_X": 18.0,
                    "Local_Y": y,
                    "v_Length": length,
                    "v_Width": 6.0,
                    "v_Class": 2,
                    "v_Vel": 40.0,
                    "v_Acc": 1.5 if vehicle == 2 else 0.0,
                    "Lane_ID": 2,
                    "Preceding": preceding,
                    "Following": 2 if vehicle == 1 else 0,
                    "Space_Headway": 50.0 if preceding else 0.0,
                    "Time_Headway": 1.25 if preceding else 0.0,
                }
            )
    table = pd.DataFrame(rows, columns=COLUMNS)
    if lane_change:
        # Car 2 changes to lane 3 for the last two frames, behind car 3 there.
        third = table[table["Vehicle_ID"] == 1].copy()
        third["Vehicle_ID"] = 3
        third["Local_Y"] += 30.0
        third["Lane_ID"] = 3
        table = pd.concat([table, third], ignore_index=True)
        late = (table["Vehicle_ID"] == 2) & (table["Frame_ID"] >= 100 + n_frames - 2)
        table.loc[late, ["Lane_ID", "Preceding", "Space_Headway"]] = [3, 3, 80.0]
    return table


def write(tmp_path, table: pd.DataFrame, name: str = "trajectories-0400-0415.csv"):
    path = tmp_path / name
    table.to_csv(path, index=False)
    return path


# --- NGSIM raw: what it reads -------------------------------------------------------------


def test_ngsim_raw_converts_feet_and_front_to_front_headway(tmp_path):
    path = write(tmp_path, ngsim_table())
    traj = read(path)
    assert traj.format == "ngsim_raw"
    assert traj.dt == pytest.approx(0.1)
    car2 = traj.vehicle("trajectories-0400-0415:2")
    first = car2.iloc[0]
    assert first["t"] == pytest.approx(10.0)  # Frame_ID 100 at 10 Hz
    assert first["x"] == pytest.approx(250.0 * FT)
    assert first["v"] == pytest.approx(40.0 * FT)
    assert first["a"] == pytest.approx(1.5 * FT)
    assert first["length"] == pytest.approx(14.0 * FT)
    assert first["leader_id"] == "trajectories-0400-0415:1"
    # Space_Headway is front to front: bumper gap = 50 ft - the LEADER's 15 ft.
    assert first["gap"] == pytest.approx((50.0 - 15.0) * FT)
    assert first["lane_id"] == 2
    assert set(traj.tracks["driver"]) == {"unknown"}
    assert traj.scene_ids == ["trajectories-0400-0415"]


def test_ngsim_raw_leader_is_per_row_through_a_lane_change(tmp_path):
    traj = read(write(tmp_path, ngsim_table(lane_change=True)))
    car2 = traj.vehicle("trajectories-0400-0415:2")
    assert list(car2["leader_id"].str.split(":").str[1]) == ["1"] * 4 + ["3"] * 2
    assert list(car2["lane_id"]) == [2] * 4 + [3] * 2
    assert car2["gap"].iloc[-1] == pytest.approx((80.0 - 15.0) * FT)


def test_ngsim_raw_headerless_txt_with_the_published_column_order(tmp_path):
    table = ngsim_table()
    table.insert(6, "Global_X", 6_042_000.0)
    table.insert(7, "Global_Y", 2_133_000.0)
    path = tmp_path / "trajectories-0400-0415.txt"
    table.to_csv(path, sep=" ", header=False, index=False)
    assert detect_format(path)[0] == "ngsim_raw"
    traj = read(path)
    assert traj.vehicle("trajectories-0400-0415:2")["gap"].iloc[0] == pytest.approx(35.0 * FT)


def test_ngsim_raw_matches_column_names_case_insensitively(tmp_path):
    table = ngsim_table().rename(columns={"v_Length": "v_length", "Local_Y": "LOCAL_Y"})
    traj = read(write(tmp_path, table))
    assert traj.tracks["length"].max() == pytest.approx(15.0 * FT)


# --- bad inputs: every error names file, row and column --------------------------------------


def test_a_vehicles_rows_are_its_rows_in_time_order_and_an_unknown_id_is_named(tmp_path):
    traj = read_ngsim_raw(write(tmp_path, ngsim_table(lane_change=True)))
    for vehicle in traj.vehicle_ids:
        expected = traj.tracks[traj.tracks["vehicle_id"] == vehicle]
        pd.testing.assert_frame_equal(traj.vehicle(vehicle), expected)
        assert expected["t"].is_monotonic_increasing
    with pytest.raises(KeyError, match="no vehicle '9'"):
        traj.vehicle("9")
    # A subset finds its own rows, not the positions of the data it came from.
    last = traj.vehicle_ids[-1]
    pd.testing.assert_frame_equal(
        traj.subset([last]).vehicle(last), traj.vehicle(last).reset_index(drop=True)
    )


def test_missing_column_is_named(tmp_path):
    path = write(tmp_path, ngsim_table().drop(columns=["Local_Y"]))
    with pytest.raises(DataError, match=r"missing column\(s\) Local_Y") as err:
        read(path, format="ngsim_raw")
    assert str(path) in str(err.value)


def test_nan_names_file_row_and_column(tmp_path):
    table = ngsim_table()
    table.loc[3, "v_Vel"] = np.nan
    path = write(tmp_path, table)
    with pytest.raises(DataError, match=r"row 5, column 'v_Vel'.*NaN") as err:
        read(path)
    assert str(path) in str(err.value)


def test_text_in_a_number_column_is_named(tmp_path):
    table = ngsim_table().astype({"Local_Y": object})
    table.loc[7, "Local_Y"] = "12,5ft"
    path = write(tmp_path, table)
    with pytest.raises(DataError, match=r"row 9, column 'Local_Y': not a number"):
        read(path)


def test_duplicate_frame_names_row(tmp_path):
    table = ngsim_table()
    table = pd.concat([table.iloc[:3], table.iloc[[2]], table.iloc[3:]], ignore_index=True)
    with pytest.raises(DataError, match=r"row 5, column 'Frame_ID': duplicate frame"):
        read(write(tmp_path, table))


def test_rows_out_of_time_order_are_sorted_as_a_logged_repair(tmp_path):
    table = ngsim_table()
    swapped = table.copy()
    swapped.loc[[2, 3]] = table.loc[[3, 2]].to_numpy()
    traj = read(write(tmp_path, swapped))
    assert any("not in time order" in r and "row 5" in r for r in traj.repairs)
    in_order = read(write(tmp_path, table, name="in_order.csv"))
    np.testing.assert_array_equal(traj.tracks["x"], in_order.tracks["x"])
    np.testing.assert_array_equal(traj.tracks["t"], in_order.tracks["t"])


def test_empty_file_and_header_only(tmp_path):
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(DataError, match="empty file"):
        read(empty, format="ngsim_raw")
    header_only = tmp_path / "header.csv"
    header_only.write_text(",".join(COLUMNS) + "\n")
    with pytest.raises(DataError, match="no data rows"):
        read(header_only, format="ngsim_raw")


def test_leader_naming_no_vehicle_is_an_error_unless_dropped(tmp_path):
    table = ngsim_table()
    table.loc[table["Vehicle_ID"] == 2, "Preceding"] = 99
    path = write(tmp_path, table)
    with pytest.raises(DataError, match=r"row 8, column 'Preceding': leader 99") as err:
        read(path)
    assert str(path) in str(err.value)
    traj = read(path, missing_leaders="drop")
    assert traj.tracks["leader_id"].isna().all()
    assert any(n.startswith("repair: ") and "leader" in n for n in traj.notes)
    with pytest.raises(DataError, match="strict mode refuses data that needed 1 repair"):
        read(path, strict=True, missing_leaders="drop")


def test_wrong_format_passed_explicitly_names_expected_columns(tmp_path):
    path = write(tmp_path, ngsim_table())
    with pytest.raises(DataError, match=r"not an OpenACC file.*Time.*Speed1"):
        read(path, format="openacc")
    with pytest.raises(DataError, match=r"not a NGSIM chain.*missing column\(s\) t1"):
        read(path, format="ngsim_chains")
    with pytest.raises(DataError, match=r"unknown format 'nope'; known formats: ngsim_raw"):
        read(path, format="nope")


def test_feet_passed_as_metres_is_refused_by_length(tmp_path):
    table = ngsim_table()
    path = write(tmp_path, table, "vehicles.csv")
    columns = {"vehicle_id": "Vehicle_ID", "t": "Frame_ID", "x": "Local_Y", "v": "v_Vel"}
    with pytest.raises(DataError, match=r"row 2, column 'length'.*are these feet"):
        read_columns(path, {**columns, "length": "v_Length"}, units="m", time_factor=0.1)
    traj = read_columns(path, {**columns, "length": "v_Length"}, units="ft", time_factor=0.1)
    assert traj.tracks["length"].max() == pytest.approx(15.0 * FT)


def test_feet_passed_as_metres_is_refused_by_jam_spacing(tmp_path):
    # A stopped queue 25 ft apart front to front, without lengths (4.5 m assumed): in "metres"
    # that is a 25 m jam spacing, which only feet explain.
    rows = [
        {"id": car, "t": 0.1 * k, "x": 1000.0 - 25.0 * car, "v": 0.0, "lead": car - 1}
        for car in range(1, 5)
        for k in range(5)
    ]
    path = write(tmp_path, pd.DataFrame(rows), "queue.csv")
    columns = {"vehicle_id": "id", "t": "t", "x": "x", "v": "v", "leader_id": "lead"}
    with pytest.raises(DataError, match=r"column 'gap'.*spacing of 25.0.*feet"):
        read_columns(path, columns, units="m", dt=0.1)
    traj = read_columns(path, columns, units="ft", dt=0.1)
    assert traj.tracks["gap"].dropna().iloc[0] == pytest.approx(25.0 * FT - 4.5)


def test_time_off_the_grid_names_row(tmp_path):
    table = pd.DataFrame({"id": 1, "t": [0.0, 0.1, 0.25, 0.3], "x": [0, 1, 2, 3], "v": 10.0})
    path = write(tmp_path, table, "cars.csv")
    with pytest.raises(DataError, match=r"row 4, column 't'.*not on the 0.1 s grid"):
        read_columns(path, {"vehicle_id": "id", "t": "t", "x": "x", "v": "v"}, dt=0.1)


def test_detection_failure_lists_known_formats_and_what_was_seen(tmp_path):
    path = tmp_path / "mystery.csv"
    path.write_text("alpha,beta\n1,2\n")
    with pytest.raises(DataError, match=r"cannot tell the format.*alpha,beta.*ngsim_raw, "):
        read(path)
    with pytest.raises(DataError, match="cannot tell the format of this folder"):
        read(tmp_path)
    with pytest.raises(DataError, match="no such file or folder"):
        read(tmp_path / "absent.csv")


def test_strict_turns_negative_gaps_into_an_error(tmp_path):
    table = ngsim_table()
    table.loc[(table["Vehicle_ID"] == 2) & (table["Frame_ID"] == 102), "Space_Headway"] = 10.0
    path = write(tmp_path, table)
    traj = read(path)
    # Space_Headway now contradicts the positions too (10 ft against 50 ft): both flags, one sample.
    assert sorted(traj.flags["kind"]) == ["gap_mismatch", "negative_gap"]
    assert traj.flags["t"].tolist() == pytest.approx([10.2, 10.2])
    with pytest.raises(DataError, match=r"strict mode refuses flagged data: 1 gap_mismatch"):
        read(path, strict=True)


def test_registry_format_names_are_readers():
    for name in ("openacc_extract", "ngsim_pairs", "ngsim_parquet", "ngsim_matrices"):
        assert callable(FORMATS[name])


# --- properties ------------------------------------------------------------------------------

PROPERTY_SETTINGS = settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@st.composite
def ngsim_tables(draw) -> pd.DataFrame:
    """A valid NGSIM table: 1-3 cars in one lane over the same frames, each following the one
    ahead, in feet; positions advance by speed x dt, Space_Headway is the front-to-front distance
    of the positions, speeds above jam speed, car lengths."""
    cars = draw(st.integers(1, 3))
    frames = draw(st.integers(2, 12))
    first_frame = draw(st.integers(1, 5000))
    finite = {"allow_nan": False, "allow_infinity": False}
    lengths = [draw(st.floats(9.0, 24.0, **finite)) for _ in range(cars)]
    spacings = [draw(st.floats(60.0, 300.0, **finite)) for _ in range(cars)]
    rows = []
    front = 2000.0
    fronts = []
    for car in range(cars):
        front -= spacings[car]
        speeds = np.array([draw(st.floats(40.0, 60.0, **finite)) for _ in range(frames)])
        y = front + np.r_[0.0, np.cumsum(0.05 * (speeds[1:] + speeds[:-1]))]
        fronts.append(y)
        for k in range(frames):
            rows.append(
                {
                    "Vehicle_ID": car + 1,
                    "Frame_ID": first_frame + k,
                    "Total_Frames": frames,
                    "Global_Time": 1_113_433_000_000 + 100 * (first_frame + k),
                    "Local_X": draw(st.floats(0.0, 80.0, **finite)),
                    "Local_Y": y[k],
                    "v_Length": lengths[car],
                    "v_Width": 6.0,
                    "v_Class": 2,
                    "v_Vel": speeds[k],
                    "v_Acc": draw(st.floats(-11.2, 11.2, **finite)),
                    "Lane_ID": 1,
                    "Preceding": car,  # 0 for the first car: no leader
                    "Following": car + 2 if car + 1 < cars else 0,
                    "Space_Headway": fronts[car - 1][k] - y[k] if car else 0.0,
                    "Time_Headway": 0.0,
                }
            )
    table = pd.DataFrame(rows, columns=COLUMNS)
    # Any interleaving of cars is valid as long as each car's frames stay in order.
    return table.sort_values(["Frame_ID", "Vehicle_ID"] if draw(st.booleans()) else ["Vehicle_ID"])


@PROPERTY_SETTINGS
@given(table=ngsim_tables())
def test_property_ngsim_round_trip_to_si(tmp_path, table):
    path = tmp_path / "prop.csv"
    table.to_csv(path, index=False, float_format="%.17g")
    traj = read_ngsim_raw(path)
    expected = table.sort_values(["Vehicle_ID", "Frame_ID"]).reset_index(drop=True)
    got = traj.tracks.sort_values(["vehicle_id", "t"], key=_natural).reset_index(drop=True)
    assert list(got["vehicle_id"]) == [f"prop:{v}" for v in expected["Vehicle_ID"]]
    np.testing.assert_allclose(got["t"], expected["Frame_ID"] * 0.1, rtol=1e-12)
    for column, source in (
        ("x", "Local_Y"),
        ("v", "v_Vel"),
        ("a", "v_Acc"),
        ("length", "v_Length"),
    ):
        np.testing.assert_allclose(got[column], expected[source] * FT, rtol=1e-12, atol=1e-12)
    leader_length = expected["Preceding"].map(expected.groupby("Vehicle_ID")["v_Length"].first())
    gap = ((expected["Space_Headway"] - leader_length) * FT).where(expected["Preceding"] > 0)
    np.testing.assert_allclose(got["gap"], gap, rtol=1e-9, atol=1e-9)
    assert got["leader_id"].isna().tolist() == (expected["Preceding"] == 0).tolist()


def _natural(column: pd.Series) -> pd.Series:
    """Sort 'prop:10' after 'prop:9' (ids carry numbers)."""
    if column.name == "vehicle_id":
        return column.str.split(":").str[1].astype(int)
    return column


@PROPERTY_SETTINGS
@given(table=ngsim_tables(), data=st.data())
def test_property_nan_anywhere_raises_naming_the_row(tmp_path, table, data):
    table = table.reset_index(drop=True).astype(float)
    row = data.draw(st.integers(0, len(table) - 1))
    column = data.draw(st.sampled_from(COLUMNS))
    table.loc[row, column] = np.nan
    path = tmp_path / "corrupt.csv"
    table.to_csv(path, index=False)
    with pytest.raises(DataError) as err:
        read_ngsim_raw(path)
    assert f"row {row + 2}" in str(err.value)
    assert column in str(err.value)
