"""Fetching data sets: from a loopback HTTP mirror only (no test touches the real network)."""

import contextlib
import functools
import http.server
import shutil
import socket
import threading
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from bayesdrive.data import registry
from bayesdrive.data.errors import DataError
from bayesdrive.data.fetch import fetch, file_url, files_to_fetch

LOOPBACK = "127.0.0.1"


@pytest.fixture(autouse=True)
def no_real_network(monkeypatch):
    """Fail any download that is not from the loopback mirror these tests start."""
    real_urlopen = urllib.request.urlopen

    def loopback_only(url, *args, **kwargs):
        host = urllib.parse.urlsplit(url).hostname
        assert host == LOOPBACK, f"test tried to reach {url}"
        return real_urlopen(url, *args, **kwargs)

    monkeypatch.setattr(urllib.request, "urlopen", loopback_only)


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format, *args):  # keep pytest output clean
        pass


@contextlib.contextmanager
def serve(folder: Path):
    """Serve ``folder`` over HTTP on a free loopback port for the duration of the block."""
    handler = functools.partial(_QuietHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer((LOOPBACK, 0), handler)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05})
    thread.start()
    try:
        yield f"http://{LOOPBACK}:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)
    assert not thread.is_alive()


def mirror_copy(source_root: Path, name: str, tmp_path: Path) -> Path:
    """A private mirror holding one data set, to corrupt at will."""
    root = tmp_path / "mirror"
    shutil.copytree(Path(source_root) / name, root / name)
    return root


# ---- URLs (no download) -------------------------------------------------------------------------


def test_origin_urls_are_raw_files_at_the_pinned_commit():
    dataset = registry.DATASETS["ngsim_i80_chains"]
    chain = next(f for f in dataset.files if f.name == "1_11_24_44_55_54.csv")
    assert file_url(dataset, chain) == (
        "https://raw.githubusercontent.com/Keke-Long/PERL_planning/"
        "53defbbe13e25360df7599a5687c3396dd9522e9/data/NGSIM_I80/1_11_24_44_55_54.csv"
    )


def test_origin_fetch_skips_files_the_origin_does_not_publish():
    dataset = registry.DATASETS["ngsim_i80_chains"]
    wanted, skipped = files_to_fetch(dataset)
    assert set(skipped) == {"PROVENANCE.txt", "SOURCE_COMMIT.txt"}
    assert len(wanted) + len(skipped) == len(dataset.files)
    # a mirror serves the data-dir layout, so it has them all
    assert files_to_fetch(dataset, "http://mirror/x")[1] == ()


def test_mirror_urls_quote_spaces_and_subfolders():
    dataset = registry.HOLDOUT["ngsim_i80_pairs_raw_c"]
    file = next(f for f in dataset.files if f.name == "Testing/Leading Speed.csv")
    assert file_url(dataset, file, "http://m/base/") == (
        "http://m/base/ngsim_i80_pairs_raw_c/Testing/Leading%20Speed.csv"
    )


# ---- fetching from a loopback mirror ------------------------------------------------------------


@pytest.mark.realdata
def test_fetch_from_a_mirror_lands_every_file_verified(data_dir, tmp_path):
    dest = tmp_path / "data"
    received = []
    with serve(data_dir) as url:
        result = fetch("ngsim_i80_chains", dest, base_url=url, progress=received.append)

    dataset = registry.DATASETS["ngsim_i80_chains"]
    assert not result.already_present
    assert result.path == dest / "ngsim_i80_chains"
    assert set(result.fetched) == {f.name for f in dataset.files}
    assert registry.verify("ngsim_i80_chains", dest) == []
    assert sum(received) == sum(f.size for f in dataset.files)
    assert [p.name for p in dest.iterdir()] == ["ngsim_i80_chains"], "staging folder left behind"


@pytest.mark.realdata
def test_fetch_handles_subfolders_and_spaces_in_names(holdout_dir, tmp_path):
    # Bytes only: nothing here reads, fits or scores the held-out data.
    with serve(holdout_dir) as url:
        fetch("ngsim_i80_pairs_raw_c", tmp_path, base_url=url)
    assert registry.verify("ngsim_i80_pairs_raw_c", tmp_path) == []


@pytest.mark.realdata
def test_fetching_again_leaves_a_verified_copy_alone(data_dir, tmp_path):
    with serve(data_dir) as url:
        fetch("interaction_fixture", tmp_path, base_url=url)
        again = fetch("interaction_fixture", tmp_path, base_url=url)
    assert again.already_present and again.fetched == ()


@pytest.mark.realdata
def test_fetch_never_overwrites_a_folder_that_differs(data_dir, tmp_path):
    existing = tmp_path / "interaction_fixture"
    existing.mkdir()
    (existing / "vehicle_tracks_000.csv").write_text("mine\n")
    with serve(data_dir) as url, pytest.raises(DataError, match="exists but differs"):
        fetch("interaction_fixture", tmp_path, base_url=url)
    assert (existing / "vehicle_tracks_000.csv").read_text() == "mine\n"


def _flip_one_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x20
    path.write_bytes(bytes(data))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-10])


def _append(path: Path) -> None:
    path.write_bytes(path.read_bytes() + b"0,0,0\n")


@pytest.mark.realdata
def test_a_corrupted_mirror_fails_on_the_checksum_and_leaves_nothing(data_dir, tmp_path):
    mirror = mirror_copy(data_dir, "interaction_fixture", tmp_path)
    corrupted = mirror / "interaction_fixture" / "vehicle_tracks_000.csv"
    _flip_one_byte(corrupted)
    expected = next(
        f.sha256
        for f in registry.DATASETS["interaction_fixture"].files
        if f.name == "vehicle_tracks_000.csv"
    )
    dest = tmp_path / "fresh"
    with serve(mirror) as url, pytest.raises(DataError) as caught:
        fetch("interaction_fixture", dest, base_url=url)

    message = str(caught.value)
    assert "interaction_fixture/vehicle_tracks_000.csv" in message
    assert f"expected sha256 {expected}" in message
    assert f"got {registry.sha256_file(corrupted)}" in message
    assert not dest.exists(), "a failed fetch must leave nothing behind"


@pytest.mark.realdata
@pytest.mark.parametrize(
    ("damage", "message"),
    [(_truncate, r"sent \d+ bytes, expected"), (_append, "sent more than")],
    ids=["truncated", "too long"],
)
def test_a_file_of_the_wrong_size_fails_and_leaves_nothing(data_dir, tmp_path, damage, message):
    mirror = mirror_copy(data_dir, "interaction_fixture", tmp_path)
    damage(mirror / "interaction_fixture" / "TestScenarioForScripts.osm")
    dest = tmp_path / "data"
    dest.mkdir()
    with serve(mirror) as url, pytest.raises(DataError, match=message):
        fetch("interaction_fixture", dest, base_url=url)
    assert list(dest.iterdir()) == []


@pytest.mark.realdata
def test_a_file_missing_on_the_mirror_names_the_url_and_status(data_dir, tmp_path):
    mirror = mirror_copy(data_dir, "interaction_fixture", tmp_path)
    (mirror / "interaction_fixture" / "LICENSE.txt").unlink()
    dest = tmp_path / "data"
    with serve(mirror) as url, pytest.raises(DataError, match=r"LICENSE\.txt.*HTTP 404"):
        fetch("interaction_fixture", dest, base_url=url)
    assert not dest.exists()


def test_an_unreachable_mirror_is_a_data_error(tmp_path):
    with socket.socket() as probe:  # a port nobody listens on: bind, note it, close
        probe.bind((LOOPBACK, 0))
        port = probe.getsockname()[1]
    with pytest.raises(DataError, match="cannot download"):
        fetch("interaction_fixture", tmp_path / "data", base_url=f"http://{LOOPBACK}:{port}")
    assert not (tmp_path / "data").exists()


def test_an_unknown_name_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="unknown data set"):
        fetch("no_such_set", tmp_path)


@pytest.mark.realdata
def test_a_fetch_killed_midway_resumes_keeping_only_the_verified_files(data_dir, tmp_path):
    dataset = registry.DATASETS["ngsim_i80_chains"]
    kept, torn = dataset.files[0].name, dataset.files[1].name
    source = data_dir / "ngsim_i80_chains"
    # What a SIGKILL leaves: the shared staging folder, one file finished, one half-written.
    dest = tmp_path / "data"
    staging = dest / ".ngsim_i80_chains.partial"
    staging.mkdir(parents=True)
    shutil.copy(source / kept, staging / kept)
    (staging / torn).write_bytes((source / torn).read_bytes()[:100])
    # The mirror no longer has the finished file: only the kept copy can supply it.
    mirror = mirror_copy(data_dir, "ngsim_i80_chains", tmp_path)
    (mirror / "ngsim_i80_chains" / kept).unlink()
    with serve(mirror) as url:
        with pytest.raises(DataError, match="HTTP 404"):  # negative control: nothing kept
            fetch("ngsim_i80_chains", tmp_path / "elsewhere", base_url=url)
        result = fetch("ngsim_i80_chains", dest, base_url=url)
    assert registry.verify("ngsim_i80_chains", dest) == []
    assert result.path == dest / "ngsim_i80_chains"
    assert [p.name for p in dest.iterdir()] == ["ngsim_i80_chains"]
