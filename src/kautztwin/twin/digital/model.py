"""The twin's digital model: the current Kautz model with its version and provenance."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..._validation import check_number
from ...approx.model import KautzModel
from ...exceptions import DataError

__all__ = ["DigitalModel"]


@dataclass(frozen=True, eq=False)
class DigitalModel:
    """A versioned :class:`~kautztwin.KautzModel`: what the digital twin runs on.

    The twin never mutates its model.  Every update (a DNN step, a
    re-identification) yields a new ``DigitalModel`` with the next version
    number, so the history store keeps every version and a run can roll back
    or be replayed.

    Parameters
    ----------
    model : KautzModel
        The model: poles (through its basis) and coefficients.
    version : int
        Version number, ``>= 0``; :meth:`initial` starts at 1 and
        :meth:`with_update` adds 1.
    provenance : str
        Where the model came from, for example ``'initial'``, ``'dnn-update'``
        or ``'reidentification'``.
    created : float
        Creation time in seconds since the epoch (``time.time()``).
    fit_percent : float or None, default=None
        Validation fit in percent (100 is a perfect fit), if one was measured.

    Raises
    ------
    DataError
        If ``model`` is not a :class:`~kautztwin.KautzModel`, ``version`` is not
        a non-negative integer, ``provenance`` is empty, or ``created`` or
        ``fit_percent`` is not finite.

    See Also
    --------
    kautztwin.KautzModel : The immutable model wrapped here.
    kautztwin.twin.HistoryStore : Stores every version of a run.

    Examples
    --------
    >>> import kautztwin as kt
    >>> from kautztwin.twin import DigitalModel
    >>> m0 = kt.KautzModel(kt.KautzBasis([-1.0, -2.0]), [1.0, 0.5])
    >>> dm = DigitalModel.initial(m0, created=0.0)
    >>> dm.version, dm.provenance
    (1, 'initial')
    >>> dm2 = dm.with_update(m0.with_coefficients([0.9, 0.6]), "dnn-update", 97.5)
    >>> dm2.version, dm2.provenance, dm2.fit_percent
    (2, 'dnn-update', 97.5)
    >>> DigitalModel.from_dict(dm2.to_dict()).allclose(dm2)
    True
    """

    model: KautzModel
    version: int
    provenance: str
    created: float
    fit_percent: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.model, KautzModel):
            raise DataError(f"model must be a KautzModel, got {type(self.model).__name__}")
        if isinstance(self.version, bool) or not isinstance(self.version, int | np.integer):
            raise DataError(f"version must be an integer, got {self.version!r}")
        if self.version < 0:
            raise DataError(f"version must be >= 0, got {self.version}")
        object.__setattr__(self, "version", int(self.version))
        if not isinstance(self.provenance, str) or not self.provenance.strip():
            raise DataError(f"provenance must be a non-empty string, got {self.provenance!r}")
        created = check_number(self.created, "created")
        object.__setattr__(self, "created", created)
        if self.fit_percent is not None:
            object.__setattr__(self, "fit_percent", check_number(self.fit_percent, "fit_percent"))

    @classmethod
    def initial(
        cls,
        model: KautzModel,
        *,
        provenance: str = "initial",
        fit_percent: float | None = None,
        created: float | None = None,
    ) -> DigitalModel:
        """Version 1 of a run's model.

        Parameters
        ----------
        model : KautzModel
            The initial model.
        provenance : str, default='initial'
            Where the model came from.
        fit_percent : float or None, default=None
            Validation fit in percent, if known.
        created : float or None, default=None
            Creation time; ``None`` means now (``time.time()``).

        Returns
        -------
        DigitalModel
        """
        return cls(model, 1, provenance, time.time() if created is None else created, fit_percent)

    def with_update(
        self,
        new_model: KautzModel,
        provenance: str,
        fit_percent: float | None = None,
        *,
        created: float | None = None,
    ) -> DigitalModel:
        """The next version: ``new_model`` with ``version + 1``.

        Parameters
        ----------
        new_model : KautzModel
            The updated model.
        provenance : str
            What produced it, for example ``'dnn-update'`` or ``'reidentification'``.
        fit_percent : float or None, default=None
            Validation fit of ``new_model`` in percent, if measured.
        created : float or None, default=None
            Creation time; ``None`` means now (``time.time()``).

        Returns
        -------
        DigitalModel
            A new object; ``self`` is unchanged.
        """
        return DigitalModel(
            new_model,
            self.version + 1,
            provenance,
            time.time() if created is None else created,
            fit_percent,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description: the model dict plus version metadata.

        Returns
        -------
        dict
            Keys ``model`` (:meth:`KautzModel.to_dict`), ``version``,
            ``provenance``, ``created`` and ``fit_percent``.
        """
        return {
            "model": self.model.to_dict(),
            "version": self.version,
            "provenance": self.provenance,
            "created": self.created,
            "fit_percent": self.fit_percent,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DigitalModel:
        """Rebuild a digital model written by :meth:`to_dict`.

        Parameters
        ----------
        data : dict
            Output of :meth:`to_dict` (possibly through JSON).

        Returns
        -------
        DigitalModel

        Raises
        ------
        DataError
            If a key is missing or a value is invalid.
        """
        try:
            model = KautzModel.from_dict(data["model"])
            return cls(
                model,
                data["version"],
                data["provenance"],
                data["created"],
                data.get("fit_percent"),
            )
        except KeyError as exc:
            raise DataError(f"digital model dict lacks the key {exc.args[0]!r}") from exc

    def allclose(self, other: DigitalModel, rtol: float = 1e-10, atol: float = 1e-12) -> bool:
        """Whether ``other`` has the same metadata and (nearly) the same model.

        Parameters
        ----------
        other : DigitalModel
            The model to compare with.
        rtol, atol : float
            Tolerances passed to :meth:`KautzModel.allclose`.

        Returns
        -------
        bool
        """
        return (
            isinstance(other, DigitalModel)
            and self.version == other.version
            and self.provenance == other.provenance
            and self.created == other.created
            and self.fit_percent == other.fit_percent
            and self.model.allclose(other.model, rtol=rtol, atol=atol)
        )

