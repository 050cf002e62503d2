"""Every result names its input: the sha256 of each file read and the repairs made to the data
(issue 14, item 3). Checksums are computed here from the bytes, not taken from the reader."""

from __future__ import annotations

import hashlib

import jax
from bad_inputs import ngsim_table, openacc_table, write_ngsim, write_openacc

from bayesdrive.data.readers import read
from bayesdrive.inference.core.output import load_result, metadata, save_result
from bayesdrive.inference.fit import fit, summary


def sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_trajectories_record_a_checksum_of_every_input_file(tmp_path):
    first = write_openacc(tmp_path / "a.csv", openacc_table())
    second = write_openacc(tmp_path / "b.csv", openacc_table(n=200))
    spec = tmp_path / "Test_veh_specifications.csv"
    spec.write_text("Model,Length(m)\nFord(S-Max),4.8\n")
    traj = read(tmp_path, format="openacc")
    assert traj.inputs == {str(p): sha256(p) for p in (first, second, spec)}
    assert traj.repairs == []


def test_a_fit_records_input_checksums_and_repairs(tmp_path):
    table = ngsim_table(n=60)
    path = write_ngsim(tmp_path, table.sample(frac=1.0, random_state=3))  # rows out of order
    traj = read(path)
    assert len(traj.repairs) == 1 and "sorted by time" in traj.repairs[0]
    # lm, the cheapest engine to compile: every engine's result gets its metadata alike.
    tree = fit(
        jax.random.key(0),
        traj,
        engine="lm",
        params=("v_des",),
        num_particles=64,
        window="all",
        seed=0,
    )
    saved = tmp_path / "result.nc"
    save_result(tree, saved)
    for meta in (metadata(tree), metadata(load_result(saved)), summary(tree)):
        assert meta["input_sha256"] == {str(path): sha256(path)}
        assert meta["input_repairs"] == traj.repairs
