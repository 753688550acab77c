"""Tests of kautztwin.data.csv.read_columns: formats it reads and one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from kautztwin.data.csv import read_columns
from kautztwin.exceptions import DataError, KautzTwinError


def _write(tmp_path, text, name="data.csv", encoding="utf-8"):
    path = tmp_path / name
    path.write_text(text, encoding=encoding)
    return path


@pytest.mark.parametrize(
    "text",
    [
        "t,h\n0,1.5\n0.5,2\n1,-3e-2\n",
        "t;h\n0;1.5\n0.5;2\n1;-3e-2\n",
        "t\th\n0\t1.5\n0.5\t2\n1\t-3e-2\n",
        "t   h\n0   1.5\n0.5 2\n  1 -3e-2\n",
        "t, h\n0, 1.5\n0.5, 2\n1, -3e-2\n",
        '"t","h"\n0,1.5\n0.5,2\n1,-3e-2\n',
    ],
    ids=["comma", "semicolon", "tab", "whitespace", "comma-space", "quoted-header"],
)
def test_reads_separators(tmp_path, text):
    data = read_columns(_write(tmp_path, text), ["t", "h"])
    np.testing.assert_array_equal(data["t"], [0.0, 0.5, 1.0])
    np.testing.assert_array_equal(data["h"], [1.5, 2.0, -0.03])
    assert data["h"].dtype == np.float64


def test_returns_requested_columns_in_order_and_ignores_others(tmp_path):
    path = _write(tmp_path, "u,h,t,note\n1,10,0,a\n1,20,1,b\n")
    data = read_columns(path, ["t", "h"])
    assert list(data) == ["t", "h"]
    np.testing.assert_array_equal(data["h"], [10.0, 20.0])


def test_pandas_index_column_with_empty_header_field(tmp_path):
    path = _write(tmp_path, ",t,h\n0,0.0,1.0\n1,0.1,0.9\n")
    data = read_columns(path, ["t", "h"])
    np.testing.assert_array_equal(data["t"], [0.0, 0.1])
    np.testing.assert_array_equal(data["h"], [1.0, 0.9])


def test_unnamed_index_column_one_field_more_than_header(tmp_path):
    path = _write(tmp_path, "t h\n0 0.0 1.0\n1 0.1 0.9\n")
    data = read_columns(path, ["t", "h"])
    np.testing.assert_array_equal(data["t"], [0.0, 0.1])


def test_savetxt_round_trip_with_hash_header(tmp_path):
    rng = np.random.default_rng(0)
    arr = rng.standard_normal((50, 2))
    path = tmp_path / "x.csv"
    np.savetxt(path, arr, delimiter=",", header="t,h", fmt="%.17g")  # writes "# t,h"
    data = read_columns(path, ["t", "h"])
    np.testing.assert_array_equal(data["t"], arr[:, 0])
    np.testing.assert_array_equal(data["h"], arr[:, 1])


def test_skips_blank_and_comment_lines_and_bom(tmp_path):
    path = _write(tmp_path, "\ufeff\nt,h\n# a comment\n0,1\n\n1,2\n", encoding="utf-8")
    data = read_columns(path, ["t", "h"])
    np.testing.assert_array_equal(data["h"], [1.0, 2.0])


def test_decimal_comma_in_semicolon_file(tmp_path):
    data = read_columns(_write(tmp_path, "t;h\n0;1,5\n1;2,25\n"), ["t", "h"])
    np.testing.assert_array_equal(data["h"], [1.5, 2.25])


def test_single_column_name_as_string(tmp_path):
    data = read_columns(_write(tmp_path, "t,h\n0,1\n"), "h")
    np.testing.assert_array_equal(data["h"], [1.0])


# --------------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    ("text", "columns", "match"),
    [
        ("", ["t"], "is empty"),
        ("\n  \n\n", ["t"], "is empty"),
        ("0,1\n1,2\n", ["t"], "no header row"),
        ("t,h\n", ["t"], "no data rows"),
        ("t,h\n0,1\n", ["y"], r"no column 'y'; available columns: 't', 'h'"),
        ("t,h,h\n0,1,2\n", ["h"], "names column 'h' 2 times"),
        ("t,h\n0,1\n1,abc\n", ["h"], r"column 'h', row 2 \(line 3\): 'abc' is not a number"),
        ("t,h\n0,1\n1,nan\n", ["h"], r"column 'h', row 2 \(line 3\) is 'nan'; .*finite"),
        ("t,h\n0,-inf\n1,1\n", ["h"], r"column 'h', row 1 \(line 2\) is '-inf'"),
        ("t,h\n0,1\n1,\n2,3\n", ["t", "h"], r"column 'h', row 2 \(line 3\) is empty"),
        ("t,h\n0,1\n1\n", ["h"], r"column 'h', row 2 \(line 3\) is empty"),
        ("t,h\n0,1,2,3\n", ["h"], "line 2: 4 fields but the header names 2 columns"),
    ],
    ids=[
        "empty", "blank", "no-header", "header-only", "missing-column", "duplicate-column",
        "non-numeric", "nan", "inf", "empty-cell", "short-row", "long-row",
    ],
)
def test_errors_are_one_line_data_errors(tmp_path, text, columns, match):
    path = _write(tmp_path, text)
    with pytest.raises(DataError, match=match) as info:
        read_columns(path, columns)
    assert "\n" not in str(info.value)
    assert str(path) in str(info.value)
    assert isinstance(info.value, KautzTwinError)


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        read_columns(tmp_path / "absent.csv", ["t"])


def test_directory_is_not_a_file(tmp_path):
    with pytest.raises(DataError, match="is a directory"):
        read_columns(tmp_path, ["t"])


def test_binary_file(tmp_path):
    path = tmp_path / "x.csv"
    path.write_bytes(b"t,h\n\xff\xfe\x00\x01\n")
    with pytest.raises(DataError, match="not a UTF-8 text file"):
        read_columns(path, ["t"])


def test_no_columns_requested(tmp_path):
    with pytest.raises(DataError, match="at least one column"):
        read_columns(_write(tmp_path, "t\n0\n"), [])
