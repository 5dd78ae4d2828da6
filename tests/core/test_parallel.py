"""The task executor: same outcomes serially and in worker processes; failures are captured, not raised."""

from __future__ import annotations

import pytest

from density_planner.parallel import run_tasks


def _square_or_fail(x: int) -> int:
    if x == 3:
        raise RuntimeError("task 3 fails on purpose")
    return x * x


@pytest.mark.parametrize("workers", [1, 2])
def test_outcomes_and_captured_errors(workers):
    outcomes = sorted(run_tasks(_square_or_fail, range(6), workers=workers), key=lambda o: o.index)
    assert [o.index for o in outcomes] == list(range(6))
    assert [o.value for o in outcomes if o.ok] == [0, 1, 4, 16, 25]
    assert not outcomes[3].ok and "task 3 fails on purpose" in outcomes[3].error


def test_bad_worker_count():
    with pytest.raises(ValueError, match="workers"):
        list(run_tasks(_square_or_fail, range(3), workers=0))


def test_loky_replacing_a_grown_worker_is_not_shown():
    """loky's warning on a worker it replaced between tasks (after a large plan) is filtered while joblib runs; the
    filter matches loky's own text."""
    import inspect
    import warnings

    from joblib.externals.loky import process_executor

    from density_planner.parallel import _LOKY_REPLACED_WORKER

    source = "".join(inspect.getsource(process_executor).replace('"', "").split())
    assert "".join(_LOKY_REPLACED_WORKER.split()) in source
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert sorted(o.value for o in run_tasks(_square_or_fail, range(3), workers=2)) == [0, 1, 4]
        warnings.warn(_LOKY_REPLACED_WORKER + ". This can be caused by a too short worker timeout or by a memory "
                      "leak.", UserWarning, stacklevel=1)
        warnings.warn("another warning", UserWarning, stacklevel=1)
    assert [str(w.message) for w in caught] == ["another warning"]
