"""bayesdrive: distributions over rule-based driver-model parameters from real trajectories.

The flat API (``import bayesdrive as bd``; :mod:`bayesdrive.api`): ``bd.load`` (a data set by
name, held-out names included, a file or a folder; ``bd.data_path`` finds a data set's folder), ``bd.from_dataframe`` (a
pandas DataFrame), ``bd.fit``, ``bd.save_result``/``bd.load_result``, ``bd.summary`` (a
DataFrame), ``bd.posterior_predictive`` (followers simulated behind a given leader),
``bd.evaluate``, ``bd.criticize`` and the driver models (``bd.models``, ``bd.get_model``). The
names load on first use (PEP 562), so that importing the package, as the command line does, does
not import JAX.
"""

__version__ = "0.1.0"

API = (
    "criticize",
    "data_path",
    "evaluate",
    "fit",
    "from_dataframe",
    "get_model",
    "load",
    "load_result",
    "models",
    "posterior_predictive",
    "save_result",
    "summary",
)
__all__ = ["__version__", *API]


def __getattr__(name: str):
    if name in API:
        from bayesdrive import api

        return getattr(api, name)
    raise AttributeError(f"module 'bayesdrive' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *API})
