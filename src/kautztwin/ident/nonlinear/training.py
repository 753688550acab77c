r"""Gradient training of the nonlinear Kautz models with MLP maps (torch, free-run simulation).

The model's whole simulation is one differentiable torch graph: the input map, the Kautz
filter recursion (:func:`~kautztwin.ident.nonlinear.filters.torch_bank_states`, an FFT
convolution of the exact impulse sequence plus the level's steady state), and the output
map.  The loss is the mean squared *simulation* error on the training samples; poles, the
initial-state level and both maps are learned together (AdamW, weight decay on the map
weights only).  The held-out samples of the same simulation score every iteration for free;
the parameters of the best held-out score are kept (early stopping), and training stops once
that score has not improved for ``patience`` iterations.  The level is kept inside the
input's range and faintly pulled towards its start, as in :mod:`.varpro`.

torch is imported inside :func:`fit_torch`; training runs on ``n_threads`` threads
(one by default: on small problems more threads are slower on a shared machine) and
restores the previous setting afterwards.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .filters import (
    poles_from_raw,
    require_torch,
    torch_bank_matrices,
    torch_bank_states,
    torch_poles_params,
)
from .maps import MLPMap, PolynomialMap, monomial_exponents
from .model import NonlinearKautzModel
from .varpro import LEVEL_PRIOR, level_bounds

__all__ = ["TorchOptions", "TorchResult", "fit_torch"]


@dataclass(frozen=True)
class TorchOptions:
    """Training options of :func:`fit_torch`.

    Parameters
    ----------
    n_hidden : int, default=16
        Hidden units of the output MLP.
    n_input_hidden : int, default=8
        Hidden units of the input MLP.
    n_input_channels : int, default=2
        Extra bank channels the input MLP produces (besides ``u`` itself).
    max_iter : int, default=1500
        Full-batch iterations.
    lr : float, default=0.01
        AdamW learning rate.
    weight_decay : float, default=0.01
        Decoupled weight decay of the map weights.
    patience : int, default=400
        Iterations without a better held-out score before stopping.
    n_threads : int, default=1
        torch threads while training.
    """

    n_hidden: int = 16
    n_input_hidden: int = 8
    n_input_channels: int = 2
    max_iter: int = 1500
    lr: float = 0.01
    weight_decay: float = 0.01
    patience: int = 400
    n_threads: int = 1


@dataclass(frozen=True)
class TorchResult:
    """A trained model with its best held-out and training errors (standardised units)."""

    model: NonlinearKautzModel
    val_mse: float
    train_mse: float
    n_iter: int


class _AdamW:
    """AdamW (decoupled weight decay), the update of ``torch.optim.AdamW`` step for step.

    Written out because constructing a ``torch.optim`` optimizer imports torch's compiler
    stack (seconds), which would dominate the training of these small models.
    """

    def __init__(self, torch: Any, groups: list[tuple[list[Any], float]], lr: float,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.groups = groups
        self.lr, self.betas, self.eps = lr, betas, eps
        self.state = {id(p): (torch.zeros_like(p), torch.zeros_like(p))
                      for params, _ in groups for p in params}
        self.n_step = 0

    def zero_grad(self) -> None:
        for params, _ in self.groups:
            for p in params:
                p.grad = None

    def step(self) -> None:
        self.n_step += 1
        b1, b2 = self.betas
        bias1 = 1 - b1**self.n_step
        bias2_sqrt = math.sqrt(1 - b2**self.n_step)
        step_size = self.lr / bias1
        for params, decay in self.groups:
            for p in params:
                if p.grad is None:
                    continue
                m, v = self.state[id(p)]
                with_grad = p.grad
                p.data.mul_(1 - self.lr * decay)
                m.lerp_(with_grad, 1 - b1)
                v.mul_(b2).addcmul_(with_grad, with_grad, value=1 - b2)
                denom = (v.sqrt() / bias2_sqrt).add_(self.eps)
                p.data.addcdiv_(m, denom, value=-step_size)


def _uniform(torch: Any, gen: Any, shape: tuple[int, ...], fan_in: int) -> Any:
    bound = 1.0 / math.sqrt(fan_in)
    return (torch.rand(shape, generator=gen, dtype=torch.float64) * 2 - 1) * bound


def fit_torch(
    structure: str, kinds: tuple[str, ...], raw0: NDArray, us: NDArray, ys: NDArray,
    train: NDArray, val: NDArray, *, level0: float, stats: tuple[float, ...], dt: float,
    seed: int, options: TorchOptions = TorchOptions(),
) -> TorchResult:
    """Train one model with MLP map(s) by gradient descent through the filter recursion.

    Parameters
    ----------
    structure : {'wiener', 'hammerstein', 'wiener-hammerstein'}
        ``wiener``: bank -> output MLP; ``hammerstein``: input MLP -> bank -> linear output;
        ``wiener-hammerstein``: input MLP -> bank -> output MLP.
    kinds, raw0 : block structure and starting unconstrained pole parameters.
    us, ys : ndarray of shape (n_samples,)
        Standardised input and output.
    train, val : ndarray of bool
        Samples of the loss / of the held-out score (``val`` may be empty).
    level0 : float
        Starting standardised level.
    stats : (u_mean, u_scale, y_mean, y_scale)
    dt : float
    seed : int
        Seeds the weight initialisation.
    options : TorchOptions

    Returns
    -------
    TorchResult
    """
    torch = require_torch()
    prev_threads = torch.get_num_threads()
    torch.set_num_threads(options.n_threads)
    try:
        return _fit(torch, structure, kinds, raw0, us, ys, train, val, level0, stats, dt,
                    seed, options)
    finally:
        torch.set_num_threads(prev_threads)


def _fit(torch: Any, structure: str, kinds: tuple[str, ...], raw0: NDArray, us: NDArray,
         ys: NDArray, train: NDArray, val: NDArray, level0: float, stats: tuple[float, ...],
         dt: float, seed: int, o: TorchOptions) -> TorchResult:
    gen = torch.Generator().manual_seed(int(seed))
    f64 = torch.float64
    u_t = torch.tensor(us, dtype=f64)[:, None]
    y_t = torch.tensor(ys, dtype=f64)
    tr = torch.tensor(train)
    va = torch.tensor(val)
    has_in = structure in ("hammerstein", "wiener-hammerstein")
    mlp_out = structure in ("wiener", "wiener-hammerstein")
    raw = torch.tensor(raw0, dtype=f64, requires_grad=True)
    lvl_lo, lvl_hi = level_bounds(us)
    level0 = float(np.clip(level0, lvl_lo, lvl_hi))
    lvl = torch.tensor([level0], dtype=f64, requires_grad=True)
    maps: dict[str, Any] = {}
    if has_in:
        h, k = o.n_input_hidden, o.n_input_channels
        maps["iW1"] = _uniform(torch, gen, (h, 1), 1) * 2.0
        maps["ib1"] = _uniform(torch, gen, (h,), 1) * 2.0
        maps["iW2"] = _uniform(torch, gen, (k, h), h)
        maps["ib2"] = torch.zeros(k, dtype=f64)

    def channels(x: Any) -> Any:
        if not has_in:
            return x
        g = torch.tanh(x @ maps["iW1"].T + maps["ib1"]) @ maps["iW2"].T + maps["ib2"]
        return torch.cat([x, g], dim=1)

    def states() -> Any:
        A, B = torch_bank_matrices(kinds, torch_poles_params(kinds, raw))
        return torch_bank_states(A, B, channels(u_t), channels(lvl[None, :])[0])

    with torch.no_grad():
        X0 = states()[tr]
        x_mean = X0.mean(dim=0)
        x_scale = torch.where(X0.std(dim=0) > 1e-12, X0.std(dim=0), torch.ones_like(x_mean))
        d = X0.shape[1]
        Z0 = (X0 - x_mean) / x_scale
        if mlp_out:
            maps["oW1"] = _uniform(torch, gen, (o.n_hidden, d), d)
            maps["ob1"] = _uniform(torch, gen, (o.n_hidden,), d)
            maps["oW2"] = _uniform(torch, gen, (1, o.n_hidden), o.n_hidden)
            maps["ob2"] = torch.zeros(1, dtype=f64)
        else:  # a least-squares start of the linear output
            Phi = torch.cat([torch.ones(Z0.shape[0], 1, dtype=f64), Z0], dim=1)
            sol = torch.linalg.lstsq(Phi, y_t[tr][:, None]).solution[:, 0]
            maps["ob2"], maps["oW2"] = sol[:1].clone(), sol[1:][None, :].clone()
    for v in maps.values():
        v.requires_grad_(True)

    def output(X: Any) -> Any:
        Z = (X - x_mean) / x_scale
        if mlp_out:
            Z = torch.tanh(Z @ maps["oW1"].T + maps["ob1"])
        return (Z @ maps["oW2"].T + maps["ob2"])[:, 0]

    weights = [v for k, v in maps.items() if "W" in k]
    others = [raw, lvl] + [v for k, v in maps.items() if "W" not in k]
    opt = _AdamW(torch, [(weights, o.weight_decay), (others, 0.0)], lr=o.lr)
    has_val = bool(val.any())
    best = (math.inf, math.inf, 0, None)
    for it in range(o.max_iter + 1):
        opt.zero_grad()
        err = output(states()) - y_t
        loss = torch.mean(err[tr] ** 2)
        prior = LEVEL_PRIOR**2 * (lvl[0] - level0) ** 2 / int(train.sum())
        score = float(torch.mean(err[va].detach() ** 2)) if has_val else float(loss.detach())
        if not math.isfinite(score):
            break
        if score < best[0]:
            snap = {k: v.detach().clone() for k, v in maps.items()}
            state = (raw.detach().clone(), lvl.detach().clone(), snap)
            best = (score, float(loss.detach()), it, state)
        elif it - best[2] > o.patience:
            break
        if it == o.max_iter:
            break
        (loss + prior).backward()
        opt.step()
        with torch.no_grad():
            lvl.clamp_(lvl_lo, lvl_hi)
    score, tr_mse, n_it, params = best
    if params is None:  # pragma: no cover - a non-finite start
        params = (raw.detach(), lvl.detach(), {k: v.detach() for k, v in maps.items()})
    raw_b, lvl_b, m = params
    npy = {k: v.numpy().astype(float) for k, v in m.items()}
    xm, xs = x_mean.numpy(), x_scale.numpy()
    in_map = None
    if has_in:
        in_map = MLPMap(npy["iW1"], npy["ib1"], npy["iW2"], npy["ib2"], [0.0], [1.0])
    if mlp_out:
        out_map: MLPMap | PolynomialMap = MLPMap(npy["oW1"], npy["ob1"], npy["oW2"],
                                                 npy["ob2"], xm, xs)
    else:
        coef = np.concatenate([npy["ob2"], npy["oW2"][0]])
        out_map = PolynomialMap(monomial_exponents(xm.size, 1), coef, xm, xs)
    u_mean, u_scale, y_mean, y_scale = stats
    model = NonlinearKautzModel(
        structure=structure, poles=poles_from_raw(kinds, raw_b.numpy()), output_map=out_map,
        input_map=in_map, u_mean=u_mean, u_scale=u_scale, y_mean=y_mean, y_scale=y_scale,
        level=u_mean + u_scale * float(lvl_b[0]), dt=dt,
    )
    return TorchResult(model, score if has_val else math.nan, tr_mse, n_it)
