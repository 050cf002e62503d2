"""Every data set the project knows, each described once.

One :class:`DataSet` per data set holds all there is to know about it: its name (which is also the
name of its folder in the data directory, or in the holdout directory when it is held out), the
format ``load`` reads it with, the :class:`Layout` of its files where the format is a named
column map (reader, column map, units), where it comes from (origins pinned to a commit), licence
and citation, every file with its size and sha256 (read from ``checksums/<name>.txt`` beside this
module, package data), its role (``"fit"`` or ``"holdout"``), and the figures its source documents.
The readers (format names and folder detection), ``registry`` (``load``, ``verify``), ``fetch``
and the ``bayesdrive data`` commands all read these descriptions; nothing else describes a data
set.

:data:`DATASETS` holds the data sets the project fits and tests on; :data:`HOLDOUT` holds those
kept for evaluation only (``role="holdout"``), which ``registry.load`` refuses. A file the origin
does not publish (the ``PROVENANCE.txt`` notes written with the copy, a convenience conversion) is
listed too, with no origin path: a mirror can serve it, the origin cannot.

This module reads no data and imports no reader, so the readers can import it.
"""

from __future__ import annotations

from collections.abc import Mapping
from importlib import resources
from types import MappingProxyType
from typing import Any, Literal, NamedTuple
from urllib.parse import quote

from bayesdrive.data.errors import DataError
from bayesdrive.data.units import FOOT_M

__all__ = [
    "DATASETS",
    "HOLDOUT",
    "LAYOUTS",
    "DataFile",
    "DataSet",
    "Layout",
    "Origin",
    "get",
]

Role = Literal["fit", "holdout"]


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


class Layout(NamedTuple):
    """How a folder whose format is not a reader of its own is read.

    Attributes:
        reader: the reader in ``readers.FORMATS`` that reads the folder (``"columns"`` or
            ``"openacc"``).
        description: what the files hold and what reading them assumes (from the folder's
            PROVENANCE file, not tuned).
        units: for the columns reader, the length unit of the files (``"m"``, ``"ft"`` or a
            factor to metres).
        columns: for the columns reader, the column map (schema name -> the file's column).
        options: the columns reader's other options (``mode``, ``patterns``, ``dt``,
            ``time_factor``, ``headway``, ``id_pattern``, ``files``).
    """

    reader: str
    description: str
    units: str | float | None = None
    columns: Mapping[str, str] | None = None
    options: Mapping[str, Any] = MappingProxyType({})

    def reader_options(self) -> dict[str, Any]:
        """The options this layout gives its reader (``read_columns`` keyword arguments)."""
        given = {"units": self.units, "columns": self.columns}
        return {**self.options, **{k: v for k, v in given.items() if v is not None}}


class DataSet(NamedTuple):
    """A data set known by name (see the module docstring).

    ``documented`` maps figures of ``trajectories.summary`` (``scenes``, ``vehicles``, ``dt_s``,
    ...) to the values the source's documentation or PROVENANCE file states; the tests check them
    on the data sets for fitting (held-out ones are only loaded, never measured, by the tests).
    """

    name: str
    format: str
    description: str
    origins: tuple[Origin, ...]
    licence: str
    citation: str
    files: tuple[DataFile, ...]
    role: Role = "fit"
    layout: Layout | None = None
    documented: Mapping[str, float] = MappingProxyType({})

    def origin_url(self, file: DataFile) -> str | None:
        """Where the origin publishes ``file``, or None when it does not."""
        if file.origin_path is None:
            return None
        return self.origins[file.origin].url(file.origin_path)


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


def _dataset(
    name: str,
    *,
    origin_prefix: str = "",
    documented: Mapping[str, float] | None = None,
    **fields: Any,
) -> DataSet:
    """A :class:`DataSet` whose files are the table ``checksums/<name>.txt``; ``origin_prefix`` is
    the path of the folder inside the origin repository."""
    return DataSet(
        name=name,
        files=_files(name, prefix=origin_prefix),
        documented=MappingProxyType(dict(documented or {})),
        **fields,
    )


_MAKRIDIS_2021 = (
    "Makridis et al. 2021, Transportation Research Part C 125:103047, doi:10.1016/j.trc.2021.103047"
)
_JRC_OPENACC = _github("mu2zhou/GT-Project", "261fc97b82ded1eab1e47c8970514da227b7c9dc")

# The file tables (checksums/*.txt) are sha256 sums of the pinned files (`sha256sum`), and the
# documented figures and layouts come from each source's PROVENANCE notes: none is a tuned number.
_NGSIM_I80_CHAINS = _dataset(
    "ngsim_i80_chains",
    format="ngsim_chains",
    description=(
        "NGSIM I-80 (Emeryville, CA) 4:00-4:15 pm, EMD-reconstructed trajectories cut into 75 "
        "chains of 6 consecutive same-lane vehicles (210 distinct vehicles), 10 Hz, metres; "
        "front-to-front headways, no lengths"
    ),
    origins=(_github("Keke-Long/PERL_planning", "53defbbe13e25360df7599a5687c3396dd9522e9"),),
    licence="Apache-2.0",
    citation="NGSIM, US DOT FHWA, doi:10.21949/1504477; chains from Keke-Long/PERL_planning",
    origin_prefix="data/NGSIM_I80/",
    documented={"scenes": 75, "vehicles": 210, "dt_s": 0.1},
)
_OPENACC_VICOLUNGO = _dataset(
    "openacc_vicolungo",
    format="openacc",
    description=(
        "JRC OpenACC, Vicolungo campaign: 5-car platoons on Italian motorways, 10 Hz, SI; two "
        "all-human recordings (374 s, 338 s) and one with ACC followers; IVS = bumper gap"
    ),
    origins=(_JRC_OPENACC,),
    licence="CC-BY-4.0",
    citation=_MAKRIDIS_2021,
    origin_prefix="Dataset/OpenACC/data/Vicolungo/",
    documented={"scenes": 3, "vehicles": 15, "dt_s": 0.1},
)
_NGSIM_MERGE_EPISODES = _dataset(
    "ngsim_merge_episodes",
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
    documented={"scenes": 98, "dt_s": 0.1},
)
_INTERACTION_FIXTURE = _dataset(
    "interaction_fixture",
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
    documented={"vehicles": 2},
)

_ACC_PLATOON_FHWA = _dataset(
    "acc_platoon_fhwa",
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
    origin_prefix="AV model funtion/MPL Modeling methodology/",
    role="holdout",
    layout=Layout("openacc", "OpenACC-like columns (Time, Speed1..5, IVS1..4), no metadata rows"),
)
_NGSIM_I80_PAIRS_A = _dataset(
    "ngsim_i80_pairs_a",
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
    origin_prefix="cf_ngsim_I80/",
    role="holdout",
    layout=Layout(
        "columns",
        "per-pair CSVs in train/ and test/, FEET; x is the front (spacing = x_leader - "
        "x_follower - leader_length, a bumper gap); ids from the file name "
        "(..._<period>_f<follower>_l<leader>_<n>); no follower length",
        units="ft",
        columns={
            "t": "t",
            "x_follower": "x_follower",
            "v_follower": "v_follower",
            "a_follower": "a_follower",
            "x_leader": "x_leader",
            "v_leader": "v_leader",
            "a_leader": "a_leader",
            "length_leader": "leader_length",
            "gap": "spacing",
        },
        options={
            "mode": "pairs",
            "patterns": ("train/*.csv", "test/*.csv"),
            "headway": "bumper",
            "dt": 0.1,
            "id_pattern": (
                r"(?P<scope>\d{4}[ap]m-\d{4}[ap]m)_f(?P<follower>\d+)_l(?P<leader>\d+)_\d+$"
            ),
        },
    ),
)
_NGSIM_I80_PAIRS_B = _dataset(
    "ngsim_i80_pairs_b",
    format="ngsim_parquet",
    description="NGSIM I-80 4:00-4:15, 142 pairs in lanes 1-3, lane changers removed; metres, 10 Hz; front-to-front headway",
    origins=(
        _github(
            "durraniu/R_workshop_materials_NGSIM_data", "cc1d26429f15d150b7ee909b0d49bed1f17e3bd7"
        ),
    ),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; tidy pairs from durraniu/R_workshop_materials_NGSIM_data",
    origin_prefix="data/tidy/",
    role="holdout",
    layout=Layout(
        "columns",
        "one parquet of pairs, metres, 10 Hz frame_id (absolute NGSIM frames), ids in "
        "vehicle_id/preceding, one scene per pair_id. space_headway (raw NGSIM, front to "
        "front) is NOT used: it disagrees with the reconstructed positions by up to 8.5 m, so "
        "the gap is computed from local_y, preceding_local_y and preceding_length",
        units="m",
        columns={
            "t": "frame_id",
            "follower_id": "vehicle_id",
            "leader_id": "preceding",
            "x_follower": "local_y",
            "v_follower": "v_vel",
            "a_follower": "v_acc",
            "length_follower": "v_length",
            "x_leader": "preceding_local_y",
            "v_leader": "preceding_vel",
            "a_leader": "preceding_acc",
            "length_leader": "preceding_length",
            "lane_id": "lane_id",
            "scene_id": "pair_id",
        },
        options={"mode": "pairs", "patterns": ("df.parquet",), "dt": 0.1, "time_factor": 0.1},
    ),
)
_NGSIM_I80_PAIRS_RAW_C = _dataset(
    "ngsim_i80_pairs_raw_c",
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
    origin_prefix="data/HDV/NGSIM I_80/",
    role="holdout",
    layout=Layout(
        "columns",
        "wide matrices (one column per pair, 350 rows at 10 Hz), FEET, positions of the "
        "front (NGSIM Local_Y); the top-level files hold all 150 pairs (Trajectory/ and "
        "Testing/ are subsets of them); no ids, lanes or lengths",
        units="ft",
        options={
            "mode": "wide",
            "dt": 0.1,
            "files": {
                "x_leader": "Leading Position.csv",
                "v_leader": "Leading Speed.csv",
                "a_leader": "Leading Acc.csv",
                "x_follower": "Following Position.csv",
                "v_follower": "Following Speed.csv",
                "a_follower": "Following Acc.csv",
            },
        },
    ),
)
_NGSIM_US101_VEHICLES = _dataset(
    "ngsim_us101_vehicles",
    format="ngsim_vehicles",
    description="NGSIM US-101 7:49-8:34 am, 60 single-vehicle files; '(m)' columns converted with 0.3084 instead of 0.3048 m/ft by their source",
    origins=(
        _github(
            "chenshimao/NGSIM-FORECASTING-WITH-LSTM", "4cbcb8b4e76a6755bbc09abca75c51297b2886bf"
        ),
    ),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; vehicle files from chenshimao/NGSIM-FORECASTING-WITH-LSTM",
    role="holdout",
    layout=Layout(
        "columns",
        "one CSV per vehicle; the '(m)' columns were made with 0.3084 m/ft instead of 0.3048, "
        "so the factor to true metres is 0.3048/0.3084; t = Frame_ID * 0.1 s; no lengths, "
        "no lane or leader ids",
        units=FOOT_M / 0.3084,
        columns={
            "vehicle_id": "Vehicle_ID",
            "t": "Frame_ID",
            "x": "local_y(m)",
            "v": "v_Vel(m)",
            "a": "v_Acc(m)",
        },
        options={
            "mode": "vehicles",
            "patterns": ("vehicles/*.csv",),
            "dt": 0.1,
            "time_factor": 0.1,
        },
    ),
)
_OPENACC_CASALE = _dataset(
    "openacc_casale",
    format="openacc",
    description="JRC OpenACC, Casale: 2 cars, human leader, follower on adaptive cruise control, 24-41 m/s, 10 Hz, SI",
    origins=(_JRC_OPENACC,),
    licence="CC-BY-4.0",
    citation=_MAKRIDIS_2021,
    origin_prefix="Dataset/OpenACC/data/Casale/",
    role="holdout",
    layout=Layout("openacc", "OpenACC platoon files (2 cars)"),
)
_OPENACC_ZALAZONE = _dataset(
    "openacc_zalazone",
    format="openacc",
    description="JRC OpenACC, ZalaZone test track: platoons at 30-60 km/h, most on ACC, one all-human (no_ACC), 10 Hz, SI",
    origins=(
        _github(
            "thibault-charlottin/ACC-platoon-fuel-consumption",
            "8781ec31a976113210a9809b98345c76594c3896",
        ),
        _JRC_OPENACC,
    ),
    licence="CC-BY-4.0",
    citation=_MAKRIDIS_2021,
    origin_prefix="data/OpenACC_data/",
    role="holdout",
    layout=Layout(
        "openacc", "OpenACC platoon files in subfolders; some cars and IVS columns missing"
    ),
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

LAYOUTS: MappingProxyType[str, Layout] = MappingProxyType(
    {d.name: d.layout for d in (*DATASETS.values(), *HOLDOUT.values()) if d.layout is not None}
)
"""The layouts of the data sets that have one, by data-set name (a view of the descriptions)."""


def get(name: str) -> DataSet:
    """The data set ``name``, from either table."""
    dataset = DATASETS.get(name) or HOLDOUT.get(name)
    if dataset is None:
        raise DataError(
            f"unknown data set {name!r}; known: {', '.join(DATASETS)} "
            f"(held out for evaluation: {', '.join(HOLDOUT)})"
        )
    return dataset
