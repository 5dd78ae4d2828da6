"""Numba kernels of :class:`~density_planner.control.fast.NumpyC3M` (optional: the ``fast`` extra installs numba).

The same law as the numpy path of ``NumpyC3M`` (``u = sat(u_ref + W2(z) tanh(W1(z) e))``, both MLPs evaluated
layer by layer in float64 from the float32 weights, exact), compiled: one call evaluates the controller
(:func:`control`) or drives the car's explicit-Euler closed loop over a stretch of reference
(:func:`track`), so the Python and numpy per-call overheads that bound the numpy path (~18 us per evaluation)
are paid once per call. ``tanh`` is a polynomial form (:func:`_tanh_inplace`, within 1e-14 of libm's) so that
its loops vectorise, and the dot products may be reassociated (``fastmath``): the outputs equal the numpy path's to
~1e-12 (``tests/control/test_fast_controller.py``; 1e-6 against torch in float64).

Importing this module imports numba (~0.3 s) and compiles nothing; the first call in a fresh environment compiles
the kernels (~6 s on this project's machine) and caches the machine code beside this file (``cache=True``), so
later processes load it (~0.5 s on their first call). ``make install`` compiles them once
(``python -m density_planner.control.fast``, :func:`warm_up`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["control", "control_many", "pack", "track", "warm_up"]

# error_model="numpy": a division does not check for zero (Python's ZeroDivisionError would keep the loops scalar)
# (forcing the helpers inline compiles 3x longer, ~16 s, for the same speed)
_kernel = numba.njit(cache=True, fastmath=True, nogil=True, error_model="numpy")


@_kernel
def _tanh_inplace(x, n):
    """``x[:n] = tanh(x[:n])`` without a libm call, so that the loop vectorises: ``1 - 2 / (e^(2|s|) + 1)`` with
    the sign of ``s``, ``e^(2|s|) = (e^(2|s| / 64))^64`` and ``e^u`` on ``u`` in [0, 0.625] by its Taylor polynomial
    of degree 12 (|s| clamped at 20, where tanh is 1 to 1e-17): within 1e-14 of libm's tanh."""
    for i in range(n):
        s = x[i]
        a = abs(s)
        u = (a if a < 20.0 else 20.0) * (2.0 / 64.0)
        p = 1.0 / 479001600.0
        p = p * u + 1.0 / 39916800.0
        p = p * u + 1.0 / 3628800.0
        p = p * u + 1.0 / 362880.0
        p = p * u + 1.0 / 40320.0
        p = p * u + 1.0 / 5040.0
        p = p * u + 1.0 / 720.0
        p = p * u + 1.0 / 120.0
        p = p * u + 1.0 / 24.0
        p = p * u + 1.0 / 6.0
        p = p * u + 0.5
        p = p * u + 1.0
        p = p * u + 1.0
        p = p * p
        p = p * p
        p = p * p
        p = p * p
        p = p * p
        p = p * p
        t = 1.0 - 2.0 / (p + 1.0)
        x[i] = t if s >= 0.0 else -t


@_kernel
def _dense(w, b, x, out, act):
    """``out[:n] = w x + b`` for ``w (n, m)`` (``tanh`` of it with ``act``)."""
    n, m = w.shape
    for i in range(n):
        s = 0.0
        for j in range(m):
            s += w[i, j] * x[j]
        out[i] = s + b[i]
    if act:
        _tanh_inplace(out, n)


@_kernel
def _features(theta, v, flat, f, z, at):
    """Write the features of one ``(theta, v)`` into ``z[at:]``; returns the next free index. ``flat[f:]``:
    ``(sincos, t0, ts, v0, vs, vf, rank)``."""
    vn = (v - flat[f + 3]) / flat[f + 4]
    if flat[f] > 0.5:
        z[at] = math.cos(theta)
        z[at + 1] = math.sin(theta)
        z[at + 2] = vn
        at += 3
    else:
        z[at] = (theta - flat[f + 1]) / flat[f + 2]
        z[at + 1] = vn
        at += 2
    if flat[f + 5] > 0.0:
        z[at] = math.tanh(v / flat[f + 5])
        at += 1
    return at


def pack(first_w, first_b, mids1, mids2, last1, last2, feat, sat):
    """The flat parameter vector and its layout ``(h, nz, n_mid, n1, n2)`` of :func:`control` (one array
    argument instead of thirteen: numba unboxes every array argument of every call). ``mids*``: lists of ``(w (h, h),
    b (h,))``; ``last*``: ``(w (n, h), b (n,))``; ``feat``: ``(sincos, t0, ts, v0, vs, vf, rank)``; ``sat``:
    ``(mode, turn_index, speed_index, a_lat, a_lat_act, k_lo..., k_hi..., c_lo..., c_hi...)``, mode 0 the hard clip
    to ``[k_lo, k_hi]``, 1 the smooth saturation, 2 with the speed-dependent turn channel."""
    h, nz = first_w.shape[0] // 2, first_w.shape[1]
    parts = [first_w, first_b] + [a for w, b in mids1 for a in (w, b)] + [a for w, b in mids2 for a in (w, b)]
    parts += [last1[0], last1[1], last2[0], last2[1], feat, sat]
    flat = np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in parts])
    layout = np.array([h, nz, len(mids1), last1[0].shape[0], last2[0].shape[0]], dtype=np.int64)
    return flat, layout


@_kernel
def _views(flat, layout):
    """The blocks of :func:`pack`'s vector as views: first layer ``(2h, nz)``, its bias, the hidden layers of the
    two networks ``(n_mid h, h)`` and biases ``(n_mid, h)``, the last layers and biases, and the offset of the
    feature / saturation block."""
    h, nz, n_mid, n1, n2 = layout[0], layout[1], layout[2], layout[3], layout[4]
    at = 2 * h * nz
    first_w = flat[:at].reshape((2 * h, nz))
    first_b = flat[at : at + 2 * h]
    at += 2 * h
    mid1_w = flat[at : at + n_mid * h * h].reshape((n_mid * h, h))
    at += n_mid * h * h
    mid1_b = flat[at : at + n_mid * h].reshape((n_mid, h))
    at += n_mid * h
    mid2_w = flat[at : at + n_mid * h * h].reshape((n_mid * h, h))
    at += n_mid * h * h
    mid2_b = flat[at : at + n_mid * h].reshape((n_mid, h))
    at += n_mid * h
    last1_w = flat[at : at + n1 * h].reshape((n1, h))
    at += n1 * h
    last1_b = flat[at : at + n1]
    at += n1
    last2_w = flat[at : at + n2 * h].reshape((n2, h))
    at += n2 * h
    last2_b = flat[at : at + n2]
    at += n2
    return first_w, first_b, mid1_w, mid1_b, mid2_w, mid2_b, last1_w, last1_b, last2_w, last2_b, at


@_kernel
def _control(x_hat, x_ref, u_ref, first_w, first_b, mid1_w, mid1_b, mid2_w, mid2_b, last1_w, last1_b, last2_w,
             last2_b, flat, f, buf, out):
    """The law on the views of :func:`_views` (``flat[f:]``: features, then saturation)."""
    z = buf[0]
    at = _features(x_hat[2], x_hat[3], flat, f, z, 0)
    _features(x_ref[2], x_ref[3], flat, f, z, at)
    h = mid1_w.shape[1]
    a, b, ta, tb = buf[1], buf[2], buf[3], buf[4]
    _dense(first_w[:h], first_b[:h], z, a, True)
    _dense(first_w[h:], first_b[h:], z, b, True)
    for layer in range(mid1_b.shape[0]):
        _dense(mid1_w[layer * h : (layer + 1) * h], mid1_b[layer], a, ta, True)
        _dense(mid2_w[layer * h : (layer + 1) * h], mid2_b[layer], b, tb, True)
        a, ta = ta, a
        b, tb = tb, b
    oa, ob = buf[5], buf[6]
    _dense(last1_w, last1_b, a, oa, False)
    _dense(last2_w, last2_b, b, ob, False)
    rank = int(flat[f + 6])
    n_err = last1_w.shape[0] // rank
    hid = buf[7]
    for r in range(rank):
        s = 0.0
        for n in range(n_err):
            s += oa[r * n_err + n] * (x_hat[n] - x_ref[n])
        hid[r] = s
    _tanh_inplace(hid, rank)
    nu = out.shape[0]
    for c in range(nu):
        s = u_ref[c]
        for r in range(rank):
            s += ob[c * rank + r] * hid[r]
        out[c] = s
    _saturate(out, x_hat, flat, f + 7)


@_kernel
def control(x_hat, x_ref, u_ref, flat, layout, buf, out):
    """``out (nu,) = controller(x_hat, x_ref, u_ref)`` with the parameters of :func:`pack`; ``buf (8, >= max
    width)`` is scratch space."""
    fw, fb, m1w, m1b, m2w, m2b, l1w, l1b, l2w, l2b, f = _views(flat, layout)
    _control(x_hat, x_ref, u_ref, fw, fb, m1w, m1b, m2w, m2b, l1w, l1b, l2w, l2b, flat, f, buf, out)


@_kernel
def _saturate(u, x_hat, flat, f):
    """Bound ``u`` in place with the saturation block of :func:`pack` at ``flat[f:]``."""
    nu = u.shape[0]
    mode = flat[f]
    for j in range(nu):
        k_lo, k_hi = flat[f + 5 + j], flat[f + 5 + nu + j]
        c_lo, c_hi = flat[f + 5 + 2 * nu + j], flat[f + 5 + 3 * nu + j]
        if mode > 1.5 and j == int(flat[f + 1]):
            v = x_hat[int(flat[f + 2])]
            k_hi = (k_hi ** -4 + (v / flat[f + 3]) ** 4) ** -0.25
            c_hi = (c_hi ** -4 + (v / flat[f + 4]) ** 4) ** -0.25
            k_lo, c_lo = -k_hi, -c_hi
        if mode < 0.5:
            if u[j] > k_hi:
                u[j] = k_hi
            elif u[j] < k_lo:
                u[j] = k_lo
        elif u[j] > k_hi:
            u[j] = k_hi + (c_hi - k_hi) * math.tanh((u[j] - k_hi) / (c_hi - k_hi))
        elif u[j] < k_lo:
            u[j] = k_lo - (k_lo - c_lo) * math.tanh((k_lo - u[j]) / (k_lo - c_lo))


@_kernel
def control_many(x_hats, x_refs, u_refs, flat, layout, buf, out):
    """``out[k] = controller(x_hats[k], x_refs[k], u_refs[k])`` for every row, one state at a time (the
    evaluations of a stretch of measurements in one call)."""
    fw, fb, m1w, m1b, m2w, m2b, l1w, l1b, l2w, l2b, f = _views(flat, layout)
    for k in range(x_hats.shape[0]):
        _control(x_hats[k], x_refs[k], u_refs[k], fw, fb, m1w, m1b, m2w, m2b, l1w, l1b, l2w, l2b, flat, f, buf,
                 out[k])


@_kernel
def track(x, x_refs, u_refs, dt, standstill, flat, layout, buf, x_out, u_first):
    """The car's explicit-Euler closed loop (state ``p_x, p_y, theta, v, theta_bias``; the controller sees the
    heading plus its bias) over ``x_refs (K, 5)``, ``u_refs (K, 2)`` from ``x``: the final state into ``x_out``,
    the first applied input into ``u_first``. ``standstill``: the speed is held at 0 after every step."""
    fw, fb, m1w, m1b, m2w, m2b, l1w, l1b, l2w, l2b, f = _views(flat, layout)
    xh = np.empty(5)
    u = np.empty(u_refs.shape[1])
    for n in range(5):
        x_out[n] = x[n]
    for k in range(x_refs.shape[0]):
        xh[0] = x_out[0]
        xh[1] = x_out[1]
        xh[2] = x_out[2] + x_out[4]
        xh[3] = x_out[3]
        xh[4] = 0.0
        _control(xh, x_refs[k], u_refs[k], fw, fb, m1w, m1b, m2w, m2b, l1w, l1b, l2w, l2b, flat, f, buf, u)
        if k == 0:
            for c in range(u.shape[0]):
                u_first[c] = u[c]
        th, v = x_out[2], x_out[3]
        x_out[0] += dt * v * math.cos(th)
        x_out[1] += dt * v * math.sin(th)
        x_out[2] += dt * u[0]
        x_out[3] += dt * u[1]
        if standstill and x_out[3] < 0.0:
            x_out[3] = 0.0


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the argument types :class:`NumpyC3M` passes, on a tiny
    network: ``make install`` runs it so that the first ``drive`` does not pause ~6 s to compile."""
    h, nz, n1, n2, nu = 2, 6, 4, 2, 2
    feat = np.array([1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0])
    sat = np.concatenate([[2.0, 0.0, 3.0, 4.0, 8.0], -np.ones(nu), np.ones(nu), -2 * np.ones(nu), 2 * np.ones(nu)])
    mid = [(np.eye(h), np.zeros(h))]
    flat, layout = pack(np.zeros((2 * h, nz)), np.zeros(2 * h), mid, mid, (np.zeros((n1, h)), np.zeros(n1)),
                        (np.zeros((n2, h)), np.zeros(n2)), feat, sat)
    buf = np.zeros((8, nz))
    x, refs, inputs = np.zeros(5), np.zeros((3, 5)), np.zeros((3, nu))
    control(x, refs[0], inputs[0], flat, layout, buf, np.empty(nu))
    control_many(refs, refs, inputs, flat, layout, buf, np.empty((3, nu)))
    track(x, refs, inputs, 0.01, False, flat, layout, buf, np.empty(5), np.empty(nu))
