"""A torch-free evaluation of the C3M controller for one state at a time (the online loop on the car).

:class:`NumpyC3M` copies the weights of a :class:`~density_planner.control.c3m.C3MController` into float64 numpy
arrays and evaluates the same law, ``u = clip(u_ref + W2(z) tanh(W1(z) e))`` with the controller's hard clip or
smooth saturation (:class:`~density_planner.control.base.SmoothSaturation`, including the speed-dependent
turn-rate box), on 1-D arrays: no autograd, no tensor dispatch. The two MLPs share their input, so their first
layers are stacked into one matrix. Its outputs equal the torch controller's to float32 round-off
(``tests/control/test_fast_controller.py``: 1e-6 against the controller evaluated in float64).

Where numba is installed (the ``fast`` extra, part of ``make install``), the same law runs compiled
(:mod:`density_planner.control._jit`): one call per evaluation, or per stretch of closed loop in :meth:`track`
(this project's 2-core machine: a 0.1-s step of the online loop, 10 evaluations in one :meth:`track` call,
0.06-0.09 ms instead of 0.2-0.4 ms; one evaluation per call 7.5-11.5 us instead of 19-36 us). ``compiled=False``
keeps the numpy path; :attr:`NumpyC3M.compiled` says which one runs. ``benchmarks/bench_controller_step.py``
times all three (torch, numpy, compiled).
"""

from __future__ import annotations

import math

import numpy as np

from .c3m import N_ERR, C3MController

__all__ = ["NumpyC3M", "warm_up"]


class NumpyC3M:
    """``controller(x_hat (nx,), x_ref (nx,), u_ref (2,)) -> u (2,)`` in plain numpy (module docstring)."""

    def __init__(self, controller: C3MController, *, compiled: bool | None = None):
        """``compiled``: ``None`` uses the numba kernels where numba is installed, ``True`` requires them,
        ``False`` uses numpy."""
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
        # where both networks have the same layer shapes (the last layer's rows zero-padded to the larger one), each
        # layer of the two is one batched product into a preallocated buffer: half the numpy calls
        self._stacked: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        shapes_match = len(l1) == len(l2) and all(a[0].shape == b[0].shape for a, b in zip(l1[:-1], l2[:-1])) and (
            l1[-1][0].shape[1] == l2[-1][0].shape[1])
        if shapes_match and self.h1 == l2[0][0].shape[0]:
            self._stacked = []
            for (w_a, b_a), (w_b, b_b) in zip(self.rest1, self.rest2):
                rows = max(w_a.shape[0], w_b.shape[0])
                w = np.zeros((2, rows, w_a.shape[1]))
                b = np.zeros((2, rows, 1))
                w[0, : w_a.shape[0]], w[1, : w_b.shape[0]] = w_a, w_b
                b[0, : w_a.shape[0], 0], b[1, : w_b.shape[0], 0] = b_a, b_b
                self._stacked.append((w, b, np.empty((2, rows, 1))))
            self._n_out = (self.rest1[-1][0].shape[0], self.rest2[-1][0].shape[0])
        self._z = np.empty(self.first_w.shape[1])
        self._h = np.empty(self.first_w.shape[0])
        self.lo = controller.input_min.detach().cpu().double().numpy().copy()
        self.hi = controller.input_max.detach().cpu().double().numpy().copy()
        sat = controller.saturation
        self.sat = sat
        if sat is not None:
            self.k_lo, self.k_hi = np.asarray(sat.input_min, float), np.asarray(sat.input_max, float)
            self.c_lo, self.c_hi = np.asarray(sat.actuator_min, float), np.asarray(sat.actuator_max, float)
            # the same bounds as Python floats: two channels are saturated faster one by one than as arrays
            self._bounds = [tuple(float(v) for v in vals) for vals in zip(self.k_lo, self.k_hi, self.c_lo,
                                                                            self.c_hi)]
        self._kernel = None  # (module, packed arguments) of the compiled path
        if compiled is not False:
            self._kernel = self._pack(l1, l2, compiled is True)

    @property
    def compiled(self) -> bool:
        """Whether the numba kernels evaluate the law (module docstring)."""
        return self._kernel is not None

    def _pack(self, l1, l2, required: bool):
        """The compiled path's arguments (weights as float64 arrays, features, saturation, work buffers), or
        ``None`` (numba missing, or layer shapes the kernel does not handle: both networks must have the same
        hidden widths)."""
        try:
            from . import _jit
        except ImportError as exc:
            if required:
                raise ValueError("NumpyC3M(compiled=True) needs numba: pip install 'density-planner[fast]'") from exc
            return None
        h = self.h1
        # the numpy path's stacking already needs both networks' layers to have the same shapes; the kernel also
        # needs the hidden layers square
        same_widths = self._stacked is not None and all(w.shape == (h, h) for w, _ in l1[1:-1])
        if not same_widths:
            if required:
                raise ValueError("NumpyC3M(compiled=True): the two networks need the same hidden widths")
            return None

        feat = np.array([1.0 if self.sincos else 0.0, self.t0, self.ts, self.v0, self.vs, self.vf, self.rank])
        if self.sat is None:
            sat = np.concatenate([[0.0, 0, 0, 1, 1], self.lo, self.hi, self.lo, self.hi])
        else:
            mode = 2.0 if self.sat.speed_dependent else 1.0
            sat = np.concatenate([[mode, self.sat.turn_index, self.sat.speed_index,
                                   self.sat.lateral_accel_max if self.sat.speed_dependent else 1.0,
                                   self.sat.actuator_lateral_accel_max if self.sat.speed_dependent else 1.0],
                                  self.k_lo, self.k_hi, self.c_lo, self.c_hi])
        width = max(h, l1[-1][0].shape[0], l2[-1][0].shape[0], self.first_w.shape[1], self.rank)
        flat, layout = _jit.pack(self.first_w, self.first_b, l1[1:-1], l2[1:-1], l1[-1], l2[-1], feat, sat)
        args = (flat, layout, np.zeros((8, width)))
        return _jit, args

    def _features(self, theta: float, v: float) -> list[float]:
        vn = (v - self.v0) / self.vs
        out = [math.cos(theta), math.sin(theta), vn] if self.sincos else [(theta - self.t0) / self.ts, vn]
        if self.vf > 0:
            out.append(math.tanh(v / self.vf))
        return out

    def raw(self, x_hat: np.ndarray, x_ref: np.ndarray, u_ref: np.ndarray) -> np.ndarray:
        z, h = self._z, self._h
        z[:] = self._features(x_hat[2], x_hat[3]) + self._features(x_ref[2], x_ref[3])
        np.matmul(self.first_w, z, out=h)
        np.add(h, self.first_b, out=h)
        np.tanh(h, out=h)
        if self._stacked is not None:
            x = h.reshape(2, self.h1, 1)
            last = len(self._stacked) - 1
            for i, (w, c, buf) in enumerate(self._stacked):
                np.matmul(w, x, out=buf)
                np.add(buf, c, out=buf)
                if i < last:
                    np.tanh(buf, out=buf)
                x = buf
            a, b = x[0, : self._n_out[0], 0], x[1, : self._n_out[1], 0]
        else:
            a, b = h[: self.h1], h[self.h1 :]
            for i, (w, c) in enumerate(self.rest1):
                a = w @ a + c
                if i < len(self.rest1) - 1:
                    a = np.tanh(a)
            for i, (w, c) in enumerate(self.rest2):
                b = w @ b + c
                if i < len(self.rest2) - 1:
                    b = np.tanh(b)
        e = np.array([x_hat[n] - x_ref[n] for n in range(N_ERR)], dtype=float)
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

        if self._kernel is not None:
            jit, args = self._kernel
            if x_refs.shape[0] < 1:
                raise ValueError("x_refs must hold at least one step")
            x_out, u0 = np.empty(5), np.empty(self.lo.shape[0])
            tc = time.perf_counter()
            jit.track(np.asarray(x, dtype=np.float64), np.ascontiguousarray(x_refs, dtype=np.float64),
                      np.ascontiguousarray(u_refs, dtype=np.float64), float(dt), bool(standstill), *args, x_out, u0)
            if times is not None:  # one call for the whole stretch: its mean per evaluation
                times.extend([(time.perf_counter() - tc) / x_refs.shape[0]] * x_refs.shape[0])
            return x_out, u0
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

    def evaluate_each(self, x_hats: np.ndarray, x_refs: np.ndarray, u_refs: np.ndarray) -> np.ndarray:
        """``(K, nu)`` inputs for the rows of ``x_hats (K, nx)``, ``x_refs (K, nx)``, ``u_refs (K, nu)``, each
        evaluated as one state (a stretch of measurements: compiled, one call; numpy, one call per row)."""
        if x_hats.shape[0] != x_refs.shape[0] or x_hats.shape[0] != u_refs.shape[0]:
            raise ValueError(f"x_hats, x_refs and u_refs need the same number of rows, got {x_hats.shape[0]}, "
                             f"{x_refs.shape[0]} and {u_refs.shape[0]}")
        if self._kernel is None:
            return np.stack([self(a, b, c) for a, b, c in zip(x_hats, x_refs, u_refs)]) if x_hats.shape[0] else \
                np.empty((0, self.lo.shape[0]))
        jit, args = self._kernel
        out = np.empty((x_hats.shape[0], self.lo.shape[0]))
        jit.control_many(np.ascontiguousarray(x_hats, dtype=np.float64), np.ascontiguousarray(x_refs, dtype=np.float64),
                         np.ascontiguousarray(u_refs, dtype=np.float64), *args, out)
        return out

    def __call__(self, x_hat: np.ndarray, x_ref: np.ndarray, u_ref: np.ndarray) -> np.ndarray:
        if self._kernel is not None:
            jit, args = self._kernel
            out = np.empty(self.lo.shape[0])
            jit.control(np.asarray(x_hat, dtype=np.float64), np.asarray(x_ref, dtype=np.float64),
                        np.asarray(u_ref, dtype=np.float64), *args, out)
            return out
        u = self.raw(x_hat, x_ref, u_ref)
        sat = self.sat
        if sat is None:
            return np.minimum(np.maximum(u, self.lo), self.hi)
        bounds = list(self._bounds)  # per channel (k_lo, k_hi, c_lo, c_hi)
        if sat.speed_dependent:
            i, v = sat.turn_index, float(x_hat[sat.speed_index])
            k = (sat.input_max[i] ** -4 + (v / sat.lateral_accel_max) ** 4) ** -0.25
            c = (sat.actuator_max[i] ** -4 + (v / sat.actuator_lateral_accel_max) ** 4) ** -0.25
            bounds[i] = (-k, k, -c, c)
        out = u.tolist()
        for j, (k_lo, k_hi, c_lo, c_hi) in enumerate(bounds):
            uj = out[j]
            if uj > k_hi:
                out[j] = k_hi + (c_hi - k_hi) * math.tanh((uj - k_hi) / (c_hi - k_hi))
            elif uj < k_lo:
                out[j] = k_lo - (k_lo - c_lo) * math.tanh((k_lo - uj) / (k_lo - c_lo))
        return np.array(out)


def warm_up() -> bool:
    """Compile the numba kernels of the compiled path now (or load them from their cache); ``False`` without numba.
    ``make install`` runs it (``python -m density_planner.control.fast``), so that the first ``drive`` does not
    pause ~6-10 s to compile."""
    try:
        from . import _jit
    except ImportError:
        return False
    _jit.warm_up()
    return True


if __name__ == "__main__":
    warm_up()
