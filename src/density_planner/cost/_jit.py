"""Numba kernels of the collision cost's fused CPU path (:class:`~density_planner.cost.terms.CollisionCost`;
optional: the ``fast`` extra installs numba).

The paper's collision term ``J_C = sum_{i,k} w_i(t_k) sum_j P_j ||c_ij - c_des,ij||^2`` reads, for every sample,
time and disc of the body, one cell of the desired-position memo; written with tensor operations that is ~20
element-wise passes over ``N x T x m`` values forward and as many backward (on 500 samples x 101 times x 4 discs,
10.6 ms forward and most of the 12 ms backward of a stage-2 iteration). Here one pass finds the memo cells
(:func:`cells`), and after the caller has filled the cells not yet known, a second computes the value *and* its
gradients in closed form (:func:`accumulate`): with ``d = c - c_des``, ``dJ/dc = 2 w P d``, the position's gradient
is the sum over the discs, the heading's ``sum_j s_j (-dJ/dc_x sin(theta) + dJ/dc_y cos(theta))`` (disc ``j`` at
``s_j`` along the heading) and the weight's ``sum_j P_j ||d_j||^2``; the backward pass only scales them.

Compiled on the first call of a fresh environment (a few seconds; ``cache=True`` keeps the machine code beside this
file, ``make install`` compiles it once, :func:`warm_up`). ``make install`` also compiles these functions ahead of
time (:mod:`._aot`), which is what the collision cost loads where it exists; both are compiled without ``fastmath``
so that they return the same bits (tested).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["accumulate", "cells", "warm_up"]

_kernel = numba.njit(cache=True, nogil=True, error_model="numpy")


@_kernel
def _pose(x, b, t, n, pos_i, pos_j, head_i, unit):
    """``(px, py, cos, sin)`` of state ``x[b, t, n]`` in its dtype (``head_i < 0``: ``unit = (1, 0)``)."""
    if head_i >= 0:
        return x[b, t, n, pos_i], x[b, t, n, pos_j], np.cos(x[b, t, n, head_i]), np.sin(x[b, t, n, head_i])
    return x[b, t, n, pos_i], x[b, t, n, pos_j], unit[0], unit[1]


@_kernel
def cells(x, pos_i, pos_j, head_i, offsets, unit, origin, cell_size, nx, ny, slices, bounds, clamp, known, lin):
    """Memo cells of every disc centre of states ``x (B, T, N, nx)`` (time before samples: the memo's slices lie
    far apart in memory, each is read in one go): ``lin (B, T, N, m)`` (int64) = ``(k nx + ix) ny + iy`` of the
    centre's nearest cell (``k = slices[t]``, the memo's own slice; centres moved onto ``bounds`` = (xmin, xmax,
    ymin, ymax) first when ``clamp``). Discs lie at ``offsets`` along the heading ``x[..., head_i]``; ``head_i <
    0``: no heading, ``unit = (1, 0)`` in ``x``'s dtype. Arithmetic in ``x``'s dtype, as the tensor path's (the
    same cells). Returns ``(number of centres in cells not yet known, whether every centre lies in the grid)``
    (``known (L,)``: the memo's mask)."""
    B, T, N = x.shape[0], x.shape[1], x.shape[2]
    m = offsets.shape[0]
    ox, oy = origin[0], origin[1]
    missing = 0
    inside_all = True
    for b in range(B):
        for t in range(T):
            k = slices[t]
            for n in range(N):
                px, py, c, s = _pose(x, b, t, n, pos_i, pos_j, head_i, unit)
                for j in range(m):
                    cx = px + offsets[j] * c
                    cy = py + offsets[j] * s
                    if clamp:
                        cx = min(max(cx, bounds[0]), bounds[1])
                        cy = min(max(cy, bounds[2]), bounds[3])
                    ix = np.rint((cx - ox) / cell_size)
                    iy = np.rint((cy - oy) / cell_size)
                    if not (ix >= 0 and ix < nx and iy >= 0 and iy < ny):
                        inside_all = False
                        ix = min(max(ix, 0), nx - 1)
                        iy = min(max(iy, 0), ny - 1)
                    v = (k * nx + np.int64(ix)) * ny + np.int64(iy)
                    lin[b, t, n, j] = v
                    if not known[v]:
                        missing += 1
    return missing, inside_all


@_kernel
def accumulate(x, w, lin, table, pos_i, pos_j, head_i, offsets, unit, value, grad_x, grad_w):
    """``value (B,)`` (float64) = ``sum_{t,n} w[b, t, n] sum_j P_j ||c_j - c_des,j||^2`` with ``(c_des, P)`` =
    ``table[lin]`` (:func:`cells`, every cell known), for states ``x (B, T, N, nx)`` and weights ``w (B, T, N)``;
    ``grad_x (B, T, N, nx)`` (zeros on entry) its gradient in the position and heading entries of ``x``, ``grad_w
    (B, T, N)`` in ``w``."""
    B, T, N = x.shape[0], x.shape[1], x.shape[2]
    m = offsets.shape[0]
    for b in range(B):
        acc = 0.0
        for t in range(T):
            for n in range(N):
                px, py, c, s = _pose(x, b, t, n, pos_i, pos_j, head_i, unit)
                wt = w[b, t, n]
                e = 0.0
                gx = 0.0
                gy = 0.0
                gh = 0.0
                for j in range(m):
                    v = lin[b, t, n, j]
                    p = table[v, 2]
                    dx = px + offsets[j] * c - table[v, 0]
                    dy = py + offsets[j] * s - table[v, 1]
                    e += p * (dx * dx + dy * dy)
                    gcx = 2.0 * wt * p * dx
                    gcy = 2.0 * wt * p * dy
                    gx += gcx
                    gy += gcy
                    gh += offsets[j] * (gcy * c - gcx * s)
                acc += wt * e
                grad_x[b, t, n, pos_i] = gx
                grad_x[b, t, n, pos_j] = gy
                if head_i >= 0:
                    grad_x[b, t, n, head_i] = gh
                grad_w[b, t, n] = e
        value[b] = acc


def warm_up(dtypes: tuple = (np.float32, np.float64)) -> None:
    """Compile (or load from the cache) both kernels for states of each of ``dtypes`` (numpy dtypes)."""
    for dtype in dtypes:
        x = np.zeros((1, 3, 2, 5), dtype=dtype)
        w = np.ones((1, 3, 2), dtype=dtype)
        off = np.array([-1.0, 1.0], dtype=dtype)
        unit = np.array([1.0, 0.0], dtype=dtype)
        lin = np.zeros((1, 3, 2, 2), dtype=np.int64)
        cells(x, 0, 1, 2, off, unit, np.zeros(2, dtype=dtype), dtype(0.5), 2, 2, np.zeros(3, dtype=np.int64),
              np.array([0.0, 1.0, 0.0, 1.0], dtype=dtype), True, np.ones(4, dtype=np.bool_), lin)
        accumulate(x, w, lin, np.zeros((4, 3), dtype=dtype), 0, 1, 2, off, unit, np.zeros(1), np.zeros_like(x),
                   np.zeros_like(w))


if __name__ == "__main__":
    warm_up()
