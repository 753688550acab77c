"""Differentiable Kautz machinery in torch: network matrices, basis signals, least squares.

The numpy core (:mod:`kautztwin.basis`) builds one basis at a time from pole
locations.  Learning the poles needs the same computation batched over many
pole sets *and* differentiable in the pole parameters, which is what this
module provides for a fixed block structure (kautz-math.md sections 2 and 4.4):

* :func:`network_matrices` -- the network realisation ``A, B`` of
  ``dF/dt = A F, F(0) = B`` from block parameters, same formulas as
  :func:`kautztwin.basis._blocks.continuous_matrices`;
* :func:`propagate` and :func:`kautz_functions` -- ``K(t) = e^{At} B`` on a time
  grid, exact (matrix exponentials, no ODE solver, no eigendecomposition);
* :func:`lstsq_coefficients` -- weighted least-squares coefficients of records
  in a batch of bases, by the normal equations with a tiny relative ridge,
  optionally under linear equality constraints;
* :func:`relative_degree_constraints` -- the linear constraints on the
  coefficients that give the model a prescribed relative degree;
* :func:`block_structure` and :func:`block_poles` -- conversion between pole
  locations and ``(kinds, params)``.

Parameters per block (``params`` columns in block order): a real pole
``s = -p`` has ``[p]`` (``p > 0``); a pair ``s = -sigma +- j omega`` has
``[sigma, omega]`` (``sigma > 0``, ``omega >= 0``).  Every function works in the
dtype of ``params`` (float64 for exactness checks and gradcheck, float32 for
speed) and supports autograd with respect to ``params`` and the records.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from numpy.typing import ArrayLike

from .._quadrature import least_squares_weights
from .._validation import check_time
from ..basis._blocks import PAIR, REAL, parse_poles
from ..basis._propagate import uniform_step
from ..exceptions import DataError, DimensionError, PoleError

__all__ = [
    "block_poles",
    "block_structure",
    "kautz_functions",
    "lstsq_coefficients",
    "n_functions",
    "n_params",
    "network_matrices",
    "propagate",
    "relative_degree_constraints",
    "response_weights",
]


def _check_kinds(kinds: Sequence[str]) -> tuple[str, ...]:
    kinds = tuple(str(k) for k in kinds)
    if not kinds:
        raise PoleError("kinds must hold at least one block ('real' or 'pair')")
    bad = [k for k in kinds if k not in (REAL, PAIR)]
    if bad:
        raise PoleError(f"block kinds must be 'real' or 'pair'; got {bad[0]!r}")
    return kinds


def n_functions(kinds: Sequence[str]) -> int:
    """Number of basis functions of a block structure.

    Parameters
    ----------
    kinds : sequence of {'real', 'pair'}
        Block kinds in order.

    Returns
    -------
    int
        One per real block, two per pair.

    Examples
    --------
    >>> from kautztwin.nn.kautz_torch import n_functions
    >>> n_functions(("pair", "real", "real"))
    4
    """
    return sum(1 if k == REAL else 2 for k in _check_kinds(kinds))


def n_params(kinds: Sequence[str]) -> int:
    """Number of block parameters of a block structure (equal to :func:`n_functions`).

    Parameters
    ----------
    kinds : sequence of {'real', 'pair'}
        Block kinds in order.

    Returns
    -------
    int
        One (rate) per real block, two (``sigma, omega``) per pair.
    """
    return n_functions(kinds)


def block_structure(poles: ArrayLike) -> tuple[tuple[str, ...], torch.Tensor]:
    """Block kinds and parameters of continuous-time pole locations.

    Parameters
    ----------
    poles : array-like of complex
        Pole locations with ``Re < 0``, each complex pole listed with its
        conjugate (as for :class:`kautztwin.KautzBasis`).

    Returns
    -------
    kinds : tuple of {'real', 'pair'}
        Block kinds in order (a pair at the position of its first member).
    params : torch.Tensor of shape (n_params,), float64
        ``[p]`` per real block and ``[sigma, omega]`` per pair.

    Raises
    ------
    PoleError
        If a pole is not finite or a complex pole has no conjugate partner.
    UnstableModelError
        If a pole has ``Re >= 0``.

    Examples
    --------
    >>> from kautztwin.nn.kautz_torch import block_structure
    >>> kinds, params = block_structure([-0.5 + 2j, -0.5 - 2j, -1.0])
    >>> kinds, params.tolist()
    (('pair', 'real'), [0.5, 2.0, 1.0])
    """
    kinds, params = parse_poles(poles, 0.0)
    return kinds, torch.as_tensor(params, dtype=torch.float64)


def _as_batch(params: torch.Tensor, kinds: tuple[str, ...]) -> tuple[torch.Tensor, bool]:
    if not isinstance(params, torch.Tensor):
        params = torch.as_tensor(np.asarray(params, dtype=float))
    single = params.ndim == 1
    P = params[None, :] if single else params
    expected = n_params(kinds)
    if P.ndim != 2 or P.shape[1] != expected:
        raise DimensionError(
            f"params must have shape (batch, {expected}) for {len(kinds)} blocks; "
            f"got {tuple(params.shape)}"
        )
    return P, single


def block_poles(kinds: Sequence[str], params: torch.Tensor) -> torch.Tensor:
    """Pole locations of a batch of block parameters, pairs as ``(p, conj p)``.

    Parameters
    ----------
    kinds : sequence of {'real', 'pair'}
        Block kinds in order.
    params : torch.Tensor of shape (n_params,) or (batch, n_params)
        Block parameters.

    Returns
    -------
    torch.Tensor of complex dtype, shape (n_functions,) or (batch, n_functions)
        Locations ``-p`` and ``-sigma +- j omega`` in block order.

    Examples
    --------
    >>> import torch
    >>> from kautztwin.nn.kautz_torch import block_poles
    >>> block_poles(("pair", "real"), torch.tensor([0.5, 2.0, 1.0], dtype=torch.float64))
    tensor([-0.5000+2.j, -0.5000-2.j, -1.0000+0.j], dtype=torch.complex128)
    """
    kinds = _check_kinds(kinds)
    P, single = _as_batch(params, kinds)
    cols = []
    col = 0
    zero = torch.zeros_like(P[:, 0])
    for kind in kinds:
        if kind == REAL:
            cols.append(torch.complex(-P[:, col], zero))
            col += 1
        else:
            cols.append(torch.complex(-P[:, col], P[:, col + 1]))
            cols.append(torch.complex(-P[:, col], -P[:, col + 1]))
            col += 2
    out = torch.stack(cols, dim=-1)
    return out[0] if single else out


def network_matrices(
    kinds: Sequence[str], params: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Network realisation ``dF/dt = A F, F(0) = B`` for a batch of pole sets.

    Same formulas as the numpy core (kautz-math.md 2.1): real block
    :math:`A_j = [-p]`, :math:`\beta_j = [\sqrt{2p}]`; pair block
    :math:`A_j = [[-b, -\sqrt c], [\sqrt c, 0]]`, :math:`\beta_j = [\sqrt{2b}, 0]`
    with :math:`b = 2\sigma`, :math:`c = \sigma^2 + \omega^2`, and
    :math:`A = \mathrm{blkdiag}(A_j) - \mathcal L(\beta\beta^T)`, :math:`B = \beta`.

    Parameters
    ----------
    kinds : sequence of {'real', 'pair'}
        Block kinds in order.
    params : torch.Tensor of shape (n_params,) or (batch, n_params)
        Block parameters (rates ``p > 0``; pairs ``sigma > 0, omega >= 0``).
        Not validated here (this runs inside training loops); non-positive
        rates give ``NaN`` entries.

    Returns
    -------
    A : torch.Tensor of shape (batch, n_functions, n_functions)
    B : torch.Tensor of shape (batch, n_functions)
        Without the batch axis if ``params`` is 1-D.

    Raises
    ------
    PoleError
        On an unknown block kind.
    DimensionError
        If ``params`` has the wrong number of columns.

    See Also
    --------
    kautz_functions : The basis signals ``e^{At} B`` on a grid.
    kautztwin.KautzBasis.state_space : The numpy realisation of one basis.

    Examples
    --------
    >>> import torch
    >>> from kautztwin.nn.kautz_torch import network_matrices
    >>> A, B = network_matrices(("real", "real"), torch.tensor([1.0, 1.0], dtype=torch.float64))
    >>> A.round(decimals=12).tolist()
    [[-1.0, 0.0], [-2.0, -1.0]]
    """
    kinds = _check_kinds(kinds)
    P, single = _as_batch(params, kinds)
    batch = P.shape[0]
    n = n_functions(kinds)
    diag = torch.zeros((batch, n, n), dtype=P.dtype, device=P.device)
    beta_cols: list[torch.Tensor] = []
    zero = torch.zeros_like(P[:, 0])
    blocks: list[int] = []
    i = col = 0
    for j, kind in enumerate(kinds):
        if kind == REAL:
            rate = P[:, col]
            diag[:, i, i] = -rate
            beta_cols.append(torch.sqrt(2.0 * rate))
            blocks.append(j)
            i += 1
            col += 1
        else:
            sigma, omega = P[:, col], P[:, col + 1]
            b = 2.0 * sigma
            root_c = torch.sqrt(sigma * sigma + omega * omega)
            diag[:, i, i] = -b
            diag[:, i, i + 1] = -root_c
            diag[:, i + 1, i] = root_c
            beta_cols += [torch.sqrt(2.0 * b), zero]
            blocks += [j, j]
            i += 2
            col += 2
    beta = torch.stack(beta_cols, dim=-1)
    blk = torch.as_tensor(blocks, device=P.device)
    lower = (blk[:, None] > blk[None, :]).to(P.dtype)
    A = diag - lower * (beta[:, :, None] * beta[:, None, :])
    if single:
        return A[0], beta[0]
    return A, beta


def propagate(A: torch.Tensor, B: torch.Tensor, t: ArrayLike) -> torch.Tensor:
    r"""``F(t) = e^{At} B`` on a time grid, batched and differentiable.

    On a uniform grid ``t_k = t_0 + k h`` (``t_0 >= 0``) the samples are built by
    doubling: :math:`F(t_0) = e^{A t_0} B`, then the block of samples
    ``[m, 2m)`` is :math:`e^{A h m}` times the block ``[0, m)``, for
    ``m = 1, 2, 4, ...``.  One matrix exponential :math:`e^{A h}` is
    computed; the factors :math:`e^{A h m}` are its repeated squares (the
    scaling-and-squaring that a matrix exponential of :math:`A h m` would do
    internally anyway).  Every sample is the product of at most
    :math:`\log_2 n` factors, so rounding does not accumulate along the
    record; the cost is about :math:`2 \log_2 n` batched small matrix
    products, and autograd differentiates it.  Other grids use one matrix
    exponential per sample.  ``F`` is zero for ``t < 0``.

    Parameters
    ----------
    A : torch.Tensor of shape (batch, N, N)
        State matrices.
    B : torch.Tensor of shape (batch, N)
        Initial states.
    t : array-like of shape (n_samples,)
        Strictly increasing sample times in seconds (numpy or torch; the times
        are data, not differentiated).

    Returns
    -------
    torch.Tensor of shape (batch, N, n_samples)

    Raises
    ------
    DataError
        If ``t`` is not strictly increasing or holds NaN/inf.
    DimensionError
        If ``A`` and ``B`` do not agree or ``t`` is not 1-D.
    """
    if isinstance(t, torch.Tensor):
        t = t.detach().cpu().numpy()
    t = check_time(np.asarray(t, dtype=float), min_samples=1)
    if A.ndim != 3 or B.ndim != 2 or A.shape[:2] != B.shape or A.shape[1] != A.shape[2]:
        raise DimensionError(
            f"A must have shape (batch, N, N) and B (batch, N); got {tuple(A.shape)} and "
            f"{tuple(B.shape)}"
        )
    h = uniform_step(t) if t.size >= 3 else (float(t[1] - t[0]) if t.size == 2 else None)
    if t.size == 1:
        h = 1.0
    if h is not None and t[0] >= 0:
        first = B
        if t[0] > 0:
            first = torch.einsum("bij,bj->bi", torch.linalg.matrix_exp(A * float(t[0])), B)
        n = t.size
        E = torch.linalg.matrix_exp(A * h)  # e^{A h m}, m = 1, 2, 4, ...
        if not (torch.is_grad_enabled() and (A.requires_grad or B.requires_grad)):
            return _propagate_into(first, E, n)
        F = first[:, :, None]
        while F.shape[-1] < n:
            m = F.shape[-1]
            F = torch.cat([F, E @ F[:, :, : min(m, n - m)]], dim=-1)
            if 2 * m < n:
                E = E @ E
        return F
    tt = torch.as_tensor(np.clip(t, 0.0, None), dtype=A.dtype, device=A.device)
    E = torch.linalg.matrix_exp(A[:, None, :, :] * tt[None, :, None, None])  # (b, n, N, N)
    F = torch.einsum("bkij,bj->bik", E, B)
    mask = torch.as_tensor(t >= 0, dtype=A.dtype, device=A.device)
    return F * mask


def _propagate_into(first: torch.Tensor, E: torch.Tensor, n: int) -> torch.Tensor:
    """The doubling of :func:`propagate` written into one preallocated array (no autograd).

    The same products in the same order as the concatenating loop (equal results to the
    last bit), without copying the growing array at every doubling: about twice as fast
    where no gradient is needed (prediction).
    """
    F = torch.empty(first.shape + (n,), dtype=first.dtype, device=first.device)
    F[:, :, 0] = first
    m = 1
    while m < n:
        k = min(m, n - m)
        torch.matmul(E, F[:, :, :k], out=F[:, :, m : m + k])
        if 2 * m < n:
            E = E @ E
        m *= 2
    return F


def kautz_functions(kinds: Sequence[str], params: torch.Tensor, t: ArrayLike) -> torch.Tensor:
    """Kautz basis functions of a batch of pole sets on a time grid.

    Equal (to rounding) to :meth:`kautztwin.KautzBasis.evaluate` of every pole
    set, and differentiable with respect to ``params``.

    Parameters
    ----------
    kinds : sequence of {'real', 'pair'}
        Block kinds in order.
    params : torch.Tensor of shape (n_params,) or (batch, n_params)
        Block parameters (see the module docstring).
    t : array-like of shape (n_samples,)
        Strictly increasing sample times in seconds.

    Returns
    -------
    torch.Tensor of shape (batch, n_functions, n_samples)
        Without the batch axis if ``params`` is 1-D.

    See Also
    --------
    network_matrices : The realisation that is propagated.
    propagate : The propagation ``e^{At} B``.

    Examples
    --------
    >>> import numpy as np
    >>> import torch
    >>> import kautztwin as kt
    >>> from kautztwin.nn.kautz_torch import block_structure, kautz_functions
    >>> poles = [-1.0, -3.0, -0.5 + 1.9365j, -0.5 - 1.9365j]
    >>> kinds, params = block_structure(poles)
    >>> t = np.linspace(0.0, 20.0, 900)
    >>> K = kautz_functions(kinds, params, t)
    >>> K.shape
    torch.Size([4, 900])
    >>> bool(np.allclose(K.numpy(), kt.KautzBasis(poles).evaluate(t), rtol=0, atol=1e-13))
    True
    """
    kinds = _check_kinds(kinds)
    P, single = _as_batch(params, kinds)
    A, B = network_matrices(kinds, P)
    K = propagate(A, B, t)
    return K[0] if single else K


def response_weights(
    t: ArrayLike, rule: str = "simpson", *, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Positive least-squares weights on a time grid.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing sample times.
    rule : {'simpson', 'uniform'}, default='simpson'
        ``'simpson'``: the weights of :func:`kautztwin.project` with
        ``method='lstsq'`` (Simpson's rule where its weights are positive, else
        the trapezoid rule).  ``'uniform'``: all ones, i.e. ordinary least
        squares, the maximum-likelihood choice for white noise.
    dtype : torch.dtype, default=torch.float64
        Dtype of the result.

    Returns
    -------
    torch.Tensor of shape (n_samples,)

    Raises
    ------
    DataError
        On an unknown rule or a bad time grid.
    """
    if isinstance(t, torch.Tensor):
        t = t.detach().cpu().numpy()
    t = check_time(np.asarray(t, dtype=float))
    if rule == "simpson":
        return torch.as_tensor(least_squares_weights(t), dtype=dtype)
    if rule == "uniform":
        return torch.ones(t.size, dtype=dtype)
    raise DataError(f"rule must be 'simpson' or 'uniform', got {rule!r}")


def lstsq_coefficients(
    K: torch.Tensor,
    h: torch.Tensor,
    weights: torch.Tensor | None = None,
    *,
    ridge: float = 1e-12,
    constraints: torch.Tensor | None = None,
) -> torch.Tensor:
    r"""Weighted least-squares coefficients of records in a batch of bases.

    Solves, for every record ``r`` with its own basis ``K[r]``,

    .. math:: \min_c \sum_k w_k\,\bigl(h_{rk} - c^T K_r(t_k)\bigr)^2
              \quad\text{subject to}\quad M_r^T c = 0 \ \text{(if given)}

    through the normal equations :math:`(G + \lambda I) c = K W h` with
    :math:`G = K W K^T` and a tiny ridge :math:`\lambda = \mathrm{ridge}\cdot
    \mathrm{tr}(G) / N` that only guards against a singular Gram matrix (the
    Kautz functions are orthonormal, so ``G`` is close to the identity on a long
    record).  With constraints the unconstrained solution :math:`c_u` is
    projected (Lagrange multipliers, :math:`\tilde G = G + \lambda I`):
    :math:`c = c_u - \tilde G^{-1} M (M^T \tilde G^{-1} M)^{-1} M^T c_u`.
    Differentiable with respect to ``K`` (hence the poles), ``h`` and ``constraints``.

    Parameters
    ----------
    K : torch.Tensor of shape (batch, N, n_samples) or (N, n_samples)
        Basis functions on the grid, one basis per record or one shared basis.
    h : torch.Tensor of shape (batch, n_samples)
        Records.
    weights : torch.Tensor of shape (n_samples,), optional
        Positive weights, e.g. from :func:`response_weights`; default ones.
    ridge : float, default=1e-12
        Relative ridge (``0`` solves the plain normal equations).
    constraints : torch.Tensor of shape (batch, N, q), optional
        Columns :math:`M` of linear equality constraints :math:`M^T c = 0`
        (linearly independent, ``q < N``), e.g. from
        :func:`relative_degree_constraints`.

    Returns
    -------
    torch.Tensor of shape (batch, N)

    Raises
    ------
    DimensionError
        If the shapes do not agree.

    See Also
    --------
    kautztwin.project : The numpy projection (``method='lstsq'`` is the same solution).

    Examples
    --------
    >>> import numpy as np
    >>> import torch
    >>> from kautztwin.nn.kautz_torch import kautz_functions, lstsq_coefficients
    >>> t = np.linspace(0.0, 20.0, 2001)
    >>> K = kautz_functions(("real",), torch.tensor([1.0], dtype=torch.float64), t)
    >>> h = torch.as_tensor(np.exp(-t))[None]       # impulse response of 1/(s+1)
    >>> lstsq_coefficients(K, h).round(decimals=6)  # 1/sqrt(2)
    tensor([[0.7071]], dtype=torch.float64)
    """
    if h.ndim != 2:
        raise DimensionError(f"h must have shape (batch, n_samples); got {tuple(h.shape)}")
    if K.ndim == 2:
        K = K[None]
    if K.ndim != 3 or K.shape[-1] != h.shape[-1] or K.shape[0] not in (1, h.shape[0]):
        raise DimensionError(
            f"K must have shape (batch, N, n_samples) matching h {tuple(h.shape)}; "
            f"got {tuple(K.shape)}"
        )
    Kw = K if weights is None else K * weights
    G = Kw @ K.transpose(-1, -2)  # (b, N, N)
    rhs = (Kw @ h[:, :, None])[..., 0] if K.shape[0] == h.shape[0] else h @ Kw[0].T
    if K.shape[0] == 1 and h.shape[0] != 1:
        G = G.expand(h.shape[0], -1, -1)
    if ridge:
        N = G.shape[-1]
        scale = torch.diagonal(G, dim1=-2, dim2=-1).sum(-1) / N
        eye = torch.eye(N, dtype=G.dtype, device=G.device)
        G = G + (ridge * scale)[:, None, None] * eye
    if constraints is None or constraints.shape[-1] == 0:
        return torch.linalg.solve(G, rhs[..., None])[..., 0]
    if constraints.ndim != 3 or constraints.shape[:2] != G.shape[:2]:
        raise DimensionError(
            f"constraints must have shape (batch, N, q) = ({G.shape[0]}, {G.shape[1]}, q); "
            f"got {tuple(constraints.shape)}"
        )
    M = constraints
    sol = torch.linalg.solve(G, torch.cat([rhs[..., None], M], dim=-1))
    c_free, GiM = sol[..., 0], sol[..., 1:]
    S = M.transpose(-1, -2) @ GiM  # (b, q, q)
    lam = torch.linalg.solve(S, (M.transpose(-1, -2) @ c_free[..., None]))
    return c_free - (GiM @ lam)[..., 0]


def relative_degree_constraints(
    A: torch.Tensor, B: torch.Tensor, relative_degree: int
) -> torch.Tensor:
    r"""Constraints on Kautz coefficients that give the model a relative degree.

    The model :math:`y(t) = c^T e^{At} B` (impulse response of
    :math:`G(s) = c^T (sI - A)^{-1} B`) has the derivatives
    :math:`y^{(k)}(0) = c^T A^k B` at ``t = 0``, the Markov parameters of
    :math:`G`.  Its relative degree is at least ``r`` exactly when the first
    ``r - 1`` of them vanish: :math:`M^T c = 0` with
    :math:`M = [B, AB, \dots, A^{r-2}B]`.  A physical system whose transfer
    function has ``r - 1`` more poles than zeros satisfies these constraints,
    whatever its poles; imposing them on a least-squares fit
    (:func:`lstsq_coefficients`) keeps the noise out of ``r - 1`` coefficient
    directions.  The columns are orthonormalised (Gram-Schmidt: the same
    constraints, well conditioned).

    Parameters
    ----------
    A : torch.Tensor of shape (batch, N, N)
    B : torch.Tensor of shape (batch, N)
        Network realisation (:func:`network_matrices`).
    relative_degree : int
        ``r >= 1`` (``1``: no constraint, an empty ``M``); at most ``N``.

    Returns
    -------
    torch.Tensor of shape (batch, N, r - 1)

    Raises
    ------
    DataError
        If ``relative_degree`` is not an integer in ``[1, N]``.

    Examples
    --------
    >>> import torch
    >>> from kautztwin.nn.kautz_torch import network_matrices, relative_degree_constraints
    >>> A, B = network_matrices(("real", "real"), torch.tensor([[1.0, 2.0]], dtype=torch.float64))
    >>> relative_degree_constraints(A, B, 2).shape
    torch.Size([1, 2, 1])
    """
    N = B.shape[-1]
    if isinstance(relative_degree, bool) or not isinstance(relative_degree, int | np.integer):
        raise DataError(f"relative_degree must be an integer; got {relative_degree!r}")
    if not 1 <= relative_degree <= N:
        raise DataError(f"relative_degree must be in [1, {N}]; got {relative_degree}")
    cols: list[torch.Tensor] = []
    v = B
    for _ in range(int(relative_degree) - 1):
        q = v
        for prev in cols:  # Gram-Schmidt: the same span, orthonormal columns
            q = q - (q * prev).sum(dim=-1, keepdim=True) * prev
        cols.append(q / q.norm(dim=-1, keepdim=True))
        v = (A @ v[..., None])[..., 0]
    if not cols:
        return B.new_zeros(B.shape + (0,))
    return torch.stack(cols, dim=-1)
