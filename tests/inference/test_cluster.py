"""``fit --cluster``: the same bits as the plain fit, and an interrupted run resumes (issue 17);
``evaluate --cluster`` and ``criticize --cluster``: the same numbers as the plain runs.

Real data (four followers of an NGSIM I-80 chain, smc with 64 particles, seed 0). One 2-worker
``LocalCluster`` made by :func:`~bayesdrive.inference.distributed.open_cluster` (``local:2``,
workers pinned to a core) serves every cluster run through its address (``--cluster tcp://...``),
so its workers compile the smc kernel once and later runs reuse it; ``--cluster local:2`` itself
differs only in who opens that cluster. Checks, all exact (no tolerance: the claim is bit
identity): with ``--chunk-size 2`` every group of result.nc equals the plain run's, and the
metadata differs only in creation time and timings; a folder left as a killed run leaves it (the
staging folder, manifest not complete, one of two chunk files) resumes, leaves the finished chunk
untouched (same inode and modification time), fits the other and ends with the same bits.
Negative control: seed 1 on the cluster gives other posterior draws, so the comparison can fail.

The cluster runs are in the ``extended`` tier (CI leaves them out for time, reports/ci_time.md);
the refusals of bad cluster options, which start no cluster, run in CI.
"""

from __future__ import annotations

import json
import os
import shutil

import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.data.outputs import MANIFEST, staging_path
from bayesdrive.inference import distributed
from bayesdrive.inference.core.output import RUN_DEPENDENT_ATTRS, load_result, metadata

pytest.importorskip("distributed")

CHAIN = "ngsim_i80_chains/124_136_140_146_162_164.csv"
runner = CliRunner()


@pytest.fixture(scope="module")
def address():
    with distributed.open_cluster("local:2") as client:
        yield client.scheduler.address


@pytest.fixture(scope="module")
def plain(data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("plain") / "fit"
    _fit(data_dir, out)
    return load_result(out / "result.nc")


def _fit(data_dir, out, *extra: str) -> None:
    args = ["fit", str(data_dir / CHAIN), "--particles", "64", "--vehicles", "4"]
    result = runner.invoke(app, [*args, *extra, "--out", str(out)])
    assert result.exit_code == 0, result.output


def _assert_same_bits(tree, plain) -> None:
    assert set(tree.children) == set(plain.children)
    for group in plain.children:
        assert tree[group].to_dataset().identical(plain[group].to_dataset()), group
    ours, theirs = metadata(tree), metadata(plain)
    for name in RUN_DEPENDENT_ATTRS:
        ours.pop(name), theirs.pop(name)
    assert ours == theirs


@pytest.mark.extended
@pytest.mark.realdata
def test_cluster_fit_is_bit_identical_and_resumes(data_dir, tmp_path, address, plain, monkeypatch):
    # Chunk files stay after the run here, to build the interrupted folder from them.
    monkeypatch.setattr(distributed, "remove_chunks", lambda folder: None)
    cluster = ["--cluster", address, "--chunk-size", "2"]
    out = tmp_path / "cluster"
    _fit(data_dir, out, *cluster)
    _assert_same_bits(load_result(out / "result.nc"), plain)
    chunks = out / "chunks"
    assert sorted(p.name for p in chunks.iterdir()) == [
        "chunk-0000.nc",
        "chunk-0001.nc",
        "index.json",
    ]

    # A killed run: its staging folder with an incomplete manifest and only the first chunk.
    resumed = tmp_path / "resumed"
    staging = staging_path(resumed)
    shutil.copytree(out, staging)
    for name in ("result.nc", "summary.json", "chunks/chunk-0001.nc"):
        (staging / name).unlink()
    manifest = json.loads((staging / MANIFEST).read_text())
    manifest["complete"] = False
    del manifest["files"]
    (staging / MANIFEST).write_text(json.dumps(manifest))
    kept = os.stat(staging / "chunks" / "chunk-0000.nc")

    _fit(data_dir, resumed, *cluster)
    assert not staging.exists()
    again = os.stat(resumed / "chunks" / "chunk-0000.nc")
    assert (again.st_ino, again.st_mtime_ns) == (kept.st_ino, kept.st_mtime_ns)
    assert (resumed / "chunks" / "chunk-0001.nc").is_file()
    _assert_same_bits(load_result(resumed / "result.nc"), plain)


@pytest.mark.extended
@pytest.mark.realdata
def test_other_seed_differs_and_chunks_are_removed(data_dir, tmp_path, address, plain):
    # Negative control: the comparison above can fail.
    out = tmp_path / "seed1"
    _fit(data_dir, out, "--cluster", address, "--chunk-size", "2", "--seed", "1")
    changed = load_result(out / "result.nc")["posterior"].to_dataset()
    assert not changed.identical(plain["posterior"].to_dataset())
    assert not (out / "chunks").exists()
    assert not any("chunks" in f for f in json.loads((out / MANIFEST).read_text())["files"])


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--chunk-size", "2"], "--chunk-size applies to --cluster only"),
        (["--cluster", "local:2", "--engine", "hierarchical"], "fits them jointly"),
        (["--cluster", "localhost:8786"], "give local, local:N or a scheduler address"),
        (["--cluster", "local:0"], "the worker count must be a positive integer"),
    ],
)
def test_bad_cluster_options_are_refused_before_any_work(tmp_path, extra, message):
    out = tmp_path / "out"
    result = runner.invoke(app, ["fit", "no-such-data.csv", *extra, "--out", str(out)])
    assert result.exit_code == 2
    assert message in " ".join(result.output.split())
    assert not out.exists() and not staging_path(out).exists()


def _evaluate(data_dir, *extra: str) -> dict:
    args = ["evaluate", str(data_dir / CHAIN), "--model", "idm-default", "--rollouts", "3"]
    result = runner.invoke(app, [*args, "--vehicles-per-scenario", "1", *extra, "--json", "-"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


@pytest.mark.extended
@pytest.mark.realdata
def test_cluster_evaluation_is_bit_identical(data_dir, address):
    # Each scenario keeps its own key, so chunks of one scenario on two workers give the plain
    # run's numbers exactly (JSON floats round-trip); another seed is the negative control.
    plain = _evaluate(data_dir)
    assert plain["scenarios"] >= 3
    assert _evaluate(data_dir, "--cluster", address, "--chunk-size", "1") == plain
    assert _evaluate(data_dir, "--seed", "1", "--cluster", address) != plain


def test_evaluate_refuses_bad_cluster_options_before_any_work():
    result = runner.invoke(app, ["evaluate", "x.csv", "--model", "cv", "--chunk-size", "2"])
    assert result.exit_code == 2 and "--chunk-size applies to --cluster only" in result.output
    result = runner.invoke(app, ["evaluate", "x.csv", "--model", "cv", "--cluster", "local:0"])
    assert result.exit_code == 2 and "positive integer" in " ".join(result.output.split())


def _criticize(data_dir, out, *extra: str) -> dict:
    """The criticism's JSON report; with ``out``, the final model is fitted and written there."""
    args = ["criticize", str(data_dir / CHAIN), "--vehicles", "4", "--particles", "32"]
    args += ["--causes", "autocorrelated_noise", "--max-rounds", "1", "--rollouts", "2"]
    if out is not None:
        args += ["--final-particles", "64", "--out", str(out)]
    result = runner.invoke(app, [*args, *extra, "--json", "-"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    report.pop("timing"), report.pop("figures", None)  # figures are written with --out only
    return report


@pytest.mark.extended
@pytest.mark.realdata
def test_cluster_criticism_is_bit_identical(data_dir, tmp_path, address):
    # Every fit of the criticism (the base model's and the screened extension's, started from
    # the base posterior) runs one vehicle a task, each from its own key, so the report equals
    # the plain run's exactly (JSON floats round-trip) and so does the final model's smc fit
    # (written by --out, fitted in chunks too); another seed is the negative control.
    plain = _criticize(data_dir, tmp_path / "plain")
    fitted = [c["name"] for c in plain["rounds"][0]["causes"] if c["gain"] is not None]
    assert fitted, "no extension was fitted: the cluster path of extension fits went untested"
    cluster = _criticize(data_dir, tmp_path / "cluster", "--cluster", address, "--chunk-size", "1")
    assert cluster == plain
    final = load_result(tmp_path / "cluster" / "final_model.nc")
    _assert_same_bits(final, load_result(tmp_path / "plain" / "final_model.nc"))
    assert not (tmp_path / "cluster" / "chunks").exists()
    # The control compares the base posterior alone, so it fits no final model.
    other = _criticize(data_dir, None, "--seed", "1", "--cluster", address)
    assert other["base"]["posterior"] != plain["base"]["posterior"]


def test_criticize_refuses_bad_cluster_options_before_any_work(tmp_path):
    out = tmp_path / "out"
    result = runner.invoke(app, ["criticize", "x.csv", "--chunk-size", "2", "--out", str(out)])
    assert result.exit_code == 2 and "--chunk-size applies to --cluster only" in result.output
    assert not out.exists() and not staging_path(out).exists()
