"""``kautztwin reproduce simulation``'s summary explains a low or negative fit (#14 item 5)."""

from __future__ import annotations

from kautztwin.cli._reproduce import low_fit_notes


def _metrics(paper_fit: float, *, quick: bool) -> dict:
    return {
        "setup": {"quick": quick, "paper_epochs": 30 if quick else None, "n_train": 50},
        "methods": {
            "paper_dnn": {"fit_mean": paper_fit, "fit_median": 26.75, "fit_min": -382.98},
            "fixed_basis_ceiling": {"fit_mean": 68.9, "fit_median": 71.5, "fit_min": 22.3},
            "adaptive": {"fit_mean": 95.3, "fit_median": 95.7, "fit_min": 84.6},
        },
    }


def test_negative_quick_fit_is_explained():
    (note,) = low_fit_notes(_metrics(-1.42, quick=True)).values()
    for part in ("-1.42 %", "below 0", "no lower bound", "median 26.75 %", "-383 %",
                 "30 epochs", "learning rate 1e-5", "50 records", "68.90 %",
                 "bench_data_budget"):
        assert part in note, part


def test_low_full_run_fit_is_explained_without_the_quick_budget():
    (note,) = low_fit_notes(_metrics(51.11, quick=False)).values()
    assert "51.11 % is low" in note and "quick" not in note and "68.90 %" in note


def test_a_fit_near_the_ceiling_gets_no_note():
    assert low_fit_notes(_metrics(65.0, quick=False)) == {}
