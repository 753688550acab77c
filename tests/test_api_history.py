"""``GET /history``'s reader (issue #12): pages of samples, predictions and set-points.

:class:`~kautztwin.service.history_reader.HistoryReader` reads an SQLite store on read-only
connections of its own and any other store through its methods; both must give the same
pages, and the set-points must follow the schedule rules of the loop (worked out by hand
below), without a running twin.
"""

import math
import threading

import numpy as np
import pytest

from kautztwin.service.history_reader import HistoryReader
from kautztwin.service.twin_view import ApiError
from kautztwin.twin.history import MemoryHistory, SQLiteHistory

DT = 0.1
N = 60
CONFIG = {"twin": {"dt": DT, "ident_duration": 1.0, "setpoints": [[1.0, 5.0], [3.0, 6.0]]},
          "plant": "test"}


def _fill(store):
    """60 samples; predictions from sample 10 on; a set-point write at 25; a restart after 39."""
    run = store.start_run(CONFIG)
    rows = [(k, k * DT, 0.5, 1.0 + k, 0) for k in range(N)]
    rows[7] = (7, 0.7, 0.5, math.nan, 3)  # a missing output, flagged
    store.append_measurements(run, rows)
    for k in range(9, N - 1):  # made at k, of sample k + 1 (the runtime's convention)
        store.add_prediction(run, k, [1000.0 + k + 1, -1.0], t=k * DT)
    store.log_event(run, "api-setpoint", "set-point 7", k=25, t=2.5,
                    payload={"value": 7.0, "k_from": 25})
    store.log_event(run, "resume", "resumed after sample 39", k=39, payload={"last_k": 39})
    store.log_event(run, "model-version", "v1", k=10, t=1.0, payload={"version": 1})
    return run


#: the set-point of every sample, by hand: none in identification (k < 10), the schedule's
#: 5.0 from t = 1 s, the API's 7.0 from sample 25, the schedule again after the restart
#: (6.0 from t = 3 s)
EXPECTED_SP = np.array([math.nan] * 10 + [5.0] * 15 + [7.0] * 15 + [6.0] * 20)
EXPECTED_PRED = np.array([math.nan] * 10 + [1000.0 + k for k in range(10, N)])


@pytest.fixture(params=["sqlite", "memory"])
def reader(request, tmp_path):
    store = (SQLiteHistory(tmp_path / "h.sqlite") if request.param == "sqlite"
             else MemoryHistory())
    run = _fill(store)
    r = HistoryReader(store)
    assert (r.path is not None) == (request.param == "sqlite")
    yield r, run
    r.close()
    store.close()


def test_a_page_holds_the_stored_samples_predictions_and_setpoints(reader):
    r, run = reader
    cols, nxt = r.page(run, ["k", "t", "u", "y", "flags", "prediction", "setpoint"], limit=N)
    assert nxt is None
    np.testing.assert_array_equal(cols["k"], np.arange(N))
    assert cols["k"].dtype == np.int64 and cols["flags"].dtype == np.int64
    assert math.isnan(cols["y"][7]) and cols["flags"][7] == 3 and cols["y"][8] == 9.0
    np.testing.assert_array_equal(cols["prediction"], EXPECTED_PRED)
    np.testing.assert_array_equal(cols["setpoint"], EXPECTED_SP)


def test_pages_follow_the_cursor_and_the_window(reader):
    r, run = reader
    seen, after = [], -1
    while True:
        cols, nxt = r.page(run, ["k", "setpoint"], after=after, limit=7)
        seen.extend(cols["k"].tolist())
        np.testing.assert_array_equal(cols["setpoint"], EXPECTED_SP[cols["k"]])
        if nxt is None:
            break
        assert nxt == seen[-1]
        after = nxt
    assert seen == list(range(N))
    cols, nxt = r.page(run, ["t", "prediction"], start=2.0, end=3.0, limit=100)
    np.testing.assert_allclose(cols["t"], np.arange(20, 31) * DT, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(cols["prediction"], EXPECTED_PRED[20:31])
    assert nxt is None
    cols, nxt = r.page(run, ["k"], start=2.0, end=3.0, limit=4)
    assert cols["k"].tolist() == [20, 21, 22, 23] and nxt == 23
    cols, nxt = r.page(run, ["k", "prediction", "setpoint"], after=N + 5)
    assert cols["k"].size == cols["prediction"].size == cols["setpoint"].size == 0
    assert nxt is None


def test_closed_reader_answers_503(reader):
    r, run = reader
    r.close()
    with pytest.raises(ApiError, match="closed") as info:
        r.page(run, ["k"])
    assert info.value.status == 503


def test_sqlite_reads_do_not_take_the_stores_lock(tmp_path):
    """The loop's writes go on while a page is read: the reader never holds the store's lock."""
    store = SQLiteHistory(tmp_path / "h.sqlite")
    run = _fill(store)
    r = HistoryReader(store)
    held, release = threading.Event(), threading.Event()

    def hold():  # the loop in a commit: it holds the store's lock
        with store._lock:
            held.set()
            release.wait(10)

    th = threading.Thread(target=hold)
    th.start()
    try:
        assert held.wait(10)
        cols, _ = r.page(run, ["k", "prediction"], limit=5)  # served all the same
    finally:
        release.set()
        th.join(10)
    assert cols["k"].tolist() == [0, 1, 2, 3, 4]
    conn = r._connection()
    with pytest.raises(Exception, match="readonly"):
        conn.execute("DELETE FROM measurements")
    r.close()
    store.close()
