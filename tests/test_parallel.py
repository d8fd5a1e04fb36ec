"""fit_many and the Dask path for grid searches and batches of experiments."""

from __future__ import annotations

import joblib
import numpy as np
import pytest
from conftest import simulate_resonant
from sklearn.model_selection import GridSearchCV, KFold

from lrmfrf import LRMBeyondNyquist, multisine
from lrmfrf.estimators.selection import LRMBeyondNyquistCV
from lrmfrf.parallel import fit_many

N, F = 300, 3
SMALL = {"half_window": 8, "num_degree": 1, "transient_degree": 1, "den_degree": 2}
GRID = {"half_window": [6, 8], "den_degree": [0, 2]}


def _records(R, rng, P=None):
    shape = (R, N) if P is None else (R, P, N)
    u = np.stack([multisine(N, rng=rng) for _ in range(int(np.prod(shape[:-1])))])
    u = u.reshape(shape)
    return u, simulate_resonant(u, F, 0.01, rng)


def _assert_same_fits(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.frf_, y.frf_)
        np.testing.assert_array_equal(x.frf_std_, y.frf_std_)


def test_fit_many_equals_one_fit_per_record():
    rng = np.random.default_rng(0)
    u, y = _records(4, rng)
    template = LRMBeyondNyquist(**SMALL)
    fits = fit_many(template, u, y, F, sample_time=0.5e-3)
    assert not hasattr(template, "frf_")  # the template is cloned, not fitted
    for r, est in enumerate(fits):
        single = LRMBeyondNyquist(**SMALL).fit(u[r], y[r], F, sample_time=0.5e-3)
        np.testing.assert_array_equal(est.frf_, single.frf_)
        assert est.sample_time_ == 0.5e-3
    assert len({id(est) for est in fits}) == 4


def test_fit_many_items_can_be_groups_of_experiments():
    rng = np.random.default_rng(1)
    u, y = _records(3, rng, P=2)
    u, y = u[:, :, None], y[:, :, None]  # items of 2 SISO experiments, 3-D
    fits = fit_many(LRMBeyondNyquist(**SMALL), list(u), list(y), F)
    assert [est.n_experiments_ for est in fits] == [2, 2, 2]
    np.testing.assert_array_equal(
        fits[1].frf_, LRMBeyondNyquist(**SMALL).fit(u[1], y[1], F).frf_)


def test_fit_many_with_worker_processes_matches_serial():
    rng = np.random.default_rng(2)
    u, y = _records(4, rng)
    serial = fit_many(LRMBeyondNyquist(**SMALL), u, y, F, n_jobs=1)
    processes = fit_many(LRMBeyondNyquist(**SMALL), u, y, F, n_jobs=2, backend="loky")
    _assert_same_fits(serial, processes)



def test_fit_many_on_threads_gives_the_blas_threads_back(two_blas_threads):
    """Fits on joblib's threading backend overlap their single-threaded BLAS
    sections; afterwards BLAS runs on as many threads as before (it stayed on
    one for the rest of the process when each fit restored what it found),
    and the fits equal serial ones."""
    from conftest import blas_threads

    rng = np.random.default_rng(4)
    u, y = _records(12, rng)
    with joblib.parallel_config(backend="threading"):
        threaded = fit_many(LRMBeyondNyquist(**SMALL), u, y, F, n_jobs=2)
    assert blas_threads() == two_blas_threads
    _assert_same_fits(threaded, fit_many(LRMBeyondNyquist(**SMALL), u, y, F))


def test_fit_many_accepts_cv_estimators():
    rng = np.random.default_rng(3)
    u, y = _records(2, rng)
    fits = fit_many(LRMBeyondNyquistCV(half_windows=(6, 8), num_degrees=(1,),
                                       den_degrees=(2,)), u, y, F)
    assert all(hasattr(est, "best_params_") for est in fits)


def test_fit_many_rejects_bad_input():
    rng = np.random.default_rng(4)
    u, y = _records(3, rng)
    with pytest.raises(ValueError, match="U_records holds 3 data set.*Y_records "
                                         "holds 2"):
        fit_many(LRMBeyondNyquist(**SMALL), u, y[:2], F)
    with pytest.raises(ValueError, match="are empty"):
        fit_many(LRMBeyondNyquist(**SMALL), [], [], F)
    with pytest.raises(TypeError, match="must be a scikit-learn style estimator"):
        fit_many(np.mean, u, y, F)
    with pytest.raises(TypeError, match="`U_records` must be a sequence"):
        fit_many(LRMBeyondNyquist(**SMALL), 3.0, y, F)
    # Errors inside one fit surface unchanged.
    with pytest.raises(ValueError, match="must have equal length"):
        fit_many(LRMBeyondNyquist(**SMALL), [list(u[:2]), [u[2][:-3], u[2]]],
                 [list(y[:2]), list(y[:2])], F)


def test_grid_search_and_batch_on_a_dask_cluster():
    """The documented Dask path: joblib's "dask" backend on a LocalCluster."""
    distributed = pytest.importorskip("distributed")
    rng = np.random.default_rng(5)
    u, y = _records(6, rng)
    serial_search = GridSearchCV(LRMBeyondNyquist(**SMALL), GRID, cv=KFold(3)).fit(
        list(u), list(y), F=F)
    serial_batch = fit_many(LRMBeyondNyquist(**SMALL), u, y, F)
    serial_cv = LRMBeyondNyquistCV(half_windows=(6, 8), num_degrees=(1, 2),
                                   den_degrees=(2,)).fit(u[0], y[0], F)
    import dask

    # The documented setting of lrmfrf.parallel (workers keep glibc's
    # adaptive mmap threshold); it changes speed, not results.
    unset = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
    with (
        dask.config.set(unset),
        # Two worker processes on the loopback interface only, no dashboard.
        distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                 host="127.0.0.1", dashboard_address=None) as cluster,
        distributed.Client(cluster) as client,
        joblib.parallel_config(backend="dask"),
    ):
        search = GridSearchCV(LRMBeyondNyquist(**SMALL), GRID, cv=KFold(3),
                              n_jobs=-1).fit(list(u), list(y), F=F)
        batch = fit_many(LRMBeyondNyquist(**SMALL), u, y, F, n_jobs=-1)
        cv = LRMBeyondNyquistCV(half_windows=(6, 8), num_degrees=(1, 2),
                                den_degrees=(2,), n_jobs=-1).fit(u[0], y[0], F)
        assert len(client.scheduler_info()["workers"]) == 2
        environ = client.run(lambda: __import__("os").environ.get(
            "MALLOC_TRIM_THRESHOLD_"))
        assert list(environ.values()) == [None, None]
    # Leaving the context shut the cluster down.
    assert cluster.status == distributed.core.Status.closed
    np.testing.assert_allclose(search.cv_results_["mean_test_score"],
                               serial_search.cv_results_["mean_test_score"],
                               rtol=1e-12)
    assert search.best_params_ == serial_search.best_params_
    _assert_same_fits(batch, serial_batch)
    np.testing.assert_array_equal(cv.cv_results_["criterion"],
                                  serial_cv.cv_results_["criterion"])


def test_fit_many_verbose_is_a_progress_bar(capsys):
    """verbose=True shows lrmfrf's progress bar (tqdm) over the data sets;
    False shows nothing; the fits are the same either way."""
    pytest.importorskip("tqdm")
    rng = np.random.default_rng(6)
    u, y = _records(3, rng)
    quiet = fit_many(LRMBeyondNyquist(**SMALL), u, y, F)
    assert capsys.readouterr().err == ""
    shown = fit_many(LRMBeyondNyquist(**SMALL), u, y, F, verbose=True)
    err = capsys.readouterr().err
    assert "fits" in err and "3/3" in err
    _assert_same_fits(quiet, shown)
    with joblib.parallel_config(backend="threading"):
        threaded = fit_many(LRMBeyondNyquist(**SMALL), u, y, F, n_jobs=2,
                            verbose=True)
    assert "3/3" in capsys.readouterr().err
    _assert_same_fits(quiet, threaded)  # in the order of the records


@pytest.mark.parametrize("old, shows_bar", [(0, False), (1, True), (10, True)])
def test_fit_many_integer_verbose_is_deprecated(capsys, old, shows_bar):
    """joblib-style integers keep working for one release: 0 -> False,
    > 0 -> True, with a FutureWarning that names the bool to pass."""
    pytest.importorskip("tqdm")
    rng = np.random.default_rng(7)
    u, y = _records(2, rng)
    with pytest.warns(FutureWarning, match=rf"verbose={old}\): an integer "
                      rf"verbosity .* is deprecated.*Pass verbose={shows_bar}"):
        fits = fit_many(LRMBeyondNyquist(**SMALL), u, y, F, verbose=old)
    assert ("2/2" in capsys.readouterr().err) == shows_bar
    assert len(fits) == 2


def test_fit_many_rejects_a_verbose_that_is_not_a_bool():
    rng = np.random.default_rng(8)
    u, y = _records(2, rng)
    with pytest.raises(TypeError, match="`verbose` must be True or False. Got "
                                        "'yes'"):
        fit_many(LRMBeyondNyquist(**SMALL), u, y, F, verbose="yes")


def test_docstring_examples_run():
    import doctest

    import lrmfrf.parallel

    result = doctest.testmod(lrmfrf.parallel,
                             optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0
