r"""The amortised pole network: record features to second-order blocks, differentiable basis.

The basis has ``max_order`` functions in ``max_order // 2`` **second-order blocks** and,
for an odd order, one real block.  A second-order block is parameterised by its
denominator :math:`s^2 + b s + c` (:math:`b, c > 0`), not by a pole pair: the same
block then holds a complex pair (:math:`b^2 < 4c`) or two real poles (:math:`b^2 > 4c`),
so every stable real pole set of order ``<= max_order`` is one point of the parameter
space and the network never has to decide between real and complex.  The realisation
is the project's pair block written in :math:`(b, c)` (kautz-math.md 2.1):
:math:`A_j = [[-b, -\sqrt c], [\sqrt c, 0]]`, :math:`\beta_j = [\sqrt{2b}, 0]`, and its
functions span :math:`\{(\alpha s + \beta)/(s^2 + b s + c)\}` times the earlier all-passes
whatever the sign of :math:`b^2 - 4c` (kautz-math.md 4.2: the span depends only on the
denominator), so a least-squares fit on it equals the fit on the Kautz basis of its roots.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

__all__ = [
    "AmortisedPoleNetwork",
    "QUAD",
    "REAL",
    "bin_features",
    "block_kinds",
    "block_matrices",
    "block_roots",
]

#: Block kinds: a second-order block ``s^2 + b s + c`` and a real pole ``s + p``.
QUAD, REAL = "quad", "real"
#: Bounds of every normalised block parameter (rates, ``sqrt(c)``): ``[LOW, HIGH]`` / record.
LOW, HIGH = 0.2, 1500.0


def block_kinds(max_order: int) -> tuple[str, ...]:
    """Blocks of a basis of ``max_order`` functions: second-order ones, then one real if odd.

    Examples
    --------
    >>> block_kinds(5)
    ('quad', 'quad', 'real')
    """
    return (QUAD,) * (max_order // 2) + ((REAL,) if max_order % 2 else ())


def _centre(kinds: Sequence[str]) -> NDArray[np.float64]:
    """Centre of the normalised block parameters: blocks spread over rates 6 .. 40."""
    out: list[float] = []
    n = len(kinds)
    for j, kind in enumerate(kinds):
        rate = 6.0 * (40.0 / 6.0) ** (j / max(n - 1, 1))
        out += [1.2 * rate, rate] if kind == QUAD else [rate]
    return np.array(out)


def block_matrices(kinds: Sequence[str], theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Network realisation ``dF/dt = A F, F(0) = B`` of a batch of block parameters.

    Parameters
    ----------
    kinds : sequence of {'quad', 'real'}
        Block kinds in order.
    theta : torch.Tensor of shape (batch, n_params)
        ``[b, sqrt(c)]`` per second-order block, ``[p]`` per real block (all ``> 0``).

    Returns
    -------
    A : torch.Tensor of shape (batch, N, N)
    B : torch.Tensor of shape (batch, N)

    Notes
    -----
    :math:`A = \mathrm{blkdiag}(A_j) - \mathcal L(\beta\beta^T)` with :math:`\mathcal L`
    the part below the diagonal blocks, as in
    :func:`kautztwin.nn.kautz_torch.network_matrices`; the realisation satisfies
    :math:`A + A^T + BB^T = 0`, so the functions are orthonormal in :math:`L_2`.
    """
    batch = theta.shape[0]
    n = sum(2 if k == QUAD else 1 for k in kinds)
    diag = torch.zeros((batch, n, n), dtype=theta.dtype, device=theta.device)
    zero = torch.zeros_like(theta[:, 0])
    beta: list[torch.Tensor] = []
    blocks: list[int] = []
    i = col = 0
    for j, kind in enumerate(kinds):
        if kind == QUAD:
            b, r = theta[:, col], theta[:, col + 1]
            diag[:, i, i] = -b
            diag[:, i, i + 1] = -r
            diag[:, i + 1, i] = r
            beta += [torch.sqrt(2.0 * b), zero]
            blocks += [j, j]
            i, col = i + 2, col + 2
        else:
            p = theta[:, col]
            diag[:, i, i] = -p
            beta.append(torch.sqrt(2.0 * p))
            blocks.append(j)
            i, col = i + 1, col + 1
    bt = torch.stack(beta, dim=-1)
    blk = torch.as_tensor(blocks, device=theta.device)
    lower = (blk[:, None] > blk[None, :]).to(theta.dtype)
    return diag - lower * (bt[:, :, None] * bt[:, None, :]), bt


def block_roots(kinds: Sequence[str], theta: NDArray[np.float64]) -> NDArray[np.complex128]:
    """Pole locations of block parameters (conjugates adjacent, a real pair as two reals).

    Parameters
    ----------
    kinds : sequence of {'quad', 'real'}
    theta : ndarray of shape (n_records, n_params)

    Returns
    -------
    ndarray of complex, shape (n_records, N)

    Examples
    --------
    >>> import numpy as np
    >>> block_roots(("quad", "real"), np.array([[3.0, np.sqrt(2.0), 5.0]])).round(12).tolist()
    [[(-1+0j), (-2+0j), (-5+0j)]]
    """
    theta = np.atleast_2d(theta)
    cols: list[NDArray] = []
    col = 0
    for kind in kinds:
        if kind == QUAD:
            b, c = theta[:, col], theta[:, col + 1] ** 2
            disc = b * b - 4.0 * c
            root = np.sqrt(np.abs(disc))
            real = disc >= 0
            # real roots: -(b -+ root)/2, the slower first; complex: -b/2 +- j root/2
            slow = np.where(real, -2.0 * c / (b + root), -b / 2.0) + 0j
            fast = np.where(real, -(b + root) / 2.0, -b / 2.0) + 0j
            slow = slow + np.where(real, 0.0, root / 2.0) * 1j
            fast = fast - np.where(real, 0.0, root / 2.0) * 1j
            cols += [slow, fast]
            col += 2
        else:
            cols.append(-theta[:, col] + 0j)
            col += 1
    return np.stack(cols, axis=-1)


def bin_features(t: NDArray[np.float64], Y: NDArray[np.float64], n_bins: int) -> NDArray:
    """Bin averages of records over ``n_bins`` equal bins of ``[t[0], t[-1]]``, unit RMS.

    The averages are exact for the trapezoid interpolant of each record (cumulative
    integral interpolated at the bin edges), on any increasing grid.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
    Y : ndarray of shape (n_records, n_samples)
    n_bins : int

    Returns
    -------
    ndarray of shape (n_records, n_bins)
    """
    Y = np.atleast_2d(Y)
    cum = np.zeros_like(Y)
    cum[:, 1:] = np.cumsum(0.5 * (Y[:, 1:] + Y[:, :-1]) * np.diff(t), axis=1)
    edges = np.linspace(t[0], t[-1], n_bins + 1)
    k = np.clip(np.searchsorted(t, edges, side="right") - 1, 0, t.size - 2)
    # integral up to an edge: the trapezoid to t[k] plus the part of the next interval
    slope = (Y[:, k + 1] - Y[:, k]) / (t[k + 1] - t[k])
    dx = edges - t[k]
    at = cum[:, k] + Y[:, k] * dx + 0.5 * slope * dx * dx
    F = np.diff(at, axis=1) / np.diff(edges)
    rms = np.sqrt(np.mean(F * F, axis=1, keepdims=True))
    return F / np.where(rms > 0, rms, 1.0)


class AmortisedPoleNetwork(nn.Module):
    r"""Features of a record to the normalised block parameters of its basis.

    A SiLU perceptron maps the unit-RMS bin averages :math:`z` of the record
    (:func:`bin_features`, time normalised by the record length) to one number
    :math:`u_i` per block parameter, and

    .. math:: \log\theta_i = \log L + (\log H - \log L)\,
              \sigma\bigl(u_i + \sigma^{-1}(\tfrac{\log\theta^0_i - \log L}{\log H - \log L})\bigr),

    so every parameter stays in ``[LOW, HIGH]`` (a stable basis by construction) and the
    untrained network (last layer zero) gives the centre :math:`\theta^0`.

    Parameters
    ----------
    max_order : int
        Basis functions (``max_order // 2`` second-order blocks, one real if odd).
    n_bins : int
        Feature length.
    hidden : sequence of int
        Hidden layer widths.
    """

    def __init__(self, max_order: int, n_bins: int, hidden: Sequence[int]) -> None:
        super().__init__()
        self.kinds = block_kinds(max_order)
        self.max_order = int(max_order)
        self.n_bins = int(n_bins)
        self.hidden = tuple(int(h) for h in hidden)
        n_out = sum(2 if k == QUAD else 1 for k in self.kinds)
        layers: list[nn.Module] = []
        fan_in = self.n_bins
        for width in self.hidden:
            layers += [nn.Linear(fan_in, width), nn.SiLU()]
            fan_in = width
        last = nn.Linear(fan_in, n_out)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        layers.append(last)
        self.body = nn.Sequential(*layers)
        share = (np.log(_centre(self.kinds)) - np.log(LOW)) / (np.log(HIGH) - np.log(LOW))
        self.register_buffer("offset", torch.as_tensor(np.log(share / (1 - share)),
                                                       dtype=torch.float32))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """Normalised block parameters ``theta`` of shape ``(batch, n_params)``."""
        u = self.body(z) + self.offset.to(z.dtype)
        lo, hi = float(np.log(LOW)), float(np.log(HIGH))
        return torch.exp(lo + (hi - lo) * torch.sigmoid(u))
