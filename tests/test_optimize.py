"""Line search, options and the BLAS thread limit: hand-checked cases."""

from contextlib import contextmanager

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
     ("start_strain_ratio", "2"), ("start_choice_modes", 0), ("start_choice_modes", 2.5)],
)
def test_options_reject_invalid_values(field, value):
    with pytest.raises(OptionError, match=field):
        RegistrationOptions(**{field: value})


def test_options_replace_names_unknown_fields():
    with pytest.raises(OptionError, match="gird"):
        RegistrationOptions().replace(gird=3)
    assert RegistrationOptions().replace(grid=32).grid == 32


def _blas_threads():
    from threadpoolctl import threadpool_info

    return min(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")


@contextmanager
def _two_blas_threads():
    """BLAS on two threads, with no thread holding threadpoolctl's control of it (>= 3.8),
    as in a process that set no limit; then as it was."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from morphmodes_vol.blas import release_blas_control

    if not any(i["user_api"] == "blas" for i in threadpool_info()):
        pytest.skip("no BLAS thread pool that threadpoolctl can see")
    limiter = threadpool_limits(limits=2, user_api="blas")
    release_blas_control()
    try:
        if _blas_threads() < 2:
            pytest.skip("this BLAS does not take two threads")
        yield
    finally:
        limiter.restore_original_limits()
        release_blas_control()


def test_blas_limit_is_restored_when_two_threads_overlap():
    """Two threads' contexts overlapping (A enters, B enters, A leaves, B leaves): BLAS stays
    on one thread until the last one leaves, and is then as before the first came in. A
    context per thread gives B every thread once A has left, and then restores the limit of
    1 that B found (measured with threadpoolctl 3.8)."""
    import threading

    from morphmodes_vol.optimize import single_threaded_blas

    with _two_blas_threads():
        a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
        seen = {}

        def a():
            with single_threaded_blas():
                seen["a"] = _blas_threads()
                a_in.set()
                b_in.wait(10)
            a_out.set()

        def b():
            a_in.wait(10)
            with single_threaded_blas():
                b_in.set()
                a_out.wait(10)
                seen["b alone"] = _blas_threads()

        threads = [threading.Thread(target=a), threading.Thread(target=b)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(20)
        assert a_out.is_set() and seen == {"a": 1, "b alone": 1}
        assert _blas_threads() == 2


def test_blas_limit_nested_in_one_thread():
    """Nested contexts in one thread: one thread inside both, two again after both."""
    from morphmodes_vol.optimize import single_threaded_blas

    with _two_blas_threads():
        with single_threaded_blas():
            with single_threaded_blas():
                assert _blas_threads() == 1
            assert _blas_threads() == 1
        assert _blas_threads() == 2


def test_registrations_on_a_thread_pool():
    """The user's case: registrations (each with its warped field's thread) run on a thread
    pool. Afterwards BLAS has the threads it had before (with a context per thread,
    overlapping runs could leave it on one); and they share no state: each gives what one
    alone gives, the same evaluations and vertices (BLAS on one thread inside each, whatever
    the others are doing)."""
    from concurrent.futures import ThreadPoolExecutor

    import morphmodes_vol as mm
    from morphmodes_vol.primitives import capsule

    X, F = capsule()
    Y = X * np.array([1.2, 0.9, 1.0])
    options = RegistrationOptions(grid=16, modes=3, initialization="none")
    with _two_blas_threads():
        alone = mm.register((X, F), (Y, F), options)
        with ThreadPoolExecutor(2) as pool:
            results = list(pool.map(lambda _: mm.register((X, F), (Y, F), options), range(4)))
        assert _blas_threads() == 2
    assert alone.evaluations > 0 and np.isfinite(alone.vertices).all()
    for r in results:
        assert r.evaluations == alone.evaluations
        np.testing.assert_array_equal(r.vertices, alone.vertices)


def test_eigenmodes_do_not_depend_on_blas_threads():
    """The capsule's eigenvalues repeat (it is symmetric about its axis): within those spaces
    the dense solver's eigenvectors followed the last bits of BLAS's sums, and differed by up
    to 1.2 between one and two BLAS threads. They are now computed on one thread."""
    from threadpoolctl import threadpool_limits

    from morphmodes_vol.eigenbasis import mesh_skinning_weights
    from morphmodes_vol.primitives import capsule

    X, F = capsule()
    with _two_blas_threads():
        W2, lam2 = mesh_skinning_weights(X, F, 6)
    with threadpool_limits(limits=1, user_api="blas"):
        W1, lam1 = mesh_skinning_weights(X, F, 6)
    np.testing.assert_array_equal(W1, W2)
    np.testing.assert_array_equal(lam1, lam2)
    assert np.sum(np.isclose(lam1[1:], lam1[1:, None], rtol=1e-6)) > lam1.size - 1  # repeats


def test_a_registration_does_not_depend_on_blas_threads():
    """The same pair with BLAS on two threads and on one: the same evaluations and vertices
    (before BLAS ran on one thread throughout, the capsule took 18 evaluations on one and 19 on
    two, from its eigenmodes)."""
    from threadpoolctl import threadpool_limits

    import morphmodes_vol as mm
    from morphmodes_vol.primitives import capsule

    X, F = capsule()
    Y = X * np.array([1.2, 0.9, 1.0])
    options = RegistrationOptions(grid=16, modes=3, initialization="none", overlap_field=False)
    with _two_blas_threads():
        two = mm.register((X, F), (Y, F), options)
    with threadpool_limits(limits=1, user_api="blas"):
        one = mm.register((X, F), (Y, F), options)
    assert one.evaluations == two.evaluations
    np.testing.assert_array_equal(one.vertices, two.vertices)


def test_presets_are_data_shipped_with_the_package():
    """Every preset is a TOML file of morphmodes_vol/presets with a description and an
    [options] table of valid fields; ``from_table`` applies one, then changes it."""
    from morphmodes_vol.options import PRESETS, preset_description, preset_table

    assert set(PRESETS) == {"default", "accurate", "fast", "fastest", "paper"}
    for name in PRESETS:
        assert preset_description(name)
        table = preset_table(name)
        assert RegistrationOptions.preset(name) == RegistrationOptions().replace(**table)
        assert RegistrationOptions.from_table({"preset": name, "seed": 3}) == \
            RegistrationOptions.preset(name).replace(seed=3)
    assert preset_table("default") == {} and preset_table("fast")["quadrature"] == "band"
    assert RegistrationOptions.preset("accurate") == RegistrationOptions(two_way=True)
    with pytest.raises(OptionError, match="preset 'turbo' is unknown"):
        RegistrationOptions.preset("turbo")
    with pytest.raises(OptionError, match="unknown option"):
        RegistrationOptions.from_table({"preset": "fast", "gird": 3})
