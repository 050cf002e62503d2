"""How an extension wraps a driver model: extra parameters, and lifting observed data to states.

Every extension wraps a model whose step is "mean acceleration plus Gaussian execution noise of
the sd its ``noise_sd`` declares, within the physical limits and the collision-free ceiling"
(:mod:`bayesdrive.drivers.execution_noise`). The wrapped model's parameters are the inner
model's, in the same order, followed by the extension's own (with defaults that switch the
extension off, so the inner model is nested in every extension).

The extensions that change the mean rule read
:class:`~bayesdrive.drivers.extensions.inputs.ExtendedInputs`, built by their model's
``inputs_at`` from the one series, and hand its car-following part to the base model, so they wrap
only base models that need no scene beyond car following (``scene`` None, :func:`check_base`). The noise extensions
read whatever the inner model reads and wrap any exactly observed model with white noise
(:func:`check_white_noise`), a ``mean`` extension included: that is how extensions compose
(:func:`~bayesdrive.drivers.extensions.compose`). Some extensions keep more in the state than the
observed position and speed (the autocorrelated noise keeps the last acceleration residual). With
exactly observed data that extra state is a function of the parameters and the observed past: the
model's ``lift`` computes it, so the likelihood stays exact and a step can be scored on its own.
Extensions whose extra state is *hidden* (drifting parameters, measurement noise) bring their own
state ``filter``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from jax import Array

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec, params_type
from bayesdrive.drivers.execution_noise import execution_noise_model
from bayesdrive.drivers.extensions.inputs import inputs_at

__all__ = [
    "ExtendedModel",
    "base_params",
    "check_base",
    "check_white_noise",
    "extended_specs",
    "gaussian_extension",
    "params_type_name",
    "state_extension",
]


class ExtendedModel(NamedTuple):
    """A driver model as the criticism fits it.

    cause: the misfit it answers ("none" for the base model itself).
    base: the wrapped base model.
    model: the wrapped :class:`~bayesdrive.drivers.base.DriverModel` (what engines fit).
    new_params: the parameters the extension adds.

    The model's full state at an exactly observed step is ``model.lift``; a model with a hidden
    state brings ``model.filter`` (:class:`~bayesdrive.drivers.base.DriverModel`).
    """

    cause: str
    base: DriverModel
    model: DriverModel
    new_params: tuple[str, ...]

    @property
    def name(self) -> str:
        return self.model.name


def check_base(base: DriverModel, cause: str) -> None:
    """Refuse a base model that declares a scene beyond car following (the extensions would drop
    it: a Cooperative IDM extended so would silently forget the merge scene)."""
    if base.scene is not None:
        raise ValueError(
            f"extension {cause!r} needs a base model that reads car-following inputs only; "
            f"{base.name!r} reads more, the {base.scene} scene (it would be lost)"
        )


def check_white_noise(inner: DriverModel, cause: str) -> None:
    """Refuse an inner model that does not declare a white Gaussian execution noise (``noise_sd``)
    on an exactly observed state (a noise extension would misread its state or noise)."""
    if not inner.observed_exactly:
        raise ValueError(
            f"extension {cause!r} needs an inner model whose state is observed exactly; "
            f"{inner.name!r} is observed through {inner.observation}"
        )
    if inner.noise_sd is None or inner.filter is not None:
        raise ValueError(
            f"extension {cause!r} needs an inner model with white Gaussian execution noise on "
            f"position and speed; {inner.name!r} keeps or filters more"
        )


def extended_specs(base: DriverModel, new: Sequence[ParamSpec]) -> tuple[ParamSpec, ...]:
    """The base model's specs followed by the extension's; refuses a name clash."""
    clash = set(base.param_names) & {s.name for s in new}
    if clash:
        raise ValueError(f"model {base.name!r} already has parameter(s) {sorted(clash)}")
    return (*base.specs, *new)


def base_params(base: DriverModel, params: Any) -> Any:
    """The base model's parameter tuple inside an extension's parameters (same leading fields)."""
    return base.params_type(*params[: len(base.specs)])


def params_type_name(cause: str) -> str:
    """An extension's parameter type name: its cause in title case, e.g. ``ReactionDelayParams``."""
    return "".join(part.title() for part in cause.split("_")) + "Params"


def state_extension(
    base: DriverModel, cause: str, specs: tuple[ParamSpec, ...], **functions: Any
) -> ExtendedModel:
    """An extension with its own transition (and state): the model ``base+cause`` over ``specs``
    (:func:`extended_specs`), observed as ``base`` is and in ``base``'s scene, its other
    :class:`~bayesdrive.drivers.base.DriverModel` fields ``functions``."""
    model = DriverModel(
        name=f"{base.name}+{cause}",
        params_type=params_type(params_type_name(cause), specs),
        specs=specs,
        observation_logpdf=base.observation_logpdf,
        scene=base.scene,
        **functions,
    )
    return ExtendedModel(cause, base, model, tuple(s.name for s in specs[len(base.specs) :]))


def gaussian_extension(
    base: DriverModel,
    cause: str,
    new_specs: Sequence[ParamSpec],
    mean_acceleration: Callable[[Any, EgoState, Any], Array],
    *,
    noise_sd: Callable[[Any, Any], Array] | None = None,
    reads_history: bool = False,
    reads: Callable[[Any, Array, int], Any] = inputs_at,
) -> ExtendedModel:
    """An extension whose step is ``mean_acceleration`` plus Gaussian noise of sd ``noise_sd``
    (default: ``base``'s, on the base's leading fields), reading the inputs ``reads`` builds
    (default: :class:`ExtendedInputs`, for a base model that reads car following alone; the caller
    checks ``base`` fits) and needing ``base``'s scene.

    Sampling and density are the base models' own
    :func:`~bayesdrive.drivers.execution_noise.noisy_step` and
    :func:`~bayesdrive.drivers.execution_noise.step_logpdf`, so the extension changes only the mean
    (or the sd).
    """
    specs = extended_specs(base, new_specs)
    if noise_sd is None:
        if base.noise_sd is None:
            raise ValueError(
                f"extension {cause!r} needs a base model with Gaussian execution noise; "
                f"{base.name!r} declares none"
            )

        def noise_sd(params, state) -> Array:
            return base.noise_sd(base_params(base, params), state)

    model = execution_noise_model(
        f"{base.name}+{cause}",
        params_type(params_type_name(cause), specs),
        specs,
        mean_acceleration,
        noise_sd,
        reads,
        base.scene,
    )._replace(
        observation_logpdf=base.observation_logpdf,
        initial_sample=base.initial_sample,
        reads_history=reads_history,
    )
    return ExtendedModel(cause, base, model, tuple(s.name for s in new_specs))
