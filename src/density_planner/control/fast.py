"""A torch-free evaluation of the C3M controller for one state at a time (the online loop on the car).

:class:`NumpyC3M` copies the weights of a :class:`~density_planner.control.c3m.C3MController` into float64 numpy
arrays and evaluates the same law, ``u = clip(u_ref + W2(z) tanh(W1(z) e))`` with the controller's hard clip or
smooth saturation (:class:`~density_planner.control.base.SmoothSaturation`, including the speed-dependent
turn-rate box), on 1-D arrays: no autograd, no tensor dispatch. The two MLPs share their input, so their first
layers are stacked into one matrix. Its outputs equal the torch controller's to float32 round-off
(``tests/control/test_fast_controller.py``: 1e-6 against the controller evaluated in float64).
``benchmarks/bench_controller_step.py`` times both.
"""

from __future__ import annotations

import math

import numpy as np

from .c3m import N_ERR, C3MController

__all__ = ["NumpyC3M"]


class NumpyC3M:
    """``controller(x_hat (nx,), x_ref (nx,), u_ref (2,)) -> u (2,)`` in plain numpy (module docstring)."""

    def __init__(self, controller: C3MController):
        if not isinstance(controller, C3MController):
            raise ValueError(f"NumpyC3M needs a C3MController, got {type(controller).__name__}")
        arch = controller.architecture
        feats = controller._features
        self.t0, self.v0, self.ts, self.vs = feats.t0, feats.v0, feats.ts, feats.vs
        self.sincos, self.vf = feats.sincos, feats.vf
        self.rank = arch.rank

        def layers(mlp):
            return [(lin.weight.detach().cpu().double().numpy().copy(), lin.bias.detach().cpu().double().numpy().copy())
                    for lin in mlp.layers]

        l1, l2 = layers(controller.w1), layers(controller.w2)
        # first layers stacked (shared input); later layers applied per network
        self.first_w = np.vstack([l1[0][0], l2[0][0]])
        self.first_b = np.concatenate([l1[0][1], l2[0][1]])
        self.h1 = l1[0][0].shape[0]
        self.rest1, self.rest2 = l1[1:], l2[1:]
        self.lo = controller.input_min.detach().cpu().double().numpy().copy()
        self.hi = controller.input_max.detach().cpu().double().numpy().copy()
        sat = controller.saturation
        self.sat = sat
        if sat is not None:
            self.k_lo, self.k_hi = np.asarray(sat.input_min, float), np.asarray(sat.input_max, float)
            self.c_lo, self.c_hi = np.asarray(sat.actuator_min, float), np.asarray(sat.actuator_max, float)

    def _features(self, theta: float, v: float) -> list[float]:
        vn = (v - self.v0) / self.vs
        out = [math.cos(theta), math.sin(theta), vn] if self.sincos else [(theta - self.t0) / self.ts, vn]
        if self.vf > 0:
            out.append(math.tanh(v / self.vf))
        return out

    def raw(self, x_hat: np.ndarray, x_ref: np.ndarray, u_ref: np.ndarray) -> np.ndarray:
        z = np.array(self._features(x_hat[2], x_hat[3]) + self._features(x_ref[2], x_ref[3]))
        h = np.tanh(self.first_w @ z + self.first_b)
        a, b = h[: self.h1], h[self.h1 :]
        for i, (w, c) in enumerate(self.rest1):
            a = w @ a + c
            if i < len(self.rest1) - 1:
                a = np.tanh(a)
        for i, (w, c) in enumerate(self.rest2):
            b = w @ b + c
            if i < len(self.rest2) - 1:
                b = np.tanh(b)
        e = np.asarray(x_hat[:N_ERR], float) - np.asarray(x_ref[:N_ERR], float)
        hidden = np.tanh(a.reshape(self.rank, N_ERR) @ e)
        return np.asarray(u_ref, float) + b.reshape(-1, self.rank) @ hidden

    @staticmethod
    def supports(system) -> bool:
        """Whether :meth:`track` can drive ``system`` (the kinematic car C3M controllers are trained for)."""
        from ..systems.car import KinematicCar

        return isinstance(system, KinematicCar)

    def track(self, x: np.ndarray, x_refs: np.ndarray, u_refs: np.ndarray, dt: float,
              times: list[float] | None = None, standstill: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Explicit-Euler closed loop of the car (state ``p_x, p_y, theta, v, theta_bias``, heading-biased
        measurement) over the references ``x_refs (K, 5)``, ``u_refs (K, 2)`` from ``x (5,)``: returns the final
        state and the first applied input; appends each controller evaluation's wall time to ``times``.
        ``standstill``: hold the speed at 0 after every step (the plant of ``System.standstill``)."""
        import time

        xn = np.array(x, dtype=np.float64)
        u_first = None
        for j in range(x_refs.shape[0]):
            xh = np.array([xn[0], xn[1], xn[2] + xn[4], xn[3], 0.0])  # KinematicCar.measure
            tc = time.perf_counter()
            u = self(xh, x_refs[j], u_refs[j])
            if times is not None:
                times.append(time.perf_counter() - tc)
            if u_first is None:
                u_first = u
            xn = xn + dt * np.array([xn[3] * math.cos(xn[2]), xn[3] * math.sin(xn[2]), u[0], u[1], 0.0])
            if standstill and xn[3] < 0:
                xn[3] = 0.0
        if u_first is None:
            raise ValueError("x_refs must hold at least one step")
        return xn, u_first

    def __call__(self, x_hat: np.ndarray, x_ref: np.ndarray, u_ref: np.ndarray) -> np.ndarray:
        u = self.raw(x_hat, x_ref, u_ref)
        sat = self.sat
        if sat is None:
            return np.minimum(np.maximum(u, self.lo), self.hi)
        k_lo, k_hi, c_lo, c_hi = self.k_lo.copy(), self.k_hi.copy(), self.c_lo.copy(), self.c_hi.copy()
        if sat.speed_dependent:
            i, v = sat.turn_index, float(x_hat[sat.speed_index])
            k = (sat.input_max[i] ** -4 + (v / sat.lateral_accel_max) ** 4) ** -0.25
            c = (sat.actuator_max[i] ** -4 + (v / sat.actuator_lateral_accel_max) ** 4) ** -0.25
            k_hi[i], c_hi[i], k_lo[i], c_lo[i] = k, c, -k, -c
        out = u.copy()
        above, below = u > k_hi, u < k_lo
        d_hi, d_lo = c_hi - k_hi, k_lo - c_lo
        out[above] = k_hi[above] + d_hi[above] * np.tanh((u[above] - k_hi[above]) / d_hi[above])
        out[below] = k_lo[below] - d_lo[below] * np.tanh((k_lo[below] - u[below]) / d_lo[below])
        return out
