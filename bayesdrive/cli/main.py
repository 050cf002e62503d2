"""The ``bayesdrive`` command: one typer app, one sub-module per command group."""

import logging

import typer

from bayesdrive.cli import (
    criticize_cmd,
    data_cmd,
    diagnose_cmd,
    evaluate_cmd,
    export_cmd,
    fit_cmd,
    reproduce_cmd,
    sbc_cmd,
    simulate_cmd,
)

app = typer.Typer(
    help="Learn distributions over rule-based driver-model parameters from real trajectories.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)
app.add_typer(data_cmd.app, name="data")
app.add_typer(export_cmd.app, name="export")
app.command("fit")(fit_cmd.fit)
app.command("evaluate")(evaluate_cmd.evaluate)
app.command("simulate")(simulate_cmd.simulate)
app.command("reproduce")(reproduce_cmd.reproduce)
app.command("report")(reproduce_cmd.report)
app.command("diagnose")(diagnose_cmd.diagnose)
app.command("sbc")(sbc_cmd.sbc)
app.command("criticize")(criticize_cmd.criticize_command)


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log repairs and flags.")):
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s")
