"""Exit codes of the command-line interface (one place; documented in the README's bad-input paragraph).

* 0: success (for ``plan``: a plan was made and its verdict is ``success``);
* 1: the planner produced no plan at all (no trajectory to judge);
* 2: bad input (a file, option, configuration key or state the tool refuses), with a one-line error;
* 3: ``plan`` made a plan but it failed its verdict (goal, collision, road or model); every output file is still
  written and ``plan.json`` lists the reasons;
* 130: interrupted.
"""

from __future__ import annotations

from typing import Any

__all__ = ["EXIT_OK", "EXIT_NO_PLAN", "EXIT_BAD_INPUT", "EXIT_VERDICT_FAILED", "EXIT_INTERRUPTED", "plan_exit_code"]

EXIT_OK = 0
EXIT_NO_PLAN = 1
EXIT_BAD_INPUT = 2
EXIT_VERDICT_FAILED = 3
EXIT_INTERRUPTED = 130


def plan_exit_code(verdict: Any | None) -> int:
    """Exit code of ``plan`` from the plan's verdict (``None``: no plan was made)."""
    if verdict is None:
        return EXIT_NO_PLAN
    return EXIT_OK if verdict.ok else EXIT_VERDICT_FAILED
