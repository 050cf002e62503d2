"""Data sets by name: where each comes from, under which licence, and the sha256 of every file.

Two frozen tables. :data:`DATASETS` holds the data sets the project fits and tests on;
:data:`HOLDOUT` holds data sets kept for evaluation only (``role="holdout"``): :func:`resolve` and
:func:`load` refuse their names, so no fit, default, prior, threshold or seed can be chosen on
them by accident; evaluation code loads them with :func:`load_holdout`.

Each data set is pinned to public origins (a repository at a fixed commit) and lists every file
of its folder with its size and sha256, computed from the copies under ``shared/data`` and
``shared/holdout`` (one table per data set in ``checksums/``, package data read here). A file the origin does not publish (the ``PROVENANCE.txt`` notes written with
the copy, a convenience conversion) is listed too, with no origin path: a mirror can serve it,
the origin cannot.

Where the data live (first match wins; see :func:`data_dir` and :func:`holdout_dir`):

1. the explicit argument (``--data-dir`` / ``--holdout-dir`` on the command line);
2. the environment variable ``BAYESDRIVE_DATA_DIR`` / ``BAYESDRIVE_HOLDOUT_DIR``;
3. ``<root>/../shared/data`` / ``<root>/../shared/holdout`` if that folder exists, where ``<root>``
   is the repository holding the current directory (the nearest parent with ``.git`` or
   ``pyproject.toml``), else the current directory itself.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Literal, NamedTuple
from urllib.parse import quote

from bayesdrive.data import readers
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories

log = logging.getLogger(__name__)

__all__ = [
    "DATASETS",
    "DATA_DIR_ENV",
    "HELD_OUT_NOTE",
    "HOLDOUT",
    "HOLDOUT_DIR_ENV",
    "DataFile",
    "DataSet",
    "Mismatch",
    "Origin",
    "check_files",
    "data_dir",
    "get",
    "holdout_dir",
    "is_holdout_name",
    "load",
    "load_any",
    "load_holdout",
    "resolve",
    "resolve_holdout",
    "sha256_file",
    "verify",
]

Role = Literal["fit", "holdout"]

DATA_DIR_ENV = "BAYESDRIVE_DATA_DIR"
HOLDOUT_DIR_ENV = "BAYESDRIVE_HOLDOUT_DIR"
_SHARED_FOLDER = {"fit": "data", "holdout": "holdout"}
_DIR_ENV = {"fit": DATA_DIR_ENV, "holdout": HOLDOUT_DIR_ENV}
_DIR_OPTION = {"fit": "--data-dir", "holdout": "--holdout-dir"}


class Origin(NamedTuple):
    """A public repository pinned to one commit, and the URL of its raw files.

    ``url_template`` holds ``{path}``, replaced by the URL-quoted path inside the repository.
    """

    repository: str
    commit: str
    url_template: str

    def url(self, path: str) -> str:
        """The download URL of ``path`` (a path inside the repository) at the pinned commit."""
        return self.url_template.format(path=quote(path))


def _github(owner_name: str, commit: str) -> Origin:
    return Origin(
        f"github.com/{owner_name}",
        commit,
        f"https://raw.githubusercontent.com/{owner_name}/{commit}/{{path}}",
    )


class DataFile(NamedTuple):
    """One file of a data set, as pinned.

    Attributes:
        name: path inside the data set's folder, ``/``-separated.
        size: bytes.
        sha256: hex digest of the pinned bytes.
        origin_path: path inside the origin repository, or None when the origin does not publish
            the file (notes written with the copy, a convenience conversion): only a mirror has it.
        origin: index into :attr:`DataSet.origins`.
    """

    name: str
    size: int
    sha256: str
    origin_path: str | None
    origin: int = 0


class DataSet(NamedTuple):
    """A data set known by name (see the module docstring)."""

    name: str
    format: str
    description: str
    origins: tuple[Origin, ...]
    licence: str
    citation: str
    files: tuple[DataFile, ...]
    role: Role = "fit"

    def origin_url(self, file: DataFile) -> str | None:
        """Where the origin publishes ``file``, or None when it does not."""
        if file.origin_path is None:
            return None
        return self.origins[file.origin].url(file.origin_path)


class Mismatch(NamedTuple):
    """A file of a data-set folder that differs from the registry.

    ``problem`` is ``"missing"``, ``"unexpected"`` (a file the registry does not list: a reader
    would read it unchecked), ``"size"`` or ``"sha256"``.
    """

    file: str
    problem: str
    expected: str
    actual: str

    def __str__(self) -> str:
        if self.problem == "missing":
            return f"{self.file}: missing"
        if self.problem == "unexpected":
            return f"{self.file}: not in the registry"
        return f"{self.file}: {self.problem} {self.actual}, expected {self.expected}"


def _files(dataset: str, prefix: str = "") -> tuple[DataFile, ...]:
    """Parse the data set's file table, ``checksums/<dataset>.txt`` beside this module (package
    data): one ``SHA256 SIZE NAME[ <- ORIGIN_PATH]`` per line.

    Without ``<-`` the origin path is ``prefix + NAME``; ``<- -`` marks a file the origin does
    not publish; ``<- [k] PATH`` takes the file from the data set's k-th origin. Names may hold
    spaces, so only the first two fields are split on whitespace.
    """
    table = resources.files(__package__).joinpath("checksums", f"{dataset}.txt").read_text()
    files = []
    for line in table.strip().splitlines():
        sha256, size, rest = line.split(maxsplit=2)
        name, arrow, source = rest.partition(" <- ")
        origin = 0
        if not arrow:
            origin_path: str | None = prefix + name
        elif source == "-":
            origin_path = None
        elif source.startswith("["):
            index, _, origin_path = source[1:].partition("] ")
            origin = int(index)
        else:
            origin_path = source
        files.append(DataFile(name, int(size), sha256, origin_path, origin))
    return tuple(files)


# The file tables (checksums/*.txt) are sha256 sums of the pinned files (`sha256sum`), not tuned
# numbers.
_NGSIM_I80_CHAINS = DataSet(
    name="ngsim_i80_chains",
    format="ngsim_chains",
    description=(
        "NGSIM I-80 (Emeryville, CA) 4:00-4:15 pm, EMD-reconstructed trajectories cut into 75 "
        "chains of 6 consecutive same-lane vehicles (210 distinct vehicles), 10 Hz, metres; "
        "front-to-front headways, no lengths"
    ),
    origins=(_github("Keke-Long/PERL_planning", "53defbbe13e25360df7599a5687c3396dd9522e9"),),
    licence="Apache-2.0",
    citation="NGSIM, US DOT FHWA, doi:10.21949/1504477; chains from Keke-Long/PERL_planning",
    files=_files("ngsim_i80_chains", prefix="data/NGSIM_I80/"),
)
_OPENACC_VICOLUNGO = DataSet(
    name="openacc_vicolungo",
    format="openacc",
    description=(
        "JRC OpenACC, Vicolungo campaign: 5-car platoons on Italian motorways, 10 Hz, SI; two "
        "all-human recordings (374 s, 338 s) and one with ACC followers; IVS = bumper gap"
    ),
    origins=(_github("mu2zhou/GT-Project", "261fc97b82ded1eab1e47c8970514da227b7c9dc"),),
    licence="CC-BY-4.0",
    citation="Makridis et al. 2021, Transportation Research Part C 125:103047, doi:10.1016/j.trc.2021.103047",
    files=_files("openacc_vicolungo", prefix="Dataset/OpenACC/data/Vicolungo/"),
)
_NGSIM_MERGE_EPISODES = DataSet(
    name="ngsim_merge_episodes",
    format="merge_episodes",
    description=(
        "98 on-ramp merge episodes from NGSIM: the merging car's speed, acceleration, distance to "
        "the end of the acceleration lane, gaps and relative speeds to up to 5 neighbours, 10 Hz, SI"
    ),
    origins=(
        _github(
            "zhexilian/On-ramp-merging-decision-making", "5f259fa54970ee08850b1e12d3bc570f6662ea45"
        ),
    ),
    licence="none stated (NGSIM-derived)",
    citation="the On-ramp-merging-decision-making repository's IEEE T-IV paper on merge planning; NGSIM, doi:10.21949/1504477",
    files=_files("ngsim_merge_episodes"),
)
_INTERACTION_FIXTURE = DataSet(
    name="interaction_fixture",
    format="interaction",
    description=(
        "The INTERACTION dataset's own test scenario (a track file and a lanelet2 map): "
        "SYNTHETIC, 2 tracks at constant speed; a format fixture, not measured data"
    ),
    origins=(
        _github(
            "interaction-dataset/interaction-dataset", "053213d8aeb4c6f6132d272325a11ae623bd4e35"
        ),
    ),
    licence="BSD-3-Clause",
    citation="Zhan et al. 2019, INTERACTION Dataset, arXiv:1910.03088",
    files=_files("interaction_fixture"),
)

_ACC_PLATOON_FHWA = DataSet(
    name="acc_platoon_fhwa",
    format="openacc_extract",
    description="5-car adaptive-cruise-control platoon, 1984 s, 10 Hz, SI (speeds and IVS gaps only); OpenACC layout, so credit JRC (CC-BY-4.0) to be safe",
    origins=(
        _github(
            "usdot-fhwa-stol/To-21-426-multivariate-piecewise-linear-ACC-car-following-model",
            "11b7f2319fc55c8c680bde54dedc298f57eb0b1f",
        ),
    ),
    licence="CC0-1.0 (stated)",
    citation="USDOT FHWA STOL, multivariate piecewise-linear ACC car-following model",
    files=_files("acc_platoon_fhwa", prefix="AV model funtion/MPL Modeling methodology/"),
    role="holdout",
)
_NGSIM_I80_PAIRS_A = DataSet(
    name="ngsim_i80_pairs_a",
    format="ngsim_pairs",
    description="NGSIM I-80, all three periods, 120 cleaned leader-follower pairs with lane ids; FEET, 10 Hz; spacing = bumper gap",
    origins=(
        _github(
            "TeRyZh/Segment-based-Calibration-of-Car-Following-Dynamics",
            "89f4f0c2fc4bfe1d975c70c7ce681d080a16f19c",
        ),
    ),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; pairs from TeRyZh/Segment-based-Calibration-of-Car-Following-Dynamics",
    files=_files("ngsim_i80_pairs_a", prefix="cf_ngsim_I80/"),
    role="holdout",
)
_NGSIM_I80_PAIRS_B = DataSet(
    name="ngsim_i80_pairs_b",
    format="ngsim_parquet",
    description="NGSIM I-80 4:00-4:15, 142 pairs in lanes 1-3, lane changers removed; metres, 10 Hz; front-to-front headway",
    origins=(
        _github(
            "durraniu/R_workshop_materials_NGSIM_data", "cc1d26429f15d150b7ee909b0d49bed1f17e3bd7"
        ),
    ),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; tidy pairs from durraniu/R_workshop_materials_NGSIM_data",
    files=_files("ngsim_i80_pairs_b", prefix="data/tidy/"),
    role="holdout",
)
_NGSIM_I80_PAIRS_RAW_C = DataSet(
    name="ngsim_i80_pairs_raw_c",
    format="ngsim_matrices",
    description="NGSIM I-80, 150 pairs x 35 s as wide matrices, raw-like (acceleration clipped); FEET, 10 Hz; no ids, lanes or lengths",
    origins=(
        _github(
            "jiangjiwan/Approximate-Bayesian-Computation-Hybrid-Car-following-Model",
            "64a2872a7dc90cf59a137b3cbbcd57a1981f55f8",
        ),
    ),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; matrices from jiangjiwan/Approximate-Bayesian-Computation-Hybrid-Car-following-Model",
    files=_files("ngsim_i80_pairs_raw_c", prefix="data/HDV/NGSIM I_80/"),
    role="holdout",
)
_NGSIM_US101_VEHICLES = DataSet(
    name="ngsim_us101_vehicles",
    format="ngsim_vehicles",
    description="NGSIM US-101 7:49-8:34 am, 60 single-vehicle files; '(m)' columns converted with 0.3084 instead of 0.3048 m/ft by their source",
    origins=(
        _github(
            "chenshimao/NGSIM-FORECASTING-WITH-LSTM", "4cbcb8b4e76a6755bbc09abca75c51297b2886bf"
        ),
    ),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; vehicle files from chenshimao/NGSIM-FORECASTING-WITH-LSTM",
    files=_files("ngsim_us101_vehicles"),
    role="holdout",
)
_OPENACC_CASALE = DataSet(
    name="openacc_casale",
    format="openacc",
    description="JRC OpenACC, Casale: 2 cars, human leader, follower on adaptive cruise control, 24-41 m/s, 10 Hz, SI",
    origins=(_github("mu2zhou/GT-Project", "261fc97b82ded1eab1e47c8970514da227b7c9dc"),),
    licence="CC-BY-4.0",
    citation="Makridis et al. 2021, Transportation Research Part C 125:103047, doi:10.1016/j.trc.2021.103047",
    files=_files("openacc_casale", prefix="Dataset/OpenACC/data/Casale/"),
    role="holdout",
)
_OPENACC_ZALAZONE = DataSet(
    name="openacc_zalazone",
    format="openacc",
    description="JRC OpenACC, ZalaZone test track: platoons at 30-60 km/h, most on ACC, one all-human (no_ACC), 10 Hz, SI",
    origins=(
        _github(
            "thibault-charlottin/ACC-platoon-fuel-consumption",
            "8781ec31a976113210a9809b98345c76594c3896",
        ),
        _github("mu2zhou/GT-Project", "261fc97b82ded1eab1e47c8970514da227b7c9dc"),
    ),
    licence="CC-BY-4.0",
    citation="Makridis et al. 2021, Transportation Research Part C 125:103047, doi:10.1016/j.trc.2021.103047",
    files=_files("openacc_zalazone", prefix="data/OpenACC_data/"),
    role="holdout",
)

DATASETS: MappingProxyType[str, DataSet] = MappingProxyType(
    {
        d.name: d
        for d in (
            _NGSIM_I80_CHAINS,
            _OPENACC_VICOLUNGO,
            _NGSIM_MERGE_EPISODES,
            _INTERACTION_FIXTURE,
        )
    }
)
"""Data sets for fitting and tests, by name."""

HOLDOUT: MappingProxyType[str, DataSet] = MappingProxyType(
    {
        d.name: d
        for d in (
            _ACC_PLATOON_FHWA,
            _NGSIM_I80_PAIRS_A,
            _NGSIM_I80_PAIRS_B,
            _NGSIM_I80_PAIRS_RAW_C,
            _NGSIM_US101_VEHICLES,
            _OPENACC_CASALE,
            _OPENACC_ZALAZONE,
        )
    }
)
"""Held-out data sets (``role="holdout"``), for evaluation only, by name."""


def get(name: str) -> DataSet:
    """The registered data set ``name``, from either table."""
    dataset = DATASETS.get(name) or HOLDOUT.get(name)
    if dataset is None:
        raise DataError(
            f"unknown data set {name!r}; known: {', '.join(DATASETS)} "
            f"(held out for evaluation: {', '.join(HOLDOUT)})"
        )
    return dataset


def _repository_root(start: Path) -> Path:
    for folder in (start, *start.parents):
        if (folder / ".git").exists() or (folder / "pyproject.toml").exists():
            return folder
    return start


def _lookup_dir(explicit: str | os.PathLike | None, role: Role) -> Path:
    if explicit is not None:
        return Path(explicit)
    env = _DIR_ENV[role]
    if os.environ.get(env):
        return Path(os.environ[env])
    shared = _repository_root(Path.cwd()) / ".." / "shared" / _SHARED_FOLDER[role]
    if shared.is_dir():
        return shared.resolve()
    raise DataError(
        f"no {'data' if role == 'fit' else 'holdout'} directory: pass {_DIR_OPTION[role]}, "
        f"or set {env}, or create {shared}"
    )


def data_dir(explicit: str | os.PathLike | None = None) -> Path:
    """The folder holding the named data sets (lookup order in the module docstring)."""
    return _lookup_dir(explicit, "fit")


def holdout_dir(explicit: str | os.PathLike | None = None) -> Path:
    """The folder holding the held-out data sets (lookup order in the module docstring)."""
    return _lookup_dir(explicit, "holdout")


def _resolve(
    name_or_path: str | os.PathLike, directory: str | os.PathLike | None, role: Role
) -> tuple[Path, DataSet | None]:
    """The path to read, and the registered data set when a name was given."""
    path = Path(name_or_path)
    if path.exists():
        return path, None
    name = str(name_or_path)
    table, other = (DATASETS, HOLDOUT) if role == "fit" else (HOLDOUT, DATASETS)
    if name in table:
        folder = _lookup_dir(directory, role) / name
        if not folder.is_dir():
            raise DataError(
                f"data set {name!r} is not in {folder.parent}: fetch it with "
                f"`bayesdrive data fetch {name}`"
            )
        return folder, table[name]
    if name in other:
        if role == "fit":
            raise DataError(
                f"{name!r} is held out for evaluation only and cannot be loaded for fitting "
                "(evaluation code loads it with load_holdout)"
            )
        raise DataError(f"{name!r} is a data set for fitting, not a held-out data set")
    raise DataError(
        f"{name!r} is neither an existing file or folder nor a known data set "
        f"(known: {', '.join(table)})"
    )


def resolve(name_or_path: str | os.PathLike, data_dir: str | os.PathLike | None = None) -> Path:
    """The file or folder to read for ``name_or_path``.

    An existing path is used as it is; otherwise a name from :data:`DATASETS` is looked up in the
    data directory. A held-out name, an unknown name and a missing data set raise
    :class:`DataError` (the last naming ``bayesdrive data fetch NAME``).
    """
    return _resolve(name_or_path, data_dir, "fit")[0]


def resolve_holdout(name: str, holdout_dir: str | os.PathLike | None = None) -> Path:
    """The folder of the held-out data set ``name`` (an existing path is used as it is)."""
    return _resolve(name, holdout_dir, "holdout")[0]


def _read(
    path: Path, dataset: DataSet | None, format: str | None, strict: bool, options: dict
) -> Trajectories:
    if dataset is None:
        return readers.read(path, format=format, strict=strict, **options)
    traj = readers.read(path, format=format or dataset.format, strict=strict, **options)
    # A name is portable across machines; the folder it was found in is not.
    return dataclasses.replace(traj, source=dataset.name)


def load(
    name_or_path: str | os.PathLike,
    format: str | None = None,
    data_dir: str | os.PathLike | None = None,
    strict: bool = False,
    **options,
) -> Trajectories:
    """Read a data set by name (with its registered format as the default) or a path.

    ``options`` go to the reader (e.g. ``columns``, ``units``, ``headway`` for the column-map
    reader). Checksums are not re-checked on every load: run :func:`verify` (or
    ``bayesdrive data list``) for that.
    """
    path, dataset = _resolve(name_or_path, data_dir, "fit")
    return _read(path, dataset, format, strict, options)


def load_holdout(
    name: str,
    format: str | None = None,
    holdout_dir: str | os.PathLike | None = None,
    strict: bool = False,
    **options,
) -> Trajectories:
    """Read a held-out data set by name, for evaluation only (see :func:`load`)."""
    path, dataset = _resolve(name, holdout_dir, "holdout")
    return _read(path, dataset, format, strict, options)


HELD_OUT_NOTE = (
    "%s is held out for evaluation only: fit it with fixed, documented settings to measure the "
    "toolkit; never choose or tune a default, prior, threshold, seed or model on it"
)


def is_holdout_name(name_or_path: str | os.PathLike) -> bool:
    """Whether ``name_or_path`` names a held-out data set (and no existing path)."""
    return str(name_or_path) in HOLDOUT and not Path(name_or_path).exists()


def load_any(
    name_or_path: str | os.PathLike,
    format: str | None = None,
    data_dir: str | os.PathLike | None = None,
    strict: bool = False,
    **options,
) -> Trajectories:
    """:func:`load`, or for a held-out name :func:`load_holdout` (``data_dir`` then names the
    held-out folder) with :data:`HELD_OUT_NOTE` logged: what users call, where fitting a held-out
    set's vehicles with fixed settings is evaluation."""
    if is_holdout_name(name_or_path):
        log.warning(HELD_OUT_NOTE, name_or_path)
        return load_holdout(str(name_or_path), format, data_dir, strict, **options)
    return load(name_or_path, format, data_dir, strict, **options)


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, read in chunks."""
    with open(path, "rb") as stream:
        return hashlib.file_digest(stream, "sha256").hexdigest()


def check_files(folder: Path, files: tuple[DataFile, ...]) -> list[Mismatch]:
    """Mismatches between ``files`` as registered and as found in ``folder`` (extras not checked)."""
    mismatches = []
    for file in files:
        path = folder / file.name
        if not path.is_file():
            mismatches.append(Mismatch(file.name, "missing", "present", "absent"))
            continue
        size = path.stat().st_size
        if size != file.size:
            mismatches.append(Mismatch(file.name, "size", f"{file.size} B", f"{size} B"))
            continue
        digest = sha256_file(path)
        if digest != file.sha256:
            mismatches.append(Mismatch(file.name, "sha256", file.sha256, digest))
    return mismatches


def verify(name: str, data_dir: str | os.PathLike | None = None) -> list[Mismatch]:
    """Every difference between the folder of data set ``name`` and the registry.

    ``data_dir`` is the folder holding the data set's folder (looked up as in :func:`data_dir`,
    or :func:`holdout_dir` for a held-out name). Files the registry does not list are reported
    too: a reader would read them unchecked. An empty list means the folder is exactly as pinned.
    """
    dataset = get(name)
    folder = _lookup_dir(data_dir, dataset.role) / name
    registered = {file.name for file in dataset.files}
    present = (
        sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
        if folder.is_dir()
        else []
    )
    unexpected = [
        Mismatch(name, "unexpected", "absent", "present")
        for name in present
        if name not in registered
    ]
    return check_files(folder, dataset.files) + unexpected
