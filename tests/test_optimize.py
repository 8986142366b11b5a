"""Line search and options: hand-checked cases."""

import numpy as np
import pytest

from morphmodes_vol import OptionError, RegistrationOptions
from morphmodes_vol.optimize import armijo_backtracking


def test_armijo_quadratic_by_hand():
    # phi(a) = (1 - a)^2, phi(0) = 1, phi'(0) = -2; a=4 gives 9 (rejected), a=2 gives 1
    # (1 <= 1 - 2e-4 * 2 * 2? no), a=1 gives 0 (accepted)
    r = armijo_backtracking(lambda a: ((1 - a) ** 2, a), 1.0, -2.0, step=4.0)
    assert r.accepted and r.step == 1.0 and r.trials == 3 and r.state == 1.0


def test_armijo_never_accepts_nan_and_reports_failure():
    r = armijo_backtracking(lambda a: (float("nan"), None), 1.0, -1.0, step=1.0, max_trials=5)
    assert not r.accepted and r.trials == 5
    r = armijo_backtracking(lambda a: (2.0, None), 1.0, -1.0, step=1.0, max_trials=3)
    assert not r.accepted


def test_stall_schedule_decays_geometrically():
    o = RegistrationOptions(modes=5, stall_start=1e-2, stall_end=1e-4)
    got = [o.stall_threshold(s) for s in range(5)]
    np.testing.assert_allclose(got, [1e-2, 10**-2.5, 1e-3, 10**-3.5, 1e-4])
    assert RegistrationOptions(modes=1).stall_threshold(0) == RegistrationOptions().stall_start


@pytest.mark.parametrize(
    "field, value",
    [("grid", 2), ("grid", 64.0), ("modes", 0), ("preconditioner", "newton"), ("backtrack", 1.0),
     ("stall_end", 1.0), ("occupancy_samples", 2), ("seed", -1), ("padding", -0.1),
     ("start_check_modes", 0), ("start_merge_distance", -1.0), ("start_strain_ratio", 0.5),
     ("start_strain_ratio", "2"), ("start_choice_modes", 0), ("start_choice_modes", 2.5), ("icp_start", 1)],
)
def test_options_reject_invalid_values(field, value):
    with pytest.raises(OptionError, match=field):
        RegistrationOptions(**{field: value})


def test_options_replace_names_unknown_fields():
    with pytest.raises(OptionError, match="gird"):
        RegistrationOptions().replace(gird=3)
    assert RegistrationOptions().replace(grid=32).grid == 32
