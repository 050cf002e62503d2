"""The data-set registry: pinned checksums match the files, lookup order, resolve, verify."""

import re
import shutil
from pathlib import Path

import pytest

from bayesdrive.data import readers, registry
from bayesdrive.data.errors import DataError
from bayesdrive.data.registry import DATASETS, HOLDOUT

HEX40 = re.compile(r"[0-9a-f]{40}")
HEX64 = re.compile(r"[0-9a-f]{64}")


# ---- the tables themselves ---------------------------------------------------------------------


def test_fitting_and_holdout_tables_are_disjoint_and_labelled():
    assert set(DATASETS).isdisjoint(HOLDOUT)
    assert set(DATASETS) == {
        "ngsim_i80_chains",
        "openacc_vicolungo",
        "ngsim_merge_episodes",
        "interaction_fixture",
    }
    assert {d.role for d in DATASETS.values()} == {"fit"}
    assert {d.role for d in HOLDOUT.values()} == {"holdout"}
    for name, dataset in {**DATASETS, **HOLDOUT}.items():
        assert dataset.name == name


@pytest.mark.parametrize("dataset", [*DATASETS.values(), *HOLDOUT.values()], ids=lambda d: d.name)
def test_every_entry_is_pinned(dataset):
    assert dataset.licence and dataset.description and dataset.format
    for origin in dataset.origins:
        assert HEX40.fullmatch(origin.commit), origin
        assert "{path}" in origin.url_template and origin.commit in origin.url_template
    names = [f.name for f in dataset.files]
    assert len(names) == len(set(names)), "a file is listed twice"
    assert any(f.origin_path is not None for f in dataset.files), "nothing can be fetched"
    for file in dataset.files:
        assert HEX64.fullmatch(file.sha256), file
        assert file.size > 0
        assert 0 <= file.origin < len(dataset.origins)
        url = dataset.origin_url(file)
        if file.origin_path is not None:
            assert f"/{dataset.origins[file.origin].commit}/" in url
            assert " " not in url, "paths must be URL-quoted"


# ---- the pinned files ---------------------------------------------------------------------------


@pytest.mark.realdata
@pytest.mark.parametrize("name", list(DATASETS))
def test_registered_checksums_match_the_data_dir(data_dir, name):
    assert registry.verify(name, data_dir) == []


@pytest.mark.realdata
@pytest.mark.parametrize("name", list(HOLDOUT))
def test_registered_checksums_match_the_holdout_dir(holdout_dir, name):
    # Bytes only: nothing here reads, fits or scores the held-out data.
    assert registry.verify(name, holdout_dir) == []


@pytest.mark.realdata
def test_registered_commits_are_those_the_copies_record(data_dir, holdout_dir):
    for table, root in ((DATASETS, data_dir), (HOLDOUT, holdout_dir)):
        for dataset in table.values():
            if "SOURCE_COMMIT.txt" in {f.name for f in dataset.files}:
                recorded = (Path(root) / dataset.name / "SOURCE_COMMIT.txt").read_text().strip()
                assert recorded == dataset.origins[0].commit, dataset.name


@pytest.mark.realdata
def test_verify_reports_changed_missing_and_unregistered_files(data_dir, tmp_path):
    shutil.copytree(Path(data_dir) / "interaction_fixture", tmp_path / "interaction_fixture")
    folder = tmp_path / "interaction_fixture"
    tracks = folder / "vehicle_tracks_000.csv"
    data = bytearray(tracks.read_bytes())
    data[100] ^= 1  # same size, one bit different
    tracks.write_bytes(bytes(data))
    (folder / "LICENSE.txt").unlink()
    (folder / "extra.csv").write_text("a,b\n1,2\n")
    truncated = folder / "TestScenarioForScripts.osm"
    truncated.write_bytes(truncated.read_bytes()[:-1])

    problems = {m.file: m for m in registry.verify("interaction_fixture", tmp_path)}

    assert set(problems) == {
        "vehicle_tracks_000.csv",
        "LICENSE.txt",
        "extra.csv",
        "TestScenarioForScripts.osm",
    }
    assert problems["vehicle_tracks_000.csv"].problem == "sha256"
    assert problems["vehicle_tracks_000.csv"].actual == registry.sha256_file(tracks)
    assert problems["LICENSE.txt"].problem == "missing"
    assert problems["extra.csv"].problem == "unexpected"
    assert problems["TestScenarioForScripts.osm"].problem == "size"


# ---- where data live ----------------------------------------------------------------------------


@pytest.fixture
def fake_repo(tmp_path, monkeypatch):
    """tmp/repo (a repository, cwd in a subfolder) beside tmp/shared/{data,holdout}."""
    repo = tmp_path / "repo"
    (repo / ".git").mkdir(parents=True)
    (repo / "sub").mkdir()
    (tmp_path / "shared" / "data").mkdir(parents=True)
    (tmp_path / "shared" / "holdout").mkdir(parents=True)
    monkeypatch.chdir(repo / "sub")
    monkeypatch.delenv(registry.DATA_DIR_ENV, raising=False)
    monkeypatch.delenv(registry.HOLDOUT_DIR_ENV, raising=False)
    return tmp_path


def test_lookup_falls_back_to_shared_beside_the_repository(fake_repo):
    assert registry.data_dir() == (fake_repo / "shared" / "data").resolve()
    assert registry.holdout_dir() == (fake_repo / "shared" / "holdout").resolve()


def test_lookup_prefers_the_environment_to_shared(fake_repo, monkeypatch):
    monkeypatch.setenv(registry.DATA_DIR_ENV, str(fake_repo / "env"))
    monkeypatch.setenv(registry.HOLDOUT_DIR_ENV, str(fake_repo / "env_holdout"))
    assert registry.data_dir() == fake_repo / "env"
    assert registry.holdout_dir() == fake_repo / "env_holdout"


def test_lookup_prefers_the_explicit_folder_to_everything(fake_repo, monkeypatch):
    monkeypatch.setenv(registry.DATA_DIR_ENV, str(fake_repo / "env"))
    assert registry.data_dir(fake_repo / "explicit") == fake_repo / "explicit"


def test_lookup_without_any_folder_says_how_to_give_one(fake_repo):
    shutil.rmtree(fake_repo / "shared")
    with pytest.raises(DataError, match=r"--data-dir.*BAYESDRIVE_DATA_DIR"):
        registry.data_dir()


# ---- resolve ------------------------------------------------------------------------------------


def test_resolve_uses_an_existing_path_as_is(tmp_path):
    path = tmp_path / "my.csv"
    path.write_text("x\n")
    assert registry.resolve(path, data_dir=tmp_path / "elsewhere") == path


def test_resolve_finds_a_name_in_the_data_dir(tmp_path):
    (tmp_path / "ngsim_i80_chains").mkdir()
    assert registry.resolve("ngsim_i80_chains", data_dir=tmp_path) == tmp_path / "ngsim_i80_chains"


def test_resolve_a_missing_data_set_names_the_fetch_command(tmp_path):
    with pytest.raises(DataError, match="bayesdrive data fetch ngsim_i80_chains"):
        registry.resolve("ngsim_i80_chains", data_dir=tmp_path)


def test_resolve_refuses_held_out_names_for_fitting(tmp_path):
    (tmp_path / "openacc_casale").mkdir()
    with pytest.raises(DataError, match="held out for evaluation only"):
        registry.resolve("openacc_casale", data_dir=tmp_path)
    assert registry.resolve_holdout("openacc_casale", tmp_path) == tmp_path / "openacc_casale"


def test_resolve_holdout_refuses_fitting_names(tmp_path):
    with pytest.raises(DataError, match="not a held-out data set"):
        registry.resolve_holdout("ngsim_i80_chains", tmp_path)


def test_resolve_an_unknown_name_lists_the_known_ones(tmp_path):
    with pytest.raises(DataError, match=r"neither an existing file.*ngsim_i80_chains"):
        registry.resolve("no_such_set", data_dir=tmp_path)


def test_get_knows_both_tables_and_nothing_else():
    assert registry.get("ngsim_i80_chains").role == "fit"
    assert registry.get("openacc_casale").role == "holdout"
    with pytest.raises(DataError, match="unknown data set 'nope'"):
        registry.get("nope")


# ---- load ---------------------------------------------------------------------------------------


def test_every_registered_format_is_a_reader():
    for dataset in (*DATASETS.values(), *HOLDOUT.values()):
        assert dataset.format in readers.FORMATS, dataset.name


@pytest.mark.realdata
def test_load_by_name_uses_the_registered_reader_and_records_the_name(data_dir):
    traj = registry.load("interaction_fixture", data_dir=data_dir)
    assert traj.format == DATASETS["interaction_fixture"].format
    assert traj.source == "interaction_fixture"


@pytest.mark.realdata
def test_load_by_path_keeps_the_path_as_source(data_dir):
    folder = Path(data_dir) / "interaction_fixture"
    assert registry.load(folder).source == str(folder)


@pytest.mark.realdata
def test_load_refuses_held_out_names_and_load_holdout_reads_them(data_dir, holdout_dir):
    with pytest.raises(DataError, match="held out for evaluation only"):
        registry.load("acc_platoon_fhwa", data_dir=data_dir)
    # Loading only (the one thing tests may do with held-out data): no figures asserted.
    traj = registry.load_holdout("acc_platoon_fhwa", holdout_dir=holdout_dir)
    assert traj.source == "acc_platoon_fhwa" and len(traj.tracks) > 0
