"""The position/speed ratio of every training data set, the figures that set ``INCREMENT_RATIO``.

``bayesdrive.data.validate.INCREMENT_RATIO`` bounds the sum of position increments over the sum
of speed x dt. This measures that ratio, as the check computes it, on the training data only
(``$BAYESDRIVE_DATA_DIR``, else ``../shared/data``; never the held-out folder): per data set as
``load`` reads it, per file read alone (what a user reading one file gets checked on), and per
vehicle with enough motion for the check (>= 10 steps, 20 m), the spread a short file of one
vehicle could show. OpenACC files add their ENU path over integrated speed per car (the
separate bound ``ENU_PATH_RATIO``). Prints one table; run:
``python benchmarks/unit_ratio_bounds.py``.
"""

from __future__ import annotations

from pathlib import Path

from bayesdrive.data import registry
from bayesdrive.data.readers import read
from bayesdrive.data.readers.openacc import enu_consistency
from bayesdrive.data.validate import increment_ratio

# A data set's files read alone, by format: the patterns its reader takes one at a time.
FILE_PATTERNS = {"ngsim_chains": "*.csv", "openacc": "JRC-*.csv"}


def _span(values: list[float]) -> str:
    return f"{min(values):.4f}-{max(values):.4f} ({len(values)})" if values else "-"


def _vehicle_ratios(traj) -> list[float]:
    ratios = []
    for _, rows in traj.tracks.groupby("vehicle_id", sort=False):
        found = increment_ratio(rows, traj.dt)
        if found is not None:
            ratios.append(found)
    return ratios


def main() -> None:
    folder = registry.data_dir()
    print(f"training data: {folder}")
    print("| data set | whole set | files read alone | vehicles | OpenACC ENU path, per car |")
    print("|---|---|---|---|---|")
    for dataset in registry.DATASETS.values():
        traj = registry.load(dataset.name)
        whole = increment_ratio(traj.tracks, traj.dt)
        files, enu = [], []
        pattern = FILE_PATTERNS.get(dataset.format)
        for path in sorted(Path(folder, dataset.name).glob(pattern)) if pattern else []:
            one = read(path, format=dataset.format)
            if (found := increment_ratio(one.tracks, one.dt)) is not None:
                files.append(found)
            if dataset.format == "openacc":
                check = enu_consistency(path)
                check = check[check["integrated_m"] >= 20.0]
                enu.extend(check["enu_path_m"] / check["integrated_m"])
        shown = "-" if whole is None else f"{whole:.4f}"
        print(
            f"| {dataset.name} | {shown} | {_span(files)} | {_span(_vehicle_ratios(traj))} "
            f"| {_span(enu)} |"
        )


if __name__ == "__main__":
    main()
