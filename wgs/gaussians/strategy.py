"""Densification as a dataclass of thresholds plus an explicit state dict (gsplat's DefaultStrategy
shape): clone small / split large Gaussians with a high accumulated 2D gradient, prune transparent
or oversized ones, reset opacities periodically, never exceed `max_gaussians`.

Parameters live in a dict of leaf tensors with one Adam optimizer per key; every structural change
goes through `_edit`, which rewrites the tensors and their Adam moments together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from .project import quat_to_rotmat

Params = dict[str, torch.Tensor]
Optimizers = dict[str, torch.optim.Optimizer]


@dataclass
class DensifyParams:
    """Thresholds and schedule of densification: the one place their defaults live (the training
    configs inherit these fields, so a renamed field cannot be missed)."""

    grad_threshold: float = 2e-4  # in NDC units, as 3DGS
    prune_opacity: float = 0.005
    grow_scale3d: float = 0.01  # times the scene extent: smaller are cloned, larger split
    prune_scale3d: float = 0.1
    refine_start: int = 300
    refine_stop: int = 1500
    refine_every: int = 100
    reset_every: int = 3000
    max_gaussians: int = 60000


@dataclass
class DensifyStrategy(DensifyParams):
    scene_extent: float = 1.0

    def initial_state(self) -> dict[str, Any]:
        return {"grad2d": None, "count": None}

    def accumulate(self, state: dict[str, Any], meta: dict[str, Any]) -> None:
        """Add this view's 2D mean gradients (after backward) to the running statistics.

        meta["means2d"]: [N, 2], or gsplat's [1, N, 2] when meta["means2d_batched"]."""
        g = meta["means2d"].grad
        if g is None:
            return
        vis = meta["visible"]
        g = g.detach()[0].clone() if meta.get("means2d_batched") else g.detach().clone()
        g[:, 0] *= meta["width"] / 2.0  # pixel -> NDC gradient scale, as 3DGS
        g[:, 1] *= meta["height"] / 2.0
        n = g.shape[0]
        if state["grad2d"] is None or state["grad2d"].shape[0] != n:
            state["grad2d"] = torch.zeros(n, device=g.device)
            state["count"] = torch.zeros(n, device=g.device)
        state["grad2d"][vis] += g[vis].norm(dim=-1)
        state["count"][vis] += 1

    def step(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], it: int, prev_it: int | None = None
    ) -> dict[str, int]:
        """Refine when the schedule position moved from prev_it (default it - 1) past a multiple of the
        interval (a time budget can advance it by more than one per step); returns what changed."""
        prev = it - 1 if prev_it is None else prev_it

        def crossed(k: int) -> bool:
            return k > 0 and prev // k < it // k

        out = {"cloned": 0, "split": 0, "pruned": 0}
        if self.refine_start <= it < self.refine_stop and crossed(self.refine_every) and state["count"] is not None:
            out.update(self._grow(params, optimizers, state))
            out["pruned"] = self._prune(params, optimizers, it)
            state["grad2d"] = None
            state["count"] = None
        if it > 0 and crossed(self.reset_every) and it < self.refine_stop:
            reset_opacity(params, optimizers, 2 * self.prune_opacity)
        return out

    def _grow(self, params: Params, optimizers: Optimizers, state: dict[str, Any]) -> dict[str, int]:
        avg = state["grad2d"] / state["count"].clamp_min(1)
        high = avg > self.grad_threshold
        big = torch.exp(params["scales"]).max(dim=-1).values > self.grow_scale3d * self.scene_extent
        room = self.max_gaussians - params["means"].shape[0]
        clone_mask = high & ~big
        split_mask = high & big
        # Within the cap, keep the Gaussians with the largest gradients.
        want = int(clone_mask.sum() + split_mask.sum())
        if want > room:
            if room <= 0:
                return {"cloned": 0, "split": 0}
            cand = torch.nonzero(high).squeeze(1)
            chosen = torch.zeros_like(high)
            chosen[cand[torch.topk(avg[cand], room).indices]] = True
            clone_mask &= chosen
            split_mask &= chosen
        n_clone, n_split = int(clone_mask.sum()), int(split_mask.sum())
        if n_clone:
            _edit(
                params,
                optimizers,
                lambda k, p: torch.cat([p, p[clone_mask]]),
                lambda k, s: torch.cat([s, torch.zeros_like(s[clone_mask])]),
            )
            split_mask = torch.cat([split_mask, torch.zeros(n_clone, dtype=torch.bool, device=split_mask.device)])
        if n_split:
            split(params, optimizers, split_mask)
        return {"cloned": n_clone, "split": n_split}

    def _prune(self, params: Params, optimizers: Optimizers, it: int) -> int:
        drop = torch.sigmoid(params["opacities"]) < self.prune_opacity
        if it > self.reset_every:
            drop |= torch.exp(params["scales"]).max(dim=-1).values > self.prune_scale3d * self.scene_extent
        drop |= ~torch.isfinite(params["means"]).all(dim=-1)
        n = int(drop.sum())
        if n:
            remove(params, optimizers, drop)
        return n


def _edit(params: Params, optimizers: Optimizers, fn_param, fn_state) -> None:
    """Replace every parameter tensor and its Adam moments together."""
    for name in list(params):
        old = params[name]
        new = fn_param(name, old.detach()).requires_grad_(True)
        params[name] = new
        opt = optimizers[name]
        for group in opt.param_groups:
            if group["params"][0] is old:
                st = opt.state.pop(old, None)
                group["params"][0] = new
                if st:
                    opt.state[new] = {
                        k: (fn_state(name, v) if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in st.items()
                    }


def remove(params: Params, optimizers: Optimizers, mask: torch.Tensor) -> None:
    keep = ~mask
    _edit(params, optimizers, lambda k, p: p[keep], lambda k, s: s[keep])


def split(params: Params, optimizers: Optimizers, mask: torch.Tensor, n: int = 2) -> None:
    """Replace each masked Gaussian by n samples from it, scales divided by 1.6 (3DGS)."""
    sel = torch.nonzero(mask).squeeze(1)
    scales = torch.exp(params["scales"][sel])
    R = quat_to_rotmat(params["quats"][sel])
    samples = (R @ (torch.randn(n, len(sel), 3, device=scales.device) * scales)[..., None])[..., 0]
    rest = ~mask

    def fn_param(name: str, p: torch.Tensor) -> torch.Tensor:
        if name == "means":
            new = (p[sel][None] + samples).reshape(-1, 3)
        elif name == "scales":
            new = torch.log(scales / 1.6).repeat(n, 1)
        else:
            new = p[sel].repeat(n, *[1] * (p.dim() - 1))
        return torch.cat([p[rest], new])

    _edit(
        params,
        optimizers,
        fn_param,
        lambda k, s: torch.cat([s[rest], torch.zeros((n * len(sel), *s.shape[1:]), device=s.device)]),
    )


def reset_opacity(params: Params, optimizers: Optimizers, value: float) -> None:
    logit = math.log(value / (1 - value))
    _edit(
        params,
        optimizers,
        lambda k, p: p.clamp_max(logit) if k == "opacities" else p,
        lambda k, s: torch.zeros_like(s) if k == "opacities" else s,
    )
