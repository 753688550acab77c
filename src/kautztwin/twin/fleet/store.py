"""One history store for a whole fleet: SQLite (WAL), the asset id in every row, batched commits.

:class:`FleetStore` keeps the samples, model versions and events of every
asset of a fleet run in one SQLite database in write-ahead-log mode.  The
samples of one fleet step are queued as one array block; :meth:`commit`
writes all queued blocks with one ``executemany`` in one transaction, so a
commit costs one fsync however many assets there are.  Each sample row is
keyed by ``(run_id, asset, k)``: a row is stored exactly once (a repeated
key is an error, not a silent duplicate).  It sits beside the single-twin
store (:mod:`kautztwin.twin.history`), whose schema has no asset column.
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._json import to_jsonable
from ..digital import DigitalModel

__all__ = ["FleetStore"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS fleet_runs (
    run_id INTEGER PRIMARY KEY AUTOINCREMENT, config TEXT NOT NULL, status TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS fleet_samples (
    run_id INTEGER NOT NULL, asset INTEGER NOT NULL, k INTEGER NOT NULL, t REAL NOT NULL,
    u REAL, y REAL, y_pred REAL, flags INTEGER NOT NULL, PRIMARY KEY (run_id, asset, k))
    WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS fleet_versions (
    run_id INTEGER NOT NULL, asset INTEGER NOT NULL, version INTEGER NOT NULL,
    k INTEGER NOT NULL, provenance TEXT, fit_percent REAL, model TEXT,
    PRIMARY KEY (run_id, asset, version));
CREATE TABLE IF NOT EXISTS fleet_setpoints (
    run_id INTEGER NOT NULL, asset INTEGER NOT NULL, k_from INTEGER NOT NULL, t REAL NOT NULL,
    value REAL NOT NULL);
CREATE TABLE IF NOT EXISTS fleet_events (
    run_id INTEGER NOT NULL, asset INTEGER NOT NULL, k INTEGER NOT NULL, kind TEXT NOT NULL,
    message TEXT NOT NULL);
"""


def _nan_none(a: NDArray[np.float64]) -> list[float | None]:
    return [None if not math.isfinite(v) else v for v in a.tolist()]


class FleetStore:
    """SQLite history of a fleet: samples, model versions and events per asset.

    Parameters
    ----------
    path : str or os.PathLike, default=':memory:'
        Database file (created when missing).

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.fleet import FleetStore
    >>> store = FleetStore()
    >>> run = store.start_run({"n_assets": 2})
    >>> store.add_samples(run, 0, 0.0, np.zeros(2), np.ones(2), np.ones(2), np.zeros(2, int))
    >>> store.commit()
    >>> store.n_samples(run), store.samples(run, asset=1)["y"].tolist()
    (2, [1.0])
    """

    def __init__(self, path: str | os.PathLike[str] = ":memory:") -> None:
        self.path = str(path)
        self._con = sqlite3.connect(self.path, check_same_thread=False)
        if self.path != ":memory:":
            self._con.execute("PRAGMA journal_mode=WAL")
            self._con.execute("PRAGMA synchronous=NORMAL")
        self._con.executescript(_SCHEMA)
        self._pending: list[tuple[int, int, float, NDArray, NDArray, NDArray, NDArray]] = []
        self.rows_written = 0

    def start_run(self, config: dict[str, Any]) -> int:
        """Open a run and return its id.

        Parameters
        ----------
        config : dict
            Stored as JSON.

        Returns
        -------
        int
        """
        cur = self._con.execute(
            "INSERT INTO fleet_runs (config, status) VALUES (?, 'running')",
            (json.dumps(to_jsonable(config)),))
        self._con.commit()
        return int(cur.lastrowid or 0)

    def find_run(self, config: dict[str, Any]) -> int | None:
        """The latest unfinished run with this configuration (to resume), else ``None``.

        Parameters
        ----------
        config : dict

        Returns
        -------
        int or None
        """
        text = json.dumps(to_jsonable(config))
        row = self._con.execute(
            "SELECT run_id FROM fleet_runs WHERE config = ? AND status = 'running' "
            "ORDER BY run_id DESC LIMIT 1", (text,)).fetchone()
        return None if row is None else int(row[0])

    def committed_steps(self, run_id: int) -> int:
        """Fleet steps committed in full: ``k`` of the first sample not stored for every asset.

        Commits write whole steps (every asset of a sample in one transaction),
        so this is one more than the largest stored ``k``.

        Parameters
        ----------
        run_id : int

        Returns
        -------
        int
        """
        row = self._con.execute(
            "SELECT MAX(k) FROM fleet_samples WHERE run_id = ?", (run_id,)).fetchone()
        return 0 if row is None or row[0] is None else int(row[0]) + 1

    def finish_run(self, run_id: int | None, status: str) -> None:
        """Commit what is pending and mark the run."""
        self.commit()
        if run_id is not None:
            self._con.execute("UPDATE fleet_runs SET status = ? WHERE run_id = ?",
                              (status, run_id))
            self._con.commit()

    def add_samples(
        self, run_id: int | None, k: int, t: float, u: NDArray, y: NDArray, y_pred: NDArray,
        flags: NDArray,
    ) -> None:
        """Queue sample ``k`` of every asset (written by the next :meth:`commit`).

        Parameters
        ----------
        run_id : int
        k : int
        t : float
        u, y, y_pred : ndarray of shape (n_assets,)
        flags : ndarray of int of shape (n_assets,)
        """
        self._pending.append((int(run_id or 0), int(k), float(t), u.copy(), y.copy(),
                              y_pred.copy(), np.asarray(flags).copy()))

    def commit(self) -> None:
        """Write every queued sample in one transaction."""
        if not self._pending:
            return
        rows: list[tuple[Any, ...]] = []
        for run_id, k, t, u, y, yp, fl in self._pending:
            n = u.size
            rows.extend(zip([run_id] * n, range(n), [k] * n, [t] * n, _nan_none(u), _nan_none(y),
                            _nan_none(yp), fl.tolist(), strict=True))
        with self._con:
            self._con.executemany(
                "INSERT INTO fleet_samples (run_id, asset, k, t, u, y, y_pred, flags) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)", rows)
        self.rows_written += len(rows)
        self._pending = []

    def add_version(self, run_id: int | None, asset: int, dm: DigitalModel, k: int) -> None:
        """Store a model version of one asset.

        Parameters
        ----------
        run_id : int
        asset : int
        dm : DigitalModel
        k : int
        """
        poles = [[float(p.real), float(p.imag)] for p in dm.model.poles]
        fit = dm.fit_percent
        with self._con:
            self._con.execute(
                "INSERT OR REPLACE INTO fleet_versions VALUES (?, ?, ?, ?, ?, ?, ?)",
                (int(run_id or 0), int(asset), int(dm.version), int(k), dm.provenance,
                 None if fit is None or not math.isfinite(fit) else float(fit),
                 json.dumps({"poles": poles,
                             "coefficients": np.asarray(dm.model.coefficients).tolist()})))

    def add_setpoints(self, run_id: int, assets: NDArray[np.intp], k_from: int, t: float,
                      value: float) -> None:
        """Store set-points written to a run (committed at once).

        Parameters
        ----------
        run_id : int
        assets : ndarray of int
        k_from : int
            The first sample that uses it.
        t : float
            That sample's time, s.
        value : float
        """
        with self._con:
            self._con.executemany(
                "INSERT INTO fleet_setpoints VALUES (?, ?, ?, ?, ?)",
                [(int(run_id), int(a), int(k_from), float(t), float(value))
                 for a in np.asarray(assets).reshape(-1).tolist()])

    def setpoints(self, run_id: int, asset: int | None = None) -> list[tuple[int, int, float]]:
        """Set-points written to a run: ``(k_from, asset, value)`` in writing order.

        Parameters
        ----------
        run_id : int
        asset : int, optional
            Only this asset's.

        Returns
        -------
        list of (int, int, float)
        """
        q = "SELECT k_from, asset, value FROM fleet_setpoints WHERE run_id = ?"
        args: tuple[Any, ...] = (int(run_id),)
        if asset is not None:
            q += " AND asset = ?"
            args += (int(asset),)
        rows = self._con.execute(q + " ORDER BY k_from, rowid", args).fetchall()
        return [(int(k), int(a), float(v)) for k, a, v in rows]

    def log_events(self, run_id: int | None, events: Sequence[tuple[int, int, str, str]]) -> None:
        """Store events ``(asset, k, kind, message)``.

        Parameters
        ----------
        run_id : int
        events : sequence of tuple
        """
        with self._con:
            self._con.executemany(
                "INSERT INTO fleet_events VALUES (?, ?, ?, ?, ?)",
                [(int(run_id or 0), int(a), int(k), kind, msg) for a, k, kind, msg in events])

    # ------------------------------------------------------------------ reading
    def n_samples(self, run_id: int) -> int:
        """Committed sample rows of a run (all assets)."""
        return int(self._con.execute(
            "SELECT COUNT(*) FROM fleet_samples WHERE run_id = ?", (run_id,)).fetchone()[0])

    def samples(self, run_id: int, *, asset: int | None = None) -> dict[str, NDArray[Any]]:
        """Committed samples as arrays ``asset, k, t, u, y, y_pred, flags`` (NaN for NULL).

        Parameters
        ----------
        run_id : int
        asset : int, optional
            Only this asset.

        Returns
        -------
        dict of str to ndarray
        """
        q = "SELECT asset, k, t, u, y, y_pred, flags FROM fleet_samples WHERE run_id = ?"
        args: tuple[Any, ...] = (run_id,)
        if asset is not None:
            q += " AND asset = ?"
            args += (int(asset),)
        rows = self._con.execute(q + " ORDER BY asset, k", args).fetchall()
        names = ("asset", "k", "t", "u", "y", "y_pred", "flags")
        out: dict[str, NDArray[Any]] = {}
        for j, name in enumerate(names):
            col = [r[j] for r in rows]
            if name in ("asset", "k", "flags"):
                out[name] = np.asarray(col, dtype=np.int64)
            else:
                out[name] = np.asarray([math.nan if v is None else v for v in col], dtype=float)
        return out

    def events(self, run_id: int) -> list[tuple[int, int, str, str]]:
        """Stored events ``(asset, k, kind, message)`` of a run."""
        return [tuple(r) for r in self._con.execute(  # type: ignore[misc]
            "SELECT asset, k, kind, message FROM fleet_events WHERE run_id = ?", (run_id,))]

    def close(self) -> None:
        """Commit what is pending and close the database."""
        self.commit()
        self._con.close()

    def __repr__(self) -> str:
        return f"FleetStore({self.path!r})"
