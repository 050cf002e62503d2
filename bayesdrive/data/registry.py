"""Data sets by name: where each comes from, under which licence, and the sha256 of every file.

Two frozen tables. :data:`DATASETS` holds the data sets the project fits and tests on;
:data:`HOLDOUT` holds data sets kept for evaluation only (``role="holdout"``): :func:`resolve` and
:func:`load` refuse their names, so no fit, default, prior, threshold or seed can be chosen on
them by accident; evaluation code loads them with :func:`load_holdout`.

Each data set is pinned to public origins (a repository at a fixed commit) and lists every file
of its folder with its size and sha256, computed from the copies under ``shared/data`` and
``shared/holdout``. A file the origin does not publish (the ``PROVENANCE.txt`` notes written with
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
import os
from pathlib import Path
from types import MappingProxyType
from typing import Literal, NamedTuple
from urllib.parse import quote

from bayesdrive.data import readers
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories

__all__ = [
    "DATASETS",
    "DATA_DIR_ENV",
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
    "load",
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


def _files(table: str, prefix: str = "") -> tuple[DataFile, ...]:
    """Parse a file table: one ``SHA256 SIZE NAME[ <- ORIGIN_PATH]`` per line.

    Without ``<-`` the origin path is ``prefix + NAME``; ``<- -`` marks a file the origin does
    not publish; ``<- [k] PATH`` takes the file from the data set's k-th origin. Names may hold
    spaces, so only the first two fields are split on whitespace.
    """
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


# The tables below are sha256 sums of the pinned files (`sha256sum`), not tuned numbers.
# fmt: off
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
    files=_files("""
c0c99cac628d80948a3e718bdefde15d13c55a68bd007a43b2da0d2cd3057056   41750 115_124_136_140_146_162.csv
eca28da0556c87921c2d1d0cd58e10d6edb436f2e0a3c94b75725f0863b77fdf   40058 11_24_44_55_54_59.csv
0bc6fde221835a513f66591df742b991718f04eba43e83530c9475578b958273   36569 124_136_140_146_162_164.csv
2bcdd436681f8fe4989d9581905a7edf74fe1e13494d9f3a7ed0f28ecaa8f7d5   41406 197_202_210_213_222_234.csv
36f5f9be3d573f28ecbeb1b3482554abf5bb982623a1447bff0095afb9b97ac8   39902 1_11_24_44_55_54.csv
d937546e41be01b21236f9bc85a523d12224c3e973449cfafebac16449b06138   41298 202_210_213_222_234_252.csv
74a733187de0089fb9068920780bfaa36e7529c12808f9ba28bdad8d199d2ffd   41305 210_213_222_234_252_253.csv
25f002ec153b173a43ade71d1cd5aede28367fc92d942c6eabdd95a55cc2f616   41661 212_224_240_244_249_255.csv
6752b7f9d5da7cff89f16be2a0311cfa59154018855d92bf0cd3739c69151e74   41312 213_222_234_252_253_254.csv
4d763bf0d52e5132ede30dd119e9c3070c150d465b3bd9b3c0e5c13b1980623d   41351 267_277_282_293_299_311.csv
4a2b0d54e2a614bba56e955c352b3c0c6c328e9ba7e2ccac6f6cdaea64b4d992   41376 277_282_293_299_311_329.csv
63f4e8eb0e031b4d656cca74a2edd720f5d04a55b86fa344008babdea9624385   41292 293_299_311_329_348_343.csv
57223716bd256cd0915995e5ad5f85640cf8c39f49863e2473f8be205f486869   41830 294_305_314_313_326_339.csv
85a015ef4893787c449ecf6304914a8d79769c82147a6bc6d43d6f678d16f52d   41338 299_311_329_348_343_354.csv
1210daeedef2fb05afaaa921ae9046ff1a0bf8e65d5d1414205cde02b663d304   41836 305_314_313_326_339_343.csv
e19a8d9fdd347c36eddfae4320e65b50998d7537f392ab8c9163c4d7599aa83d   41373 311_329_348_343_354_362.csv
d5625d5ec9cb46bf755b3563d7f092dec0a2da398d528afdf7bce49cdb614561   41165 329_348_343_354_362_368.csv
8b6b8fed081292f60e5e4e90f8f1da2cc4b1772a34610c13896d5a1584452863   41259 343_354_362_368_378_381.csv
e7802294e38b0aa56a75f05715c0bf48c735c661ed998dbca1a46841df462440   42913 344_357_371_386_389_416.csv
756363dff7011daf962a579182e1149460962ffcbf6727ab10a8ac308fb97898   42045 346_350_355_361_364_372.csv
480372cc0a8565337bc56fd8c71485f047a8251f485aaf9f63d115765dbc981b   41210 348_343_354_362_368_378.csv
63ccede27874581ae6cfe206718baa5c658d8cc3011884319b60b0690577b3cb   42285 350_355_361_364_372_379.csv
6a5c2a66b9cf8533a1066b1485c6bdf88f1d6539a7e13ed8fdf33d2b413572d7   41701 354_362_368_378_381_391.csv
c8a48239ce8cd03f4b418d7775eb373403259fe9f1bba077a9516868800486f3   41838 362_368_378_381_391_397.csv
37cf66075189d7529ce8ca1f2370f2355c99c1f283b77536ddfa0814751b4aef   42915 371_386_389_416_426_425.csv
9a1a23a8f095e3cc964662afcf9f9b93cf9163da89622b32c268aa97e914340b   42420 379_386_392_396_402_407.csv
b78341f5cae8376e1aad78d1344272fa00d23efaf08213fb71919719708cb6c4   41837 383_401_413_421_433_445.csv
974a67be9379fc8ab8899ce2eedab76a248ecd2396019f4950acfd3931f8ee30   42421 386_392_396_402_407_415.csv
a21295bb377f9eca226c436959a3b6c4b814606f9941bf5a42e5f6e251c444fe   41988 392_396_402_407_415_418.csv
3334b4d5283168e917b6b7aa4afc38de063ccd9a0b48cc87ef6dc60b6a41ecb9   41990 396_402_407_415_418_427.csv
9577a72a4ef987f68fd6f06dc79e19ea10f49cfb3f3af2fef51340f72c5430c8   41941 402_407_415_418_427_440.csv
67f1176a3724b91ea1533c5f74eb7859bab80ccfe1402d9ac98aac3872ad4b58   41668 417_436_448_459_469_472.csv
d4b97b656af6541efcd29696f8420e2a40671fe0c8929b8294123c57d925b172   41285 427_428_435_449_453_459.csv
169b8d4d62f8d07bc85ddeb85f1a0a0d1f5132c939f2cacf74c9044770e86950   42357 438_446_455_465_482_481.csv
ea7a9569069e80f27548469ba9c629f2653b3a91ce137fc045687d305d4468fc   39874 43_61_67_77_94_102.csv
f161f11f6c54ff287af46092ffae7b7d3532ad87a16e2fc80e211df487aef3d3   39616 45_53_68_72_81_89.csv
5e1e50aa59b05d0b14437d83e167cfc73b3c4d5ab6a614ed6d919d6ec9266d23   40204 46_45_53_68_72_81.csv
09f3da9a19ab394541b3dac2260b9d80c4360db09afcf50c3f1318cbf2e4d25c   41325 472_488_494_507_510_515.csv
79563d2f030e620f27172a901d699483db82cf6a2c35e910bbb861df85ee9b74   41800 488_494_507_510_515_521.csv
5773e2a641197fbd5bbc5570934af32c0ad03c3c728efdacb738b41eb9762920   41944 503_511_519_538_546_554.csv
8561d57ae6074822d6c8e4e0bf8475f67c6cbcdc32dfda7c74c5aeaa37b392f6   41869 510_515_521_533_542_561.csv
0efe1341835b6bc84939dae95c1987739fd797b46762cbf2073ef87cdb21aa25   41694 511_519_538_546_554_566.csv
1f82a6e951476abf501febb9fcb724f54dc2e178c8e20604547718cede034e4d   41803 521_533_542_561_565_571.csv
8b973e5ff3e9a22761a69503fcd59eadd7fb9b0165b096a2f17a5cfad06ef1aa   41360 522_525_537_559_567_572.csv
ba6f20b276c36aa354badf38d3f5f8e5e24686e9f4c5abfc9b0122a4a8b24fd2   41407 525_537_559_567_572_575.csv
4582c6cc11b0bbd8e53921c89e53322ea2c5e3dc2334da5e88045ba4584377f8   41721 533_542_561_565_571_582.csv
63dccee84ac5efaec8f4f983a135ba5cea3a3c0acf72370501499fe5e02655ff   39947 53_68_72_81_89_103.csv
866eaeb843551e2514c0018fc9c32cbc4c0be5104bf1f4ccf5167613c9d2eb1d   41723 542_561_565_571_582_611.csv
80385fe5a6698006f8f319cb3d223098502bdc2986ed97b8c99ae48d8026ca15   39929 54_59_79_87_93_97.csv
0598e014bf7639d8d0bc466a7626b94a3d974b04006c1296bc6b94d59b33b651   39925 55_54_59_79_87_93.csv
c596a17e672f61696cecfedd25d9ca52f43d3ea1074e1fa78fafd95a4acd1f45   41668 561_565_571_582_611_621.csv
b3d66a6666f2b3d1ccdb0b05ad7d727e2b783e9f2698c68d5a593ebe60ac4bcb   41713 565_571_582_611_621_636.csv
b6efd82b6959c8b670069eee1dd36f85a3c5cb9ff3f2f7425fca4812322e192d   33687 586_598_609_611_621_625.csv
98dc5a911fcafea2db8f24ec4911d6f467e888d0a7717156c8788a659cf9f72f   40129 59_79_87_93_97_116.csv
0811f7bae2ce7437e10ff48e20be41f6d79762f0e49b6eba1b73abed9ee24a2b   41553 611_621_636_649_655_660.csv
143629a59d841c9e7a770501e6773490524d143cf9d2d2fd5eec5ed1fe26b871   41830 621_636_649_655_660_683.csv
75e52782b4b485ca3f4981ad59886c8098f5618f4008064e62d1ada99e88d470   41853 636_649_655_660_683_681.csv
33db0a9b7e90d5eb3890c56ae6fa6d5a4fee2bae1ccc9c3f64ca615fcf898ca3   41815 649_655_660_683_681_694.csv
b9090d944f4ad7e9901d317dbe1dff0326e2c5443e108912cd10198680ebdda9   33876 650_656_662_666_706_705.csv
3d8af1e5c334b14a936a4251f75a03807032cdaa1d7c664e57195fc4e6f87a52   41823 655_660_683_681_694_695.csv
4dd7f8cc8d232b374e5c975ad778623efb37bda8735d6b372a1f5cd57383840e   41803 660_683_681_694_695_711.csv
5f763f261f3939c5e7def51a2f3d6e7867bd76eee04bbf8cae3c88419921ec1b   39970 66_74_60_84_100_107.csv
45be26d9a4a51314c833c94556cee11dacb598479bc9fc27f821c7dc984ae0ac   41878 720_748_749_753_764_773.csv
5aa90db435669d8764bdfa46d7c26ce000e59f3d32fec4914ec84fbc68015609   42182 730_765_766_769_804_793.csv
e15e448c4e8f655a51b50e3b3d5a7cb263fdaee8b5e1b8468bf6d97982ed1318   41910 748_749_753_764_773_782.csv
2faf7e4553b80dd456aa08eb9e189c0c65e774ba2dad221555affc94fce4f203   40428 74_60_84_100_107_122.csv
a2e75752d535a5636d8efe2ee343345261fed41839f84dafb876dc51105a044c   33185 755_767_775_785_787_799.csv
c3217cf8070108bfad3b5389171ba87ecbad31179cf0fb89d9839e3e4fdef6bb   41011 77_94_102_109_123_126.csv
271b3781045045361014483b4a9aaba1570b5417ab6ccb2a884b50794b1d7676   40365 79_87_93_97_116_117.csv
8387285c075e4a926b500e4543f745dc0b83232683cad3bb39586df5b90ef3a3   41734 804_793_812_839_841_852.csv
664165ea5677f41003d7eef92d0778df029c378dedc77088bce8927fc03c63e8   41016 87_90_93_97_112_116.csv
382edc2a81e3e762892b47e173c3df4f8eafb787dd79caaab49a4b580f197193   41854 890_898_905_909_916_920.csv
bf8d51af9c38844ef0a1c826859a84ba8292775e5fe4a83a430e3a3aac0f132e   32686 903_907_914_926_920_939.csv
4b5232e742e8c5432094722a260a51ea75d6bfd62103067d25a23a51800fb243   41135 90_93_97_112_116_117.csv
f729791f0d92208df36766ac19c9966df3a1cb24cdbc70ba2b5e538a608732c9   41265 94_102_109_123_126_150.csv
4931d5f241c4612036779d310eb79188fbb3eeae763ccf7295d67d7598229439   11338 LICENSE.txt <- LICENSE
90ac53717b7250006411aaa864181034c4596cde04c524b4a740feaa42a33482     533 PROVENANCE.txt <- -
f46a248f4ce8ce38908148f0b3910e1474927d9bf770eb4e1dc1a83c6a8d8cb7      41 SOURCE_COMMIT.txt <- -
""", prefix="data/NGSIM_I80/"),
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
    files=_files("""
39cecdfa2cc9c2823915ac9bca4492bc944243143f2b6c6b30722a4ac1914862 1535128 JRC-VC_260219_part3.csv
9c637cb01113315034eb00fa917a83419391f628e8684f5bd44a8cfc2a475fae 3963648 JRC-VC_280219_part2.csv
1eb98e74543131dd7d096b632a14e7b18c6ab1ce497b5e0688ca479f7f23b7f9 3608937 JRC-VC_280219_part3.csv
abf18c663325ba97a5204f6994a201a53afc2fa3a85cdb4f4c8310b54df624ea     469 PROVENANCE.txt <- -
0c101982da3d9c1cb3d88ecc4d8dfa9b3064e5a2f511ef460c1d7b37d39427e5      41 SOURCE_COMMIT.txt <- -
b12b79cbd6900d78179910cf91f1e6be771225fdc7827beda7ce47dc10d6d798    3209 Vicolungo_notes.txt
b612a7305a68fa2c874f7ad89159ae7711fd07f3192b6810fe5f8dd8bfb337a1     492 Vicolungo_veh_specifications.csv
35eb9c10f5a35d65d54918b5267232553da44a89866c2d1db63bb285a21dffe1     540 copyright.txt
""", prefix="Dataset/OpenACC/data/Vicolungo/"),
)
_NGSIM_MERGE_EPISODES = DataSet(
    name="ngsim_merge_episodes",
    format="merge_episodes",
    description=(
        "98 on-ramp merge episodes from NGSIM: the merging car's speed, acceleration, distance to "
        "the end of the acceleration lane, gaps and relative speeds to up to 5 neighbours, 10 Hz, SI"
    ),
    origins=(_github("zhexilian/On-ramp-merging-decision-making", "5f259fa54970ee08850b1e12d3bc570f6662ea45"),),
    licence="none stated (NGSIM-derived)",
    citation="the On-ramp-merging-decision-making repository's IEEE T-IV paper on merge planning; NGSIM, doi:10.21949/1504477",
    files=_files("""
5064a90d41c7cd4979f9855bb122c4c5454c4a9ca73bfae2f70e22521b405a94    3597 PROVENANCE.txt <- -
20e04dde16e67320d005c2b12f28d99f5c2e97d02c7c0999c9f0af117e4eef94  546352 dataset.npy
6692ddb9f9bd0b2b0f70b711ef10fc08809c38df7769429faaf721234bd95520  560322 dataset_with_episode_ids.csv <- -
"""),
)
_INTERACTION_FIXTURE = DataSet(
    name="interaction_fixture",
    format="interaction",
    description=(
        "The INTERACTION dataset's own test scenario (a track file and a lanelet2 map): "
        "SYNTHETIC, 2 tracks at constant speed; a format fixture, not measured data"
    ),
    origins=(_github("interaction-dataset/interaction-dataset", "053213d8aeb4c6f6132d272325a11ae623bd4e35"),),
    licence="BSD-3-Clause",
    citation="Zhan et al. 2019, INTERACTION Dataset, arXiv:1910.03088",
    files=_files("""
5f5926d73e756102b69a74f9ecffe9e0980a9c66892ad2075e9582f21df58933    1730 LICENSE.txt <- LICENSE
bd8ee6194daa486e2e2c60a5148c505d05447e545dfbaae11d2ff000b17cd1e3     403 PROVENANCE.txt <- -
d9a7947d0db85774e2c6169b093f508d3bb6d47bfbfd39c3f6bfa5514ca325f4      41 SOURCE_COMMIT.txt <- -
15a373398fe5b2ffca47d1d6a1e52e0cf99651b539d300dcb1a235430e0d23b0    1632 TestScenarioForScripts.osm <- maps/.TestScenarioForScripts.osm
71c83b14956e5792c4a2e7368eab9118f91344bca3c01543eb3f75fb9c5857d3    6182 vehicle_tracks_000.csv <- recorded_trackfiles/.TestScenarioForScripts/vehicle_tracks_000.csv
"""),
)

_ACC_PLATOON_FHWA = DataSet(
    name="acc_platoon_fhwa",
    format="openacc_extract",
    description="5-car adaptive-cruise-control platoon, 1984 s, 10 Hz, SI (speeds and IVS gaps only); OpenACC layout, so credit JRC (CC-BY-4.0) to be safe",
    origins=(_github("usdot-fhwa-stol/To-21-426-multivariate-piecewise-linear-ACC-car-following-model", "11b7f2319fc55c8c680bde54dedc298f57eb0b1f"),),
    licence="CC0-1.0 (stated)",
    citation="USDOT FHWA STOL, multivariate piecewise-linear ACC car-following model",
    files=_files("""
922692d6b02babd7910a61c435dff3c5cdfaff4bf86702b1fcb8083ac9141974     455 PROVENANCE.txt <- -
8b42f7e407f20d2a81b275cfcfec0a7c9491ab80d69598f633a2bf6e9e48f756      41 SOURCE_COMMIT.txt <- -
d79aeca943321cc4ef2ddd93b2670e3dd1a68551aa1a9334ec0208669e83e433 2204823 data_example.csv
""", prefix="AV model funtion/MPL Modeling methodology/"),
    role="holdout",
)
_NGSIM_I80_PAIRS_A = DataSet(
    name="ngsim_i80_pairs_a",
    format="ngsim_pairs",
    description="NGSIM I-80, all three periods, 120 cleaned leader-follower pairs with lane ids; FEET, 10 Hz; spacing = bumper gap",
    origins=(_github("TeRyZh/Segment-based-Calibration-of-Car-Following-Dynamics", "89f4f0c2fc4bfe1d975c70c7ce681d080a16f19c"),),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; pairs from TeRyZh/Segment-based-Calibration-of-Car-Following-Dynamics",
    files=_files("""
6611002a4bd8da5b06fc4ca74a3dcfeb649b561eabedec7af4a89ef9cce0843b     679 PROVENANCE.txt <- -
825b9d37d8cc572ea22f71f65b32a18d82ebb0b9299a8d678dfd698f99022252      41 SOURCE_COMMIT.txt <- -
ea649c9bd8eab84fb635a2714c32ddd71e53fcdb8f385e1e28ba721404bf731c     861 extraction_config.json
a6e9681fd077204bde7b91659e7183a9967e92ae184939a1294553ce9e45ef14   42292 manifest.csv
7f43f938980511f36f9f9a56d75e191ce9e588b86057ae29ee6cb6a64f703b74   72581 test/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1542_l1544_00004.csv
4721bc9854882b245d84750ce9a9f675d377bef2bc97627ae9b60ea4aa663fe9   66720 test/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2358_l2352_00014.csv
ffdb2aa8204c653513339cb105dcdfacd833804b1e627acfb5cc7fd488451d85   70298 test/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f280_l269_00007.csv
67a1c405e79fc8ba50faff91c92e2024ff999cbd0bcb2025977e55c37a7aa024   90062 test/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2824_l2814_00006.csv
814ed58b9f696866b958bda2d95a85f9ca5542be6969ca2f571662bcb32d2b63   94651 test/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2853_l2842_00003.csv
39f2175eb304c277d929df4cafc9e28b53a3b5b535294fa5f9acb91c354854d6   76203 test/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f695_l694_00011.csv
bb6db5d0eaf1343bab746b3e6fdbf5827cc44f12ac07365e74e5c0da8d36ea2b  116867 test/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1097_l1092_00001.csv
2427f7a529af1d45f461439786acad6cc5db7e112fc585473295fda0e2dc75c2  108196 test/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1488_l1484_00017.csv
ab95aa23d3b63bca2a83eccd6a56cdc25813be16017fbdbfef48708a8a08d553  112374 test/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1542_l1536_00005.csv
df8c47e5255b0b43431b83d8d9e5db3e501f1088292133376923f7fe17d25a0b  111648 test/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1610_l1604_00020.csv
a5f56bc82e14bcbcb20c2d8367c26d2e7a4b142ca321f3f910587c96f85e63b6   98066 test/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1755_l1733_00010.csv
05143d7d2e9a7993bcbd9ae1e00b88dd7f140d773b2640937384706f133705d9  122298 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1097_l1089_00002.csv
c7a77964c182b6f3b1a7051a2b2f63a59f8928441a1352f55a6e661e74f2a48a   78179 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1242_l1229_00016.csv
432a8a5f072c4bb202b81765268aef2b95435d528df1f2eeb585998d9f0dc320   96801 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1402_l1394_00013.csv
5dba05b041f3f0101898a2d0077593d7b579d64287fe75c50d4b20361071a024   77067 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1488_l1483_00018.csv
5d4a89366c8cfab76479bb77f2588a32faa1af30b922d69444d3089f740da204  110868 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f280_l276_00008.csv
1fc738bda03a53155636b3f3a40da387ab153b89d9e9fb7c5fd5e70e91212272   74345 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f403_l391_00012.csv
1c8be25bc5aef7805faaa565b70e4f5585aad0dee2ebcdd24544279effcb73a1   86388 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f58_l48_00019.csv
cf91aeb9afdaa009bdbfdd9bd63a9271f6c51f1dd4be3dea8cb71e5d9727d0d1   99186 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f696_l685_00015.csv
c1a0c762624be2bab4c6172ec66874a613d6592e0341ce75d9601062713413ca  121679 test/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f874_l868_00009.csv
6aa7a384770a09e5774cac10bf3893251a47f9466fb44b7e78e0cc18eb0b35d4   64491 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1032_l1025_00046.csv
3587bcf743c6e00363f89733a8618c52d32969db05d3fe779cd53a0f5eafa7b7   78435 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f103_l89_00022.csv
edd625aa2fd519f4dbb0f1848735337ebc9d6d2ee1fb60d3164e413964b8fb8b   77346 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1126_l1122_00024.csv
fb9178b160a7b0df3fa31976a73334d964dc4f0eb5957276017ef4f797b7c61e   71374 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1157_l1149_00019.csv
dbb95391748443a3f941d919a06cece69531975fa158f71621cd1acd915417e6   65855 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1158_l1150_00068.csv
ba7ea2bfa3848ade9c2577122b829774489f2fa200a8809d0ec5cffbce20def9   66374 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1167_l1161_00062.csv
ede6e13509d440a22f40fb383bddaf4ae41936c5cde68e63b207273a24915ddb   64183 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1198_l1192_00048.csv
8dc59d9c6aadfd0a2832c812c20c6c403a809555628086192a181277da3780fe   76220 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1314_l1309_00060.csv
a5317044886c059cbe5daf8b6afd60da1a21ecc7bef2d43fccd47e562e34bccf   81433 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1367_l1358_00039.csv
c4bf1cf8f4a987918105e7beac4404a935000d8dab7ee4f973328ec9641f2700  104262 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f13_l15_00035.csv
855e85a0cde405668ff7130b4881e4cac1ef8bb2fedb1441ac4c9e2f6225f7ff   67506 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1437_l1429_00037.csv
fad3552f2551f35804ffc99d321c3777a93b40e7764fc101fb18fffe0b733a01   66885 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1525_l1521_00029.csv
47cd4683aed2527d8faf868a335bbdbd3d0d1db33d0d7259f358f11aa06c7834   70420 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1585_l1577_00041.csv
6707f51f0b24740efef2c9b565cf79b74e491716664d97f8ca4e8c769bb7e771   82634 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1779_l1764_00052.csv
517920e9e729ebd47784db2e415fd522aa6554457cdcb03977b78f2fd23be20e   74631 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1819_l1815_00057.csv
31e72d207587845023e29e99d315bc4a586e8747f80d7c8352a5a7c78c782033   63404 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1911_l1908_00054.csv
80486452e301aa22e69b2108eb02d538d75d81ba2e6a4e249c7d2bee9f66a690   82477 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f1954_l1914_00094.csv
0aa71b09166dc9798f002db32e8fbc4ac9c34a94e986ae7de1ab227e76eecde7  112917 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2013_l1965_00088.csv
4b0ab34d0bdd93a22c0ccfea5de042a2184021c613a50ed5fc36c7a58a7a70da  115499 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2045_l1995_00049.csv
0bc602657e42b42c3e74b733799f1bb311562b221aefd734b48c1478f7922afc   81979 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2118_l2107_00007.csv
3a2f780bbb8614508c155f66e1f64a95d37aaac42afba6de7facb2c6d67106c5   86730 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2122_l2113_00031.csv
c8462373a81756f82dbd374ae81925ab95f5a5a6e5fc24eb077a30db00650b3d   83334 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2128_l2122_00023.csv
42e00f0d29832193742ff2db1a85c96c63367cf265bf5768695de07497d07885   85659 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2132_l2128_00079.csv
3e1d863baa7b146964c22aaeee9b77dac8cea0ca8ad682f525e548ca1e786e7b   71609 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2257_l2252_00013.csv
f480e1880b06edde31ce60979a216aa5d53a3f746f2cc8a6a834d2b6b35ab7c7   81709 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2308_l2301_00006.csv
dd3e2e0828f19c5ebdbdbf23a55150a0d9ddeaa572ea88698991a2ddad6d229d   62831 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2394_l2384_00032.csv
b0a771c1eeac451a54c2573ab029946a6fa2a959a7a8e169a9febd225d1ce5f4   95644 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2408_l2417_00067.csv
6c937423c39a1dcfeef7357025cc33734461a875182d453f7b40459e1d59e35d   92770 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2411_l2405_00097.csv
2308af43ea8d61e9783635c69cae4945308fda5c553f80852b666c30b40b413c   74220 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f2774_l2775_00008.csv
6ce046bb98ee8671d82436daa55b1f24305457826e3de2b50c15549dbd0b926c   77723 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f293_l282_00066.csv
edcb15356015c48602028cb55e6c84735b132df88071753b7864a933cecbc3f6   68115 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f396_l392_00026.csv
1fb83ae85c07c03963aac9f471cb884b8151ffc7126ff23cd209fa7ffde755bf   80940 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f459_l448_00043.csv
806aa344e1339a2e64e27472d48bd76408373485eb308dea2b575abad9449d88   79742 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f469_l459_00089.csv
3d9a20efb56708a5c7aa578ef95d1ac50b185deb1ec76b983ea1bf3f8344218d   70222 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f479_l470_00017.csv
f3d40dbff6c67948a260a8ba0f5b4af4afaef5c4ecf8cc399c7cbc019f8aae54   76942 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f829_l818_00083.csv
67d2611421712ad250823964b486c59755313cf38a991619be092f826d5d10b5   71071 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f868_l857_00071.csv
a04a81d2cb33bb1dfa63f683ba90a080b39f0788916dbb3fa6a91bc23589c2ce   69946 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f889_l876_00075.csv
31affd4cd2308d7d94cf3ccc79d5779b1253966fd858d91b6fc92b0dc33ddaa9   72866 train/ngsim_final_I80_trajectories-0400pm-0415pm_runfinal_I80_trajectories-0400pm-0415pm_f903_l875_00004.csv
13e2c8649796c4cf9745575d7393ed6468d022bf0b3e9298ee2dc36fee1dedd7   62368 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1032_l1020_00047.csv
47494c87f4370f3c75d82e12178b98e662cc637bbfff600e1cd94a6f6d5d84c4  110579 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1061_l1056_00095.csv
3ccf436cdb5121ea992fa27edc9f3838f7ab08eff979dfe5fac59a2c77182ee6  109196 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1115_l1108_00012.csv
874b9a349b63d0bea05da1c2c2129e900901aa1f2b7b47c4f34326549a8c3cca   63661 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1158_l1156_00069.csv
c4a464164c61f58c523198ae735a472725d2991dc53119b3f1c0eb837e3d0cad  117895 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1278_l1267_00098.csv
56ba19945f400cd8f16eea80fe1bcba8c709a2edad6f470ef0cd59be0ae9f844  135294 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1314_l1311_00061.csv
eec204c62a48771751292be84e8e116daa413ff2adcc7d8b9ee1dae80fe37a11   68723 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1325_l1320_00063.csv
4dc5d5d0cdeeeebbfe1d2c4da99438c4d36d797596976ef4b4465146b1636004   76450 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1329_l1323_00018.csv
221ec71591982e1c72d2471deb30c61450a1c08176267b7effc17d11ec8975ac   66153 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1367_l1358_00040.csv
4aee01425bb8a0e2c2ba73e70cc93bd0e15a008d2f50657e9865395718c82f9c   63462 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1380_l1376_00091.csv
62187b9a851febbb87ee7fd3dfc82c36bef3d1e241c9729b1db56639b231d589   74176 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1423_l1414_00073.csv
4b2e0b7997c47228abbb79032b5b3e61419d9163cd8262e85848177c86441251  102282 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1429_l1420_00064.csv
7f817616c85b8548f774ca9d0e7e292ed58f598b87b99b5150b47ed4a70da976   91497 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1437_l1434_00038.csv
73d4db08562d5edf54034e06fe83f93aa04b8b64854ac4d0ede957aebfdd0730   84982 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1480_l1466_00082.csv
77f83a56fb12d94421f05a14495172de1db2d5cf2f58e113f92568944c924e04   89819 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1525_l1520_00030.csv
4988380da94164249706d526c0aa07fda9700493910d4d46df6c36de984b1fa8   75432 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1574_l1566_00080.csv
3e1ca38533d6be234e784ff4e6ef46123ac095d98b804aca42dc7c6c25c5033a   67411 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1585_l1581_00042.csv
2047871e434ed701ee8bcff38dea1b25d2008aa28144861b3720d1fa64400fb8   63413 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1839_l1830_00074.csv
c5989f6c3e37aaac3e03e1b114778ef3676772ad5a676307eb02d1967b1fd5ba  192499 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1911_l1905_00055.csv
1200e5c6c8ab523b617cddec6891eb4bd4fa8a149d778b09ece570e61619fa88   82200 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f1972_l1945_00025.csv
aaf6c9af6525812a92b8896fbaff6db51f5bf40d29be86ab7eca0a64fdb34590  167791 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f2001_l1990_00033.csv
c69330844ea9567d57a5e56332faa2ce392ad4e5e24794b564cbb1902fc25e9f  178594 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f2045_l2044_00050.csv
683c2594a4e3366a77bb577aabd184fb2cd76f767421c4d7f787cdfd8b46024a   73469 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f396_l397_00027.csv
5eaff8e7ca3f7f511e3bb17e42c7c24d3af15cb736fbfc7c0883cf183f5c1dff   80950 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f459_l453_00044.csv
b24c9fd710de85e16531c21195ec34b86bad31e33497125f2178be21810fad18   80392 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f610_l604_00086.csv
10d3ffa5ec5a52b6f7c7d98ee879914231b4b48b55ca7ca5c4e1f551feefcde9   64715 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f711_l701_00036.csv
c7b914e0e4300ed0eae5f58d37526b465fd31d7295d2f6f78b294b865a4d4691   92981 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f755_l751_00001.csv
81462ef58cdc6eb8bc2801daab9c08221aeb1712d83118170d1d3f3f5c388f77   87055 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f829_l822_00084.csv
63d04978c8f333a3dde052bcaaaa1e8e61a629748508391f727af86701962b2f   64630 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f844_l837_00010.csv
d791aba7180dc61dbe7bfcd012184d7d9ae510adc0c62fd50bf2e0efb98c23ce   86042 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f846_l835_00090.csv
96330375a0290fea243d84782beb8abb68b33a4eb06f3409167f970b2f6b2762   64038 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f882_l876_00015.csv
29b2ab4862cd9f3424765e6d3b7aeded0d6345b84f7d8f124a0195f563b801cc   84010 train/ngsim_final_I80_trajectories-0500pm-0515pm_runfinal_I80_trajectories-0500pm-0515pm_f929_l916_00014.csv
87167531c418f9016f87887064a4ac3f6a2ec6cee279dd31148a1273ea58a172   93898 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1061_l1042_00096.csv
b6bad0dc13b256e824e0d48288adcb1d7d121800b8fb7e1d1c76ca4a94cc6a19   75117 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1157_l1150_00020.csv
67d7515aa2487050b690a4d8e79946c038d8e5dea64534713ed7298caeed3726   79766 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1215_l1208_00051.csv
fc3f3e7a1aa3e0db8faf450eb9fd9ce9bb59e9ffc9e7e20feff2726a8d8c355f   68343 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1278_l1273_00099.csv
d4edae15945c118a2eb441d9c754e58e1126ceb4c1149571d622be6101ffec31   99473 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1380_l1366_00092.csv
c25fa3909080f1794c00ec2fe0b296d067bb9b845f2ba5ce1ed942ce9aacc5d4  103153 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1416_l1409_00021.csv
1e23a0a41412f33d05b054d8281f713170832e4aa1b9fd6ba17330c6df838de0   75206 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1429_l1423_00065.csv
8527b9fc78b0708b369fdeecdccad58f2011f5518b9d16b164b1d9a9d80c1dad  149962 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1551_l1546_00078.csv
ad3c4463fe51e0563966492dd31375e605e0fc51ccd55d267dd1d79214e0fd8b  189959 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f1574_l1565_00081.csv
d3d640263a265e3d25c305cd5a841b6e4d11345e9ce0b55d32abfc295f19e3dd   79840 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f198_l180_00093.csv
abd856f431f76b53ddfd40fb7b16ae1b5098dc3162d82e812d4e375efab6bad3   95597 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f210_l194_00070.csv
6a5c72c6839fec3ea685ab42ee75b8cdfa8a31d774438885d6318ad97a4e5db1  104786 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f252_l265_00002.csv
831836abfbc85486e0e15db571907ebad4c1cadd6bad9042507a7bfb2b1314c6  103457 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f262_l252_00053.csv
b81610f0c515deaa96cb651248bc8c287b6e45f4e8a586c62f376f2e64e9ce95   67596 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f309_l302_00085.csv
fa3a0053c2c02910728b5ad2de4760371a2256f07ad15f1f09032b6a065f2732   82744 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f317_l301_00059.csv
94f02374d00e65a51ebcf0b7f44eae6eb465cf9e5ec0cf1720f1c01fb5ccdb0d   74906 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f396_l387_00028.csv
f80eb13a3e0d734ec6923326671ea9482ecab86d68ebe9c037853d0bb19e8217   72704 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f443_l415_00100.csv
07871e5b6a3fa267c1c4c433422fb01ff2ef87f34b75f5ca2aa938cc64229ea3   67685 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f459_l454_00045.csv
963378c78cfe09e928f543f7ba89723529050815b0c8f5188972b86169bac2d2   93986 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f461_l453_00058.csv
c764d6a457eb946afcbdec73a17c0be83d775ff41c7480bdaa1c8ef4f18fe365   67661 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f493_l484_00077.csv
d86f831b7671369137f38a63492a30506afb22b221992d3d6bb73db7622b9ce5   68202 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f582_l573_00016.csv
faf48768f900204055751c88efa43bcdb782c0265c612a4dfefe1a9c15e08475   66174 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f610_l604_00087.csv
b96071316699c69ebdba543cc2e40e6fc2d248a6dc904b24514ae97c1d91ada4   70442 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f620_l610_00003.csv
444bc2d6be4e9579a382002e8988505c7db0d0b7fc9fa6ca973cb74ffcf3b652   87077 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f69_l59_00009.csv
20d7be904e3185def288c81fbb1fdc5b8cb9969efabd1eb48bf18a6768c85b21   88932 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f779_l769_00034.csv
8dbedc2229e55dce0e1f0d6c7636115453d166ac587e5296d33a09659fbad55a   99731 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f844_l836_00011.csv
bd7f1455ce3d5c0193ce3df819c63e6158e40cf8aaca89e6db246ef866743685  118427 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f865_l857_00056.csv
68223f86215ad4ca68ba8223b6764c666fe53d8159c69fadc60aed8a6f786b3f  117324 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f868_l856_00072.csv
48b725b6fd7e0f6b20557416ecd925c5820b370546cd4346ef76c5f370c3bc9a  113721 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f889_l880_00076.csv
c7b468e099663ec8c710a16bf7e17ea02893630738aba5ee8f5f627730e434fa  113955 train/ngsim_final_I80_trajectories-0515pm-0530pm_runfinal_I80_trajectories-0515pm-0530pm_f903_l898_00005.csv
""", prefix="cf_ngsim_I80/"),
    role="holdout",
)
_NGSIM_I80_PAIRS_B = DataSet(
    name="ngsim_i80_pairs_b",
    format="ngsim_parquet",
    description="NGSIM I-80 4:00-4:15, 142 pairs in lanes 1-3, lane changers removed; metres, 10 Hz; front-to-front headway",
    origins=(_github("durraniu/R_workshop_materials_NGSIM_data", "cc1d26429f15d150b7ee909b0d49bed1f17e3bd7"),),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; tidy pairs from durraniu/R_workshop_materials_NGSIM_data",
    files=_files("""
ae3aebfd6c0da81341616966c6e1538c86a5b8e142514390500d9b491a8c0ac4     449 PROVENANCE.txt <- -
48a47adbe3f087fcb43bfd7059a6a56ae88f6639170d721eedffa8707fac9d3f      41 SOURCE_COMMIT.txt <- -
7674222de710fb17fcb0895f0104393d3e48408676b72123229c6c37e9a2efc8 1430082 df.parquet
""", prefix="data/tidy/"),
    role="holdout",
)
_NGSIM_I80_PAIRS_RAW_C = DataSet(
    name="ngsim_i80_pairs_raw_c",
    format="ngsim_matrices",
    description="NGSIM I-80, 150 pairs x 35 s as wide matrices, raw-like (acceleration clipped); FEET, 10 Hz; no ids, lanes or lengths",
    origins=(_github("jiangjiwan/Approximate-Bayesian-Computation-Hybrid-Car-following-Model", "64a2872a7dc90cf59a137b3cbbcd57a1981f55f8"),),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; matrices from jiangjiwan/Approximate-Bayesian-Computation-Hybrid-Car-following-Model",
    files=_files("""
9cc4b420af14057640285989727cce1417329620c6dcb7e041efcd7983b5663a     163 Description.txt
e4b426832d2c62dc5bdd5ad0771eaa20741ba57624ff01f597de6d5f94a8bee5  393107 Following Acc.csv
04473a6bc095407d71b2fba20f4109dee4ad7bc04329c4e415fc0e7c3b21893a  474355 Following Position.csv
7668f3b019f55d68777e7ece6b6d21c51cbffed08a60b381d7a813d24d4c2d8e  401399 Following Speed.csv
708ed73832499ef2106b5165ce07dde40b608d69beb03e7556a04a307be42f8c  393574 Leading Acc.csv
36dddc0633bad359cc09b97853f2a6963d66755929c063b4714a355966b9353c  477962 Leading Position.csv
7266caeb5683d60ff87b7a59e1fce289d01f4228f027f5b0b71cabe8a2ebb5f3  401563 Leading Speed.csv
eb2ffb21bce2dab9333f2d67ac6f483490899939629d95e5ca7febead0addcff     513 PROVENANCE.txt <- -
b904d9c4427891e18b184930ab526cb1b11a9fe0cd4e186d34048bbb80a0c04a      41 SOURCE_COMMIT.txt <- -
b16f986e64012a32870c4ce78a579e438aaa50d2fdafb1814a14b7649e9b82d9  118510 Testing/Following Acc.csv
6872b08d749a5bd01104333eaea506f57e9f80ad54a085cf9b29755fe8cf64c7  140720 Testing/Following Position.csv
fd6502d54ca6ffce179b147a06e87749456aac150bdb25f01769c73f38795d36  117591 Testing/Following Speed.csv
61d192471ca57090503592ddf3e282211a61b8b321cc6dfac1399a01e73123ec  118637 Testing/Leading Acc.csv
a7189c399bb2463a46a25a9acdb4f3af2f8ea061293aca46691a362571f7307e  141702 Testing/Leading Position.csv
82b0a0ea1558b6821a1bb4952b0fe9a18baf07325f482f5ef674a02009f7b756  120099 Testing/Leading Speed.csv
fb8b6289a128678aca24df51e8588e91817eebe4e80d87b6a82b6333208d9d7c  274947 Trajectory/Following Acc.csv
b247618ab6ac6daf9e84f66498f3b7ac57cc6325dddea2dff0fa3da4f70b26ac  332180 Trajectory/Following Position.csv
d91348fef78083606f487f0e37767f0b88efe59414d3a825d3bb09be785a1987  281766 Trajectory/Following Speed.csv
97d3596762ba09d9e77dbf5ab5475b7773086d9ca8c8d5e743a7fadbf8ff64e2  275287 Trajectory/Leading Acc.csv
6b6bdcfb57a887d707e616e8f33bc9142ba564fdb3d00aa1da41fbc0b5b64071  334798 Trajectory/Leading Position.csv
bb5e396ee3688da8419d2023c0b7962872c50719a03e7a07ba3be19c6aa0dd02  281814 Trajectory/Leading Speed.csv
""", prefix="data/HDV/NGSIM I_80/"),
    role="holdout",
)
_NGSIM_US101_VEHICLES = DataSet(
    name="ngsim_us101_vehicles",
    format="ngsim_vehicles",
    description="NGSIM US-101 7:49-8:34 am, 60 single-vehicle files; '(m)' columns converted with 0.3084 instead of 0.3048 m/ft by their source",
    origins=(_github("chenshimao/NGSIM-FORECASTING-WITH-LSTM", "4cbcb8b4e76a6755bbc09abca75c51297b2886bf"),),
    licence="none stated",
    citation="NGSIM, doi:10.21949/1504477; vehicle files from chenshimao/NGSIM-FORECASTING-WITH-LSTM",
    files=_files("""
f1abc2dc43817a81392c4f90335d21ee4b67f54de844c6fe8a43e02259736987     585 PROVENANCE.txt <- -
c5b113aaadead59e9730153ad6bca3221c46b234b0ba92bc19358b35a2a5ea63      41 SOURCE_COMMIT.txt <- -
2e08f0604f1b6135baf3bf3d2dc466fa234df53ba9a2d76272e56de89ab3cc08   59301 vehicles/104.csv <- ngsim_data/部分数据/104.csv
dba10c5f11d93a193bb5830419c316fabd19da9b8ce541d48b6c06f5a26796e4   74090 vehicles/11.csv <- ngsim_data/部分数据/11.csv
1786e8b8892575f16921d809b0e3365261d9892a41c2673a80a9df637ae2f59f   66631 vehicles/110.csv <- ngsim_data/部分数据/110.csv
94c43193146ec366b34df970efc21f17d60948cfc209d77cd237b54df0693fbf   50148 vehicles/114.csv <- ngsim_data/部分数据/114.csv
c53cd0dd6e27c09b915b7c03445829f3296fc9e115ef2dcdd190cf41fa01fc66   55426 vehicles/115.csv <- ngsim_data/部分数据/115.csv
f8c5c98603949f24093c7d0e2c64e415cea7b159aeede24d1083158222969877   54783 vehicles/116.csv <- ngsim_data/部分数据/116.csv
b7d611836957b1cecf17049abbda64c3290b7c09ffce187d32fd7b2e66f6ef74   53063 vehicles/124.csv <- ngsim_data/部分数据/124.csv
5b2257623d08e31741393d428018b6a996e11b6b9e56a77df51ba3125be22df4   53131 vehicles/125.csv <- ngsim_data/部分数据/125.csv
343dc8ad33f856d66d578acecaffa352fcfc69609fcc4f5285f00476e987502e   59285 vehicles/148.csv <- ngsim_data/部分数据/148.csv
eda34d15ed577f125cec3e08f7acb6a70b4b889180f28971ce168abdb5ef6f8c   67385 vehicles/155.csv <- ngsim_data/部分数据/155.csv
9de41099d47b1f6bf5e000b841e51c9c51cdc0acb046ffc896d1d765780584d8   43819 vehicles/190.csv <- ngsim_data/部分数据/190.csv
0434631f4aadeab9b669c1c093053bf39fbfec156f7efacd58e392f28bb2733f   45597 vehicles/198.csv <- ngsim_data/部分数据/198.csv
9179cadcf6b9d06b618ca8fd7e173b687526db44a157362a47a8806c2193df84   63926 vehicles/200.csv <- ngsim_data/部分数据/200.csv
62eec1c4872579bca6b03b9ef8e1401ac537ad62cc0fc37962acb64b7279d937   57570 vehicles/209.csv <- ngsim_data/部分数据/209.csv
1678387ed8499164180d34c3466176cdc6508678b4c26da2a9d255991ca89c65   47817 vehicles/214.csv <- ngsim_data/部分数据/214.csv
90bcc36c2e0b34b53d470b65a3c6c9b40090fb08413cff8d31e7e037555c9b75   50037 vehicles/217.csv <- ngsim_data/部分数据/217.csv
19db885dce11e5691b19ab1c46091368c3c80affc4f5558faaea12f227984a16   53416 vehicles/221.csv <- ngsim_data/部分数据/221.csv
63c59db4b0a0e8e83563642a4ab9ea532886d5d4ce79f742821abd603881718e   55215 vehicles/227.csv <- ngsim_data/部分数据/227.csv
0afd8cb68c4365e5910f5baf3689133edf31af35f349d9467175668c762997f9   52134 vehicles/233.csv <- ngsim_data/部分数据/233.csv
e17f4dd70711703803f15966d550fbe45e54e94162828049bd82e1ce9ec5df28   59363 vehicles/242.csv <- ngsim_data/部分数据/242.csv
2adc506457027811bfa7daea6484dc6d73e6396238361165cbdb7b33834c91de   62562 vehicles/243.csv <- ngsim_data/部分数据/243.csv
8abcdf8d79e8481611eefb96a663d819403edbd8a8050b2f24201d45aad3f41a   59616 vehicles/244.csv <- ngsim_data/部分数据/244.csv
39837c2b0281b264090dbec51498551c3b7f65ed69971552d4a4fad5a0ffad8c   54608 vehicles/245.csv <- ngsim_data/部分数据/245.csv
40d74a9ef5ad904b8724a9776f72242407c05900c0840afeb1ddda58d64603e5   50294 vehicles/249.csv <- ngsim_data/部分数据/249.csv
81025554e61c100ad1c8b72ddc56028bd5708ddad92e08e5f55d7710273088a1   58160 vehicles/250.csv <- ngsim_data/部分数据/250.csv
e0558ed4ff004ad88048604dfd37ebd79d1af8f8625f3f3c6bd6a022d6f24bca  105667 vehicles/274.csv <- ngsim_data/部分数据/274.csv
8141694e97e89788578add33d4b94d5e4c9e5eafbe71623a687e74f79d2620b5   58281 vehicles/275.csv <- ngsim_data/部分数据/275.csv
df2b0b372c5ec94521e994af89e16fd94e1b7c75e13cedc6e5cf7f89f0f1112d   61703 vehicles/291.csv <- ngsim_data/部分数据/291.csv
a4e921dcfbfd8dc22adccba92f92d7847df718f2a82d26cf1b9f4438c8577f22   64643 vehicles/299.csv <- ngsim_data/部分数据/299.csv
64bcc11d17ba3a5e321a87d6a1fc41c202b3627fd66b5c9cc2d4729c8c9b79ad   60001 vehicles/305.csv <- ngsim_data/部分数据/305.csv
bb02b1f13640f62ccbde32921fcbec83957d8191d60b5b11e9a30da1236cc0f9   51814 vehicles/308.csv <- ngsim_data/部分数据/308.csv
ddba1ed23d665382d0ee13a06a89105aac4bab9d08ebf97666fedda3d87eceda   55702 vehicles/31.csv <- ngsim_data/部分数据/31.csv
6cbbe18add7c8aa630b4bc084d7a43a801edd000126f38d45663514166f54ce3   59058 vehicles/317.csv <- ngsim_data/部分数据/317.csv
5a16024a430791498796430d2f1d0f72a9a1edefcae1ecdab59fe2dfe4e8bdfe   51314 vehicles/323.csv <- ngsim_data/部分数据/323.csv
20fe1badaab7017503b6292f3b9fa9e5695e78f4ee9fa7bb3624b0cee9f0fc53   70909 vehicles/325.csv <- ngsim_data/部分数据/325.csv
e154478438ac342dd53eaf23b830ea14e89d4b89c0c1cc27f6df90934f82ffc8   58801 vehicles/329.csv <- ngsim_data/部分数据/329.csv
aec2a9aa5d0228c874f1f8105fa319e405b421df5bac16b7e3d34658cf92764b   73558 vehicles/336.csv <- ngsim_data/部分数据/336.csv
46aeb45b53a2dd4b310f3da0e77d6d9e99f63788a3012ea731e370d1bb82e1a7   85796 vehicles/337.csv <- ngsim_data/部分数据/337.csv
56112e27fb4f56e775a2ad2c0f958c99ebe4230c9c1ae436b39a69d4b151c6f8   49498 vehicles/350.csv <- ngsim_data/部分数据/350.csv
559e45bf4d77736841998ea4ac6da783bbaa6c9190cd0b93fad198922edca2ab   52254 vehicles/366.csv <- ngsim_data/部分数据/366.csv
effc59adc8d185088d4d46b69c694c91dd9bfeaf45599cd4f1cf64092cec9da1   48453 vehicles/37.csv <- ngsim_data/部分数据/37.csv
6ec9df1461a90da6b996bbeb11a42834ea7b46ba37e9e9d3585dd9abf7b173cc   78945 vehicles/376.csv <- ngsim_data/部分数据/376.csv
4250b0f43a393a7f06e272f4f5ec855b0430857eb3d1eb0d566d62b1a2345f6b   58033 vehicles/388.csv <- ngsim_data/部分数据/388.csv
94fb9fd9982fbe32839bbfa2f6ac04a8192db8b468daddf1a4caa9a5ca830fdd   78688 vehicles/397.csv <- ngsim_data/部分数据/397.csv
0dee5e4df771376c3f71618db489507d2e5f35c991a0909db2abffba3455bc8c   46501 vehicles/40.csv <- ngsim_data/部分数据/40.csv
69800e280117384b5ad06b2de5964ebfa5823798c861a1b7425fa130a6405d03   32292 vehicles/407.csv <- ngsim_data/部分数据/407.csv
4119fa4681f6515b60b8d75ecf51552832bc55f944f93a6b32659c847c631a9a   60112 vehicles/410.csv <- ngsim_data/部分数据/410.csv
221a55a38d25d4cb2d761cad1cd1be60d82e9ce5352d266868cc8e96ef65b8de   61287 vehicles/411.csv <- ngsim_data/部分数据/411.csv
248b5d1d4f2fa6fc4d98934dccbcd00a48aa06d13829d610fd3212622c703a5e   59396 vehicles/415.csv <- ngsim_data/部分数据/415.csv
1352532a4ec2412de05e1ae2c9d50825c3a29e3c530f94a3309846ffd9916b94   48853 vehicles/49.csv <- ngsim_data/部分数据/49.csv
9b5ca5b37fad45520b68e73a1f36d308cce44071f1d2aa26ef144d70db8e412f   50946 vehicles/51.csv <- ngsim_data/部分数据/51.csv
dd91ab273a892798fe775bb105e54dbffc79324d3611d9fc2a777a9dd4424501   57559 vehicles/56.csv <- ngsim_data/部分数据/56.csv
2ae57239ee559e0687b543b402c10bf3ff3e494ad861aba62fa6ff519e25d4d9   58093 vehicles/61.csv <- ngsim_data/部分数据/61.csv
a0dc8bd5b8b4eace4821410e28bc0002c2fe1fa5c0c0e6e35873f7655529240c   49689 vehicles/64.csv <- ngsim_data/部分数据/64.csv
918741db7c51c1912c20fa00083a5c80996144530c0d3d993fe96a2c5b738336   60241 vehicles/69.csv <- ngsim_data/部分数据/69.csv
9ab0e6cd7d46bb04797aba78020c68c4ffebbe86dc736e4a773cfbf8e312bae9   47440 vehicles/76.csv <- ngsim_data/部分数据/76.csv
36dd02175ec38f6a4ee5ff8c33d4ed002f882ffb6353c81504c195137f539ef0   51342 vehicles/79.csv <- ngsim_data/部分数据/79.csv
db036040022a5510e22ffe894c81b3e53ba4e3df6aa7a32db05813f86ba9b5ce   67528 vehicles/81.csv <- ngsim_data/部分数据/81.csv
24881e046eb8814af8944dcabd11564f4e9a6a4754b66dbdd6b7780b7f37efdc   54434 vehicles/91.csv <- ngsim_data/部分数据/91.csv
65998c4dd4d2ccd8de8ae6043b01dd922f6ea7a239531702f46ac0a70377a3e1   62044 vehicles/92.csv <- ngsim_data/部分数据/92.csv
"""),
    role="holdout",
)
_OPENACC_CASALE = DataSet(
    name="openacc_casale",
    format="openacc",
    description="JRC OpenACC, Casale: 2 cars, human leader, follower on adaptive cruise control, 24-41 m/s, 10 Hz, SI",
    origins=(_github("mu2zhou/GT-Project", "261fc97b82ded1eab1e47c8970514da227b7c9dc"),),
    licence="CC-BY-4.0",
    citation="Makridis et al. 2021, Transportation Research Part C 125:103047, doi:10.1016/j.trc.2021.103047",
    files=_files("""
67841e3fb8317d00a6c5f71cb22789d24baf5fc89f5aac96be06583c5708a6a3    2167 Casale_notes.txt
abf18c663325ba97a5204f6994a201a53afc2fa3a85cdb4f4c8310b54df624ea     469 PROVENANCE.txt <- -
9337acc900c837a3cd12b9672cdea24b01695ebe2d592b4f9cd4388a98fa06c4     237 Veh_specifications.csv
35eb9c10f5a35d65d54918b5267232553da44a89866c2d1db63bb285a21dffe1     540 copyright.txt
0026f4a2ddf12f142b71e3b1054bd645f620a82ae01bfcba3c2d2d2ba8ec21fe  900973 part10.csv
db1640d233ca3744def1ff3bbfddd79c6b9d141bbfb76f001aa49b29e9d73d5c  873524 part11.csv
9f52b0b1ec33413f6057083c6cb09042ed807207b7b8f223ec038071f72e8bc6  675781 part3.csv
c2c73a2af5d63e1b389c218aa78d1c548855130eb4aeeef01a8691acb4cd0bed  304950 part4.csv
7bb32b84eb6465520e1a3a8a9e0ddbcb51991b56cc4422ef81b11c753921d2c5  280178 part5.csv
11deea2d3a01fe264cffa760439c93f9f7cc2a2ee7d64ed3c6c4e96a6faa74de  266595 part8.csv
f4c8550f0c5a0b079752b19767a2f7d4596e363c4b7ccc5991f6631cc3576840  411616 part9.csv
""", prefix="Dataset/OpenACC/data/Casale/"),
    role="holdout",
)
_OPENACC_ZALAZONE = DataSet(
    name="openacc_zalazone",
    format="openacc",
    description="JRC OpenACC, ZalaZone test track: platoons at 30-60 km/h, most on ACC, one all-human (no_ACC), 10 Hz, SI",
    origins=(
        _github("thibault-charlottin/ACC-platoon-fuel-consumption", "8781ec31a976113210a9809b98345c76594c3896"),
        _github("mu2zhou/GT-Project", "261fc97b82ded1eab1e47c8970514da227b7c9dc"),
    ),
    licence="CC-BY-4.0",
    citation="Makridis et al. 2021, Transportation Research Part C 125:103047, doi:10.1016/j.trc.2021.103047",
    files=_files("""
ed1c88a5cb22131fa691e81645d44753fd141386394448ffcf2ccbca424dc679     126 NOTES_PROVENANCE.txt <- -
3ea93a05ad9f7cf0ba4140e65e879c389345753b3f60f6934146b47f3f5e5170     387 PROVENANCE.txt <- -
b63790e02a01fbef490210cfda2b4336186a1be6d52ba4992feea2d309242852      41 SOURCE_COMMIT.txt <- -
8c6bc137d986a65d655da9aa6dae3bd174b9172c066d0ca478fb616565b2a5ec     647 ZalaZONE_veh_specifications.csv <- [1] Dataset/OpenACC/data/ZalaZone/ZalaZONE_veh_specifications.csv
1f47b0130acd3df704157cd5c1a1e179ef2a9f5977e935ca6d122027c8cae9cc    4380 Zala_notes.txt <- [1] Dataset/OpenACC/data/ZalaZone/Zala_notes.txt
35eb9c10f5a35d65d54918b5267232553da44a89866c2d1db63bb285a21dffe1     540 copyright.txt <- [1] Dataset/OpenACC/data/ZalaZone/copyright.txt
8071e7ecb00b90f8d488d23aae1bd35911c60be416ea8f16a758eb033fc1eeab 1017043 long_setting/dynamic_part16.csv
5d6dab96f35ac9da3d623ba4a5d311fbf0accb25bab8e52bce495dec5236e04f  703545 mixed/dynamic_part7.csv
d6a41ac1a315d6d73723cae3de2189d807e195d9a2495e40383f745b6b110d1d 2256871 no_ACC/handling_part40.csv
63efb464aad5ab1b70c88033a77aefae253a7d43a1d9280d1083d35d416f6ab9  354335 short_setting/dynamic_part22.csv
eab51b8e26c5c6226571179527a90eb8ffc55399100cfd62a370ec6fc43c4f2a  703450 short_setting/dynamic_part23.csv
11310c5beb3f2784cc2cf5f70397e9b961fc92c29becdce2bf2d31290274fb4e  393497 short_setting/dynamic_part26.csv
74b685d3be11eb3735d46d0b59e55d8677cad9c104030aee3f9349cc57742a71  835237 short_setting/handling_part45.csv
""", prefix="data/OpenACC_data/"),
    role="holdout",
)
# fmt: on

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
