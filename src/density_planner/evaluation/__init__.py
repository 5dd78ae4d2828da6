"""Closed-loop evaluation: tracking checks of controllers and the paper's benchmarks of planners (§V).

* :mod:`.controller`: closed-loop tracking accuracy of tracking controllers on random references;
* :mod:`.simulate`: execute a plan from a true initial state (tracked reference, receding-horizon MPC, or the
  oracle's open-loop inputs), with online step times;
* :mod:`.receding`: the receding-horizon closed loop (the plant) around a planner that solves one step at a time
  (the MPC baselines);
* :mod:`.metrics`: per-run scores (J_G, J_I, J_B, J_C, collision probability, Monte-Carlo collision frequency,
  failure flags) and their aggregation (failure rate, CRI/GCI/ICI against the best valid method, time means over
  valid runs);
* :mod:`.benchmark`: the ``ablation``, ``artificial`` and ``real`` sweeps with one resumable JSON record per run,
  serial, joblib or Dask; its settings (:mod:`.benchmark_settings`), environments (:mod:`.environments`), jobs
  (:mod:`.jobs`, the worker side) and records on disk (:mod:`.records`);
* :mod:`.report`: ``summary.csv`` / ``summary.md`` from the records alone (figures:
  :mod:`density_planner.viz.benchmark`);
* :mod:`.verdict`: the verdict on every plan (goal region in time, true-shape collision, on road, within model),
  shared by ``plan``, the benchmarks and this API;
* :mod:`.commonroad_bench`: ``bench commonroad``, every scenario of a folder judged by the verdict.
"""

from .benchmark import BenchmarkSpec, SweepReport, run_benchmark
from .benchmark_settings import SETTINGS, Setting
from .config import EvaluationConfig
from .controller import TrackingEvaluation, evaluate_tracking
from .environments import EnvSpec, artificial_envs, real_envs
from .metrics import MethodSummary, cost_increase, failure_flags, monte_carlo_metrics, run_metrics, summarise
from .records import load_records
from .simulate import Execution, ExecutionMode, execute, execution_mode, monte_carlo
from .verdict import Verdict, VerdictConfig, judge, judge_plan

__all__ = [
    "TrackingEvaluation",
    "evaluate_tracking",
    "EvaluationConfig",
    "ExecutionMode",
    "Execution",
    "execute",
    "execution_mode",
    "monte_carlo",
    "run_metrics",
    "monte_carlo_metrics",
    "failure_flags",
    "cost_increase",
    "summarise",
    "MethodSummary",
    "Setting",
    "SETTINGS",
    "EnvSpec",
    "BenchmarkSpec",
    "SweepReport",
    "artificial_envs",
    "real_envs",
    "run_benchmark",
    "load_records",
    "Verdict",
    "VerdictConfig",
    "judge",
    "judge_plan",
]
