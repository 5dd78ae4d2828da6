"""Adam over a batch of independent candidates, with per-candidate state resets, update clipping, projection and
backtracking.

Used by the gradient planners: every candidate parameter set ``params[m]`` is optimised independently (its own
step counter and moments), the *update* (not the gradient) is clipped to ``+-update_clip`` per entry (the paper's
"gradient clipping", ``docs/spec.md`` §10), and the parameters are projected onto ``[low, high]`` after every
step (the original intended this but never applied it).

Backtracking (:meth:`BatchedAdam.backtrack`): Adam moves every coordinate by about ``lr`` per step whatever the
size of its gradient, so a tiny, consistent gradient (a collision term switched on at a probability of 1e-3, the
first steps after a moment reset) carries a plan's turn rates far off in a few steps: on the CommonRoad suite plans
at the goal left it by 10 m and spent half their iterations there. A candidate whose cost exceeds its best by more
than a factor goes back to its best parameters with fresh moments and half the step size (a trust region on the
step, decided by the cost, which is deterministic given the planner's fixed samples).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["BatchedAdam"]


class BatchedAdam:
    """Adam on ``params (M, ...)`` updated in place; ``step(grad)`` and ``reset(mask)``."""

    def __init__(
        self,
        params: Tensor,
        *,
        lr: float = 1e-2,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        update_clip: float | None = 0.02,
        low: float | Tensor | None = None,
        high: float | Tensor | None = None,
        scale: Tensor | None = None,
    ):
        if lr <= 0:
            raise ValueError(f"lr must be > 0, got {lr}")
        if not (0 <= betas[0] < 1 and 0 <= betas[1] < 1):
            raise ValueError(f"betas must lie in [0, 1), got {betas}")
        if update_clip is not None and update_clip <= 0:
            raise ValueError(f"update_clip must be > 0 or None, got {update_clip}")
        self.params = params
        self.lr, self.betas, self.eps, self.update_clip = lr, betas, eps, update_clip
        # bounds broadcastable to params, e.g. (nu, 1) for per-channel input bounds
        self.low = None if low is None else torch.as_tensor(low).to(params)
        self.high = None if high is None else torch.as_tensor(high).to(params)
        #: per-coordinate step scale broadcastable to params (e.g. ``(nu, 1)``): the step is Adam's on
        #: ``params / scale`` (lr and update_clip then act in those units); ``None``: 1
        self.scale = None if scale is None else torch.as_tensor(scale).to(params)
        self.m = torch.zeros_like(params)
        self.v = torch.zeros_like(params)
        self.t = torch.zeros(params.shape[0], dtype=params.dtype, device=params.device)
        #: per-candidate factor on the step (lr and update_clip), halved by every :meth:`backtrack`
        self.rate = torch.ones(params.shape[0], dtype=params.dtype, device=params.device)

    def _bcast(self, x: Tensor) -> Tensor:
        return x.reshape(-1, *([1] * (self.params.ndim - 1)))

    def reset(self, mask: Tensor) -> None:
        """Forget the moments and step count of the candidates where ``mask (M,)`` is True."""
        keep = self._bcast(~mask).to(self.params.dtype)
        self.m.mul_(keep)
        self.v.mul_(keep)
        self.t.mul_((~mask).to(self.t.dtype))

    @torch.no_grad()
    def backtrack(self, mask: Tensor, to: Tensor, factor: float = 0.5) -> None:
        """Candidates where ``mask (M,)`` is True return to ``to`` (same shape as params), forget their moments and
        scale their step by ``factor``."""
        m = self._bcast(mask)
        self.params.copy_(torch.where(m, to, self.params))
        self.reset(mask)
        self.rate.mul_(torch.where(mask, torch.full_like(self.rate, factor), torch.ones_like(self.rate)))

    @torch.no_grad()
    def step(self, grad: Tensor, mask: Tensor | None = None) -> None:
        """One Adam step with gradient ``grad`` (same shape as params); ``mask (M,)`` limits it to some candidates."""
        b1, b2 = self.betas
        grad = torch.nan_to_num(grad, nan=0.0, posinf=1e15, neginf=-1e15).clamp(-1e15, 1e15)
        active = torch.ones_like(self.t, dtype=torch.bool) if mask is None else mask
        a = self._bcast(active).to(self.params.dtype)
        self.t.add_(active.to(self.t.dtype))
        self.m.copy_(a * (b1 * self.m + (1 - b1) * grad) + (1 - a) * self.m)
        self.v.copy_(a * (b2 * self.v + (1 - b2) * grad * grad) + (1 - a) * self.v)
        t = self._bcast(self.t.clamp_min(1))
        m_hat = self.m / (1 - b1**t)
        v_hat = self.v / (1 - b2**t)
        rate = self._bcast(self.rate)
        update = self.lr * m_hat / (v_hat.sqrt() + self.eps)
        if self.update_clip is not None:
            update = update.clamp(-self.update_clip, self.update_clip)
        update = update * rate  # lr and update_clip both scaled by the candidate's rate
        if self.scale is not None:
            update = update * self.scale
        self.params.sub_(a * update)
        if self.low is not None:
            torch.maximum(self.params, self.low, out=self.params)
        if self.high is not None:
            torch.minimum(self.params, self.high, out=self.params)
