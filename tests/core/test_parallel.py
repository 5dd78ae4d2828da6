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
