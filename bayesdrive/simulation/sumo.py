"""Fitted IDM drivers as SUMO vehicle types: a ``vTypeDistribution`` for SUMO's own IDM.

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
sigma         (none: sigma = 0)      our sigma is the sd (m/s^2) of Gaussian execution noise on
                                     the acceleration; SUMO's ``sigma`` is Krauss-style
                                     dawdling in [0, 1], a different quantity, so the types are
                                     deterministic and our value is kept as a ``<param>``
============  =====================  =========================================================

Not mapped and worth knowing: bayesdrive integrates positions by the trapezoid rule (SUMO's
``--step-method.ballistic``), SUMO's default is semi-implicit Euler; bayesdrive's IDM has no
braking limit, SUMO's caps braking at ``emergencyDecel`` (9 m/s^2 by default); vehicle length is
not fitted (the types leave SUMO's default). Parameters a model has beyond the IDM's (e.g. the
C-IDM's cooperation ``c``) have no SUMO counterpart: they are kept as ``<param>`` entries and
logged. Every file records its source result, the seed of any draws and the code that wrote it.

Measured on an NGSIM follower behind its recorded leader (``tests/test_sumo_export.py``, 25 s at
a 0.1 s step): with the ballistic update and stepping 0.1 s, SUMO's follower stays within 4e-5 m
and 1.3e-5 m/s of bayesdrive's deterministic rollout; SUMO's default Euler update moves it by
0.36 m, and stepping 0.025 s (four sub-steps holding the leader's speed) by 0.07 m.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import xarray as xr
from jax import Array

from bayesdrive.data.atomic import write_atomic
from bayesdrive.data.provenance import provenance_line
from bayesdrive.drivers.idm import DELTA
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.output import metadata
from bayesdrive.simulation.posterior import fixed_params, particles_by_vehicle, population_draws

__all__ = [
    "IDM_TO_SUMO",
    "Driver",
    "export_header",
    "fitted_step_length",
    "per_vehicle_drivers",
    "population_drivers",
    "posterior_drivers",
    "sumo_attributes",
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
# Deterministic types driving exactly their own v_des (see the table above).
_FIXED_ATTRIBUTES = {"carFollowModel": "IDM", "sigma": "0", "speedFactor": "1", "speedDev": "0"}


class Driver(NamedTuple):
    """One exported driver: a SUMO-safe id, every model parameter by name, and where it came from."""

    id: str
    params: dict[str, float]
    source: str


def _number(value: float) -> str:
    # Seven significant digits hold a float32 draw exactly enough for SUMO's doubles.
    return f"{value:.7g}"


def _all_parameters(tree: xr.DataTree, values: Mapping[str, float]) -> dict[str, float]:
    """Inferred ``values`` completed by the fit's fixed parameters (the model's defaults)."""
    meta = metadata(tree)
    model = get_model(meta["model"])
    missing = [name for name in IDM_TO_SUMO if name not in model.param_names]
    if missing:
        raise ValueError(f"model {model.name!r} has no IDM parameter(s) {missing}: not an IDM")
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
            params=_all_parameters(tree, dict(zip(params, flat[d], strict=True))),
            source=f"population new-driver draw {d}",
        )
        for i, d in enumerate(index.tolist())
    ]


def sumo_attributes(params: Mapping[str, float], stepping: float) -> dict[str, str]:
    """The SUMO IDM vType attributes of one driver (module docstring for the mapping)."""
    attributes = dict(_FIXED_ATTRIBUTES)
    for name, sumo_names in IDM_TO_SUMO.items():
        for sumo_name in sumo_names:
            attributes[sumo_name] = _number(params[name])
    attributes["delta"] = _number(DELTA)
    attributes["stepping"] = _number(stepping)
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
    unmapped = sorted(set(drivers[0].params) - set(IDM_TO_SUMO) - {"sigma"})
    if unmapped:
        log.warning(
            "SUMO's IDM has no counterpart of %s: kept as <param> entries only, not simulated",
            unmapped,
        )
    for driver in drivers:
        vtype = ET.SubElement(
            distribution,
            "vType",
            id=f"{distribution_id}_{driver.id}",
            probability="1",
            **sumo_attributes(driver.params, stepping),
        )
        for name in sorted(set(driver.params) - set(IDM_TO_SUMO)):
            ET.SubElement(
                vtype, "param", key=f"bayesdrive.{name}", value=_number(driver.params[name])
            )
        ET.SubElement(vtype, "param", key="bayesdrive.source", value=driver.source)
    ET.indent(root)
    return ET.ElementTree(root)


def export_header(tree: xr.DataTree, source: str, how: str, seed: int | None) -> str:
    """The comment atop an exported file: what it holds, how it was drawn and what does not map."""
    meta = metadata(tree)
    drawn = "" if seed is None else f", seed {seed}"
    return (
        f" bayesdrive {meta['model']} drivers from {source} ({meta['engine']} fit of "
        f"{meta['data_source']}): {how}{drawn}. Written by {provenance_line()}. "
        "Mapping: v_des -> maxSpeed and desiredMaxSpeed, d_min -> minGap, tau -> tau, "
        "a_max -> accel, b_pref -> decel, delta = 4, stepping = the fitted step length. "
        "Not mapped: bayesdrive's sigma (sd of Gaussian execution noise) is not SUMO's sigma "
        "(dawdling), so sigma = 0 and the value is kept as a param; set SUMO's option "
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
