"""``bayesdrive diagnose RESULT...``: convergence of each result and agreement between engines.

For each saved result: R-hat (two or more chains), bulk and tail ESS and MCSE per vehicle and
parameter (ArviZ), NUTS divergences, emcee autocorrelation times (see
:mod:`bayesdrive.inference.diagnostics.agreement`); for a hierarchical result also how drivers differ
(:func:`~bayesdrive.inference.population.summary.how_drivers_differ`). With two or more results on the
same data and model, the agreement table of every pair: difference of means in posterior sds, sd ratio, Wasserstein
distance, and the verdict |Δmean| <= max(0.1 sd, 3 combined MCSE) with sds within max(10%, 3 combined MCSE of the sds).
``--out DIR`` writes the tables as CSV and the pictures (marginal overlays, agreement heat map).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from bayesdrive.cli.common import (
    ForceResults,
    JsonOut,
    console,
    emit_json,
    fail,
    optional_results,
    results_command,
)
from bayesdrive.data.atomic import write_text_atomic

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["diagnose", "worst_convergence"]


def worst_convergence(table: pd.DataFrame) -> dict[str, dict[str, float | None]]:
    """Per parameter, the worst vehicle's figures: max R-hat, min ESS, max MCSE / sd, etc.

    R-hat is None for single-chain results (emcee, particle engines).
    """
    worst: dict[str, dict[str, float | None]] = {}
    for name, rows in table.groupby("param", sort=False):
        entry: dict[str, float | None] = {
            "max_rhat": None if rows["rhat"].isna().all() else float(rows["rhat"].max()),
            "min_ess_bulk": float(rows["ess_bulk"].min()),
            "min_ess_tail": float(rows["ess_tail"].min()),
            "max_mcse_over_sd": float((rows["mcse_mean"] / rows["sd"]).max()),
        }
        if "divergences" in rows:
            entry["divergences"] = float(rows["divergences"].sum())
        if "autocorr_time" in rows:
            entry["max_autocorr_time"] = float(rows["autocorr_time"].max())
            entry["unreliable_autocorr_vehicles"] = float((rows["autocorr_reliable"] == 0).sum())
        worst[str(name)] = entry
    return worst


def _labels(paths: list[Path], trees: list[Any]) -> list[str]:
    """The engine name of each result, numbered where two results share one."""
    from bayesdrive.inference.core.output import metadata

    engines = [str(metadata(tree).get("engine")) for tree in trees]
    return [
        f"{engine}#{i + 1}" if engines.count(engine) > 1 else engine
        for i, engine in enumerate(engines)
    ]


def _print_convergence(label: str, path: Path, worst: dict[str, dict[str, float]]) -> None:
    table = Table(title=escape(f"{label}: {path}"), title_justify="left")
    columns = list(next(iter(worst.values())))
    table.add_column("param")
    for column in columns:
        table.add_column(column.replace("_", " "), justify="right")
    for name, entry in worst.items():
        table.add_row(name, *(_format(entry[c]) for c in columns))
    console.print(table)


def _print_population(label: str, rows: dict[str, dict[str, Any]]) -> None:
    table = Table(title=escape(f"{label}: how drivers differ"), title_justify="left")
    for column in ("param", "median [90% CI]", "drivers 10-90%", "between sd", "within sd"):
        table.add_column(column, justify="left" if column == "param" else "right")
    for name, row in rows.items():
        table.add_row(
            name,
            f"{row['median']:.3g} [{row['median_q05']:.3g}, {row['median_q95']:.3g}]",
            f"{row['q10']:.3g} - {row['q90']:.3g}",
            f"{row['between_sd']:.3g}",
            f"{row['within_sd']:.3g}",
        )
    console.print(table)


def _print_agreement(summary: pd.DataFrame) -> None:
    from bayesdrive.inference.diagnostics.agreement import CRITERION

    table = Table(title="agreement per engine pair and parameter", title_justify="left")
    for column in (
        "pair",
        "param",
        "vehicles",
        "agree",
        "means",
        "sds",
        "max |Δmean|/sd",
        "median sd ratio",
        "max W1/sd",
    ):
        table.add_column(column, justify="left" if column in ("pair", "param") else "right")
    for row in summary.itertuples():
        table.add_row(
            f"{row.b} vs {row.a}",
            row.param,
            str(row.vehicles),
            f"{row.agree:.0%}",
            f"{row.agree_mean:.0%}",
            f"{row.agree_sd:.0%}",
            f"{row.max_abs_mean_diff_sd:.3f}",
            f"{row.median_sd_ratio:.3f}",
            f"{row.max_wasserstein_sd:.3f}",
        )
    console.print(table)
    console.print(f"criterion: {escape(CRITERION)}")


def _format(value: float | None) -> str:
    import numpy as np

    if value is None or np.isnan(value):
        return "-"
    return f"{value:.0f}" if abs(value) >= 100 or float(value).is_integer() else f"{value:.3f}"


def _records(frame: pd.DataFrame) -> list[dict[str, Any]]:
    """Rows as JSON-ready dicts; NaN (e.g. R-hat of one chain) becomes null."""
    import numpy as np

    return [
        {k: (None if isinstance(v, float) and np.isnan(v) else v) for k, v in row.items()}
        for row in frame.to_dict(orient="records")
    ]


@results_command
def diagnose(
    results: Annotated[list[Path], typer.Argument(help="Saved result files (netCDF) to diagnose.")],
    json_out: JsonOut = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Folder for CSV tables and pictures (marginals, agreement heat map)."
        ),
    ] = None,
    force: ForceResults = False,
) -> None:
    """Convergence of each result and, for several results on the same data, their agreement."""
    # Imported here so that `bayesdrive diagnose --help` does not import JAX and ArviZ.
    from bayesdrive.inference.core.output import load_result, metadata
    from bayesdrive.inference.diagnostics.agreement import (
        CRITERION,
        agreement_summary,
        agreement_table,
        convergence_table,
        same_data,
    )
    from bayesdrive.inference.population.summary import how_drivers_differ
    from bayesdrive.reports.diagnostic_plots import plot_agreement_heatmap, plot_marginals

    missing = [str(p) for p in results if not p.is_file()]
    if missing:
        raise fail(f"no such result file(s): {', '.join(missing)}")
    results_dir = optional_results(out, "diagnose", json_out=json_out, force=force)
    trees = []
    for path in results:
        try:
            trees.append(load_result(path))
        except (OSError, ValueError, KeyError) as error:
            raise fail(f"{path}: cannot read as a result ({error})") from error
    labels = _labels(results, trees)
    by_label = dict(zip(labels, trees, strict=True))

    report: dict[str, Any] = {"results": {}}
    tables = {}
    for label, path, tree in zip(labels, results, trees, strict=True):
        table = convergence_table(tree)
        tables[label] = table
        report["results"][label] = {
            "path": str(path),
            "engine": metadata(tree).get("engine"),
            "seed": metadata(tree).get("seed"),
            "worst": worst_convergence(table),
            "per_vehicle": _records(table),
        }
        if "population_mu" in tree["sample_stats"]:
            report["results"][label]["how_drivers_differ"] = how_drivers_differ(tree)

    agreement = None
    if len(trees) >= 2:
        try:
            same_data(by_label)
            agreement = agreement_table(by_label)
        except ValueError as error:
            raise fail(str(error)) from error
        summary = agreement_summary(agreement)
        report["agreement"] = {
            "criterion": CRITERION,
            "summary": _records(summary),
            "per_vehicle": _records(agreement),
        }

    if results_dir is not None:
        staged = results_dir.path
        figures = plot_marginals(by_label, staged)
        for label, table in tables.items():
            write_text_atomic(staged / f"convergence_{label}.csv", table.to_csv(index=False))
        if agreement is not None:
            write_text_atomic(staged / "agreement.csv", agreement.to_csv(index=False))
            figures.append(plot_agreement_heatmap(agreement, staged / "agreement_heatmap.png"))
        results_dir.commit()
        report["figures"] = [str(out / f.relative_to(staged)) for f in figures]

    if emit_json(report, json_out):
        return
    for label, path in zip(labels, results, strict=True):
        _print_convergence(label, path, report["results"][label]["worst"])
        if "how_drivers_differ" in report["results"][label]:
            _print_population(label, report["results"][label]["how_drivers_differ"])
    if agreement is not None:
        _print_agreement(agreement_summary(agreement))
    if out is not None:
        console.print(f"tables and figures written to {escape(str(out))}")
