"""Every registered driver model is consistent: names, parameter layout, defaults inside priors."""

from __future__ import annotations

import numpy as np
import pytest

from bayesdrive.drivers.cidm import CIDM
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import MODELS, get_model


def test_models_are_found_by_their_own_name():
    assert get_model("idm") is IDM
    assert get_model("cidm") is CIDM
    assert all(get_model(name).name == name for name in MODELS)


def test_unknown_model_names_the_known_ones():
    with pytest.raises(KeyError, match=r"'mobil'.*\['cidm', 'gipps', 'idm', 'ovm'\]"):
        get_model("mobil")


@pytest.mark.parametrize("name", sorted(MODELS))
def test_parameter_layout_and_priors_are_consistent(name):
    model = get_model(name)
    assert model.params_type._fields == model.param_names
    for spec in model.specs:
        assert spec.lower < spec.upper, spec
        assert spec.lower <= spec.default <= spec.upper, spec
        # pf builds its grid from these: at least two points inside the bounds.
        assert spec.grid_step is not None and spec.grid_step <= (spec.upper - spec.lower) / 2, spec
    # lm and the SBC control find the execution-noise sd by this mark, never by its name.
    assert model.execution_noise_param == "sigma"
    prior = model.prior()
    defaults = np.array([float(getattr(model.defaults(), n)) for n in prior.names])
    assert np.isfinite(float(prior.logpdf(defaults)))


def test_cidm_extends_the_idm_by_cooperation_only():
    assert CIDM.param_names == (*IDM.param_names, "c")
    assert CIDM.specs[:-1] == IDM.specs
    assert (CIDM.spec("c").lower, CIDM.spec("c").upper) == (0.0, 1.0)
