"""The assets of a fleet: their configurations, seeded signals and one-off setup jobs.

Every asset of a fleet runs the :class:`~kautztwin.twin.runtime.TwinConfig`
of the fleet with its own ``seed`` (its excitation and dither).  The
excitation signals are drawn here with the runtime's own
:func:`~kautztwin.twin.runtime.excitation.excitation` and kept as ``int8``
signs (a binary signal is ``+-amplitude``).  The one-off jobs of an asset,
which run in a worker pool, are plain functions of picklable arguments:
:func:`identify_job` (the initial identification) and :func:`controller_job`
(the weight tuning of the first version and the controller built on a model
version from the command history, returned as arrays).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...approx.model import KautzModel
from ...exceptions import DataError
from ..optimization import Optimizer
from ..prediction import MPCSettings
from ..prediction.controller import _prepare_controller
from ..runtime import TwinConfig
from ..runtime.excitation import excitation
from ..runtime.twins import identify_initial
from ..update import OutputErrorFit
from .mpc_batch import QPBatch, extract_qp

__all__ = ["ControllerBuild", "FleetSignals", "asset_config", "config_state", "controller_job",
           "identify_job", "pack_fit", "reid_job", "unpack_fit"]


def asset_config(config: TwinConfig, seed: int) -> TwinConfig:
    """The configuration of one asset: the fleet's with the asset's seed.

    Parameters
    ----------
    config : TwinConfig
    seed : int

    Returns
    -------
    TwinConfig
    """
    return replace(config, seed=int(seed))


@dataclass(frozen=True, eq=False)
class FleetSignals:
    """The seeded identification input and dither of every asset, one bit per sample.

    A binary signal is ``+-amplitude``: the bits (1 for ``+``) are packed
    eight samples to a byte (:func:`numpy.packbits`).

    Parameters
    ----------
    ident_bits : ndarray of uint8 of shape (n_assets, ceil(n_ident / 8))
    dither_bits : ndarray of uint8 of shape (n_assets, ceil(n_samples / 8))
    ident_level, ident_amplitude, dither : float
    n_samples : int
    """

    ident_bits: NDArray[np.uint8]
    dither_bits: NDArray[np.uint8]
    ident_level: float
    ident_amplitude: float
    dither: float
    n_samples: int

    @classmethod
    def draw(cls, config: TwinConfig, seeds: NDArray[np.int64]) -> FleetSignals:
        """Draw every asset's signals with the runtime's generator and its seed.

        Parameters
        ----------
        config : TwinConfig
        seeds : ndarray of int

        Returns
        -------
        FleetSignals
        """
        n_id, n = config.n_ident, config.n_samples
        ident = np.zeros((seeds.size, n_id), dtype=bool)
        dith = np.zeros((seeds.size, n), dtype=bool)
        for i, s in enumerate(seeds.tolist()):
            u_id, d = excitation(asset_config(config, s))
            ident[i] = u_id > config.ident_level
            dith[i] = d > 0
        return cls(np.packbits(ident, axis=1), np.packbits(dith, axis=1), config.ident_level,
                   config.ident_amplitude, config.dither, n)

    @staticmethod
    def _signs(bits: NDArray[np.uint8], k: int) -> NDArray[np.float64]:
        b = (bits[:, k >> 3] >> (7 - (k & 7))) & 1
        return 2.0 * b - 1.0

    def u_ident(self, k: int) -> NDArray[np.float64]:
        """Identification inputs of sample ``k``."""
        if self.ident_amplitude == 0:
            return np.full(self.ident_bits.shape[0], self.ident_level)
        return self.ident_level + self.ident_amplitude * self._signs(self.ident_bits, k)

    def d(self, k: int) -> NDArray[np.float64]:
        """Dither of sample ``k``."""
        if self.dither == 0:
            return np.zeros(self.dither_bits.shape[0])
        return self.dither * self._signs(self.dither_bits, k)

    def dither_history(self, i: int, first: int, n: int) -> NDArray[np.float64]:
        """Asset ``i``'s dither of samples ``first .. n - 1``."""
        if self.dither == 0:
            return np.zeros(n - first)
        bits = np.unpackbits(self.dither_bits[i], count=self.n_samples)[first:n]
        return self.dither * (2.0 * bits - 1.0)


def config_state(config: TwinConfig) -> dict[str, Any]:
    """The fields of a configuration as a picklable dict (for worker processes and Ray).

    Parameters
    ----------
    config : TwinConfig

    Returns
    -------
    dict
        ``TwinConfig(**state)`` rebuilds it.
    """
    state = {name: getattr(config, name) for name in config.__dataclass_fields__}
    state["updater"] = dict(config.updater)
    return state


def pack_fit(fit: OutputErrorFit) -> dict[str, Any]:
    """An identification result as plain data (a model's basis does not pickle).

    Parameters
    ----------
    fit : OutputErrorFit

    Returns
    -------
    dict
        :func:`unpack_fit` rebuilds it (the model through
        :meth:`~kautztwin.KautzModel.to_dict` / ``from_dict``).
    """
    return {name: (fit.model.to_dict() if name == "model" else getattr(fit, name))
            for name in OutputErrorFit.__dataclass_fields__}


def unpack_fit(data: dict[str, Any]) -> OutputErrorFit:
    """The :class:`~kautztwin.twin.update.OutputErrorFit` of :func:`pack_fit`.

    Parameters
    ----------
    data : dict

    Returns
    -------
    OutputErrorFit
    """
    return OutputErrorFit(**{**data, "model": KautzModel.from_dict(data["model"])})


def reid_job(job: Any) -> dict[str, Any] | None:
    """One re-identification fit (the update module's ``_fit_window``), packed for a pool.

    Parameters
    ----------
    job : _ReidJob

    Returns
    -------
    dict or None
        :func:`pack_fit` of the best start.
    """
    from ..update.worker import _fit_window

    out = _fit_window(job)
    return None if out.fit is None else pack_fit(out.fit)


def identify_job(args: tuple[dict[str, Any], NDArray, NDArray]) -> dict[str, Any] | str:
    """The initial identification of one asset (the runtime's), or the error message.

    Parameters
    ----------
    args : (dict, ndarray, ndarray)
        The settings ``n_poles, dt, operating_input, min_rate`` of the
        configuration and the identification samples ``u``, ``y`` (NaN: unusable).

    Returns
    -------
    dict or str
        :func:`pack_fit` of the fit, or the error message.
    """
    settings, u, y = args
    try:
        return pack_fit(identify_initial(SimpleNamespace(**settings), u, y))  # type: ignore[arg-type]
    except Exception as exc:  # noqa: BLE001 - reported per asset by the fleet
        return str(exc)


@dataclass(frozen=True, eq=False)
class ControllerBuild:
    """A controller built for one asset in a worker: settings, QP arrays and filter states.

    Parameters
    ----------
    settings : MPCSettings
    qp : QPBatch
    A, B, c, xv, xv_prev, xd : ndarray
    tuning : dict
        The tuning's payload (empty when none ran).
    """

    settings: MPCSettings
    qp: QPBatch
    A: NDArray[np.float64]
    B: NDArray[np.float64]
    c: NDArray[np.float64]
    xv: NDArray[np.float64]
    xv_prev: NDArray[np.float64]
    xd: NDArray[np.float64]
    tuning: dict[str, Any]


def controller_job(args: tuple[Any, ...]) -> ControllerBuild | str:
    """Tune (first version) and build one asset's controller on a model version.

    Parameters
    ----------
    args : tuple
        ``(model, settings, tune, step, u_op, y_op, v_history, d_history, input_offset)``
        (``model`` as :meth:`~kautztwin.KautzModel.to_dict`):
        with ``tune`` the increment weight is retuned first
        (:meth:`~kautztwin.twin.optimization.Optimizer.tune_controller`, as the
        runtime does for the first version) and the tuned settings are used
        when the tuning is accepted.

    Returns
    -------
    ControllerBuild or str
        The build, or the message of the :class:`~kautztwin.exceptions.DataError`
        that refused it.
    """
    model_data, settings, tune, step, u_op, y_op, v_hist, d_hist, u_offset = args
    model = KautzModel.from_dict(model_data)  # a model's basis does not pickle: sent as data
    payload: dict[str, Any] = {}
    if tune:
        tuning = Optimizer().tune_controller(model, settings, step=step, u_op=u_op, y_op=y_op)
        payload = dict(tuning.payload())
        settings = tuning.settings if tuning.accepted else settings
    try:
        p = _prepare_controller(model, settings, v_hist, d_hist, u_offset)
        qp = extract_qp(p.problem)
    except DataError as exc:
        return str(exc)
    return ControllerBuild(settings, qp, np.array(p.A), np.array(p.B).reshape(-1),
                           np.array(p.c), np.array(p.xv), np.array(p.xv_prev), np.array(p.xd),
                           payload)
