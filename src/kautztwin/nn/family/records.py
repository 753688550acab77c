"""Records of a plant family: parameter draws (uniform or normal), noise colours, data sets.

Uniform draws are :func:`~kautztwin.datasets.draw_parameters`; white and AR(1) noise are
:func:`~kautztwin.datasets.make_dataset`'s own.  What is new here: truncated normal draws
and the drift colour (a random walk added on top of the white noise).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from ..._validation import check_int, check_nonnegative
from ...basis import KautzBasis
from ...datasets import ParametricSystem, ResponseDataset, draw_parameters, make_dataset
from ...exceptions import DataError
from .spec import PlantFamily

__all__ = ["draw_family_parameters", "drift_noise", "family_dataset"]

_MAX_TRIES = 100


def draw_family_parameters(
    system: ParametricSystem,
    tolerance: Mapping[str, float],
    n: int,
    rng: np.random.Generator,
    distribution: str = "uniform",
) -> NDArray[np.float64]:
    r"""Parameter vectors of a family, unstable draws redrawn.

    ``uniform``: :func:`~kautztwin.datasets.draw_parameters` (each parameter uniform in
    :math:`\theta^0_j (1 \pm u_j)`).  ``normal``: :math:`\theta^0_j (1 + u_j \varepsilon)`,
    :math:`\varepsilon \sim N(0, 1)`, truncated to stable systems by redrawing.

    Parameters
    ----------
    system : ParametricSystem
    tolerance : mapping of str to float
        Relative tolerance per parameter name (missing names: 0).
    n : int
        Number of vectors, ``>= 1``.
    rng : numpy.random.Generator
    distribution : {'uniform', 'normal'}, default='uniform'

    Returns
    -------
    ndarray of shape (n, n_parameters)

    Raises
    ------
    DataError
        On an unknown distribution or name, or vectors still unstable after 100 draws.
    """
    if distribution == "uniform":
        return draw_parameters(system, dict(tolerance), n, random_state=rng)
    if distribution != "normal":
        raise DataError(f"distribution must be 'uniform' or 'normal', got {distribution!r}")
    n = check_int(n, "n", minimum=1)
    unknown = sorted(set(tolerance) - set(system.parameter_names))
    if unknown:
        raise DataError(f"unknown parameter name(s) {unknown} for {system.name!r}")
    u = np.array([check_nonnegative(tolerance.get(k, 0.0), f"tolerance[{k!r}]")
                  for k in system.parameter_names])
    nominal = np.asarray(system.nominal, dtype=float)

    def draw(m: int) -> NDArray[np.float64]:
        return nominal * (1.0 + u * rng.standard_normal((m, nominal.size)))

    P = draw(n)
    bad = np.flatnonzero(~system.is_stable(P))
    tries = 1
    while bad.size and tries < _MAX_TRIES:
        P[bad] = draw(bad.size)
        bad = bad[~system.is_stable(P[bad])]
        tries += 1
    if bad.size:
        raise DataError(
            f"{bad.size} of {n} normal draws of {system.name!r} were still unstable after "
            f"{_MAX_TRIES} tries; reduce the tolerances"
        )
    return P


def drift_noise(n_records: int, n_samples: int, rng: np.random.Generator) -> NDArray[np.float64]:
    r"""Unit drift: Gaussian random walks from 0 with standard deviation 1 at the last sample.

    :math:`d_0 = 0`, :math:`d_k = d_{k-1} + w_k / \sqrt{n - 1}`, :math:`w_k \sim N(0, 1)`,
    so :math:`\operatorname{var} d_k = k / (n - 1)`.

    Parameters
    ----------
    n_records, n_samples : int
    rng : numpy.random.Generator

    Returns
    -------
    ndarray of shape (n_records, n_samples)

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.nn.family import drift_noise
    >>> d = drift_noise(4000, 101, np.random.default_rng(0))
    >>> float(d[:, 0].max()), round(float(d[:, -1].std()), 1)
    (0.0, 1.0)
    """
    n_samples = check_int(n_samples, "n_samples", minimum=2)
    w = rng.standard_normal((check_int(n_records, "n_records", minimum=1), n_samples - 1))
    d = np.zeros((n_records, n_samples))
    d[:, 1:] = np.cumsum(w, axis=1) / np.sqrt(n_samples - 1)
    return d


def family_dataset(family: PlantFamily, n: int, seed: int) -> ResponseDataset:
    """Noisy records of a family with their truth, labelled in the nominal Kautz basis.

    Parameters
    ----------
    family : PlantFamily
    n : int
        Number of records.
    seed : int
        Seed of the parameter draws and of the noise (independent streams).

    Returns
    -------
    ResponseDataset
        ``noise_kind`` is ``'colored'`` for AR(1) noise and ``'white'`` otherwise (the
        drift is in ``responses`` but not in the data set's noise fields; the family
        describes it).
    """
    ss = np.random.SeedSequence([int(seed), 7])
    draw_rng, noise_rng, drift_rng = (np.random.default_rng(s) for s in ss.spawn(3))
    P = draw_family_parameters(family.system, family.tolerance, n, draw_rng, family.distribution)
    data = make_dataset(
        family.system,
        P,
        KautzBasis(family.system.poles()),
        family.t,
        kind=family.kind,
        noise=family.noise,
        noise_kind="colored" if family.color == "ar1" else "white",
        color_pole=family.ar1_pole,
        random_state=noise_rng,
    )
    if family.color == "drift" and family.drift > 0:
        peak = np.max(np.abs(data.clean), axis=1, keepdims=True)
        drift = family.drift * peak * drift_noise(len(data), data.n_samples, drift_rng)
        data = dataclasses.replace(data, responses=data.responses + drift)
    return data
