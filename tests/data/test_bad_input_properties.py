"""Property tests of the readers' handling of bad input: each mutation of a valid file has a stated
expected outcome, checked against the figures the builder put in (never against the reader's own
output on other data). CI runs them derandomized (the ``ci`` profile in conftest.py)."""

from __future__ import annotations

import numpy as np
import pytest
from bad_inputs import FT, ngsim_table, write_ngsim
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers import read

PROPERTY = settings(
    max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
N = 40
STEM = "trajectories-0400-0415"


def _read(tmp_path, table, name="trajectories-0400-0415.csv"):
    return read(write_ngsim(tmp_path, table, name=name))


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1))
def test_any_row_order_reads_as_the_sorted_file(tmp_path, seed):
    """Mutation: rows permuted. Expected: the same tracks as the file in order; a repair is
    recorded exactly when some vehicle's rows are out of time order."""
    table = ngsim_table(n=N)
    shuffled = table.sample(frac=1.0, random_state=seed)
    traj = _read(tmp_path, shuffled)
    for vehicle in (1, 2):
        own = table[table["Vehicle_ID"] == vehicle]
        got = traj.vehicle(f"{STEM}:{vehicle}")
        np.testing.assert_allclose(got["x"], own["Local_Y"] * FT)
        np.testing.assert_allclose(got["t"], own["Frame_ID"] * 0.1)
    out_of_order = (shuffled.groupby("Vehicle_ID")["Frame_ID"].diff() < 0).any()
    assert bool(traj.repairs) == bool(out_of_order)


@PROPERTY
@given(factor=st.one_of(st.floats(1.06, 5.0), st.floats(0.2, 0.94)))
def test_positions_in_another_unit_than_speeds_are_refused(tmp_path, factor):
    """Mutation: Local_Y scaled by a unit-like factor (0.2-0.94 or 1.06-5: km/h read as ft/s gives
    0.91). Expected: refused, naming Local_Y and the ratio of increments to speed x dt."""
    table = ngsim_table(n=N)
    table["Local_Y"] *= factor
    table["Space_Headway"] *= factor
    table["v_Length"] = 15.0  # lengths stay plausible: only positions changed unit
    with pytest.raises(DataError, match=r"column 'Local_Y'.*positions advance ([\d.]+) times") as e:
        _read(tmp_path, table)
    ratio = float(e.value.args[0].split("positions advance ")[1].split(" times")[0])
    assert ratio == pytest.approx(factor, abs=0.006)  # the message rounds to 2 decimals


@PROPERTY
@given(factor=st.floats(0.96, 1.04))
def test_positions_within_four_percent_of_speeds_are_accepted(tmp_path, factor):
    """Mutation: Local_Y scaled by 0.96-1.04 (a calibration error, no unit mix-up). Expected: read,
    positions as written (the negative control of the property above)."""
    table = ngsim_table(n=N)
    table["Local_Y"] = table["Local_Y"] * factor
    table["Space_Headway"] = table["Space_Headway"] * factor
    traj = _read(tmp_path, table)
    np.testing.assert_allclose(traj.tracks["x"].max(), table["Local_Y"].max() * FT)


@PROPERTY
@given(ids=st.lists(st.integers(10**14, 10**30), min_size=2, max_size=3, unique=True))
def test_long_integer_ids_come_back_exactly(tmp_path, ids):
    """Mutation: vehicle ids of 15-31 digits (beyond float precision). Expected: every id back
    as its exact decimal text, leaders too; no two vehicles merged."""
    traj = _read(tmp_path, ngsim_table(n=N, ids=tuple(ids)))
    assert sorted(traj.vehicle_ids) == sorted(f"{STEM}:{i}" for i in ids)
    follower = traj.vehicle(f"{STEM}:{ids[1]}")
    assert follower["leader_id"].eq(f"{STEM}:{ids[0]}").all()


@PROPERTY
@given(row=st.integers(0, 2 * N - 1), fraction=st.floats(0.01, 0.99))
def test_a_fractional_frame_is_refused_naming_its_row(tmp_path, row, fraction):
    """Mutation: one Frame_ID given a fractional part. Expected: refused, naming that file row
    (header is line 1) and column Frame_ID."""
    table = ngsim_table(n=N)
    table["Frame_ID"] = table["Frame_ID"].astype(float)
    table.loc[row, "Frame_ID"] += fraction
    with pytest.raises(DataError, match=rf"row {row + 2}, column 'Frame_ID': .* is not a whole"):
        _read(tmp_path, table)


@PROPERTY
@given(step=st.sampled_from([1, 2, 3, 5]))
def test_the_sampling_rate_is_found_from_the_frames(tmp_path, step):
    """Mutation: frames every ``step`` frames (10, 5, 3.3, 2 Hz). Expected: dt = step x 0.1 s,
    noted when step > 1; the recorded times are the frames x 0.1 s."""
    table = ngsim_table(n=N, frame_step=step)
    traj = _read(tmp_path, table)
    assert traj.dt == pytest.approx(0.1 * step)
    assert any("sampled every" in n for n in traj.notes) == (step > 1)
    np.testing.assert_allclose(np.unique(traj.tracks["t"]), np.unique(table["Frame_ID"]) * 0.1)


@PROPERTY
@given(lines=st.lists(st.integers(1, 2 * N), min_size=1, max_size=4))
def test_blank_lines_anywhere_change_nothing(tmp_path, lines):
    """Mutation: blank lines inserted between data rows. Expected: the same tracks as without,
    the blank lines noted (not a repair: no data changed)."""
    table = ngsim_table(n=N)
    path = write_ngsim(tmp_path, table)
    text = path.read_text().splitlines()
    for line in sorted(lines, reverse=True):
        text.insert(line + 1, "")
    path.write_text("\n".join(text) + "\n")
    traj = read(path)
    np.testing.assert_allclose(
        traj.vehicle(f"{STEM}:2")["v"], table.loc[table["Vehicle_ID"] == 2, "v_Vel"] * FT
    )
    assert any("blank line" in n for n in traj.notes) and not traj.repairs
