"""Car following for predicted road users: the intelligent driver model (IDM) along their lane paths.

A constant-speed prediction drives a car through the car stopped ahead of it. With ``[online.prediction]
lane_speed = "idm"`` the lane-following prediction (:class:`~.prediction.ObservedPrediction`, ``motion_model =
"lane"``) moves each vehicle along its lane path with the acceleration of the intelligent driver model
(Treiber, Hennecke and Helbing, "Congested traffic states in empirical observations and microscopic simulations",
Phys. Rev. E 62, 2000) behind its *leader*, the nearest road user ahead on that path, which is itself predicted the
same way (one joint integration over all rows)::

    a = min(a_free, a_int),   a_free = a_max (1 - (v / v_obs)^4),   a_int = a_max (1 - (s* / g)^2),
    s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b))),

with ``g`` the bumper-to-bumper gap along the path, ``dv = v - v_leader`` the closing speed, ``s0`` the minimum gap,
``b`` the comfortable deceleration, and ``a`` clipped to ``[-max_decel, a_max]``. Two departures from the textbook
model keep the prediction equal to constant speed wherever nothing is ahead:

* the free-road term uses the *observed* speed as the desired one and is taken as a bound (``min``), not added:
  a vehicle with a free road keeps its observed speed exactly (the constant-speed prediction), and one that braked
  for its leader recovers towards its observed speed once the gap opens;
* the time headway ``T`` of each follower is the one it is observed to keep, ``(g0 - s0) / v_obs`` clipped to
  ``[min_headway, max_headway]``: a vehicle following at an observed steady gap keeps it (``a_int = 0`` at
  ``tau = 0`` when the speeds match) and reacts only to closing speed or a gap shorter than its own.

**Observed acceleration** (``accel``, ``accel_hold`` > 0; ``[online.prediction] accel_hold``): the free-road speed
is no longer the observed one but ``v_ref(tau) = max(0, v_obs + a_obs min(tau, accel_hold))``, the observed
acceleration ``a_obs`` kept for ``accel_hold`` seconds (a car braking for a red light is predicted to stop, one
pulling away to speed up), and the free-road term becomes ``a_free = a_max (1 - (v / v_ref)^4) + dv_ref/dtau``, so
that a vehicle on a free road follows ``v_ref`` exactly and one slowed by its leader recovers towards it.

Stopped vehicles (observed speed below ``min_speed``, not observed pulling away) stay where they are; they are
leaders for the others.
The leader of a row is found once, at the observation (:func:`find_leaders`): the nearest road user (vehicles and
bicycles, not pedestrians) within ``leader_offset`` of the path whose heading is within ``leader_heading_error`` of the
path's (or that stands still), ahead of the follower. Its advance along the follower's path is taken to be its own
predicted advance along its own path. Lane changes, merging and traffic-light stops are not modelled.

The integration is the ballistic (trapezoidal-position) Euler scheme usual for IDM at ``dt`` = 0.1 s, vectorised
over rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..checks import check_positive

__all__ = ["IDMConfig", "find_leaders", "idm_distances"]

#: integration step of the car-following model [s]
DT = 0.1


@dataclass(frozen=True)
class IDMConfig:
    """``[online.prediction.idm]``: the car-following model of ``lane_speed = "idm"`` (module docstring). The
    defaults are the usual urban IDM values (Treiber and Kesting, "Traffic Flow Dynamics", Springer 2013, Table 11.2:
    a = 1.0-1.5 m/s^2, b = 1.5-2.0 m/s^2, s0 = 2 m, T = 1.0-1.5 s)."""

    #: acceleration a_max [m/s^2] (recovering towards the observed speed)
    max_accel: float = 1.5
    #: comfortable deceleration b [m/s^2] of the closing-speed term
    comfort_decel: float = 2.0
    #: the hardest braking predicted [m/s^2]
    max_decel: float = 8.0
    #: minimum bumper-to-bumper gap s0 [m]
    min_gap: float = 2.0
    #: the range [s] the observed time headway of a follower is clipped to
    min_headway: float = 0.5
    max_headway: float = 2.0
    #: a leader's centre lies within this of the follower's path [m] (about half a lane)
    leader_offset: float = 1.5
    #: a leader's heading is within this of the path's direction [rad] (unless it stands still)
    leader_heading_error: float = 0.6
    #: below this observed speed [m/s] a vehicle stands still (and stays so)
    min_speed: float = 0.5

    def __post_init__(self) -> None:
        for name in ("max_accel", "comfort_decel", "max_decel", "min_gap", "min_headway", "max_headway",
                     "leader_offset", "leader_heading_error", "min_speed"):
            check_positive(f"online.prediction.idm.{name}", getattr(self, name),
                           allow_zero=name not in ("max_accel", "comfort_decel"))
        if self.min_headway > self.max_headway:
            raise ValueError(f"online.prediction.idm.min_headway ({self.min_headway}) must be <= max_headway "
                             f"({self.max_headway})")


def find_leaders(paths: np.ndarray, step: float, row_user: np.ndarray, users_xy: np.ndarray,
                 users_heading: np.ndarray, users_speed: np.ndarray, candidate: np.ndarray,
                 config: IDMConfig) -> tuple[np.ndarray, np.ndarray]:
    """The leader of every row: ``(leader (R,), ahead (R,))``, the index of the road user ahead on the row's path
    (``-1`` where none) and its distance along the path from the row's start [m] (``inf`` where none).

    Args:
        paths: ``(R, M, 2)`` points of each row's path at arc lengths ``0, step, 2 step, ...`` from the follower's
            position (NaN-padded where shorter; a path of one point has no leader).
        row_user: ``(R,)`` the road user each row predicts (it is not its own leader).
        users_xy, users_heading, users_speed: ``(N, 2)``, ``(N,)``, ``(N,)`` the observed road users.
        candidate: ``(N,)`` which users may lead (vehicles, bicycles).
        config: ``leader_offset``, ``leader_heading_error`` and ``min_speed`` (a user slower than it leads whatever
            its heading).
    """
    r_rows, m = paths.shape[:2]
    leader = np.full(r_rows, -1, dtype=np.int64)
    ahead = np.full(r_rows, np.inf)
    if r_rows == 0 or m < 2 or users_xy.shape[0] == 0:
        return leader, ahead
    seg = np.diff(paths, axis=1)  # (R, M - 1, 2)
    head = np.arctan2(seg[..., 1], seg[..., 0])
    for r in range(r_rows):
        pts = paths[r]
        valid = np.isfinite(pts[:, 0])
        n_pts = int(valid.sum())
        if n_pts < 2:
            continue
        pts = pts[:n_pts]
        reach = config.leader_offset + 0.5 * step
        lo, hi = pts.min(axis=0) - reach, pts.max(axis=0) + reach
        users = np.nonzero(candidate & np.all((users_xy >= lo) & (users_xy <= hi), axis=1))[0]  # near the path
        users = users[users != row_user[r]]
        if users.size == 0:
            continue
        xy = users_xy[users]
        d = np.hypot(xy[:, None, 0] - pts[None, :, 0], xy[:, None, 1] - pts[None, :, 1])  # (n, M)
        k = np.argmin(d, axis=1)
        near = d[np.arange(d.shape[0]), k] <= reach
        kk = np.minimum(k, n_pts - 2)
        h = head[r, kk]
        along = k * step + (np.cos(h) * (xy[:, 0] - pts[k, 0]) + np.sin(h) * (xy[:, 1] - pts[k, 1]))
        turn = np.abs(np.remainder(users_heading[users] - h + math.pi, 2 * math.pi) - math.pi)
        ok = near & (along > 0) & ((turn <= config.leader_heading_error)
                                   | (np.abs(users_speed[users]) < config.min_speed))
        if ok.any():
            m = int(np.argmin(np.where(ok, along, np.inf)))
            leader[r], ahead[r] = int(users[m]), float(along[m])
    return leader, ahead


def idm_distances(tau: np.ndarray, speed: np.ndarray, moving: np.ndarray, leader: np.ndarray, gap: np.ndarray,
                  config: IDMConfig, accel: np.ndarray | None = None,
                  accel_hold: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Distances travelled and speeds ``(s (R, K), v (R, K))`` at the times ``tau`` (``(K,)`` or one row per row,
    ``(R, K)``; >= 0) of rows that start at speeds ``speed (R,)`` (module docstring). All rows are integrated on one
    clock from ``tau = 0`` (a leader's distance is read at the follower's ``tau``).

    Args:
        moving: ``(R,)`` rows that follow the model; the others keep their speed (``s = speed * tau``).
        leader: ``(R,)`` the row whose distance leads each row (``-1``: a free road).
        gap: ``(R,)`` bumper-to-bumper gap to the leader at ``tau = 0`` [m] (``inf`` for a free road).
        accel, accel_hold: ``(R,)`` observed accelerations [m/s^2], kept for ``accel_hold`` seconds on a free road
            (module docstring, "observed acceleration"); ``None`` or a hold of 0: the observed speed is kept.
    """
    speed = np.asarray(speed, dtype=np.float64)
    r_rows = speed.shape[0]
    tau = np.broadcast_to(np.asarray(tau, dtype=np.float64), (r_rows, np.shape(tau)[-1]))
    if r_rows == 0 or tau.size == 0:
        return np.zeros(tau.shape), np.zeros(tau.shape)
    c, dt = config, DT
    n = max(int(math.ceil(float(tau.max()) / dt - 1e-9)), 0)
    grid = dt * np.arange(n + 1)
    has = (leader >= 0) & np.isfinite(gap)
    lead = np.where(has, leader, 0)
    v_obs = np.maximum(speed, 0.0)
    # the free-road speed: the observed one, or changing at the observed acceleration for accel_hold seconds
    hold = float(accel_hold) if accel is not None and accel_hold > 0 else 0.0
    a_obs = np.nan_to_num(np.asarray(accel, np.float64)) if hold > 0 else np.zeros(r_rows)
    v_top = np.maximum(v_obs, v_obs + a_obs * hold)  # the fastest a row may get
    with np.errstate(divide="ignore", invalid="ignore"):
        headway = np.where(has & (v_obs > 0), (gap - c.min_gap) / v_obs, c.max_headway)
    headway = np.clip(np.nan_to_num(headway, nan=c.max_headway), c.min_headway, c.max_headway)
    root = 2.0 * math.sqrt(c.max_accel * c.comfort_decel)
    s = np.zeros((r_rows, n + 1))
    v = np.zeros((r_rows, n + 1))
    v[:, 0] = speed
    follows = moving & (v_top > 0)
    a_ceiling = np.maximum(c.max_accel, a_obs)  # an observed acceleration is kept even above max_accel
    for k in range(n):
        vk, sk = v[:, k], s[:, k]
        tk = k * dt
        v_ref = np.maximum(v_obs + a_obs * min(tk, hold), 0.0)
        dv_ref = np.where((tk < hold) & ((v_ref > 0) | (a_obs > 0)), a_obs, 0.0)  # none once braked to a stop
        with np.errstate(divide="ignore", invalid="ignore"):
            a_free = c.max_accel * (1.0 - (vk / v_ref) ** 4) + dv_ref
        # a free-road speed of 0: starting (observed accelerating from a stop), or braked to a stop
        a_free = np.where(v_ref > 0, a_free, np.where(dv_ref > 0, dv_ref, np.where(vk > 0, -c.max_decel, 0.0)))
        g = np.where(has, gap + s[lead, k] - sk, np.inf)
        closing = vk - v[lead, k]
        s_star = c.min_gap + np.maximum(0.0, vk * headway + vk * closing / root)
        a_int = np.where(has, c.max_accel * (1.0 - (s_star / np.maximum(g, 0.1)) ** 2), np.inf)
        a = np.clip(np.minimum(a_free, a_int), -c.max_decel, a_ceiling)
        a = np.where(follows, np.nan_to_num(a, nan=0.0), 0.0)
        v_next = np.clip(vk + a * dt, 0.0, np.maximum(v_top, vk))
        v_next = np.where(follows, v_next, vk)
        s[:, k + 1] = sk + 0.5 * (vk + v_next) * dt
        v[:, k + 1] = v_next
    s_out = np.stack([np.interp(tau[r], grid, s[r]) for r in range(r_rows)])
    v_out = np.stack([np.interp(tau[r], grid, v[r]) for r in range(r_rows)])
    return s_out, v_out
