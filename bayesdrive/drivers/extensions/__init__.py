"""Model extensions, one cause of misfit each, how they compose, and the registry the criticism uses.

Each extension wraps a model (see :mod:`.compose`) and adds parameters with documented priors
whose defaults switch it off, so the model it wraps is nested in it. :data:`EXTENSIONS` maps the
cause name that ``bayesdrive criticize`` reports to the wrapper.

**Composition.** Every extension is of one kind (:data:`KINDS`), and a model joins at most one
extension of each kind to its base, applied in the order of :data:`KIND_ORDER` (innermost first):

==============  ==========================================================  =====================
kind            extensions                                                  wraps
==============  ==========================================================  =====================
``mean``        reaction_delay, second_leader_anticipation,                 a base model that
                cut_in_overreaction, leader_acceleration_anticipation,      reads car following
                state_correction
``noise``       autocorrelated_noise, speed_dependent_noise                 any exactly observed
                                                                            model with white noise
``parameters``  drifting_parameters                                         the base model alone
``observation`` measurement_noise, video_noise                              base or ``mean``
==============  ==========================================================  =====================

The two observation models (:mod:`bayesdrive.drivers.measurement_noise`,
:mod:`bayesdrive.drivers.video_noise`) are extensions of the ``observation`` kind, so a model has
at most one. :data:`CAUSES` are the extensions the criticism can screen: all but video noise, whose
cause is measurement noise's. :data:`DEFAULT_CAUSES` are those it screens unless told otherwise:
all but the state correction (:mod:`.state_correction`), screened on request. Its coefficients
take either sign, so its score test is two-sided in all three
(:func:`bayesdrive.criticism.checks.score_check`). On records as short as the detection
study's it did not name the generator's state-dependent braking (reports/state_correction), so
in the default family it would widen every run's Holm family and add a fit wherever it is
screened in, for no cause found; on longer records its held-out gain is measured there.

So ``idm+reaction_delay+autocorrelated_noise``, ``cidm+autocorrelated_noise`` and
``gipps+second_leader_anticipation+measurement_noise`` exist, and :func:`compose` refuses the
rest in one line naming the rule: two extensions of one kind (their mean rules or noise models
would have to be merged); ``drifting_parameters`` with anything (its Kalman filter linearises the
base rule alone); an observation model over a noise extension (its filter assumes white
execution noise); a ``mean`` extension of a base that reads more than car following (the
Cooperative IDM's merge scene has no history window to delay, and the extensions would drop it).
The priors stay those of each extension. Confounded pairs keep them too: a reaction delay and
autocorrelated noise both make consecutive residuals of the undelayed white-noise model
correlated, so with both the posterior of (reaction_time, noise_time_s) is often a ridge; the held-out
gain of the composite over either alone is what tells them apart (``bayesdrive criticize``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from types import MappingProxyType

from bayesdrive.drivers import measurement_noise, video_noise
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.extensions import (
    autocorrelated_noise,
    cut_in,
    drifting_parameters,
    leader_acceleration,
    reaction_delay,
    second_leader,
    speed_dependent_noise,
    state_correction,
)
from bayesdrive.drivers.extensions.compose import ExtendedModel

__all__ = [
    "CAUSES",
    "DEFAULT_CAUSES",
    "EXTENSIONS",
    "KINDS",
    "KIND_ORDER",
    "NO_CAUSE",
    "PARTS",
    "as_extended",
    "compose",
    "composition_problem",
    "extend",
    "ordered_causes",
    "with_measurement_noise",
    "with_video_noise",
]

NO_CAUSE = "none"


@functools.cache
def with_measurement_noise(base: DriverModel) -> ExtendedModel:
    """The one measurement-noise model (:mod:`bayesdrive.drivers.measurement_noise`) as the
    extension for its cause; it keeps the base model's inputs, so it wraps any base model."""
    model = measurement_noise.with_measurement_noise(base)
    return ExtendedModel(measurement_noise.CAUSE, base, model, (measurement_noise.SIGMA_OBS.name,))


@functools.cache
def with_video_noise(base: DriverModel) -> ExtendedModel:
    """The video-noise observation model (:mod:`bayesdrive.drivers.video_noise`) as an extension;
    like measurement noise it keeps the base model's inputs, so it wraps any base model."""
    model = video_noise.with_video_noise(base)
    return ExtendedModel(video_noise.NAME, base, model, (measurement_noise.SIGMA_OBS.name,))


EXTENSIONS: MappingProxyType[str, Callable[[DriverModel], ExtendedModel]] = MappingProxyType(
    {
        reaction_delay.CAUSE: reaction_delay.with_reaction_delay,
        autocorrelated_noise.CAUSE: autocorrelated_noise.with_autocorrelated_noise,
        speed_dependent_noise.CAUSE: speed_dependent_noise.with_speed_dependent_noise,
        second_leader.CAUSE: second_leader.with_second_leader_anticipation,
        cut_in.CAUSE: cut_in.with_cut_in_heuristic,
        leader_acceleration.CAUSE: leader_acceleration.with_leader_acceleration_anticipation,
        state_correction.CAUSE: state_correction.with_state_correction,
        drifting_parameters.CAUSE: drifting_parameters.with_drifting_time_gap,
        measurement_noise.CAUSE: with_measurement_noise,
        video_noise.NAME: with_video_noise,
    }
)
# Every extension a model name may join to its base.
PARTS = tuple(EXTENSIONS)
# The extensions the criticism can screen: video noise answers measurement noise's cause.
CAUSES = tuple(part for part in PARTS if part != video_noise.NAME)
# Those it screens unless told otherwise: the state correction on request (module docstring).
DEFAULT_CAUSES = tuple(cause for cause in CAUSES if cause != state_correction.CAUSE)
KIND_ORDER = ("mean", "noise", "parameters", "observation")
KINDS = MappingProxyType(
    {
        reaction_delay.CAUSE: "mean",
        second_leader.CAUSE: "mean",
        cut_in.CAUSE: "mean",
        leader_acceleration.CAUSE: "mean",
        state_correction.CAUSE: "mean",
        autocorrelated_noise.CAUSE: "noise",
        speed_dependent_noise.CAUSE: "noise",
        drifting_parameters.CAUSE: "parameters",
        measurement_noise.CAUSE: "observation",
        video_noise.NAME: "observation",
    }
)


def ordered_causes(causes: Sequence[str]) -> tuple[str, ...]:
    """``causes`` in the order they are applied (:data:`KIND_ORDER`); a KeyError names an unknown."""
    unknown = [cause for cause in causes if cause not in KINDS]
    if unknown:
        raise KeyError(f"unknown cause(s) {unknown}; known causes: {list(PARTS)}")
    return tuple(sorted(causes, key=lambda cause: KIND_ORDER.index(KINDS[cause])))


def composition_problem(causes: Sequence[str]) -> str | None:
    """Why these extensions cannot be joined in one model (module docstring), or None."""
    ordered = ordered_causes(causes)
    if len(set(ordered)) < len(ordered):
        return f"an extension is named twice in {list(causes)}"
    kinds = [KINDS[cause] for cause in ordered]
    for kind in KIND_ORDER:
        same = [cause for cause in ordered if KINDS[cause] == kind]
        if len(same) > 1:
            return f"{same} are both {kind!r} extensions; a model takes one of each kind"
    if "parameters" in kinds and len(ordered) > 1:
        return (
            f"{drifting_parameters.CAUSE} composes with no other extension (its Kalman filter "
            "linearises the base rule alone)"
        )
    if "observation" in kinds and "noise" in kinds:
        observation = ordered[kinds.index("observation")]
        return (
            f"{observation} does not compose with a noise extension (its filter assumes white "
            "execution noise)"
        )
    return None


@functools.cache
def compose(base: DriverModel, causes: tuple[str, ...]) -> DriverModel:
    """``base`` with every extension of ``causes`` applied, in :func:`ordered_causes` order (so any
    spelling gives the same model object); a ValueError names the rule a combination breaks."""
    problem = composition_problem(causes)
    if problem is not None:
        raise ValueError(f"cannot extend {base.name!r}: {problem}")
    model = base
    for cause in ordered_causes(causes):
        model = EXTENSIONS[cause](model).model
    return model


@functools.cache
def as_extended(base: DriverModel) -> ExtendedModel:
    """The base model itself in the :class:`ExtendedModel` form (cause "none", nothing added)."""
    return ExtendedModel(NO_CAUSE, base, base, ())


def extend(cause: str, base: DriverModel, present: tuple[str, ...] = ()) -> ExtendedModel:
    """``base`` with the extensions ``present`` (the model the criticism has so far), extended
    for ``cause`` (or that model itself for "none"); a KeyError lists the causes, a ValueError
    names a composition rule broken (module docstring)."""
    current = compose(base, present)
    if cause == NO_CAUSE:
        return as_extended(current)
    if cause not in EXTENSIONS:
        raise KeyError(f"unknown cause {cause!r}; known causes: {list(PARTS)}")
    model = compose(base, (*present, cause))
    new_params = tuple(name for name in model.param_names if name not in current.param_names)
    return ExtendedModel(cause, current, model, new_params)
