"""Is the occupancy model of recorded traffic calibrated? Predicted collision risk against true-shape hits.

The collision probability a plan reports on a recorded road scene reads an *occupancy model*: the road users'
footprints blurred with a position uncertainty (and, past the end of the recording, extrapolated with constant
velocity), read by the body's disc cover (:mod:`density_planner.risk.body`). Whether that model is conservative
is a question about the road users, not about the estimator (which :mod:`.risk_validation` checks), so it is
answered against the ground truth, the road users' recorded true shapes:

for ``M`` initial states ``x0_m`` drawn from the plan's initial law and their closed loops ``x_m(t)`` (simulated
exactly, as the risk check does),

* predicted ``p_m(t) = P_body(x_m(t), t)`` on the occupancy of the **road users only** (the scene rebuilt with
  ``commonroad.offroad_occupied = false``: the road's edge is not a road user);
* observed ``I_m(t) = 1`` when the vehicle's rectangle at ``x_m(t)`` intersects the true shape of any road user
  *recorded* at ``t`` (shapely, the verdict's test). Past the end of a road user's recording its future is not
  known, so it cannot be a ground truth: those times count no hit, while the prediction still holds the
  extrapolated footprint (``extras["extrapolated_share"]`` is the share of (road user, time) pairs that are
  extrapolated; where it is large the comparison leans conservative by construction).

Per time, ``P_pred(t) = mean_m p_m(t)`` is the plan's road-user collision probability and ``P_obs(t) = mean_m
I_m(t)`` the frequency with which the vehicle actually hits a road user (standard error ``sqrt(P(1-P)/M)``). The
pairs ``(p_m(t), I_m(t))`` are binned by ``p`` (:class:`CalibrationResult`): in each bin the mean prediction against
the observed hit frequency is a **reliability diagram**; points below the diagonal mean the model is conservative
(predicts more risk than the recorded traffic realises), above it that it misses hits. Results of several plans
add up bin by bin (:meth:`CalibrationResult.pooled`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

__all__ = ["CalibrationResult", "bin_pairs", "road_user_hits", "calibrate_plan"]


@dataclass
class CalibrationResult:
    """Predicted road-user collision risk against true-shape hits of one plan (or pooled over several)."""

    #: planning times [s] relative to the plan's start, ``(T,)`` (empty when pooled)
    times: np.ndarray
    #: mean predicted road-user occupancy of the body over the samples, ``(T,)``
    predicted: np.ndarray
    #: frequency of true-shape hits over the samples, ``(T,)``
    observed: np.ndarray
    #: closed loops per time
    n: int
    #: bin edges of the predicted probability, ``(B + 1,)``
    bin_edges: np.ndarray
    #: (sample, time) pairs per bin, ``(B,)``
    bin_count: np.ndarray
    #: sum of the predictions per bin, ``(B,)``
    bin_predicted: np.ndarray
    #: number of hits per bin, ``(B,)``
    bin_hits: np.ndarray
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def observed_se(self) -> np.ndarray:
        p = self.observed
        return np.sqrt(np.clip(p * (1 - p), 0, None) / max(self.n, 1))

    def bins(self) -> list[dict[str, float]]:
        """Per non-empty bin: edges, pairs, mean prediction, observed frequency and its standard error."""
        out = []
        for k in range(self.bin_count.size):
            c = int(self.bin_count[k])
            if c == 0:
                continue
            f = float(self.bin_hits[k]) / c
            out.append({"lo": float(self.bin_edges[k]), "hi": float(self.bin_edges[k + 1]), "pairs": c,
                        "predicted": float(self.bin_predicted[k]) / c, "observed": f,
                        "observed_se": math.sqrt(max(f * (1 - f), 0.0) / c)})
        return out

    @property
    def total_predicted(self) -> float:
        """Mean prediction over every (sample, time) pair."""
        c = float(self.bin_count.sum())
        return float(self.bin_predicted.sum()) / c if c else math.nan

    @property
    def total_observed(self) -> float:
        """Hit frequency over every (sample, time) pair."""
        c = float(self.bin_count.sum())
        return float(self.bin_hits.sum()) / c if c else math.nan

    def to_dict(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "times": self.times.tolist(),
            "predicted": self.predicted.tolist(),
            "observed": self.observed.tolist(),
            "observed_se": self.observed_se.tolist(),
            "predicted_max": float(self.predicted.max()) if self.predicted.size else None,
            "observed_max": float(self.observed.max()) if self.observed.size else None,
            "mean_predicted": self.total_predicted,
            "mean_observed": self.total_observed,
            "bin_edges": self.bin_edges.tolist(),
            "bin_count": self.bin_count.tolist(),
            "bin_predicted": self.bin_predicted.tolist(),
            "bin_hits": self.bin_hits.tolist(),
            "bins": self.bins(),
            **self.extras,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CalibrationResult:
        return cls(np.asarray(d.get("times", []), dtype=float), np.asarray(d.get("predicted", []), dtype=float),
                   np.asarray(d.get("observed", []), dtype=float), int(d.get("n", 0)),
                   np.asarray(d["bin_edges"], dtype=float), np.asarray(d["bin_count"], dtype=np.int64),
                   np.asarray(d["bin_predicted"], dtype=float), np.asarray(d["bin_hits"], dtype=np.int64))

    @classmethod
    def pooled(cls, results: list[CalibrationResult]) -> CalibrationResult:
        """The bins of several results added up (same bin edges); per-time curves are left empty."""
        if not results:
            raise ValueError("nothing to pool")
        edges = results[0].bin_edges
        for r in results[1:]:
            if r.bin_edges.shape != edges.shape or not np.allclose(r.bin_edges, edges):
                raise ValueError("calibration results with different bin edges cannot be pooled")
        empty = np.zeros(0)
        return cls(empty, empty, empty, sum(r.n for r in results), edges,
                   np.sum([r.bin_count for r in results], axis=0), np.sum([r.bin_predicted for r in results], axis=0),
                   np.sum([r.bin_hits for r in results], axis=0), {"plans": len(results)})


def road_user_hits(road: Any, poses: np.ndarray, times: np.ndarray, *, include_predicted: bool = False
                   ) -> np.ndarray:
    """``(M, T)`` bool: the vehicle rectangle (``road.vehicle_length x road.vehicle_width``) at ``poses (M, T, 3)``
    (``x, y, heading``) intersects the true shape of a road user of ``road`` recorded at the absolute times
    ``times (T,)`` [s] (``include_predicted``: also its extrapolation past the end of its recording)."""
    import shapely

    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[-1] != 3:
        raise ValueError(f"poses must have shape (M, T, 3), got {poses.shape}")
    m, t, _ = poses.shape
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if times.size != t:
        raise ValueError(f"times must have {t} entries (one per pose column), got {times.size}")
    boxes = road.vehicle_polygons(poses.reshape(-1, 3)).reshape(m, t)
    hits = np.zeros((m, t), dtype=bool)
    polys = road.obstacle_polygons(times, include_predicted=include_predicted)  # (n_obstacles, T)
    for k in range(t):
        present = [p for p in polys[:, k] if p is not None] if polys.size else []
        if not present:
            continue
        tree = shapely.STRtree(present)
        idx_box, _ = tree.query(boxes[:, k], predicate="intersects")
        hits[np.unique(idx_box), k] = True
    return hits


def bin_pairs(p: np.ndarray, hit: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(count, sum of p, hits)`` per bin of ``edges`` for the pairs ``p, hit`` (any equal shapes); bin ``k``
    holds ``edges[k] < p <= edges[k + 1]`` (``p = edges[0]`` in bin 0)."""
    bins = len(edges) - 1
    p = np.asarray(p, dtype=np.float64).ravel()
    hit = np.asarray(hit, dtype=bool).ravel()
    if p.shape != hit.shape:
        raise ValueError(f"p and hit must have the same number of pairs, got {p.size} and {hit.size}")
    b = np.clip(np.digitize(p, edges[1:-1], right=True), 0, bins - 1)
    return (np.bincount(b, minlength=bins), np.bincount(b, weights=p, minlength=bins),
            np.bincount(b[hit], minlength=bins).astype(np.int64))


@torch.no_grad()
def calibrate_plan(
    problem: Any,
    plan: Any,
    controller: Any,
    road_users: Any,
    road: Any,
    *,
    n: int = 2_000,
    seed: int = 0,
    config: Any = None,
    bins: int = 10,
    chunk: int = 2_000,
) -> CalibrationResult:
    """Calibration of ``plan`` (module docstring).

    Args:
        problem: the planning problem the plan was made for (initial law, system, time of the first slice).
        plan: a tracked plan (``plan.reference``).
        controller: the tracking controller.
        road_users: :class:`~density_planner.risk.collision.CollisionModel` on the road users' occupancy only
            (same grid lattice and slices as the problem's scene).
        road: the scene's :class:`~density_planner.environment.road.RoadScene` (true shapes).
        n: closed loops.
        bins: equal-width bins of the predicted probability on ``[0, 1]``.
    """
    from .risk_validation import simulate_closed_loops

    if road is None:
        raise ValueError("calibration needs a road scene (recorded road users with their true shapes)")
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    system = problem.system
    if system.heading_index is None:
        raise ValueError(f"calibration draws the vehicle's rectangle and needs a heading; {type(system).__name__} "
                         "has none")
    t_len = plan.reference.x_plan.shape[-2]
    slices = problem.slices(t_len)
    times_rel = np.arange(t_len, dtype=np.float64) * problem.parameterization.plan_dt
    times_abs = float(problem.scene.t_start) + times_rel
    edges = np.linspace(0.0, 1.0, bins + 1)
    count = np.zeros(bins, dtype=np.int64)
    pred_sum = np.zeros(bins)
    hit_sum = np.zeros(bins, dtype=np.int64)
    pred_t = np.zeros(t_len)
    obs_t = np.zeros(t_len)
    for x in simulate_closed_loops(problem, plan, controller, n=n, seed=seed, config=config, chunk=chunk):
        x = x.to(torch.float64)
        p = road_users.occupancy(x, slices[: x.shape[1]]).numpy()  # (chunk, T)
        pos = system.positions(x).numpy()
        heading = system.headings(x).numpy()
        hit = road_user_hits(road, np.concatenate([pos, heading[..., None]], -1), times_abs[: x.shape[1]])
        pred_t[: p.shape[1]] += p.sum(0)
        obs_t[: p.shape[1]] += hit.sum(0)
        c, ps, hs = bin_pairs(p, hit, edges)
        count += c
        pred_sum += ps
        hit_sum += hs
    n_any = sum(int(o.present(times_abs).sum()) for o in road.obstacles)
    n_rec = sum(int(o.present(times_abs, include_predicted=False).sum()) for o in road.obstacles)
    extrapolated = (n_any - n_rec) / n_any if n_any else 0.0
    return CalibrationResult(times_rel, pred_t / n, obs_t / n, n, edges, count, pred_sum, hit_sum,
                             {"extrapolated_share": extrapolated})
