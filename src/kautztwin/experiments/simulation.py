"""``kautztwin reproduce simulation``: the paper's section 3.1, made honest.

The sample system ``G(s) = k / ((s + a)(s + b)(s^2 + 2 zeta wn s + wn^2))`` with
nominal ``k = 6, a = 1, b = 3, wn = 2, zeta = 0.25`` (6/((s+1)(s+3)(s^2+s+4))),
+-50 % uniform uncertainty on every parameter, impulse responses on 0..20 s
with 900 samples and white noise of 10 % of each record's peak; 50 training
records split 85/15 as in the paper; evaluation on fresh test records against
the noise-free truth.  Methods:

``paper_dnn``
    The paper's networks (one per coefficient, ``paper`` preset) on the fixed
    nominal basis.
``projection``
    The noisy record projected onto the nominal basis (no learning).
``fixed_basis_ceiling``
    The noise-free truth projected onto the nominal basis (least squares on the
    grid): no estimator on this basis can fit better, record by record.
``adaptive``
    Our estimator that also predicts the poles (kautztwin.nn.AdaptivePoleEstimator), its
    least squares under the relative degree read from the training records (4: the
    system has no zeros).
``oracle``
    Nonlinear least squares with the true model structure, started at the true
    parameters: the statistical limit.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..basis import KautzBasis
from ..data import reference_poles
from ..datasets import ResponseDataset, draw_parameters, make_dataset, paper_system
from ..metrics import fit_percent

__all__ = ["SimulationSetup", "reproduce_simulation"]

PAPER_CLAIMS = {"accuracy_percent": 99.7, "coefficient_mse": 1e-6}


@dataclass(frozen=True)
class SimulationSetup:
    """Sizes and budgets of one reproduction run.

    Parameters
    ----------
    n_train : int
        Training records of the paper's networks (the paper: 50).
    n_test : int
        Fresh test records of the main case.
    n_sweep : int
        Test records per cell of the uncertainty x noise sweep.
    paper_epochs : int or None
        Epoch budget of the ``paper`` preset (``None``: the preset's 1000).
    adaptive_train : int
        Training records of the adaptive estimator (free synthetic data).
    adaptive_epochs : int or None
        Epoch budget of the adaptive estimator (``None``: its default of 6); the full run
        gives it 12, as ``benchmarks/bench_adaptive.py`` does: at 10 % noise its fit still
        improves after 6 epochs.
    oracle_records : int
        Test records the (slow) oracle is run on in the main case.
    sweep_adaptive_train : int
        Training records of the adaptive estimators of the sweep's other noise
        levels (the main case's estimator is reused at its noise level); 20 000, as the
        main case: with 8 000 the +-50 % / 5 % cell missed the 0.2-point bar (0.25).
    sweep_per_coefficient : bool
        Whether the sweep trains one paper network per coefficient (as the main
        case) or the single multi-output variant (4x cheaper; the default, to
        keep the full run within its budget).
    uncertainties, noises : tuple of float
        The sweep grid.
    """

    n_train: int = 50
    n_test: int = 1000
    n_sweep: int = 100
    paper_epochs: int | None = None
    adaptive_train: int = 20000
    adaptive_epochs: int | None = 12
    oracle_records: int = 1000
    uncertainties: tuple[float, ...] = (0.0, 0.1, 0.25, 0.5)
    noises: tuple[float, ...] = (0.0, 0.01, 0.05, 0.1)

    sweep_per_coefficient: bool = False
    sweep_adaptive_train: int = 20000

    @classmethod
    def quick(cls) -> SimulationSetup:
        """A small run for smoke tests and CI (well under a minute on 2 quiet cores)."""
        return cls(
            n_train=50,
            n_test=200,
            n_sweep=20,
            paper_epochs=30,
            adaptive_train=1000,
            adaptive_epochs=3,
            oracle_records=30,
            uncertainties=(0.0, 0.5),
            noises=(0.1,),
        )


T_GRID = np.linspace(0.0, 20.0, 900)


def _data(
    uncertainty: float, noise: float, n: int, seed: int, basis: KautzBasis
) -> ResponseDataset:
    system = paper_system()
    params = draw_parameters(system, uncertainty, n, random_state=seed)
    return make_dataset(system, params, basis, T_GRID, noise=noise, random_state=seed + 7)


def _stats(fits: NDArray, seconds_per_record: float, coef_mse: float | None = None) -> dict:
    out = {
        "fit_mean": float(np.mean(fits)),
        "fit_median": float(np.median(fits)),
        "fit_p10": float(np.percentile(fits, 10)),
        "fit_min": float(np.min(fits)),
        "seconds_per_record": float(seconds_per_record),
        "n_records": int(fits.size),
    }
    if coef_mse is not None:
        out["coef_mse"] = float(coef_mse)
    return out


def _timed(fn: Callable[[], Any], n: int) -> tuple[Any, float]:
    start = time.perf_counter()
    out = fn()
    return out, (time.perf_counter() - start) / max(n, 1)


class _Methods:
    """The estimators of one (uncertainty, noise) case, trained once."""

    def __init__(
        self,
        setup: SimulationSetup,
        uncertainty: float,
        noise: float,
        seed: int,
        basis: KautzBasis,
        progress: bool,
        adaptive: Any | None,
        per_coefficient: bool = True,
    ) -> None:
        from ..nn import CoefficientEstimator

        self.basis = basis
        self.K = basis.evaluate(T_GRID)  # (N, n)
        train = _data(uncertainty, noise, setup.n_train, seed, basis)
        cfg = None if setup.paper_epochs is None else {"max_epochs": setup.paper_epochs}
        self.paper = CoefficientEstimator(
            preset="paper",
            per_coefficient=per_coefficient,
            random_state=seed,
            progress=progress,
            config=cfg,
        ).fit(train)
        self.adaptive = adaptive

    def fits(self, test: ResponseDataset, *, with_oracle: int) -> dict[str, tuple[dict, NDArray]]:
        from ..approx import project
        from ..nn.oracle import oracle_fit

        n = len(test)
        clean, noisy, labels = test.clean, test.responses, test.coefficients
        # ceiling: least-squares projection of the truth on the grid (the fit-percent norm)
        c_ceiling, s_ceiling = _timed(
            lambda: np.linalg.lstsq(self.K.T, clean.T, rcond=None)[0].T, n
        )
        fit_ceiling = fit_percent(clean, c_ceiling @ self.K)
        out = {"fixed_basis_ceiling": (_stats(fit_ceiling, s_ceiling), fit_ceiling)}
        c_proj, s_proj = _timed(lambda: project(self.basis, T_GRID, noisy), n)
        f = fit_percent(clean, c_proj @ self.K)
        out["projection"] = (_stats(f, s_proj, np.mean((c_proj - labels) ** 2)), f)
        c_dnn, s_dnn = _timed(lambda: self.paper.predict(noisy), n)
        f = fit_percent(clean, c_dnn @ self.K)
        out["paper_dnn"] = (_stats(f, s_dnn, np.mean((c_dnn - labels) ** 2)), f)
        if self.adaptive is not None:
            y_ad, s_ad = _timed(lambda: self.adaptive.predict_responses(noisy), n)
            f = fit_percent(clean, y_ad)
            out["adaptive"] = (_stats(f, s_ad), f)
        if with_oracle:
            m = min(with_oracle, n)
            system = paper_system()

            def run_oracle() -> NDArray:
                return np.array(
                    [
                        oracle_fit(T_GRID, noisy[i], system, test.parameters[i]).response
                        for i in range(m)
                    ]
                )

            y_or, s_or = _timed(run_oracle, m)
            f = fit_percent(clean[:m], y_or)
            out["oracle"] = (_stats(f, s_or), f)
        return out


def reproduce_simulation(
    out_dir: str | Path,
    *,
    quick: bool = False,
    setup: SimulationSetup | None = None,
    random_state: int = 0,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the paper's simulation study and write metrics, figures and a report.

    Parameters
    ----------
    out_dir : str or Path
        Output folder (created): ``metrics.json``, ``report.md``,
        ``fig7_training.png``, ``fig8_approximations.png``, ``sweep.png``.
    quick : bool, default=False
        Use :meth:`SimulationSetup.quick` (a smoke run) unless ``setup`` is given.
    setup : SimulationSetup, optional
        Sizes and budgets.
    random_state : int, default=0
        Master seed.
    progress : bool, default=False
        Progress bars while training.
    log : callable, optional
        Receives one line per stage (e.g. ``print``).

    Returns
    -------
    dict
        The content of ``metrics.json``.
    """
    import torch

    from ..nn.adaptive import AdaptivePoleEstimator

    torch.set_num_threads(max(1, torch.get_num_threads()))
    say = log or (lambda _msg: None)
    setup = setup or (SimulationSetup.quick() if quick else SimulationSetup())
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    basis = KautzBasis(reference_poles())  # block order of the paper: -1, -3, pair
    t_start = time.perf_counter()

    # ---------------------------------------------------------------- main case
    say(f"training the paper's networks on {setup.n_train} records (+-50 %, 10 % noise)")
    adaptive_cfg = None if setup.adaptive_epochs is None else {"max_epochs": setup.adaptive_epochs}
    s0 = time.perf_counter()
    main = _Methods(setup, 0.5, 0.1, random_state, basis, progress, None)
    paper_seconds = time.perf_counter() - s0
    say(f"training the adaptive estimator on {setup.adaptive_train} synthetic records")
    s0 = time.perf_counter()
    adaptive = AdaptivePoleEstimator(
        config=adaptive_cfg, random_state=random_state, progress=progress,
        relative_degree="auto",
    ).fit_distribution(paper_system(), 0.5, T_GRID, noise=0.1, n_train=setup.adaptive_train)
    adaptive_seconds = time.perf_counter() - s0
    main.adaptive = adaptive
    test = _data(0.5, 0.1, setup.n_test, random_state + 1000, basis)
    say(f"evaluating on {setup.n_test} fresh test records (oracle on {setup.oracle_records})")
    results = main.fits(test, with_oracle=setup.oracle_records)
    methods = {name: stats for name, (stats, _) in results.items()}
    sanity = _sanity(results)

    # ---------------------------------------------------------------- sweep
    sweep = []
    for noise in setup.noises:
        say(f"sweep: noise {noise:.0%}")
        ad = (
            adaptive
            if noise == 0.1
            else AdaptivePoleEstimator(
                config=adaptive_cfg, random_state=random_state, progress=progress,
                relative_degree="auto",
            ).fit_distribution(
                paper_system(),
                0.5,
                T_GRID,
                noise=noise,
                n_train=min(setup.adaptive_train, setup.sweep_adaptive_train),
            )
        )
        for unc in setup.uncertainties:
            cell = _Methods(
                setup,
                unc,
                noise,
                random_state + 17,
                basis,
                False,
                ad,
                per_coefficient=setup.sweep_per_coefficient,
            )
            data = _data(unc, noise, setup.n_sweep, random_state + 2000, basis)
            res = cell.fits(data, with_oracle=setup.n_sweep)
            for name, (stats, _) in res.items():
                sweep.append(
                    {
                        "uncertainty": unc,
                        "noise": noise,
                        "method": name,
                        "fit_mean": stats["fit_mean"],
                    }
                )
            say(
                f"  uncertainty {unc:.0%}: "
                + ", ".join(f"{k} {v[0]['fit_mean']:.2f}" for k, v in res.items())
            )

    metrics: dict[str, Any] = {
        "setup": {
            **setup.__dict__,
            "t_end": 20.0,
            "n_samples": T_GRID.size,
            "uncertainty": 0.5,
            "noise": 0.1,
            "quick": quick,
            "random_state": random_state,
        },
        "methods": methods,
        "sweep": sweep,
        "train": {
            "paper_dnn": {
                "seconds": paper_seconds,
                "final_train_loss": [h.train_loss[-1] for h in main.paper.histories_],
                "final_val_loss": [h.val_loss[-1] for h in main.paper.histories_],
                "epochs": [len(h.train_loss) for h in main.paper.histories_],
            },
            "adaptive": {
                "seconds": adaptive_seconds,
                "final_train_loss": adaptive.histories_[-1].train_loss[-1],
                "final_val_loss": adaptive.histories_[-1].val_loss[-1],
                "epochs": sum(len(h.train_loss) for h in adaptive.histories_),
                "n_records": setup.adaptive_train,
            },
        },
        "sanity": sanity,
        "paper_claims": PAPER_CLAIMS,
        "seconds_total": time.perf_counter() - t_start,
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    _figures(out, main, test)
    _sweep_figure(out, sweep)
    (out / "report.md").write_text(_report(metrics))
    say(f"wrote {out}/metrics.json, report.md and figures in {metrics['seconds_total']:.0f} s")
    return metrics


def _sanity(results: dict[str, tuple[dict, NDArray]]) -> dict[str, Any]:
    """No estimator on the nominal basis may beat the ceiling, record by record."""
    ceiling = results["fixed_basis_ceiling"][1]
    out: dict[str, Any] = {"tolerance": 1e-9}
    for name in ("paper_dnn", "projection"):
        above = results[name][1] > ceiling + 1e-9
        out[f"{name}_records_above_ceiling"] = int(np.sum(above))
    out["passed"] = all(v == 0 for k, v in out.items() if k.endswith("above_ceiling"))
    if not out["passed"]:  # pragma: no cover - a failure here is a bug in the pipeline
        raise AssertionError(f"sanity check failed: {out}")
    return out


def _figures(out: Path, main: _Methods, test: ResponseDataset) -> None:
    from ..nn.plots import plot_history
    from ..plotting import _new_figure, save_figure

    fig, axes = _new_figure(len(main.paper.histories_), ncols=2, panel_size=(4.0, 3.2))
    for i, (ax, h) in enumerate(zip(np.ravel(axes), main.paper.histories_, strict=False)):
        plot_history(h, ax=ax)
        ax.set_title(f"network of c{i + 1} (paper preset)")
    save_figure(fig, out / "fig7_training.png")

    fig, axes = _new_figure(4, ncols=2, panel_size=(4.5, 3.2))
    noisy = test.responses[:4]
    c_dnn = main.paper.predict(noisy)
    y_ad = main.adaptive.predict_responses(noisy)
    for i, ax in enumerate(np.ravel(axes)):
        ax.plot(T_GRID, noisy[i], color="0.75", lw=0.8, label="measured (noisy)")
        ax.plot(T_GRID, test.clean[i], "k", lw=1.5, label="truth")
        ax.plot(T_GRID, c_dnn[i] @ main.K, "--", label="paper_dnn")
        ax.plot(T_GRID, y_ad[i], ":", lw=1.8, label="adaptive")
        ax.set_xlabel("t [s]")
        ax.set_title(f"test record {i + 1}")
        if i == 0:
            ax.legend(fontsize=7)
    save_figure(fig, out / "fig8_approximations.png")


def _sweep_figure(out: Path, sweep: list[dict]) -> None:
    from ..plotting import _new_figure, save_figure

    methods = sorted({r["method"] for r in sweep})
    cells = sorted({(r["uncertainty"], r["noise"]) for r in sweep})
    table = {(r["uncertainty"], r["noise"], r["method"]): r["fit_mean"] for r in sweep}
    grid = np.array([[table.get((u, nz, x), np.nan) for (u, nz) in cells] for x in methods])
    fig, (ax,) = _new_figure(1, panel_size=(max(6.0, 0.6 * len(cells)), 0.6 * len(methods) + 2))
    im = ax.imshow(grid, aspect="auto", cmap="viridis", vmin=max(0.0, np.nanmin(grid)), vmax=100)
    for i in range(grid.shape[0]):
        for j in range(grid.shape[1]):
            ax.text(
                j,
                i,
                f"{grid[i, j]:.1f}",
                ha="center",
                va="center",
                fontsize=7,
                color="k" if grid[i, j] > 60 else "w",
            )
    ax.set_yticks(range(len(methods)), methods)
    ax.set_xticks(range(len(cells)), [f"u{u:.0%}\nn{nz:.0%}" for u, nz in cells], fontsize=7)
    ax.set_title("mean fit % vs noise-free truth (u: uncertainty, n: noise)")
    fig.colorbar(im, ax=ax)
    save_figure(fig, out / "sweep.png")


def _report(m: dict[str, Any]) -> str:
    meth = m["methods"]
    order = ["oracle", "adaptive", "fixed_basis_ceiling", "projection", "paper_dnn"]
    lines = [
        "# Simulation study (the paper's section 3.1), reproduced",
        "",
        "System `6/((s+1)(s+3)(s^2+s+4))` with +-50 % uniform uncertainty on gain, both rates,",
        "natural frequency and damping; impulse responses on 0..20 s (900 samples) with white",
        "noise of 10 % of each record's peak; the paper's networks trained on 50 records (85/15).",
        f"Test: {meth['projection']['n_records']} fresh records; every fit is against the",
        "noise-free truth (MATLAB `compare` fit percent)."
        + (" **Quick run: small budgets.**" if m["setup"]["quick"] else ""),
        "",
        "| method | fit mean % | median % | p10 % | min % | coef MSE | s / record |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in order:
        if name not in meth:
            continue
        s = meth[name]
        mse = f"{s['coef_mse']:.3g}" if "coef_mse" in s else "-"
        lines.append(
            f"| `{name}` | {s['fit_mean']:.2f} | {s['fit_median']:.2f} | {s['fit_p10']:.2f} | "
            f"{s['fit_min']:.2f} | {mse} | {s['seconds_per_record']:.2e} |"
        )
    p, ceil = meth["paper_dnn"], meth["fixed_basis_ceiling"]
    ad, orc = meth.get("adaptive"), meth.get("oracle")
    lines += [
        "",
        "## Beside the paper's claims",
        "",
        f"* The paper reports about {PAPER_CLAIMS['accuracy_percent']} % accuracy and a "
        f"coefficient MSE of about {PAPER_CLAIMS['coefficient_mse']:g}.",
        "  Our `paper_dnn` reaches a mean fit of",
        f"  {p['fit_mean']:.2f} % against the noise-free truth and a coefficient MSE of "
        f"{p['coef_mse']:.3g}.",
        f"* No estimator on the fixed nominal basis can exceed the `fixed_basis_ceiling` "
        f"(mean {ceil['fit_mean']:.2f} %,",
        f"  minimum {ceil['fit_min']:.2f} %): under +-50 % uncertainty the four nominal Kautz",
        "  functions cannot represent many of the systems, whatever the network does. A figure",
        "  near 99.7 % is therefore not reachable on this basis in this setting; the paper's",
        "  figure must refer to another error measure or a narrower setting.",
        f"* Sanity check (no `paper_dnn` or `projection` record above the ceiling): "
        f"{'passed' if m['sanity']['passed'] else 'FAILED'}.",
    ]
    if ad and orc:
        gap = orc["fit_mean"] - ad["fit_mean"]
        speed = orc["seconds_per_record"] / max(ad["seconds_per_record"], 1e-12)
        lines += [
            f"* `adaptive` (poles predicted per record) reaches {ad['fit_mean']:.2f} % against the",
            f"  oracle's {orc['fit_mean']:.2f} % (gap {gap:.2f} points) and is {speed:.0f}x faster",
            "  per record than the oracle.",
        ]
    lines += [
        "",
        "## Training",
        "",
        f"* paper networks: {m['train']['paper_dnn']['seconds']:.1f} s, epochs "
        f"{m['train']['paper_dnn']['epochs']}, final validation losses "
        f"{', '.join(f'{v:.3g}' for v in m['train']['paper_dnn']['final_val_loss'])}",
        f"* adaptive: {m['train']['adaptive']['seconds']:.1f} s on "
        f"{m['train']['adaptive']['n_records']} records, {m['train']['adaptive']['epochs']} epochs",
        "",
        "## Sweep (mean fit %, uncertainty x noise)",
        "",
    ]
    methods = sorted({r["method"] for r in m["sweep"]})
    cells = sorted({(r["uncertainty"], r["noise"]) for r in m["sweep"]})
    lines.append("| uncertainty | noise | " + " | ".join(f"`{x}`" for x in methods) + " |")
    lines.append("|---|---|" + "---|" * len(methods))
    table = {(r["uncertainty"], r["noise"], r["method"]): r["fit_mean"] for r in m["sweep"]}
    for u, nz in cells:
        row = [f"{table.get((u, nz, x), float('nan')):.2f}" for x in methods]
        lines.append(f"| {u:.0%} | {nz:.0%} | " + " | ".join(row) + " |")
    lines += [
        "",
        "Figures: `fig7_training.png` (paper networks' loss curves),",
        "`fig8_approximations.png` (truth vs estimates), `sweep.png`.",
        "",
    ]
    return "\n".join(lines)
