"""Laguerre (N = 8, 16) versus the matched Kautz basis (N = 4) on the reference system.

The reference system G(s) = 6 / ((s+1)(s+3)(s^2+s+4)) has a lightly damped
complex pair.  A Laguerre basis (one repeated real pole) needs many functions
to follow the oscillation, while a Kautz basis with the system's poles
represents it exactly with four.  Coefficients come from the Sylvester
equation (exact, no quadrature); fits are evaluated on t = 0, 0.1, ..., 20
(201 points).  The numbers reproduce the table of kautz-math.md section 9.2,
and the script stops with an error if they do not.

Usage: python examples/laguerre_vs_kautz.py [OUTPUT_DIR]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import scipy.signal  # noqa: E402

import kautztwin as kt  # noqa: E402
from kautztwin.data import reference_poles, reference_system  # noqa: E402

# kautz-math.md 9.2: ISE, impulse fit %, step fit %, G_N(0)
REFERENCE = {
    "Laguerre a=1, N=8": (4.781179e-3, 80.659037, 81.018361, 0.5485387731),
    "Laguerre a=2, N=8": (2.451284e-3, 85.334798, 86.454059, 0.5193259442),
    "Laguerre a=2, N=16": (4.125863e-5, 98.097903, 98.842639, 0.5025194066),
    "Kautz (system poles), N=4": (0.0, 100.0, 100.0, 0.5),
}


def main(out_dir: Path) -> None:
    system = reference_system()
    t = np.arange(201) * 0.1
    _, h = scipy.signal.impulse(system, T=t)
    _, y = scipy.signal.step(system, T=t)
    bases = {
        "Laguerre a=1, N=8": kt.LaguerreBasis(pole=-1.0, n=8),
        "Laguerre a=2, N=8": kt.LaguerreBasis(pole=-2.0, n=8),
        "Laguerre a=2, N=16": kt.LaguerreBasis(pole=-2.0, n=16),
        "Kautz (system poles), N=4": kt.KautzBasis(reference_poles()),
    }

    header = f"{'basis':<27}{'ISE':>11}{'impulse fit %':>15}{'step fit %':>12}{'G_N(0)':>10}"
    print(header)
    print("-" * len(header))
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(t, h, "k", lw=2, label="system")
    mismatches = []
    for name, basis in bases.items():
        model = kt.KautzModel(basis, kt.coefficients_from_system(basis, system))
        row = (
            kt.ise_from_system(basis, system),
            kt.fit_percent(h, model.impulse(t)),
            kt.fit_percent(y, model.step(t)),
            model.dc_gain,
        )
        print(f"{name:<27}{row[0]:>11.3e}{row[1]:>15.4f}{row[2]:>12.4f}{row[3]:>10.5f}")
        if not np.allclose(row, REFERENCE[name], rtol=1e-6, atol=1e-9):
            mismatches.append(name)
        ax.plot(t, model.impulse(t), "--", label=name)
    if mismatches:
        raise SystemExit(f"results differ from kautz-math.md 9.2 for: {', '.join(mismatches)}")
    print("\nall rows agree with kautz-math.md 9.2 (relative tolerance 1e-6)")

    ax.set(title="Impulse response of the reference system", xlabel="t [s]")
    ax.legend()
    fig.tight_layout()
    path = out_dir / "laguerre_vs_kautz.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    print("figure:", path)


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="kautztwin-"))
    out.mkdir(parents=True, exist_ok=True)
    main(out)
