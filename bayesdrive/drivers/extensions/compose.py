"""How an extension wraps a base driver model: extra parameters, and lifting observed data to states.

Every extension wraps a car-following base model whose step is "mean acceleration plus Gaussian
execution noise of sd ``params.sigma``" (the IDM: :func:`~bayesdrive.drivers.idm.noisy_step` and
:func:`~bayesdrive.drivers.idm.step_logpdf`), and reads the base model's inputs from the
car-following part of :class:`~bayesdrive.drivers.extensions.inputs.ExtendedInputs`. The wrapped
model's parameters are the base model's, in the same order, followed by the extension's own (with
defaults that switch the extension off, so the base model is nested in every extension).

Some extensions keep more in the state than the observed position and speed (the autocorrelated
noise keeps the last acceleration residual). With exactly observed data that extra state is a
function of the parameters and the observed past: :attr:`ExtendedModel.lift` computes it, so the
likelihood stays exact and a step can be scored on its own. Extensions whose extra state is
*hidden* (drifting parameters, measurement noise) bring their own state ``filter``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from jax import Array

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.idm import execution_noise_model, execution_noise_sd

__all__ = [
    "ExtendedModel",
    "base_params",
    "extended_specs",
    "gaussian_extension",
    "observed_lift",
    "params_type",
]


class ExtendedModel(NamedTuple):
    """A driver model as the criticism fits it.

    cause: the misfit it answers ("none" for the base model itself).
    base: the wrapped base model.
    model: the wrapped :class:`~bayesdrive.drivers.base.DriverModel` (what engines fit).
    new_params: the parameters the extension adds.
    lift: ``(params, EgoState, ExtendedInputs) -> state``, the model's full state at an exactly
        observed step (identity on the observed state for most extensions; for a model with a
        hidden state, its value at the start of a simulation).
    filter: for a model with a hidden state, ``(params, steps) -> (T,)`` the one-step predictive
        log densities of one vehicle's steps from a state filter (``steps`` is a
        :class:`~bayesdrive.criticism.tempering.VehicleSteps`); None when each step can be scored
        on its own from the lifted state.
    """

    cause: str
    base: DriverModel
    model: DriverModel
    new_params: tuple[str, ...]
    lift: Callable[[Any, EgoState, Any], Any]
    filter: Callable[[Any, Any], Array] | None = None

    @property
    def name(self) -> str:
        return self.model.name


def observed_lift(params: Any, state: EgoState, inputs: Any) -> EgoState:
    """The observed state is the whole state (no extra state to recover)."""
    del params, inputs
    return state


def extended_specs(base: DriverModel, new: Sequence[ParamSpec]) -> tuple[ParamSpec, ...]:
    """The base model's specs followed by the extension's; refuses a name clash."""
    clash = set(base.param_names) & {s.name for s in new}
    if clash:
        raise ValueError(f"model {base.name!r} already has parameter(s) {sorted(clash)}")
    return (*base.specs, *new)


def params_type(type_name: str, specs: Sequence[ParamSpec]) -> type:
    """A parameter NamedTuple with one field per spec, in order (the docstring lists units)."""
    cls = NamedTuple(type_name, [(s.name, Array) for s in specs])
    cls.__doc__ = f"{type_name}: " + ", ".join(f"{s.name} ({s.unit}): {s.doc}" for s in specs)
    return cls


def base_params(base: DriverModel, params: Any) -> Any:
    """The base model's parameter tuple inside an extension's parameters (same leading fields)."""
    return base.params_type(*params[: len(base.specs)])


def gaussian_extension(
    base: DriverModel,
    cause: str,
    new_specs: Sequence[ParamSpec],
    mean_acceleration: Callable[[Any, EgoState, Any], Array],
    *,
    noise_sd: Callable[[Any, Any], Array] = execution_noise_sd,
) -> ExtendedModel:
    """An extension whose step is ``mean_acceleration`` plus Gaussian noise of sd ``noise_sd``.

    Sampling and density are the base models' own :func:`~bayesdrive.drivers.idm.noisy_step` and
    :func:`~bayesdrive.drivers.idm.step_logpdf`, so the extension changes only the mean (or the sd).
    """
    specs = extended_specs(base, new_specs)
    type_name = "".join(part.title() for part in cause.split("_")) + "Params"
    model = execution_noise_model(
        f"{base.name}+{cause}",
        params_type(type_name, specs),
        specs,
        mean_acceleration,
        noise_sd,
    )._replace(observation_logpdf=base.observation_logpdf, initial_sample=base.initial_sample)
    return ExtendedModel(cause, base, model, tuple(s.name for s in new_specs), observed_lift)
