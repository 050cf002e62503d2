"""``bayesdrive data``: list, inspect and fetch data sets."""

import typer

app = typer.Typer(help="List, inspect and fetch trajectory data sets.", no_args_is_help=True)
