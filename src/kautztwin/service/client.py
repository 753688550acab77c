"""A thin Python client of the twin's HTTP API (:mod:`kautztwin.service.api`), over httpx.

For scripts and notebooks: :class:`TwinClient` reads the state, the model
versions (as :class:`~kautztwin.twin.DigitalModel`), the history as numpy arrays
(paged for you), and asks what-ifs, set-points and re-identifications.  An
answer other than 2xx raises :class:`ApiClientError` with the server's
one-line message.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..exceptions import KautzTwinError

__all__ = ["ApiClientError", "TwinClient"]


class ApiClientError(KautzTwinError):
    """The API answered with an error.

    Parameters
    ----------
    status : int
        The HTTP status.
    message : str
        The server's message.
    """

    def __init__(self, status: int, message: str) -> None:
        super().__init__(f"HTTP {status}: {message}")
        self.status = int(status)


class TwinClient:
    """Client of a running ``twin serve --http`` service.

    Parameters
    ----------
    url : str
        ``http://HOST:PORT`` of the service.
    token : str, optional
        The API token (writes, what-ifs).
    timeout : float, default=30
        Seconds per request.
    transport : httpx.BaseTransport, optional
        For tests (an in-process app).

    Examples
    --------
    >>> from kautztwin.service.client import TwinClient
    >>> with TwinClient("http://127.0.0.1:8000", token="...") as twin:  # doctest: +SKIP
    ...     twin.state()["y"], twin.history(signals="t,y,prediction", start=10)["y"][:3]
    ...     twin.set_setpoint(101.5)
    ...     twin.what_if(setpoint=98.0, steps=400)["y"][-1]
    """

    def __init__(self, url: str, token: str | None = None, *, timeout: float = 30.0,
                 transport: Any = None) -> None:
        import httpx

        headers = {"Authorization": f"Bearer {token}"} if token else {}
        kwargs: dict[str, Any] = {"base_url": url.rstrip("/"), "headers": headers,
                                  "timeout": timeout}
        if transport is not None:
            kwargs["transport"] = transport
        self._http = httpx.Client(**kwargs)

    def _get(self, path: str, **params: Any) -> Any:
        return self._check(self._http.get(path, params={k: v for k, v in params.items()
                                                        if v is not None}))

    def _post(self, path: str, body: dict[str, Any]) -> Any:
        return self._check(self._http.post(path, json=body))

    @staticmethod
    def _check(r: Any) -> Any:
        if r.status_code >= 400:
            try:
                message = r.json().get("message") or r.text
            except ValueError:
                message = r.text
            raise ApiClientError(r.status_code, message)
        return r.json() if r.headers.get("content-type", "").startswith(
            "application/json") else r.text

    # ------------------------------------------------------------------ reads
    def health(self) -> dict[str, Any]:
        """``GET /health``.

        Returns
        -------
        dict
        """
        return self._get("/health")

    def state(self) -> dict[str, Any]:
        """``GET /state``: the latest sample, fit, model version, link.

        Returns
        -------
        dict
        """
        return self._get("/state")

    def models(self) -> list[dict[str, Any]]:
        """``GET /models``: every model version with provenance and fit.

        Returns
        -------
        list of dict
        """
        return self._get("/models")

    def model(self, version: int) -> Any:
        """One stored model version as a :class:`~kautztwin.twin.DigitalModel`.

        Parameters
        ----------
        version : int

        Returns
        -------
        DigitalModel
        """
        from ..twin.digital import DigitalModel

        return DigitalModel.from_dict(self._get(f"/models/{int(version)}", format="file"))

    def history(self, signals: str = "k,t,u,y,flags", start: float | None = None,
                end: float | None = None, page: int = 10_000) -> dict[str, NDArray[Any]]:
        """``GET /history``, every page: the stored samples as numpy arrays.

        Parameters
        ----------
        signals : str, default='k,t,u,y,flags'
            Comma-separated, among ``k, t, u, y, flags, prediction`` (the twin's
            one-step prediction of each sample) and ``setpoint`` (the set-point in
            force).
        start, end : float, optional
            Time window, plant seconds.
        page : int, default=10000
            Samples per request.

        Returns
        -------
        dict of ndarray
            One array per signal: ``k`` and ``flags`` int64, the others float (NaN for
            a missing number: no prediction or set-point in the identification phase).

        Raises
        ------
        ApiClientError
            An unknown signal, a bad window (422, naming the field).
        """
        names = [s.strip() for s in signals.split(",") if s.strip()]
        cols: dict[str, list[Any]] = {s: [] for s in names}
        after = -1
        while True:
            r = self._get("/history", signals=signals, start=start, end=end, limit=page,
                          after=after)
            for s in names:
                cols[s].extend(r["signals"][s])
            if r["next"] is None:
                break
            after = r["next"]
        return {s: (np.asarray(v, dtype=np.int64) if s in ("k", "flags") else
                    np.array([np.nan if x is None else x for x in v], dtype=float))
                for s, v in cols.items()}

    def events(self, kind: str | None = None) -> list[dict[str, Any]]:
        """``GET /events``, every page.

        Parameters
        ----------
        kind : str, optional
            Only this kind.

        Returns
        -------
        list of dict
        """
        out: list[dict[str, Any]] = []
        after = 0
        while True:
            r = self._get("/events", kind=kind, after=after, limit=10_000)
            out.extend(r["events"])
            if r["next"] is None:
                return out
            after = r["next"]

    # ------------------------------------------------------------------ predictions, writes
    def what_if(self, u: ArrayLike | None = None, *, setpoint: float | None = None,
                steps: int = 200) -> dict[str, Any]:
        """``POST /whatif``: the current model's response from the current state.

        Parameters
        ----------
        u : array-like, optional
            Planned inputs of the next samples.
        setpoint : float, optional
            Or a set-point step (the steady input for it, held ``steps`` samples).
        steps : int, default=200

        Returns
        -------
        dict
            ``t``, ``u``, ``y``, ``lower``, ``upper`` as numpy arrays (the band
            ``None`` when unknown), and the rest of the answer.
        """
        body: dict[str, Any] = ({"u": np.asarray(u, dtype=float).tolist()} if u is not None
                                else {"setpoint": setpoint, "steps": steps})
        r = self._post("/whatif", body)
        for key in ("t", "u", "y", "lower", "upper"):
            if r.get(key) is not None:
                r[key] = np.array([np.nan if x is None else x for x in r[key]], dtype=float)
        return r

    def set_setpoint(self, value: float) -> dict[str, Any]:
        """``POST /setpoint``: hold ``value`` from the next sample on.

        Parameters
        ----------
        value : float

        Returns
        -------
        dict
        """
        return self._post("/setpoint", {"value": float(value)})

    def reidentify(self, reason: str = "") -> dict[str, Any]:
        """``POST /reidentify``: schedule a re-identification attempt.

        Parameters
        ----------
        reason : str, optional

        Returns
        -------
        dict
        """
        return self._post("/reidentify", {"reason": reason})

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def __enter__(self) -> TwinClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
