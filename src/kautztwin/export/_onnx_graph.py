"""A small ONNX graph builder and the Kautz machinery written in plain ONNX operators.

The estimators' networks are a handful of layer types (``Linear``, ``PReLU``, ``SiLU``,
softmax); the adaptive estimator also builds a Kautz basis per record, which in torch uses
``torch.linalg.matrix_exp`` and ``torch.linalg.solve``, two operations ONNX does not have.
Here they are unrolled for the fixed sizes of one trained estimator:

* :meth:`Graph.expm` -- scaling and squaring with a degree-12 Taylor polynomial, the
  number of squarings fixed at export time from a bound on the matrix norm over every pole
  the network can produce (its poles stay within ``pole_range`` of the centre);
* :meth:`Graph.solve_spd` -- Gauss-Jordan elimination without pivoting, exact in exact
  arithmetic and backward stable for the symmetric positive definite normal equations;
* :meth:`Graph.design` and :meth:`Graph.lstsq` -- the basis signals on a uniform grid
  (the same doubling recursion as :func:`kautztwin.nn.kautz_torch.propagate`) and the
  ridge-guarded least-squares coefficients of
  :func:`kautztwin.nn.kautz_torch.lstsq_coefficients`.

Only ``onnx.helper`` and ``onnx.numpy_helper`` are used: no exporter, no tracing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["Graph", "KautzLayout"]

#: degree of the Taylor polynomial of the matrix exponential (after scaling to norm <= 1/4,
#: its truncation error is below 0.25**13 / 13! = 2.4e-18)
TAYLOR_DEGREE = 12
_SCALED_NORM = 0.25


class KautzLayout:
    """Constant maps from block parameters to the network matrices of one block structure.

    Parameters
    ----------
    kinds : sequence of {'real', 'pair'}
        Block structure (:mod:`kautztwin.nn.kautz_torch` parameter order).
    """

    def __init__(self, kinds: Sequence[str]) -> None:
        self.kinds = tuple(kinds)
        n = sum(1 if k == "real" else 2 for k in self.kinds)
        n_pairs = sum(k == "pair" for k in self.kinds)
        self.n = n
        self.diag = np.zeros((n, n * n))  # params -> blkdiag entries that are linear
        self.root = np.zeros((max(n_pairs, 1), n * n))  # sqrt(sigma^2 + omega^2) -> entries
        self.square = np.zeros((n, max(n_pairs, 1)))  # params^2 -> sigma^2 + omega^2
        self.beta = np.zeros((n, n))  # params -> beta^2
        self.pole_re = np.zeros((n, n))
        self.pole_im = np.zeros((n, n))
        blocks: list[int] = []
        i = col = pair = 0
        for j, kind in enumerate(self.kinds):
            if kind == "real":
                self.diag[col, i * n + i] = -1.0
                self.beta[col, i] = 2.0
                self.pole_re[col, i] = -1.0
                blocks.append(j)
                i += 1
                col += 1
            else:
                self.diag[col, i * n + i] = -2.0
                self.square[col, pair] = self.square[col + 1, pair] = 1.0
                self.root[pair, i * n + i + 1] = -1.0
                self.root[pair, (i + 1) * n + i] = 1.0
                self.beta[col, i] = 4.0
                self.pole_re[col, i] = self.pole_re[col, i + 1] = -1.0
                self.pole_im[col + 1, i] = 1.0
                self.pole_im[col + 1, i + 1] = -1.0
                blocks += [j, j]
                i += 2
                col += 2
                pair += 1
        self.n_pairs = n_pairs
        blk = np.asarray(blocks)
        self.lower = (blk[:, None] > blk[None, :]).astype(float)

    def matrices(self, params: NDArray) -> tuple[NDArray, NDArray]:
        """``A, B`` of one parameter vector (numpy, for the norm bound)."""
        p = np.asarray(params, dtype=float)
        flat = p @ self.diag
        if self.n_pairs:
            flat = flat + np.sqrt((p * p) @ self.square) @ self.root
        beta = np.sqrt(p @ self.beta)
        A = flat.reshape(self.n, self.n) - self.lower * np.outer(beta, beta)
        return A, beta


class Graph:
    """Nodes and initializers of one ONNX graph; every method returns output names.

    Parameters
    ----------
    dtype : numpy dtype
        Default element type of constants.
    """

    def __init__(self, dtype: Any = np.float32) -> None:
        self.dtype = np.dtype(dtype)
        self.nodes: list[Any] = []
        self.initializers: list[Any] = []
        self._count = 0
        self._consts: dict[tuple, str] = {}

    # ------------------------------------------------------------------ primitives
    def _name(self, hint: str) -> str:
        self._count += 1
        return f"{hint}_{self._count}"

    def const(self, value: Any, dtype: Any = None, hint: str = "c") -> str:
        """An initializer holding ``value`` (cast to ``dtype``, default the graph's)."""
        from onnx import numpy_helper

        arr = np.asarray(value, dtype=self.dtype if dtype is None else dtype)
        key = (arr.dtype.str, arr.shape, arr.tobytes()) if arr.size <= 64 else None
        if key is not None and key in self._consts:
            return self._consts[key]
        name = self._name(hint)
        self.initializers.append(numpy_helper.from_array(np.ascontiguousarray(arr), name))
        if key is not None:
            self._consts[key] = name
        return name

    def ints(self, values: Sequence[int]) -> str:
        """An int64 initializer (shapes, axes, pads)."""
        return self.const(np.asarray(values, dtype=np.int64), np.int64, "i")

    def op(self, op_type: str, *inputs: str, hint: str | None = None, **attrs: Any) -> str:
        """Append one node with one output; return the output's name."""
        from onnx import helper

        out = self._name(hint or op_type.lower())
        self.nodes.append(helper.make_node(op_type, list(inputs), [out], **attrs))
        return out

    def rename(self, name: str, new: str) -> str:
        """Give the tensor ``name`` a second, public name (an ``Identity`` node)."""
        from onnx import helper

        self.nodes.append(helper.make_node("Identity", [name], [new]))
        return new

    # ------------------------------------------------------------------ layers
    def linear(self, x: str, weight: NDArray, bias: NDArray, dtype: Any) -> str:
        """``x @ weight.T + bias`` (a torch ``Linear``)."""
        return self.op("Gemm", x, self.const(weight, dtype, "W"), self.const(bias, dtype, "b"),
                       transB=1)

    def silu(self, x: str) -> str:
        """``x * sigmoid(x)``."""
        return self.op("Mul", x, self.op("Sigmoid", x))

    def scale(self, x: str, value: float, n: int, dtype: Any) -> str:
        """``x * value`` for ``x`` of shape ``(..., n, n)``, by an ``(n, n)`` constant.

        onnxruntime fuses a ``MatMul`` next to a ``Mul`` by a *scalar* constant into a
        ``FusedMatMul`` whose scale is a ``float32`` attribute, which would round
        ``value`` to single precision in a ``float64`` graph; a full matrix is not fused.
        """
        return self.op("Mul", x, self.const(np.full((n, n), value), dtype, "scale"))

    def slice(self, x: str, axis: int, start: int, end: int) -> str:
        """``x`` restricted to ``start:end`` along ``axis``."""
        return self.op("Slice", x, self.ints([start]), self.ints([end]), self.ints([axis]))

    # ------------------------------------------------------------------ linear algebra
    def expm(self, M: str, n: int, norm_bound: float, dtype: Any) -> str:
        """Matrix exponentials of a batch ``(b, n, n)`` whose 1-norms are at most ``norm_bound``.

        Scaling by ``2**-s`` (``s`` fixed from the bound) to norm ``<= 1/4``, a
        degree-12 Taylor polynomial in Horner form, then ``s`` squarings.
        """
        s = 0 if norm_bound <= _SCALED_NORM else math.ceil(math.log2(norm_bound / _SCALED_NORM))
        X = self.scale(M, 2.0 ** (-s), n, dtype) if s else M
        eye = self.const(np.eye(n), dtype, "eye")
        T = self.op("Add", eye, self.scale(X, 1.0 / TAYLOR_DEGREE, n, dtype))
        for k in range(TAYLOR_DEGREE - 1, 0, -1):
            T = self.op("Add", eye, self.scale(self.op("MatMul", X, T), 1.0 / k, n, dtype))
        for _ in range(s):
            T = self.op("MatMul", T, T)
        return T

    def solve_spd(self, G: str, rhs: str, n: int, dtype: Any) -> str:
        """Solutions ``(b, n)`` of ``G c = rhs`` for SPD ``G (b, n, n)``, ``rhs (b, n, 1)``.

        Gauss-Jordan elimination without pivoting (the pivots of a symmetric positive
        definite matrix are positive), unrolled for the fixed size ``n``.
        """
        M = self.op("Concat", G, rhs, axis=2)
        for k in range(n):
            row = self.slice(M, 1, k, k + 1)  # (b, 1, n + 1)
            pivot = self.slice(row, 2, k, k + 1)  # (b, 1, 1)
            col = self.slice(M, 2, k, k + 1)  # (b, n, 1)
            mask = np.ones((n, 1))
            mask[k] = 0.0
            factor = self.op("Mul", self.op("Div", col, pivot), self.const(mask, dtype))
            M = self.op("Sub", M, self.op("Mul", factor, row))
        diag = self.op("ReduceSum", self.op("Mul", self.slice(M, 2, 0, n),
                                            self.const(np.eye(n), dtype, "eye")),
                       self.ints([2]), keepdims=0)
        return self.op("Div", self.op("Squeeze", self.slice(M, 2, n, n + 1), self.ints([2])),
                       diag)

    def solve_spd_columns(self, G: str, rhs: str, n: int, k: int, dtype: Any) -> str:
        """Solutions ``(b, n, k)`` of ``G X = rhs`` for SPD ``G (b, n, n)``, ``rhs (b, n, k)``.

        :meth:`solve_spd` with ``k`` right-hand sides.
        """
        M = self.op("Concat", G, rhs, axis=2)
        for j in range(n):
            row = self.slice(M, 1, j, j + 1)  # (b, 1, n + k)
            pivot = self.slice(row, 2, j, j + 1)  # (b, 1, 1)
            col = self.slice(M, 2, j, j + 1)  # (b, n, 1)
            mask = np.ones((n, 1))
            mask[j] = 0.0
            factor = self.op("Mul", self.op("Div", col, pivot), self.const(mask, dtype))
            M = self.op("Sub", M, self.op("Mul", factor, row))
        diag = self.op("ReduceSum", self.op("Mul", self.slice(M, 2, 0, n),
                                            self.const(np.eye(n), dtype, "eye")),
                       self.ints([2]), keepdims=1)
        return self.op("Div", self.slice(M, 2, n, n + k), diag)

    def relative_degree_constraints(self, layout: KautzLayout, params: str, relative_degree: int,
                                    dtype: Any) -> str:
        """Constraint columns ``(b, n, r - 1)`` of a relative degree ``r >= 2``.

        :func:`kautztwin.nn.kautz_torch.relative_degree_constraints`: ``B, AB, ...``
        orthonormalised by Gram-Schmidt.
        """
        A, beta = self.network_matrices(layout, params, dtype)
        cols: list[str] = []
        v = beta
        for _ in range(relative_degree - 1):
            q = v
            for prev in cols:
                dot = self.op("ReduceSum", self.op("Mul", q, prev), self.ints([1]), keepdims=1)
                q = self.op("Sub", q, self.op("Mul", dot, prev))
            norm = self.op("Sqrt", self.op("ReduceSumSquare", q, axes=[1], keepdims=1))
            cols.append(self.op("Div", q, norm))
            v = self.op("Squeeze", self.op("MatMul", A, self.op("Unsqueeze", v, self.ints([2]))),
                        self.ints([2]))
        parts = [self.op("Unsqueeze", c, self.ints([2])) for c in cols]
        return parts[0] if len(parts) == 1 else self.op("Concat", *parts, axis=2)

    def lstsq(self, K: str, h: str, weights: NDArray | None, n: int, dtype: Any,
              ridge: float = 1e-12, constraints: tuple[str, int] | None = None) -> str:
        """Weighted least-squares coefficients ``(b, n)`` of records ``h`` in bases ``K``.

        The normal equations with the relative ridge of
        :func:`kautztwin.nn.kautz_torch.lstsq_coefficients`; ``constraints`` is
        ``(M, q)``, the columns ``M (b, n, q)`` of equality constraints ``M^T c = 0``
        (projected as in torch: Lagrange multipliers).
        """
        Kw = K if weights is None else self.op("Mul", K, self.const(weights, dtype, "w"))
        G = self.op("MatMul", Kw, self.op("Transpose", K, perm=[0, 2, 1]))
        rhs = self.op("MatMul", Kw, self.op("Unsqueeze", h, self.ints([2])))
        if ridge:
            eye = self.const(np.eye(n), dtype, "eye")
            trace = self.op("ReduceSum", self.op("Mul", G, eye), self.ints([1, 2]), keepdims=1)
            G = self.op("Add", G, self.op("Mul", self.op("Mul", trace,
                                                         self.const(ridge / n, dtype)), eye))
        if constraints is None:
            return self.solve_spd(G, rhs, n, dtype)
        M, q = constraints
        sol = self.solve_spd_columns(G, self.op("Concat", rhs, M, axis=2), n, q + 1, dtype)
        c_free, GiM = self.slice(sol, 2, 0, 1), self.slice(sol, 2, 1, q + 1)
        Mt = self.op("Transpose", M, perm=[0, 2, 1])
        lam = self.solve_spd_columns(self.op("MatMul", Mt, GiM), self.op("MatMul", Mt, c_free),
                                     q, 1, dtype)
        c = self.op("Sub", c_free, self.op("MatMul", GiM, lam))
        return self.op("Squeeze", c, self.ints([2]))

    def combine(self, c: str, K: str) -> str:
        """``sum_i c_i K_i``: ``(b, n) x (b, n, m) -> (b, m)``."""
        out = self.op("MatMul", self.op("Unsqueeze", c, self.ints([1])), K)
        return self.op("Squeeze", out, self.ints([1]))

    # ------------------------------------------------------------------ Kautz machinery
    def network_matrices(self, layout: KautzLayout, params: str, dtype: Any) -> tuple[str, str]:
        """``A (b, n, n)`` and ``B (b, n)`` of a batch of block parameters ``(b, n_params)``."""
        n = layout.n
        flat = self.op("MatMul", params, self.const(layout.diag, dtype, "Mdiag"))
        if layout.n_pairs:
            sq = self.op("MatMul", self.op("Mul", params, params),
                         self.const(layout.square, dtype, "Msq"))
            flat = self.op("Add", flat, self.op("MatMul", self.op("Sqrt", sq),
                                                self.const(layout.root, dtype, "Mroot")))
        beta = self.op("Sqrt", self.op("MatMul", params, self.const(layout.beta, dtype, "Mb")))
        outer = self.op("Mul", self.op("Unsqueeze", beta, self.ints([2])),
                        self.op("Unsqueeze", beta, self.ints([1])))
        A = self.op("Sub", self.op("Reshape", flat, self.ints([-1, n, n])),
                    self.op("Mul", outer, self.const(layout.lower, dtype, "lower")))
        return A, beta

    def propagate(self, A: str, first: str, size: int, t0: float, h: float, n_samples: int,
                  norm_bound: float, dtype: Any) -> str:
        """``e^{A t_k} first`` on the uniform grid ``t_k = t0 + k h``: ``(b, size, n_samples)``.

        ``norm_bound`` bounds the 1-norm of ``A``.  The doubling of
        :func:`kautztwin.nn.kautz_torch.propagate`.
        """
        F = self.op("Unsqueeze", first, self.ints([2]))
        if t0 > 0:
            E0 = self.expm(self.scale(A, t0, size, dtype), size, norm_bound * t0, dtype)
            F = self.op("MatMul", E0, F)
        E = self.expm(self.scale(A, h, size, dtype), size, norm_bound * h, dtype)
        m = 1
        while m < n_samples:
            part = F if min(m, n_samples - m) == m else self.slice(F, 2, 0, n_samples - m)
            F = self.op("Concat", F, self.op("MatMul", E, part), axis=2)
            if 2 * m < n_samples:
                E = self.op("MatMul", E, E)
            m *= 2
        return F

    def design(self, layout: KautzLayout, params: str, batch_of: str, kind: str, t0: float,
               h: float, n_samples: int, bound: tuple[float, float], dtype: Any) -> str:
        """Basis signals ``(b, n, n_samples)`` of block parameters: Kautz functions or steps.

        Step records use the augmented matrix ``[[A, B], [0, 0]]``, whose exponential
        holds :math:`A^{-1}(e^{At} - I)B` in its last column (the same quantity that
        :meth:`~kautztwin.nn.AdaptivePoleNetwork.design` gets from a linear solve).
        ``bound`` is ``(1-norm bound of A, bound of |B|)``; ``batch_of`` a tensor whose
        first axis is the batch.
        """
        n = layout.n
        A, beta = self.network_matrices(layout, params, dtype)
        if kind == "impulse":
            return self.propagate(A, beta, n, t0, h, n_samples, bound[0], dtype)
        aug = self.op("Concat", A, self.op("Unsqueeze", beta, self.ints([2])), axis=2)
        aug = self.op("Pad", aug, self.ints([0, 0, 0, 0, 1, 0]))  # a zero last row
        batch = self.slice(self.op("Shape", batch_of), 0, 0, 1)
        unit = np.zeros((1, n + 1))
        unit[0, n] = 1.0
        first = self.op("Expand", self.const(unit, dtype, "unit"),
                        self.op("Concat", batch, self.ints([n + 1]), axis=0))
        F = self.propagate(aug, first, n + 1, t0, h, n_samples, bound[0] + bound[1], dtype)
        return self.slice(F, 1, 0, n)

    # ------------------------------------------------------------------ the model
    def model(self, inputs: list[Any], outputs: list[Any], *, name: str, doc: str,
              metadata: dict[str, str], opset: int) -> Any:
        """The ``onnx.ModelProto`` of the graph (checked by ``onnx.checker``)."""
        import onnx
        from onnx import helper

        graph = helper.make_graph(self.nodes, name, inputs, outputs, self.initializers,
                                  doc_string=doc)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)],
                                  producer_name="kautztwin", ir_version=8)
        helper.set_model_props(model, metadata)
        onnx.checker.check_model(model)
        return model
