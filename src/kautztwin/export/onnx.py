"""ONNX export of the trained estimators (coefficient networks and adaptive-pole estimator).

The graph is written operator by operator with ``onnx.helper`` from the estimator's
weights (:mod:`kautztwin.export._onnx_graph`), not traced by an exporter: it needs only
the ``onnx`` package, and the parts ONNX lacks (matrix exponential, linear solve) are
unrolled for the estimator's fixed sizes.  Every graph takes the raw records and does what
``predict`` does, standardisation included:

========================  ==========================================  ====================
estimator                 inputs -> outputs (``float64``)             as torch
========================  ==========================================  ====================
``CoefficientEstimator``  ``responses (b, n_samples)`` ->             ``predict``
                          ``coefficients (b, N)``
``AdaptivePoleEstimator`` ``responses (b, n_samples)`` ->             ``predict(...,
                          ``poles_real``, ``poles_imag`` (b, N),      refine=False)``
                          ``coefficients (b, N)``,
                          ``block_parameters (b, N)``
========================  ==========================================  ====================

The coefficient networks run in ``float32`` as in torch; the adaptive estimator's graph runs
in ``float64`` by default (:func:`export_onnx` says why), its final least squares in
``float64`` as in torch.  The variable
projection refinement (``refine=True``) is an iterative optimisation per record and is
not part of the graph.  The model's metadata (``metadata_props``) name the estimator, its
time grid, kind and basis.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import DataError, KautzTwinError
from ._onnx_graph import Graph, KautzLayout

__all__ = ["ONNX_OPSET", "export_onnx", "load_estimator_file"]

#: the ONNX operator set of the exported graphs (onnxruntime >= 1.13 runs it)
ONNX_OPSET = 17

_FORMATS = {
    "kautztwin.CoefficientEstimator": "CoefficientEstimator",
    "kautztwin.AdaptivePoleEstimator": "AdaptivePoleEstimator",
}


def _require_onnx() -> None:
    try:
        import onnx  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "ONNX export needs the onnx package: pip install 'kautztwin[export]'"
        ) from exc


def load_estimator_file(directory: str | Path) -> Any:
    """Load the trained estimator in a model folder (either kind), verified.

    Parameters
    ----------
    directory : str or path-like
        A folder written by ``save`` of an estimator (``kautztwin train`` writes
        ``OUT/model``).

    Returns
    -------
    CoefficientEstimator or AdaptivePoleEstimator

    Raises
    ------
    DataError
        If the folder or its ``metadata.json`` is missing or unreadable, names no
        estimator kautztwin knows, or fails the estimator's checks (checksums).
    """
    path = Path(directory)
    meta_path = path / "metadata.json"
    if not path.is_dir():
        raise DataError(f"model folder {str(path)!r} does not exist")
    if not meta_path.is_file():
        raise DataError(f"{str(path)!r} is not a model folder: no metadata.json")
    try:
        fmt = json.loads(meta_path.read_text(encoding="utf-8")).get("format")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError) as exc:
        msg = " ".join(str(exc).split())
        raise DataError(f"cannot read model file {str(meta_path)!r}: {msg}") from None
    if fmt not in _FORMATS:
        raise DataError(
            f"{str(meta_path)!r} is not a kautztwin estimator (format {fmt!r}); ONNX export "
            "takes the model folder of a CoefficientEstimator or AdaptivePoleEstimator"
        )
    from .. import nn

    return getattr(nn, _FORMATS[fmt]).load(path)


def _uniform_grid(t: np.ndarray) -> tuple[float, float]:
    from ..basis._propagate import uniform_step

    h = uniform_step(np.asarray(t, dtype=float))
    if h is None or t[0] < 0:
        raise DataError(
            "ONNX export of the adaptive estimator needs a uniform time grid starting at "
            "t >= 0 (the basis is built by a fixed recursion); this estimator's grid is not"
        )
    return float(t[0]), float(h)


def _grid_meta(t: np.ndarray) -> dict[str, str]:
    return {"t0": repr(float(t[0])), "t_end": repr(float(t[-1])), "n_samples": str(t.size)}


def _coefficient_graph(
    est: Any, dtype: np.dtype
) -> tuple[Graph, list[Any], list[Any], dict[str, str]]:
    from onnx import TensorProto, helper

    g = Graph(dtype)
    f64 = np.float64
    x = "responses"
    z = g.op("Div", g.op("Sub", x, g.const(est.input_scaler_.mean, f64, "in_mean")),
             g.const(est.input_scaler_.scale, f64, "in_scale"))
    if dtype == np.float32:
        z = g.op("Cast", z, to=TensorProto.FLOAT)
    parts = []
    for net in est.networks_:
        s = None
        for branch in net.branches:
            hcur = z
            layers = list(branch)
            for lin, act in zip(layers[0::2], layers[1::2], strict=True):
                hcur = g.linear(hcur, _array(lin.weight), _array(lin.bias), dtype)
                hcur = g.op("PRelu", hcur, g.const(_array(act.weight), dtype, "slope"))
            s = hcur if s is None else g.op("Add", s, hcur)
        merged = g.op("Add", g.op("Softmax", s, axis=-1), s)
        parts.append(g.linear(merged, _array(net.head.weight), _array(net.head.bias), dtype))
    out = parts[0] if len(parts) == 1 else g.op("Concat", *parts, axis=1)
    if dtype == np.float32:
        out = g.op("Cast", out, to=TensorProto.DOUBLE)
    out = g.op("Add", g.op("Mul", out, g.const(est.label_scaler_.scale, f64, "lab_scale")),
               g.const(est.label_scaler_.mean, f64, "lab_mean"))
    g.rename(out, "coefficients")
    n = est.n_functions_
    inputs = [helper.make_tensor_value_info(x, TensorProto.DOUBLE, ["batch", est.n_samples_])]
    outputs = [helper.make_tensor_value_info("coefficients", TensorProto.DOUBLE, ["batch", n])]
    meta = {
        "basis_poles": json.dumps([[p.real, p.imag] for p in est.basis_.poles]),
        "basis_dt": repr(float(est.basis_.dt)),
    }
    return g, inputs, outputs, meta


def _array(tensor: Any) -> np.ndarray:
    """A torch tensor's values as a float64 array (cast to the graph's dtype later)."""
    return tensor.detach().cpu().double().numpy()


def _stage(g: Graph, stage: Any, inp: str, dtype: Any) -> str:
    h = g.op("Div", g.op("Sub", inp, g.const(_array(stage.mean), dtype, "mean")),
             g.const(_array(stage.scale), dtype, "scale"))
    layers = list(stage.body)
    for layer in layers:
        if layer.__class__.__name__ == "Linear":
            h = g.linear(h, _array(layer.weight), _array(layer.bias), dtype)
        else:
            h = g.silu(h)
    return h


def _adaptive_graph(
    est: Any, dtype: np.dtype
) -> tuple[Graph, list[Any], list[Any], dict[str, str]]:
    import torch
    from onnx import TensorProto, helper

    from ..nn.adaptive.inference import weights_tensor

    net = est.network_
    onnx_type = TensorProto.FLOAT if dtype == np.float32 else TensorProto.DOUBLE
    g = Graph(dtype)
    layout = KautzLayout(net.kinds)
    t = np.asarray(est.t_, dtype=float)
    t0, h = _uniform_grid(t)
    n, n_samples = layout.n, t.size
    log_centre = net.log_centre.detach().double().numpy()
    rho = math.log(net.pole_range)
    # every parameter the network can produce lies within pole_range of the centre, so the
    # entries of |A| and |B| are bounded by those at the largest parameters (all monotone)
    A_max, beta_max = layout.matrices(np.exp(log_centre + rho))
    bound = (float(np.abs(A_max).sum(axis=0).max()) * (1 + 1e-6),
             float(np.max(beta_max)) * (1 + 1e-6))

    x64 = "responses"
    x = g.op("Cast", x64, to=onnx_type) if dtype == np.float32 else x64
    P = g.const(_array(net.projector), dtype, "projector")
    z0 = g.op("MatMul", x, P)
    norm = g.op("Sqrt", g.op("ReduceSumSquare", z0, axes=[1], keepdims=1))
    norm = g.op("Max", norm, g.const(np.finfo(dtype).tiny, dtype))
    z = g.op("Div", z0, norm)
    centre = g.const(log_centre, dtype, "log_centre")
    lp = g.op("Add", centre, g.op("Mul", g.const(rho, dtype),
                                  g.op("Tanh", _stage(g, net.stages[0], z, dtype))))
    w_net = net.ls_weights()
    w_net = None if w_net is None else _array(w_net)
    lo, hi = g.const(log_centre - rho, dtype, "lo"), g.const(log_centre + rho, dtype, "hi")
    r_stages, r_fit = int(net.relative_degree), int(est.relative_degree_)

    def constraints(params: str, arithmetic: Any, r: int) -> tuple[str, int] | None:
        if r <= 1:
            return None
        return g.relative_degree_constraints(layout, params, r, arithmetic), r - 1

    for k in range(1, net.n_stages):
        stage_params = g.op("Exp", lp)
        K = g.design(layout, stage_params, x, net.kind, t0, h, n_samples, bound, dtype)
        c = g.lstsq(K, x, w_net, n, dtype, constraints=constraints(stage_params, dtype, r_stages))
        residual = g.op("Div", g.op("MatMul", g.op("Sub", x, g.combine(c, K)), P), norm)
        inp = g.op("Concat", z, residual, g.op("Sub", lp, centre), g.op("Div", c, norm), axis=1)
        step = g.op("Mul", g.const(net.step, dtype),
                    g.op("Tanh", _stage(g, net.stages[k], inp, dtype)))
        lp = g.op("Min", g.op("Max", g.op("Add", lp, step), lo), hi)
    params = g.op("Exp", lp)
    if dtype == np.float32:
        params = g.op("Cast", params, to=TensorProto.DOUBLE)
    f64 = np.float64
    w = weights_tensor(t, est.weights, torch.float64)
    K64 = g.design(layout, params, x64, net.kind, t0, h, n_samples, bound, f64)
    coef = g.lstsq(K64, x64, None if w is None else w.numpy(), n, f64,
                   constraints=constraints(params, f64, r_fit))
    g.rename(params, "block_parameters")
    g.rename(g.op("MatMul", params, g.const(layout.pole_re, f64, "Mre")), "poles_real")
    g.rename(g.op("MatMul", params, g.const(layout.pole_im, f64, "Mim")), "poles_imag")
    g.rename(coef, "coefficients")
    D = TensorProto.DOUBLE
    inputs = [helper.make_tensor_value_info(x64, D, ["batch", n_samples])]
    outputs = [helper.make_tensor_value_info(name, D, ["batch", n])
               for name in ("poles_real", "poles_imag", "coefficients", "block_parameters")]
    meta = {
        "block_kinds": json.dumps(list(net.kinds)),
        "centre_poles": json.dumps([[p.real, p.imag] for p in est.centre_poles_]),
        "refine": "false (the variable-projection refinement is not part of the graph)",
        "relative_degree": str(r_fit),
    }
    return g, inputs, outputs, meta


def export_onnx(
    estimator: Any, path: str | Path, *, dtype: str = "auto", opset: int = ONNX_OPSET
) -> Path:
    """Write a trained estimator as an ONNX model that runs without torch.

    Parameters
    ----------
    estimator : CoefficientEstimator or AdaptivePoleEstimator
        A fitted estimator (or a model folder, read by :func:`load_estimator_file`).
    path : str or path-like
        The ``.onnx`` file to write (its folder must exist).
    dtype : {'auto', 'float32', 'float64'}, default='auto'
        Arithmetic of the networks inside the graph.  ``'auto'``: ``float32`` for the
        coefficient networks (torch's own arithmetic: the graph matches ``predict`` to
        rounding), ``float64`` for the adaptive estimator (see Notes).
    opset : int, default=17
        ONNX operator set version (17 or later).

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    DataError
        On an unfitted or unsupported estimator, an adaptive estimator on a
        non-uniform grid, or a missing output folder.

    See Also
    --------
    kautztwin.export.export_fmu : FMUs of identified linear and Kautz models.

    Notes
    -----
    Inputs and outputs are ``float64`` with a free batch axis (module docstring).
    For the adaptive estimator the number of squarings of every matrix exponential is
    fixed from the largest poles the network can produce (``pole_range`` times the
    centre), so the graph is exact to rounding for every record.

    The adaptive estimator's correction stages read the residual of a least-squares
    fit, a small difference of large numbers; in ``float32`` its rounding reaches the
    predicted poles at about ``1e-5`` relative (torch's own ``float32`` and ``float64``
    evaluations of the same trained network differ by that much).  No other
    implementation can follow torch's ``float32`` rounding, so the adaptive graph
    computes in ``float64`` by default: it then equals torch's ``float64`` evaluation
    of the trained weights to about ``1e-12``, and differs from the ``float32``
    ``predict`` only by the latter's own rounding.
    """
    _require_onnx()
    import onnx

    from ..nn import AdaptivePoleEstimator, CoefficientEstimator

    if isinstance(estimator, (str, Path)):
        estimator = load_estimator_file(estimator)
    path = Path(path)
    if not path.parent.is_dir():
        raise DataError(f"folder {str(path.parent)!r} of {str(path)!r} does not exist")
    if dtype not in ("auto", "float32", "float64"):
        raise DataError(f"dtype must be 'auto', 'float32' or 'float64'; got {dtype!r}")
    if isinstance(estimator, CoefficientEstimator):
        build = _coefficient_graph
        auto = "float32"
    elif isinstance(estimator, AdaptivePoleEstimator):
        build = _adaptive_graph
        auto = "float64"
    else:
        raise DataError(
            "ONNX export takes a CoefficientEstimator or an AdaptivePoleEstimator; got "
            f"{type(estimator).__name__} (linear and Kautz models go to FMUs: export_fmu)"
        )
    try:
        estimator._check_is_fitted()
    except KautzTwinError as exc:
        raise DataError(str(exc)) from None
    from .. import __version__

    arithmetic = np.dtype(auto if dtype == "auto" else dtype)
    g, inputs, outputs, meta = build(estimator, arithmetic)
    name = type(estimator).__name__
    metadata = {
        "format": f"kautztwin.{name}.onnx",
        "kautztwin_version": __version__,
        "estimator": name,
        "dtype": arithmetic.name,
        "kind": str(estimator.kind_),
        **_grid_meta(np.asarray(estimator.t_)),
        **meta,
    }
    doc = (f"kautztwin {name}: records on a grid of {estimator.n_samples_} samples from "
           f"t = {float(estimator.t_[0]):g} to {float(estimator.t_[-1]):g} s ({estimator.kind_} "
           "responses) -> Kautz model")
    model = g.model(inputs, outputs, name=name, doc=doc, metadata=metadata, opset=int(opset))
    onnx.save_model(model, str(path))
    return path
