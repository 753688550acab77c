"""History store of the twin (SQLite and in memory) and the versioned digital model."""

from __future__ import annotations

import inspect
import json
import math
import os
import queue
import signal
import sqlite3
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import kautztwin
from kautztwin import KautzBasis, KautzModel
from kautztwin.exceptions import DataError
from kautztwin.twin import (
    SCHEMA_VERSION,
    DigitalModel,
    HistoryError,
    HistoryStore,
    Measurement,
    Measurements,
    MemoryHistory,
    SampleFlag,
    SQLiteHistory,
)


def _model(scale: float = 1.0) -> KautzModel:
    basis = KautzBasis([-1.0, -0.5 + 2j, -0.5 - 2j])
    return KautzModel(basis, scale * np.array([1.0, -0.25, 0.125]))


def _rows(ks, seed: int = 0) -> list[tuple[int, float, float, float, int]]:
    rng = np.random.default_rng(seed)
    return [(int(k), 0.1 * k, float(rng.normal()), float(rng.normal()), 0) for k in ks]


@pytest.fixture(params=["sqlite", "memory"])
def store(request, tmp_path):
    s = SQLiteHistory(tmp_path / "history.db") if request.param == "sqlite" else MemoryHistory()
    yield s
    s.close()


# ---------------------------------------------------------------------- digital model
class TestDigitalModel:
    def test_initial_is_version_one(self):
        dm = DigitalModel.initial(_model(), created=10.0)
        assert (dm.version, dm.provenance, dm.created, dm.fit_percent) == (1, "initial", 10.0, None)

    def test_with_update_increments_version_and_keeps_original(self):
        dm = DigitalModel.initial(_model(), created=10.0)
        new = dm.with_update(_model(2.0), "dnn-update", 91.5, created=11.0)
        assert (new.version, new.provenance, new.fit_percent, new.created) == (
            2,
            "dnn-update",
            91.5,
            11.0,
        )
        assert dm.version == 1 and dm.model.allclose(_model())
        np.testing.assert_allclose(new.model.coefficients, 2.0 * _model().coefficients, rtol=0)

    def test_dict_round_trip_through_json(self):
        dm = DigitalModel(_model(), 7, "reidentification", 123.25, 88.0)
        back = DigitalModel.from_dict(json.loads(json.dumps(dm.to_dict())))
        assert back.allclose(dm, rtol=0, atol=0)

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"version": -1}, "version must be >= 0"),
            ({"version": True}, "version must be an integer"),
            ({"version": 1.5}, "version must be an integer"),
            ({"provenance": " "}, "provenance must be a non-empty string"),
            ({"created": math.nan}, "created must be finite"),
            ({"fit_percent": math.inf}, "fit_percent must be finite"),
            ({"model": "not a model"}, "model must be a KautzModel"),
        ],
        ids=["negative-version", "bool-version", "float-version", "empty-provenance",
             "nan-created", "inf-fit", "wrong-model"],
    )  # fmt: skip
    def test_invalid_fields_raise(self, kwargs, match):
        fields = {"model": _model(), "version": 1, "provenance": "initial", "created": 0.0}
        with pytest.raises(DataError, match=match):
            DigitalModel(**{**fields, **kwargs})

    def test_from_dict_missing_key_raises(self):
        data = DigitalModel.initial(_model(), created=0.0).to_dict()
        del data["provenance"]
        with pytest.raises(DataError, match="lacks the key 'provenance'"):
            DigitalModel.from_dict(data)


# ---------------------------------------------------------------------- behaviour (both stores)
def test_store_implements_protocol(store):
    assert isinstance(store, HistoryStore)


def test_start_run_stores_config_and_status(store):
    config = {"dt": 0.1, "poles": np.array([-1.0, -2.0]), "n": np.int64(3), "name": "tclab"}
    a = store.start_run(config, started=100.0)
    b = store.start_run()
    assert a != b
    info = store.run_info(a)
    assert (info.run_id, info.started, info.finished, info.status) == (a, 100.0, None, "running")
    assert info.config == {"dt": 0.1, "poles": [-1.0, -2.0], "n": 3, "name": "tclab"}
    assert store.run_info(b).config == {}
    assert [r.run_id for r in store.runs()] == [a, b]


def test_finish_run_sets_status_and_end_time(store):
    run = store.start_run()
    store.finish_run(run, "failed")
    info = store.run_info(run)
    assert info.status == "failed" and info.finished is not None


def test_config_that_json_cannot_hold_raises(store):
    with pytest.raises(DataError, match="config holds a object"):
        store.start_run({"x": object()})


@pytest.mark.parametrize(
    "call",
    [
        lambda s: s.append_measurements(99, _rows([0])),
        lambda s: s.measurements(99),
        lambda s: s.resume(99),
        lambda s: s.active_model(99),
        lambda s: s.log_event(99, "alarm"),
        lambda s: s.events(99),
        lambda s: s.finish_run(99),
        lambda s: s.run_info(99),
    ],
    ids=["append", "measurements", "resume", "active_model", "log_event", "events", "finish",
         "run_info"],
)  # fmt: skip
def test_unknown_run_raises(store, call):
    with pytest.raises(HistoryError, match="no run with run_id = 99"):
        call(store)


def test_append_and_read_back_exactly(store):
    run = store.start_run()
    rows = _rows(range(50), seed=1)
    rows[3] = (3, 0.3, 0.5, math.nan, int(SampleFlag.DROPOUT | SampleFlag.HELD))
    rows[4] = (4, 0.4, None, math.inf, int(SampleFlag.OUTLIER | SampleFlag.CLIPPED))
    assert store.append_measurements(run, rows[:20]) == 20
    assert store.append_measurements(run, rows[20:]) == 30
    m = store.measurements(run)
    assert len(m) == 50
    np.testing.assert_array_equal(m.k, np.arange(50))
    expected = np.array(rows, dtype=float)
    for i, name in enumerate(["t", "u", "y"], start=1):
        np.testing.assert_array_equal(getattr(m, name), expected[:, i])  # NaN == NaN here
    np.testing.assert_array_equal(m.flags, expected[:, 4].astype(int))
    assert m.k.dtype == np.int64 and m.y.dtype == np.float64
    assert not m.y.flags.writeable


def test_measurements_since_returns_later_samples(store):
    run = store.start_run()
    store.append_measurements(run, _rows(range(10)))
    np.testing.assert_array_equal(store.measurements(run, since=6).k, [7, 8, 9])
    assert len(store.measurements(run, since=9)) == 0


def test_measurements_are_ordered_by_k(store):
    run = store.start_run()
    store.append_measurements(run, _rows([5, 1, 3]))
    np.testing.assert_array_equal(store.measurements(run).k, [1, 3, 5])


def test_empty_run_gives_empty_arrays(store):
    run = store.start_run()
    m = store.measurements(run)
    assert len(m) == 0 and m.k.shape == (0,) and m.y.shape == (0,)


def test_runs_are_isolated(store):
    a, b = store.start_run(), store.start_run()
    store.append_measurements(a, _rows(range(3)))
    store.append_measurements(b, _rows(range(5)))
    assert (len(store.measurements(a)), len(store.measurements(b))) == (3, 5)


def test_append_accepts_measurement_rows_and_measurements(store):
    run = store.start_run()
    store.append_measurements(run, [Measurement(0, 0.0, 1.0, 2.0), Measurement(1, 0.1, 1, 2, 4)])
    copy = store.start_run()
    store.append_measurements(copy, store.measurements(run))
    np.testing.assert_array_equal(store.measurements(copy).flags, [0, 4])


def test_duplicate_k_rolls_back_whole_batch(store):
    run = store.start_run()
    store.append_measurements(run, _rows(range(5)))
    with pytest.raises(HistoryError, match="already has sample k = 4; nothing of this batch"):
        store.append_measurements(run, _rows([5, 6, 4, 7]))
    np.testing.assert_array_equal(store.measurements(run).k, np.arange(5))


def test_repeated_k_within_batch_raises(store):
    run = store.start_run()
    with pytest.raises(DataError, match="rows repeat the sample index k = 2"):
        store.append_measurements(run, _rows([1, 2, 2]))
    assert len(store.measurements(run)) == 0


@pytest.mark.parametrize(
    ("rows", "match"),
    [
        ([(0, 0.0, 1.0)], r"rows\[0\] must have 4 or 5 fields"),
        ([(-1, 0.0, 1.0, 2.0)], r"rows\[0\].k must be >= 0"),
        ([(1.5, 0.0, 1.0, 2.0)], r"rows\[0\].k must be an integer"),
        ([(0, 0.0, "x", 2.0)], r"rows\[0\].u must be a real number"),
        ([(0, 0.0, 1.0, 2.0, -1)], r"rows\[0\].flags must be >= 0"),
        ([5], r"rows\[0\] must be a \(k, t, u, y\[, flags\]\) sequence"),
        ("abc", "rows must be an iterable"),
    ],
    ids=["short", "negative-k", "float-k", "string-u", "negative-flags", "scalar-row", "string"],
)
def test_malformed_rows_raise(store, rows, match):
    run = store.start_run()
    with pytest.raises(DataError, match=match):
        store.append_measurements(run, rows)


def test_model_versions_and_active_model(store):
    run = store.start_run()
    assert store.active_model(run) is None
    v1 = DigitalModel.initial(_model(), created=1.0, fit_percent=90.0)
    v2 = v1.with_update(_model(1.1), "dnn-update", 93.0, created=2.0)
    v3 = v2.with_update(_model(0.9), "reidentification", 80.0, created=3.0)
    assert store.add_model_version(run, v1, k=0) == 1
    assert store.add_model_version(run, v2, k=100) == 2
    assert store.active_model(run).allclose(v2, rtol=0, atol=0)
    store.add_model_version(run, v3, active=False)  # a candidate, not (yet) active
    assert store.active_model(run).version == 2
    stored = store.model_versions(run)
    assert [m.version for m in stored] == [1, 2, 3]
    assert all(a.allclose(b, rtol=0, atol=0) for a, b in zip(stored, [v1, v2, v3], strict=True))


def test_activate_model_rolls_back(store):
    run = store.start_run()
    v1 = DigitalModel.initial(_model(), created=1.0)
    store.add_model_version(run, v1)
    store.add_model_version(run, v1.with_update(_model(3.0), "dnn-update", created=2.0))
    store.activate_model(run, 1)
    assert store.active_model(run).version == 1
    assert store.resume(run).active_version == 1


def test_duplicate_model_version_raises(store):
    run = store.start_run()
    v1 = DigitalModel.initial(_model(), created=1.0)
    store.add_model_version(run, v1)
    with pytest.raises(HistoryError, match="already has model version 1"):
        store.add_model_version(run, v1)
    with pytest.raises(HistoryError, match="has no model version 5"):
        store.activate_model(run, 5)
    assert store.active_model(run).version == 1


def test_resume_reports_last_sample_and_active_version(store):
    run = store.start_run()
    state = store.resume(run)
    assert (state.last_k, state.last_t, state.n_samples, state.next_k) == (None, None, 0, 0)
    store.append_measurements(run, _rows(range(12)))
    store.add_model_version(run, DigitalModel.initial(_model(), created=0.0))
    store.finish_run(run, "aborted")
    state = store.resume(run)
    assert (state.last_k, state.next_k, state.n_samples) == (11, 12, 12)
    assert state.last_t == pytest.approx(1.1, abs=1e-15)
    assert (state.active_version, state.previous_status) == (1, "aborted")
    assert store.run_info(run).status == "running"
    resumes = store.events(run, kind="resume")
    assert [e.payload for e in resumes] == [
        {"last_k": None, "previous_status": "running"},
        {"last_k": 11, "previous_status": "aborted"},
    ]


def test_events_round_trip_and_filter(store):
    run = store.start_run()
    payload = {"coef": np.array([1.0, np.nan]), "n": np.int32(2), "ok": np.bool_(True)}
    e1 = store.log_event(run, "model-update", "version 2", k=10, t=5.0, payload=payload)
    e2 = store.log_event(run, "alarm", "y above limit", k=11, t=6.0)
    e3 = store.log_event(run, "model-update", t=7.0)
    assert e1 < e2 < e3
    events = store.events(run)
    assert [e.kind for e in events] == ["model-update", "alarm", "model-update"]
    first = events[0]
    assert (first.k, first.t, first.message) == (10, 5.0, "version 2")
    assert first.payload == {"coef": [1.0, None], "n": 2, "ok": True}
    assert [e.event_id for e in store.events(run, kind="model-update")] == [e1, e3]
    assert store.events(run, kind="none-such") == []


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kind": ""}, "kind must be a non-empty string"),
        ({"kind": "x", "t": math.nan}, "t must be a finite number"),
        ({"kind": "x", "k": -2}, "k must be >= 0"),
        ({"kind": "x", "payload": {"f": print}}, "payload holds a builtin_function"),
    ],
    ids=["empty-kind", "nan-time", "negative-k", "bad-payload"],
)
def test_invalid_event_raises(store, kwargs, match):
    run = store.start_run()
    with pytest.raises(DataError, match=match):
        store.log_event(run, **kwargs)


def test_predictions_round_trip(store):
    run = store.start_run()
    store.add_model_version(run, DigitalModel.initial(_model(), created=0.0))
    store.add_prediction(run, 10, [1.0, 2.0, np.nan], model_version=1, t=1.0)
    store.add_prediction(run, 5, np.arange(4.0))
    preds = store.predictions(run)
    assert [(p.k, p.horizon, p.model_version, p.t) for p in preds] == [
        (5, 4, None, None),
        (10, 3, 1, 1.0),
    ]
    np.testing.assert_array_equal(preds[1].y_pred, [1.0, 2.0, np.nan])
    assert [p.k for p in store.predictions(run, since=5)] == [10]
    with pytest.raises(HistoryError, match="has no model version 4"):
        store.add_prediction(run, 11, [0.0], model_version=4)
    with pytest.raises(DataError, match="y_pred must be 1-D"):
        store.add_prediction(run, 11, np.zeros((2, 2)))


def test_closed_store_raises_and_close_is_idempotent(store):
    run = store.start_run()
    store.close()
    store.close()
    with pytest.raises(HistoryError, match="closed"):
        store.measurements(run)


def test_context_manager_closes(tmp_path):
    with SQLiteHistory(tmp_path / "h.db") as s:
        s.start_run()
    with pytest.raises(HistoryError, match="closed"):
        s.runs()
    with MemoryHistory() as m:
        m.start_run()
    with pytest.raises(HistoryError, match="closed"):
        m.runs()


def test_threads_share_one_store(store):
    run = store.start_run()

    def writer(offset: int) -> None:
        for k in range(offset, offset + 100, 4):
            store.append_measurements(run, [(k, 0.0, 1.0, 2.0)])

    threads = [threading.Thread(target=writer, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    np.testing.assert_array_equal(store.measurements(run).k, np.arange(100))


def test_measurements_validates_arrays():
    with pytest.raises(DataError, match="y has 2 samples but k has 3"):
        Measurements([0, 1, 2], [0.0, 1.0, 2.0], [0.0] * 3, [0.0] * 2, [0] * 3)


# ---------------------------------------------------------------------- SQLite specifics
def test_sqlite_schema_pragmas_and_indices(tmp_path):
    path = tmp_path / "h.db"
    with SQLiteHistory(path) as s:
        assert s.journal_mode == "wal"
        assert s._conn.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
        assert s._conn.execute("PRAGMA foreign_keys").fetchone()[0] == 1
    conn = sqlite3.connect(path)
    try:
        names = {
            (kind, name)
            for kind, name in conn.execute("SELECT type, name FROM sqlite_master")
            if not name.startswith("sqlite_")
        }
        assert conn.execute("SELECT version FROM schema_version").fetchall() == [(SCHEMA_VERSION,)]
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    finally:
        conn.close()
    tables = {"schema_version", "runs", "measurements", "model_versions", "predictions", "events"}
    indices = {"measurements_run_t", "model_versions_one_active", "predictions_run_k",
               "events_run_t", "events_run_kind"}  # fmt: skip
    assert {n for k, n in names if k == "table"} == tables
    assert {n for k, n in names if k == "index"} == indices


def test_sqlite_synchronous_normal_is_accepted_and_bad_value_raises(tmp_path):
    with SQLiteHistory(tmp_path / "h.db", synchronous="normal") as s:
        assert s._conn.execute("PRAGMA synchronous").fetchone()[0] == 1
    with pytest.raises(DataError, match="synchronous must be one of"):
        SQLiteHistory(tmp_path / "h.db", synchronous="OFF")


def test_sqlite_data_persist_across_reopen(tmp_path):
    path = tmp_path / "h.db"
    with SQLiteHistory(path) as s:
        run = s.start_run({"a": 1})
        s.append_measurements(run, _rows(range(7)))
        s.add_model_version(run, DigitalModel.initial(_model(), created=0.0))
    with SQLiteHistory(path) as s:
        assert s.run_info(run).config == {"a": 1}
        assert len(s.measurements(run)) == 7
        assert s.active_model(run).model.allclose(_model(), rtol=0, atol=0)


def test_sqlite_one_active_model_enforced_by_database(tmp_path):
    with SQLiteHistory(tmp_path / "h.db") as s:
        run = s.start_run()
        v1 = DigitalModel.initial(_model(), created=0.0)
        s.add_model_version(run, v1)
        s.add_model_version(run, v1.with_update(_model(2.0), "dnn-update", created=1.0))
        with pytest.raises(sqlite3.IntegrityError, match="UNIQUE"):
            s._conn.execute("UPDATE model_versions SET active = 1 WHERE run_id = ?", (run,))


def test_sqlite_reader_sees_committed_samples_while_writer_is_open(tmp_path):
    path = tmp_path / "h.db"
    with SQLiteHistory(path) as writer, SQLiteHistory(path) as reader:
        run = writer.start_run()
        writer.append_measurements(run, _rows(range(3)))
        np.testing.assert_array_equal(reader.measurements(run).k, [0, 1, 2])
        writer.append_measurements(run, _rows([3]))
        np.testing.assert_array_equal(reader.measurements(run, since=2).k, [3])


def test_sqlite_other_schema_version_raises(tmp_path):
    path = tmp_path / "h.db"
    SQLiteHistory(path).close()
    conn = sqlite3.connect(path)
    with conn:
        conn.execute("UPDATE schema_version SET version = 99")
    conn.close()
    with pytest.raises(HistoryError, match="schema version 99; this kautztwin reads version 1"):
        SQLiteHistory(path)


def test_sqlite_foreign_database_raises(tmp_path):
    path = tmp_path / "other.db"
    conn = sqlite3.connect(path)
    with conn:
        conn.execute("CREATE TABLE foo (x)")
    conn.close()
    with pytest.raises(HistoryError, match="no kautztwin history"):
        SQLiteHistory(path)


def test_sqlite_file_that_is_not_a_database_raises(tmp_path):
    path = tmp_path / "garbage.db"
    path.write_bytes(b"this is not a database" * 100)
    with pytest.raises(HistoryError, match="not a usable SQLite database"):
        SQLiteHistory(path)


# ---------------------------------------------------------------------- kill -9
def _sample(k):
    """The sample the writer process commits as index ``k`` (recomputed by the test)."""
    dropout = k % 7 == 3
    return (k, 0.01 * k, math.sin(0.1 * k), math.nan if dropout else 0.5 * k + 0.25, int(dropout))


_WRITER = """
import math
import sys

import numpy as np

from kautztwin import KautzBasis, KautzModel
from kautztwin.twin import DigitalModel, SQLiteHistory

{sample}

path, mode = sys.argv[1], sys.argv[2]
store = SQLiteHistory(path)
basis = KautzBasis([-1.0, -0.5 + 2j, -0.5 - 2j])
if mode == "new":
    run = store.start_run({{"dt": 0.01}})
    k = 0
    dm = None
else:
    run = int(mode)
    k = store.resume(run).next_k
    dm = store.active_model(run)
print("run", run, flush=True)
while True:
    # one model version per 25 samples, added idempotently (a restart may repeat k)
    version = 1 + k // 25
    if dm is None or dm.version < version:
        model = KautzModel(basis, np.array([1.0, -0.25, 0.125]) * version)
        dm = DigitalModel(model, version, "initial" if version == 1 else "dnn-update", float(k))
        store.add_model_version(run, dm, k=k)
    store.append_measurements(run, [_sample(k)])  # one transaction per sample
    print(k, flush=True)
    k += 1
"""


def _start_writer(script: Path, db: Path, mode: str) -> tuple[subprocess.Popen, queue.Queue]:
    env = dict(os.environ)
    src = str(Path(kautztwin.__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join([src, env.get("PYTHONPATH", "")])
    proc = subprocess.Popen(
        [sys.executable, str(script), str(db), mode],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    lines: queue.Queue = queue.Queue()

    def pump() -> None:
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return proc, lines


def _run_and_kill(script: Path, db: Path, mode: str, n_commits: int) -> tuple[int, int]:
    """Start a writer, SIGKILL it after ``n_commits`` printed commits; (run_id, last printed k)."""
    proc, lines = _start_writer(script, db, mode)
    run_id, printed = None, []
    try:
        while len(printed) < n_commits:
            try:
                line = lines.get(timeout=30)
            except queue.Empty:
                pytest.fail("the writer process printed nothing for 30 s")
            if line is None:
                pytest.fail(f"the writer process ended early: {proc.stderr.read()}")
            if line.startswith("run"):
                run_id = int(line.split()[1])
            else:
                printed.append(int(line))
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()  # no-op once it is dead
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    while (line := lines.get(timeout=30)) is not None:  # commits printed before the kill
        printed.append(int(line))
    proc.stdout.close()
    proc.stderr.close()
    assert printed == list(range(printed[0], printed[-1] + 1))
    return run_id, printed[-1]


def _check_intact(store: SQLiteHistory, run: int, at_least: int) -> int:
    m = store.measurements(run)
    last = len(m) - 1
    assert last >= at_least, f"committed sample {at_least} lost: the store ends at {last}"
    expected = np.array([_sample(k) for k in range(last + 1)], dtype=float)
    np.testing.assert_array_equal(m.k, np.arange(last + 1))  # no gaps
    np.testing.assert_array_equal(m.t, expected[:, 1])
    np.testing.assert_array_equal(m.u, expected[:, 2])
    np.testing.assert_array_equal(m.y, expected[:, 3])
    np.testing.assert_array_equal(m.flags, expected[:, 4].astype(int))
    return last


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs POSIX SIGKILL")
def test_kill_9_loses_no_committed_sample_and_resumes(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(_WRITER.format(sample=inspect.getsource(_sample)), encoding="utf-8")
    db = tmp_path / "twin.db"

    run, printed = _run_and_kill(script, db, "new", n_commits=40)
    with SQLiteHistory(db) as s:
        last = _check_intact(s, run, printed)

    # a restarted writer resumes the same run after the last committed sample
    run2, printed2 = _run_and_kill(script, db, str(run), n_commits=40)
    assert run2 == run and printed2 >= last + 40

    with SQLiteHistory(db) as s:
        last = _check_intact(s, run, printed2)
        state = s.resume(run)
        assert (state.last_k, state.n_samples) == (last, last + 1)
        assert state.previous_status == "running"  # killed runs never finished
        # exactly one active model, the newest version, consistent with the samples
        versions = [m.version for m in s.model_versions(run)]
        assert versions == list(range(1, versions[-1] + 1))
        assert state.active_version == versions[-1]
        assert state.active_version in (1 + last // 25, 1 + (last + 1) // 25)
        resumes = s.events(run, kind="resume")
        assert len(resumes) == 2 and resumes[0].k >= printed
        # and the run continues
        s.append_measurements(run, [_sample(k) for k in range(state.next_k, state.next_k + 10)])
        s.finish_run(run)
    with SQLiteHistory(db) as s:
        assert _check_intact(s, run, last + 10) == last + 10
        assert s.run_info(run).status == "finished"


def test_read_run_setpoints_follow_api_writes_and_restarts():
    """twin history shows the set-point the loop used: NaN while identifying, the configured
    schedule, a value written through the API from its sample on, the schedule again after
    a restart (the same rule as the service's GET /history)."""
    from kautztwin.twin.history import MemoryHistory, read_run

    h = MemoryHistory()
    rid = h.start_run({"twin": {"dt": 0.5, "ident_duration": 1.0,
                                "setpoints": [[0.0, 1.0], [4.0, 2.0]]}, "plant": "p"})
    h.append_measurements(rid, [(k, 0.5 * k, 0.0, 0.0, 0) for k in range(14)])
    h.log_event(rid, "api-setpoint", "set-point 5 from the API", k=3, t=1.5,
                payload={"value": 5.0, "k_from": 4})
    h.log_event(rid, "resume", "restart", k=9, t=4.5, payload={"last_k": 9})
    sp = read_run(h, signals=("setpoint",)).columns["setpoint"]
    # k: 0 1 (identification) | 2 3 configured 1.0 | 4..9 API 5.0 | 10.. configured (t >= 4: 2.0)
    expected = [np.nan, np.nan, 1.0, 1.0, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 2.0, 2.0, 2.0, 2.0]
    np.testing.assert_array_equal(sp, expected)
