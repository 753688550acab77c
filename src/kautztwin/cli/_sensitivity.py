"""``kautztwin sensitivity``: ISE maps over each basis pole's location (Figure 3)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from ._common import (
    CLIError,
    add_data_arguments,
    check_output,
    format_pole,
    load_record,
    parse_poles,
    parse_span,
    print_json,
)

__all__ = ["register", "run"]

_MAX_GRID = 1000

DESCRIPTION = """\
Map how the approximation error depends on the basis poles (the paper's
Figure 3).  Each pole is moved in turn while the others stay where --poles puts
them, and for every candidate location the integral of squared error (ISE) of
the best approximation is computed:

  * a real pole p gets a curve of ISE against its location, from LO*p to HI*p;
  * a complex pair -a +- bj gets a surface of log10 ISE over its real part
    (-LO*a ... -HI*a) and imaginary part (LO*b ... HI*b), the conjugate moving along.

All maps go into one figure (--out), one panel per real pole or pair, with the
minimum marked.  Without DATA the target is the built-in reference system
6/((s+1)(s+3)(s^2+s+4)) and the ISE is exact (Sylvester and Lyapunov equations;
with --kind step: its sampled step response).  With DATA the ISE is that of
the least-squares fit on the record's grid.
"""

EPILOG = """\
examples:
  kautztwin sensitivity --poles "-1,-3,-0.5+1.9365j,-0.5-1.9365j" --out fig3.png
  kautztwin sensitivity --poles "-1.1,-0.8,-2.1" --grid 200 --span 0.1:4 --out maps.png --json
  kautztwin sensitivity examples/measured.csv --time t --response h --poles "-1,-2" --out s.png
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``sensitivity`` command to the command-line parser."""
    p = subparsers.add_parser(
        "sensitivity", parents=[common], allow_abbrev=False,
        help="maps of the ISE over each basis pole's location (Figure 3)",
        description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    data = p.add_argument_group("data")
    add_data_arguments(data, noise=False)
    maps = p.add_argument_group("maps")
    maps.add_argument(
        "--poles", required=True, metavar="LIST",
        help="comma-separated basis poles around which to map, e.g. "
        "\"-1,-3,-0.5+1.9365j,-0.5-1.9365j\"; each complex pole with its conjugate "
        "(or a+-bj for both); 'i' may replace 'j'",
    )
    maps.add_argument("--grid", type=int, default=100, metavar="N",
                      help="points per axis: N per curve, N x N per surface (default: %(default)s)")
    maps.add_argument(
        "--span", default="0.2:3", metavar="LO:HI",
        help="range of each map as factors of the pole's rate |Re p| (and, for a pair, of its "
        "imaginary part) (default: %(default)s)",
    )
    out = p.add_argument_group("output")
    out.add_argument("--out", required=True, metavar="FILE",
                     help="figure file to write (.png, .pdf, .svg, ...)")
    out.add_argument(
        "--json", action="store_true",
        help="print one JSON object instead of the table: source, kind, poles, ise (at the "
        "given poles), span, grid, and per map its index, type, pole, best location and best_ise",
    )
    p.set_defaults(run=run)


def _target(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Keyword arguments of ``pole_sensitivity`` for the target, and its description."""
    if args.data is None and args.kind == "impulse" and args.amplitude is None \
            and args.input is None:
        from ..data import reference_system

        return {"system": reference_system()}, "built-in reference system, exact ISE"
    record = load_record(args)
    source = record.source
    if record.amplitude != 1:
        source += (
            f", per unit input (divided by {record.amplitude:g} from {record.amplitude_source})"
        )
    return {"t": record.t, "h": record.y, "kind": args.kind}, source


def run(args: argparse.Namespace) -> int:
    """Run ``kautztwin sensitivity``; return the exit status."""
    import kautztwin

    from .. import plotting

    out = check_output(args.out, "--out")
    lo, hi = parse_span(args.span)
    if not 2 <= args.grid <= _MAX_GRID:
        raise CLIError(f"--grid must be between 2 and {_MAX_GRID}, got {args.grid}")
    poles = parse_poles(args.poles)
    kautztwin.KautzBasis(poles)  # validates stability and pairing up front
    target, source = _target(args)

    factors = np.linspace(lo, hi, args.grid)
    panels = [i for i, p in enumerate(poles) if p.imag >= 0]
    nominal = float(kautztwin.pole_sensitivity(poles, panels[0], [poles[panels[0]]], **target)[0])
    fig, axes = plotting._new_figure(len(panels))
    maps: list[dict[str, Any]] = []
    for ax, i in zip(axes, panels, strict=True):
        p = poles[i]
        if p.imag == 0:
            values = p.real * factors
            ise = kautztwin.pole_sensitivity(poles, i, values, **target)
            k = int(np.argmin(ise))
            best = complex(values[k])
            plotting.plot_sensitivity_curve(
                values, ise, ax=ax, nominal=p.real, xlabel=f"location of pole {i + 1}",
                title=f"real pole {i + 1}: p = {format_pole(p)}",
            )
        else:
            re, im = p.real * factors, p.imag * factors
            grid = re[None, :] + 1j * im[:, None]
            ise = kautztwin.pole_sensitivity(poles, i, grid, **target)
            k = int(np.argmin(ise))
            best = complex(grid.flat[k])
            plotting.plot_sensitivity_surface(
                re, im, ise, ax=ax, nominal=p,
                title=f"pair {i + 1}: p = {p.real:.4g} ± {p.imag:.4g}j",
            )
        maps.append({
            "index": i,
            "type": "real" if p.imag == 0 else "pair",
            "pole": [p.real, p.imag],
            "best": [best.real, best.imag],
            "best_ise": float(ise.flat[k]),
        })
    fig.suptitle(f"ISE vs. basis pole locations ({source})")
    plotting.save_figure(fig, out)

    summary = {
        "source": source,
        "kind": args.kind,
        "poles": [[p.real, p.imag] for p in poles],
        "ise": nominal,
        "span": [lo, hi],
        "grid": args.grid,
        "maps": maps,
        "out": str(out),
    }
    if args.json:
        print_json(summary)
        return 0
    lines = [
        f"target:  {source}",
        f"ISE at the given poles: {nominal:.6g}",
        "",
        f"{'i':>3}  {'type':<5} {'pole':<22}{'best location':<24}{'best ISE':>12}",
    ]
    for m in maps:
        best = complex(*m["best"])
        if m["type"] == "real":
            best_text = format_pole(best)
        else:
            best_text = f"{best.real:.6g}±{best.imag:.6g}j"
        lines.append(
            f"{m['index'] + 1:>3}  {m['type']:<5} {format_pole(complex(*m['pole'])):<22}"
            f"{best_text:<24}{m['best_ise']:>12.4g}"
        )
    lines += ["", f"wrote {out} ({len(maps)} maps, span {lo:g}:{hi:g}, grid {args.grid})"]
    sys.stdout.write("\n".join(lines) + "\n")
    return 0
