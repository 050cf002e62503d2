"""Fitted drivers as SUMO vehicle types: a ``vTypeDistribution`` for SUMO's own IDM (IDM
results) or its Krauss model (Gipps results).

Which drivers (:func:`per_vehicle_drivers`, :func:`posterior_drivers`,
:func:`population_drivers`): one type per fitted vehicle at its posterior medians (each
parameter's marginal median: robust to the long v_des tails of congested vehicles); or N drivers
drawn from the pooled posterior (every fitted vehicle equally likely, then one of its draws); or N
drivers drawn from the hierarchical engine's population distribution of a new driver
(``population_new_driver``). Parameters the fit held fixed take their recorded values (the
model's defaults where unrecorded).

How the parameters map onto SUMO's IDM (``carFollowModel="IDM"``, SUMO >= 1.15):

============  =====================  =========================================================
bayesdrive    SUMO attribute         note
============  =====================  =========================================================
v_des         maxSpeed,              SUMO's IDM drives towards min(maxSpeed, speedFactor x
              desiredMaxSpeed        min(desiredMaxSpeed, speed limit)) (measured, SUMO 1.28);
                                     speedFactor 1 and speedDev 0 keep the driver's own v_des
                                     wherever the speed limit is not below it
d_min         minGap                 SUMO's IDM adds minGap back to the gap it is handed, so its
                                     gap is the bumper gap and minGap is d_min exactly
tau           tau
a_max         accel
b_pref        decel                  also the "comfortable" b of the IDM's desired gap
(4)           delta                  the exponent, fixed at 4 in bayesdrive
dt of fit     stepping               SUMO's IDM integrates each simulation step in
                                     round(step-length / stepping) Euler sub-steps holding the
                                     leader's speed; stepping = the data's step length makes it
                                     one step of the fitted dt at that step length
sigma         (none: sigma = 0)      not carried (:data:`SIGMA_NOT_CARRIED`): the types are
                                     deterministic and our value is kept as a ``<param>``
============  =====================  =========================================================

Execution noise has no carrier in SUMO with its meaning. bayesdrive's ``sigma`` is the sd
(m/s^2) of Gaussian noise added to the acceleration, drawn afresh each step. SUMO's noise
carriers mean other things: a vType's ``sigma`` is Krauss dawdling (a random slow-down, a
fraction in [0, 1]); the EIDM's driving error (``sigmaerror``) is a Wiener process with its own
correlation time (``tPersDrive``), scaled by an intensity and a criticality of the situation,
on a model with other changes to the IDM; the driverstate device's Ornstein-Uhlenbeck error
enters at the perception stage only, as errors of the perceived gap and speed difference in
proportion to the gap (SUMO's Driver State documentation, ``MSSimpleDriverState``), not as an
acceleration error. So ``sigma`` is written as a ``<param>`` and refused as a simulated
quantity in one line naming it; the extensions' driver parameters (``noise_time_s``,
``reaction_time``, ...) have no carrier either, and a result of such a model is refused in one
line naming the parameter. Parameters of the observation (``sigma_obs``) describe the data, not
the driver, and are kept as ``<param>`` entries.

Gipps goes to SUMO's ``Krauss`` model, the nearest of its family but not the same rule:

============  =====================  =========================================================
bayesdrive    SUMO attribute         note
============  =====================  =========================================================
v_des         maxSpeed,              as for the IDM
              desiredMaxSpeed
a_max         accel                  Krauss accelerates at accel up to the desired speed;
                                     Gipps' free branch 2.5 a_max (1 - v/v_des)
                                     sqrt(0.025 + v/v_des) fades with speed
b_max         decel                  the braking both safe speeds plan with
d_min         minGap                 Gipps' leader size is its length plus d_min
dt of fit     tau                    Gipps' reaction time is the step; Krauss keeps tau as
                                     the time headway of its safe speed, which solves the
                                     braking distances otherwise than Gipps' formula
b_lead        (none)                 the follower's estimate of its leader's braking; SUMO's
                                     Krauss reads the leader's own ``apparentDecel``, so it is
                                     kept as a ``<param>`` (``validate sumo`` gives the
                                     replayed leader that apparentDecel)
============  =====================  =========================================================

How far Krauss is from Gipps is measured by ``bayesdrive validate sumo`` on a Gipps result
(``reports/sumo/README.md``).

Not mapped and worth knowing: bayesdrive integrates positions by the trapezoid rule (SUMO's
``--step-method.ballistic``), SUMO's default is semi-implicit Euler; bayesdrive's IDM has no
braking limit, SUMO's caps braking at ``emergencyDecel`` (9 m/s^2 by default); SUMO never
drives above desiredMaxSpeed (it refuses a car that starts faster and caps its speed there) where
bayesdrive's IDM brakes smoothly towards v_des from above; vehicle length is
not fitted (the types leave SUMO's default). Parameters a model has beyond the IDM's (e.g. the
C-IDM's cooperation ``c``) have no SUMO counterpart: they are kept as ``<param>`` entries and
logged. Every file records its source result, the seed of any draws and the code that wrote it.

SUMO is run with the ballistic update at bayesdrive's 0.1 s step: that is what reproduces
bayesdrive's deterministic rollout (``tests/simulation/test_sumo_export.py`` holds the tolerance;
``reports/sumo/README.md`` the round trip); SUMO's default Euler update, or sub-steps holding the
leader's speed, do not.
"""

from __future__ import annotations

import contextlib
import logging
import math
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple

import jax
import numpy as np
import xarray as xr
from jax import Array

from bayesdrive.data.atomic import write_atomic
from bayesdrive.data.provenance import provenance_line
from bayesdrive.drivers.extensions.state_correction import STATE_CORRECTION_SPECS
from bayesdrive.drivers.idm import DELTA
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import metadata
from bayesdrive.simulation.posterior import fixed_params, particles_by_vehicle, population_draws

__all__ = [
    "GIPPS_TO_KRAUSS",
    "IDM_TO_SUMO",
    "NOT_CARRIED",
    "NO_SUMO_CARRIER",
    "SIGMA_NOT_CARRIED",
    "SUMO_MODELS",
    "Driver",
    "SumoFollower",
    "SumoModel",
    "base_model",
    "export_header",
    "fitted_step_length",
    "follow_in_sumo",
    "per_vehicle_drivers",
    "population_drivers",
    "posterior_drivers",
    "straight_road",
    "sumo_attributes",
    "sumo_home",
    "vtype_distribution",
    "write_vtype_distribution",
]

log = logging.getLogger(__name__)

# bayesdrive's IDM parameter -> the SUMO vType attributes that carry it (module docstring).
IDM_TO_SUMO = {
    "v_des": ("maxSpeed", "desiredMaxSpeed"),
    "d_min": ("minGap",),
    "tau": ("tau",),
    "a_max": ("accel",),
    "b_pref": ("decel",),
}
# bayesdrive's Gipps parameter -> the SUMO Krauss vType attributes that carry it.
GIPPS_TO_KRAUSS = {
    "v_des": ("maxSpeed", "desiredMaxSpeed"),
    "a_max": ("accel",),
    "b_max": ("decel",),
    "d_min": ("minGap",),
}


class SumoModel(NamedTuple):
    """A bayesdrive base model's SUMO car-following model, parameter mapping, and the attributes
    set from the stepping (s): the IDM's exponent and sub-step, Gipps' reaction time (said in
    words by ``stepping_note``)."""

    car_follow_model: str
    mapping: dict[str, tuple[str, ...]]
    from_stepping: Callable[[float], dict[str, float]]
    stepping_note: str


_SUMO_IDM = SumoModel(
    "IDM",
    IDM_TO_SUMO,
    lambda step: {"delta": DELTA, "stepping": step},
    f"delta = {DELTA}, stepping = the fitted step length",
)
SUMO_MODELS = {
    "idm": _SUMO_IDM,
    # The Cooperative IDM follows its leader as the IDM does; its c is kept as a <param>.
    "cidm": _SUMO_IDM,
    "gipps": SumoModel(
        "Krauss",
        GIPPS_TO_KRAUSS,
        lambda step: {"tau": step},
        "tau = the fitted step length (Gipps' reaction time)",
    ),
}
# What SUMO cannot carry with the parameter's meaning (module docstring), one line each.
SIGMA_NOT_CARRIED = (
    "sigma (sd of Gaussian execution noise on the acceleration, fresh each step) is not carried: "
    "SUMO's sigma is Krauss dawdling, the EIDM's sigmaerror a situation-scaled Wiener process and "
    "the driverstate device's error a perception error of gap and speed difference; the types "
    "are deterministic and sigma is kept as a <param>"
)
NO_SUMO_CARRIER = {
    "noise_time_s": "the correlation time of the execution noise: SUMO's only Ornstein-Uhlenbeck "
    "error (driverstate device) perturbs the perceived gap and speed difference, not the "
    "acceleration",
    "noise_lag_s": "the lag through which the execution error reaches the acceleration: SUMO "
    "carries no execution noise on the acceleration",
    "reaction_time": "a delay of the driver's inputs: SUMO's actionStepLength holds decisions "
    "between action points, and the EIDM's treaction sits in a model that is not the IDM",
    "noise_speed_slope": "execution noise growing with speed: SUMO carries no execution noise",
    "tau_drift": "a time headway drifting within a vehicle: SUMO's tau is fixed per type",
    **{
        name: "a correction of the acceleration on features of the state (state_correction): "
        "SUMO's IDM has no term to add it to"
        for name in (spec.name for spec in STATE_CORRECTION_SPECS)
    },
}
# Kept as <param> entries, not simulated: one line each, printed on export.
NOT_CARRIED = {
    "sigma": SIGMA_NOT_CARRIED,
    "b_lead": "b_lead (the follower's estimate of its leader's braking) is not carried: SUMO's "
    "Krauss reads the leader's own apparentDecel; it is kept as a <param>",
}
# Observation-model parameters: about the data, nothing to simulate.
OBSERVATION_PARAMETERS = ("sigma_obs",)
# Deterministic types driving exactly their own v_des (see the table above).
_FIXED_ATTRIBUTES = {"sigma": "0", "speedFactor": "1", "speedDev": "0"}


class Driver(NamedTuple):
    """One exported driver: a SUMO-safe id, its base model (a key of :data:`SUMO_MODELS`), every
    model parameter by name, and where it came from."""

    id: str
    model: str
    params: dict[str, float]
    source: str


def _number(value: float) -> str:
    # Seven significant digits hold a float32 draw exactly enough for SUMO's doubles.
    return f"{value:.7g}"


def base_model(tree: xr.DataTree) -> str:
    """The result's base model, one SUMO carries (:data:`SUMO_MODELS`); a clear error if not."""
    base = str(metadata(tree)["model"]).split("+")[0]
    if base not in SUMO_MODELS:
        raise ValueError(f"model {base!r} has no SUMO export; exported: {sorted(SUMO_MODELS)}")
    return base


def _all_parameters(tree: xr.DataTree, values: Mapping[str, float]) -> dict[str, float]:
    """Inferred ``values`` completed by the fit's fixed parameters (the model's defaults)."""
    meta = metadata(tree)
    model = get_model(meta["model"])
    mapping = SUMO_MODELS[base_model(tree)].mapping
    missing = [name for name in mapping if name not in model.param_names]
    if missing:
        raise ValueError(f"model {model.name!r} lacks the parameter(s) {missing} SUMO needs")
    refused = [name for name in model.param_names if name in NO_SUMO_CARRIER]
    if refused:
        name = refused[0]
        raise ValueError(
            f"model {model.name!r}: {name} has no SUMO carrier ({NO_SUMO_CARRIER[name]}); "
            "export a fit of the base model"
        )
    fixed = fixed_params(model, meta)._asdict()
    return {name: float(values.get(name, fixed[name])) for name in model.param_names}


def _inferred(tree: xr.DataTree) -> tuple[str, ...]:
    return tuple(metadata(tree)["params"])


def per_vehicle_drivers(tree: xr.DataTree) -> list[Driver]:
    """One driver per fitted vehicle, at the vehicle's marginal posterior medians."""
    names = _inferred(tree)
    return [
        Driver(
            id=f"vehicle_{vehicle}",
            model=base_model(tree),
            params=_all_parameters(tree, dict(zip(names, np.median(draws, axis=0), strict=True))),
            source=f"posterior medians of vehicle {vehicle}",
        )
        for vehicle, draws in particles_by_vehicle(tree, names).items()
    ]


def posterior_drivers(key: Array, tree: xr.DataTree, num_drivers: int) -> list[Driver]:
    """``num_drivers`` draws of the pooled posterior: a uniformly chosen fitted vehicle, then a
    uniformly chosen draw of its posterior (every vehicle has the same number of draws)."""
    names = _inferred(tree)
    by_vehicle = particles_by_vehicle(tree, names)
    vehicles = list(by_vehicle)
    key_vehicle, key_draw = jax.random.split(key)
    chosen = np.asarray(jax.random.randint(key_vehicle, (num_drivers,), 0, len(vehicles)))
    num_draws = len(by_vehicle[vehicles[0]])
    draw = np.asarray(jax.random.randint(key_draw, (num_drivers,), 0, num_draws))
    return [
        Driver(
            id=f"draw_{i}",
            model=base_model(tree),
            params=_all_parameters(tree, dict(zip(names, by_vehicle[vehicles[v]][d], strict=True))),
            source=f"posterior draw {d} of vehicle {vehicles[v]}",
        )
        for i, (v, d) in enumerate(zip(chosen.tolist(), draw.tolist(), strict=True))
    ]


def population_drivers(key: Array, tree: xr.DataTree, num_drivers: int) -> list[Driver]:
    """``num_drivers`` new drivers from the hierarchical engine's population distribution: a
    uniformly chosen posterior draw of ``population_new_driver`` each."""
    params, flat = population_draws(tree)
    index = np.asarray(jax.random.randint(key, (num_drivers,), 0, len(flat)))
    return [
        Driver(
            id=f"population_{i}",
            model=base_model(tree),
            params=_all_parameters(tree, dict(zip(params, flat[d], strict=True))),
            source=f"population new-driver draw {d}",
        )
        for i, d in enumerate(index.tolist())
    ]


def sumo_attributes(driver: Driver, stepping: float) -> dict[str, str]:
    """The SUMO vType attributes of one driver (module docstring for the mappings)."""
    sumo_model = SUMO_MODELS[driver.model]
    attributes = {"carFollowModel": sumo_model.car_follow_model, **_FIXED_ATTRIBUTES}
    for name, sumo_names in sumo_model.mapping.items():
        for sumo_name in sumo_names:
            attributes[sumo_name] = _number(driver.params[name])
    for sumo_name, value in sumo_model.from_stepping(stepping).items():
        attributes[sumo_name] = _number(value)
    return attributes


def vtype_distribution(
    drivers: list[Driver], *, distribution_id: str, stepping: float, header: str
) -> ET.ElementTree:
    """An ``<additional>`` file holding one ``vTypeDistribution`` of equally likely drivers;
    parameters without a SUMO counterpart are kept as ``<param key="bayesdrive.NAME">``."""
    if not drivers:
        raise ValueError("no drivers to export")
    if "--" in header:
        raise ValueError("an XML comment cannot hold '--': reword the header")
    if not (math.isfinite(stepping) and stepping > 0):
        raise ValueError(f"stepping must be a positive number of seconds, got {stepping}")
    root = ET.Element("additional")
    root.append(ET.Comment(header))
    distribution = ET.SubElement(root, "vTypeDistribution", id=distribution_id)
    mapping = SUMO_MODELS[drivers[0].model].mapping
    unmapped = sorted(
        set(drivers[0].params) - set(mapping) - {*NOT_CARRIED, *OBSERVATION_PARAMETERS}
    )
    if unmapped:
        log.warning(
            "SUMO has no counterpart of %s: kept as <param> entries only, not simulated",
            unmapped,
        )
    for driver in drivers:
        vtype = ET.SubElement(
            distribution,
            "vType",
            id=f"{distribution_id}_{driver.id}",
            probability="1",
            **sumo_attributes(driver, stepping),
        )
        for name in sorted(set(driver.params) - set(mapping)):
            ET.SubElement(
                vtype, "param", key=f"bayesdrive.{name}", value=_number(driver.params[name])
            )
        ET.SubElement(vtype, "param", key="bayesdrive.source", value=driver.source)
    ET.indent(root)
    return ET.ElementTree(root)


def export_header(tree: xr.DataTree, source: str, how: str, seed: int | None) -> str:
    """The comment atop an exported file: what it holds, how it was drawn and what does not map."""
    meta = metadata(tree)
    sumo_model = SUMO_MODELS[base_model(tree)]
    drawn = "" if seed is None else f", seed {seed}"
    mapped = ", ".join(
        f"{name} -> {' and '.join(attributes)}" for name, attributes in sumo_model.mapping.items()
    )
    not_carried = "; ".join(
        line for name, line in NOT_CARRIED.items() if name in get_model(meta["model"]).param_names
    )
    return (
        f" bayesdrive {meta['model']} drivers from {source} ({meta['engine']} fit of "
        f"{meta['data_source']}): {how}{drawn}. Written by {provenance_line()}. "
        f"SUMO model {sumo_model.car_follow_model}. Mapping: {mapped}; {sumo_model.stepping_note}. "
        f"Not mapped: {not_carried}. Set SUMO's option "
        "step-method.ballistic to true to integrate positions as bayesdrive does. "
    )


def write_vtype_distribution(path: str | Path, tree_xml: ET.ElementTree) -> Path:
    """Write the file atomically (a crash leaves no partial file)."""
    path = Path(path)
    write_atomic(path, lambda tmp: tree_xml.write(tmp, encoding="UTF-8", xml_declaration=True))
    return path


def fitted_step_length(tree: xr.DataTree, meta: Mapping[str, Any] | None = None) -> float:
    """The step length (s) of the data the result was fitted to."""
    if "observed_data" in tree.children and "dt" in tree["observed_data"].attrs:
        return float(tree["observed_data"].attrs["dt"])
    meta = metadata(tree) if meta is None else meta
    if "dt" in meta:
        return float(meta["dt"])
    raise ValueError(
        "the result records no step length (observed_data.attrs['dt'] or the attribute dt): "
        "give the stepping (CLI: --stepping SECONDS, the fitted data's step length)"
    )


# Where the follower starts on SUMO's road (m): room behind it, none needed ahead of the leader.
START_M = 100.0
# The replayed leader's type: limits far beyond any recorded speed change, so setSpeed rules.
_REPLAY_LIMIT = 20.0


def _libsumo() -> ModuleType:
    """libsumo, imported with what it prints on import (a pyarrow version notice, about output
    formats not used here) sent to standard error, so standard output stays the command's."""
    with contextlib.redirect_stdout(sys.stderr):
        import libsumo
    return libsumo


def sumo_home() -> Path:
    """SUMO's installation (the ``sumo`` extra's eclipse-sumo, with libsumo to drive it); a clear
    error without them."""
    try:
        _libsumo()
        import sumo
    except ImportError:
        raise RuntimeError(
            "eclipse-sumo is not installed: pip install -e '.[sumo]' (SUMO and libsumo)"
        ) from None
    return Path(sumo.SUMO_HOME)


def straight_road(folder: Path, home: Path, length_m: float) -> Path:
    """A straight single-lane road of ``length_m`` metres (speed limit 50 m/s, above every
    v_des the priors allow), built by SUMO's netconvert into ``folder``; returns the net file."""
    (folder / "road.nod.xml").write_text(
        f'<nodes><node id="a" x="0" y="0"/><node id="b" x="{length_m:.1f}" y="0"/></nodes>'
    )
    (folder / "road.edg.xml").write_text(
        '<edges><edge id="road" from="a" to="b" numLanes="1" speed="50"/></edges>'
    )
    net = folder / "road.net.xml"
    command = [home / "bin" / "netconvert", "-n", folder / "road.nod.xml"]
    command += ["-e", folder / "road.edg.xml", "-o", net]
    subprocess.run(command, check=True, capture_output=True)
    return net


class SumoFollower(NamedTuple):
    """SUMO's follower, one value per step from the start: position from its start (m), speed
    (m/s) and bumper gap to the leader (m)."""

    x: np.ndarray
    v: np.ndarray
    gap: np.ndarray


def follow_in_sumo(
    home: Path,
    net: Path,
    vtypes: Path,
    vtype_id: str,
    lead_v: np.ndarray,
    *,
    gap: float,
    v0: float,
    dt: float,
    leader_length: float,
    folder: Path,
    leader_apparent_decel: float = _REPLAY_LIMIT,
) -> SumoFollower:
    """One follower of type ``vtype_id`` (from the additional file ``vtypes``) behind a leader
    that replays the speeds ``lead_v`` (one per step, from the first) through libsumo's
    ``setSpeed`` with every speed check off; the follower starts ``gap`` metres (bumper to
    bumper) behind it at speed ``v0``. ``leader_apparent_decel`` is the braking (m/s^2) the
    leader announces, which SUMO's Krauss plans with (Gipps' b_lead). Positions are integrated
    by SUMO's ballistic update, as bayesdrive integrates them (module docstring)."""
    libsumo = _libsumo()
    routes = folder / "routes.xml"
    routes.write_text(
        f'<routes><vType id="replay" length="{float(leader_length)!r}" maxSpeed="60" '
        f'accel="{_REPLAY_LIMIT}" decel="{_REPLAY_LIMIT}" emergencyDecel="{_REPLAY_LIMIT}" '
        f'apparentDecel="{float(leader_apparent_decel)!r}" '
        'sigma="0"/><route id="r" edges="road"/>'
        f'<vehicle id="leader" type="replay" route="r" depart="0" '
        f'departPos="{float(START_M + gap + leader_length)!r}" departSpeed="{float(lead_v[0])!r}" '
        'insertionChecks="none"/>'
        f'<vehicle id="follower" type="{vtype_id}" route="r" depart="0" departPos="{START_M}" '
        f'departSpeed="{float(v0)!r}" insertionChecks="none"/></routes>'
    )
    libsumo.start(
        [
            str(home / "bin" / "sumo"),
            *("-n", str(net), "-a", str(vtypes), "-r", str(routes)),
            *("--step-length", str(dt), "--step-method.ballistic", "true"),
            *("--no-step-log", "true", "--no-warnings", "true"),
            # A collision is a result to compare (bayesdrive keeps the colliding car), not a
            # reason to teleport the follower away.
            *("--collision.action", "none"),
        ]
    )
    try:
        libsumo.simulationStep()  # inserts both cars at their recorded state
        libsumo.vehicle.setSpeedMode("leader", 0)
        x, v, lead_x = [], [], []
        for speed in [*lead_v[1:], None]:
            x.append(libsumo.vehicle.getLanePosition("follower"))
            v.append(libsumo.vehicle.getSpeed("follower"))
            lead_x.append(libsumo.vehicle.getLanePosition("leader"))
            if speed is not None:
                libsumo.vehicle.setSpeed("leader", float(speed))
                libsumo.simulationStep()
    finally:
        libsumo.close()
    x, lead_x = np.array(x), np.array(lead_x)
    return SumoFollower(x - START_M, np.array(v), lead_x - leader_length - x)
