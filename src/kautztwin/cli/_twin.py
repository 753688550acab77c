"""``kautztwin twin run`` / ``serve`` / ``history``: the twin offline, as a service, read back.

``run`` also settles what the store's unfinished runs become (resumed with the same options,
refused with other ones, ``abandoned`` with ``--new``); ``history`` reads a run back
(:func:`kautztwin.twin.history.read_run`).
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from pathlib import Path
from typing import Any

from .._validation import check_memory
from ._common import CLIError, print_json, stop_on_signals

__all__ = ["history", "register", "run", "serve"]

# the run's per-sample arrays (15), their copy in the result, the excitation and the report's
# temporaries: about 40 float64 values per sample
_BYTES_PER_SAMPLE = 40 * 8

DESCRIPTION = """\
Run the digital twin of a plant: an open-loop identification phase (binary
excitation, output-error identification of a Kautz model), then closed-loop
Kautz/Laguerre MPC tracking of set-point steps while the twin keeps itself
synchronised (recursive least squares on Kautz filters, re-identification on
desynchronisation, pole re-optimisation and MPC weight retuning, each
validated before it replaces the running version).  Every sample is committed
to a SQLite history; a run that is killed resumes from it when the same
command is run again.

Writes DIR/metrics.json, DIR/report.md, DIR/outputs.png, DIR/sync_fit.png,
DIR/tracking.png, DIR/timings.png and DIR/history.sqlite.  See docs/twin.md.
"""

RUN_DESCRIPTION = DESCRIPTION + """
plants:
  hydraulic      electro-hydraulic servo drive (valve command 0.3..0.7, speed in
                 rad/s, dt 0.02 s); --drift moves its dominant pole during the run
  tclab          Temperature Control Lab emulator (heater 0..100 %, temperature in
                 degC, dt 1 s)
  replay:FILE    a recorded CSV (columns t, u, y); the twin follows the record
                 (no control)
"""

EPILOG = """\
examples:
  kautztwin twin run --plant hydraulic --duration 90 --drift 0.4 --out runs/hyd
  kautztwin twin run --plant hydraulic --quick --drift 0.4 --faults dropout=0.01,outlier=0.005 \\
      --out runs/quick
  kautztwin twin run --plant tclab --setpoints 50,40,45 --out runs/tclab
  kautztwin twin run --plant hydraulic --setpoints 20:97,45:103,70:100 --drift 0.4@30,60 \\
      --speedup 5 --out runs/live
  kautztwin twin run --plant hydraulic --speedup 1 --no-background --out runs/sync
  kautztwin twin run --plant hydraulic --quick --duration 30 --out runs/new --new
  kautztwin twin history runs/quick --signals y,u,prediction --start 20 --end 25

Set-points are in the plant's output units: values at equal intervals over the
closed-loop phase, or time:value pairs (seconds from the start of the run).
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``twin`` command (with its ``run`` and ``serve`` actions) to the parser.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``kautztwin`` command's subparsers.
    common : argparse.ArgumentParser
        Parent parser with the flags every command shares (``--debug``).
    """
    p = subparsers.add_parser(
        "twin", parents=[common], allow_abbrev=False,
        help="run the digital twin (identification, MPC, updates, history) on a plant",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = p.add_subparsers(dest="action", title="actions", metavar="ACTION", required=True)
    r = actions.add_parser(
        "run", parents=[common], allow_abbrev=False,
        help="run (or resume) the twin on a plant and write metrics, report and plots",
        description=RUN_DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    r.add_argument("--plant", required=True, metavar="PLANT",
                   help="hydraulic, tclab or replay:FILE (see above)")
    r.add_argument("--duration", type=float, metavar="S",
                   help="run length in seconds (default: 90 hydraulic, 3600 tclab, the record "
                   "for a replay; --quick: 40 and 1800)")
    r.add_argument("--setpoints", metavar="LIST",
                   help="set-points in output units: v1,v2,... at equal intervals, or t:v pairs "
                   "(default: 97,103,100 rad/s hydraulic; 50,40,45 degC tclab)")
    r.add_argument(
        "--drift", metavar="FRACTION[@T1,T2,...]",
        help="hydraulic only: slow the dominant pole by FRACTION (0.4 = 40 %%) in equal steps "
        "starting at T1, T2, ... s (default: at 1/3 and 2/3 of the run); a negative value "
        "needs '=' (--drift=-0.2)",
    )
    r.add_argument("--faults", metavar="SPEC",
                   help="inject sensor faults after the identification phase, e.g. "
                   "dropout=0.01,outlier=0.005,late=0.005[,size=40]")
    r.add_argument("--quick", action="store_true",
                   help="a short run for a smoke test (well under a minute)")
    r.add_argument("--speedup", type=float, metavar="X",
                   help="pace the run in real time, X plant seconds per wall-clock second "
                   "(default: as fast as possible)")
    r.add_argument("--background", action=argparse.BooleanOptionalAction, default=None,
                   help="re-identify, retune the MPC and retrain the estimator in worker "
                   "threads, off the sampling path (default: on with --speedup, where "
                   "synchronous work would make samples late; off otherwise, so that a run as "
                   "fast as possible is reproducible)")
    r.add_argument("--seed", type=int, default=0,
                   help="seed of the excitation, the dither, the faults and the sensor noise "
                   "(default: %(default)s)")
    r.add_argument("--store", metavar="PATH",
                   help="SQLite history file (default: DIR/history.sqlite)")
    r.add_argument("--new", "--no-resume", dest="new", action="store_true",
                   help="start a new run even if the store holds an unfinished one (that one "
                   "is marked 'abandoned'); without it, an unfinished run started with the "
                   "same options is resumed and one started with other options is an error")
    r.add_argument("--no-static", action="store_true",
                   help="skip the static-twin comparison (updates disabled)")
    r.add_argument("--no-plots", action="store_true", help="write no plots")
    r.add_argument("--no-progress", action="store_true",
                   help="no live progress display (it is shown only on a terminal anyway)")
    r.add_argument("--out", required=True, metavar="DIR",
                   help="folder for metrics.json, report.md, the plots and the history")
    r.add_argument("--json", action="store_true",
                   help="print metrics.json to stdout instead of the one-line summary")
    r.set_defaults(run=run)
    _register_serve(actions, common)
    _register_history(actions, common)


SERVE_DESCRIPTION = """\
Run the digital twin as a long-lived service on the wall clock: the same
modules as 'twin run' (identification, Kautz MPC, updates, history), attached
to a plant that runs on its own - an in-process simulator paced in real time
(--speed X times faster) or an OPC UA server (a PLC, or 'kautztwin plant
serve').  Runs until SIGTERM / Ctrl-C (or --duration wall-clock seconds),
then commits what is pending, writes DIR/metrics.json and DIR/report.md and
exits 0; the same command resumes the run from DIR/history.sqlite.  Events
(model versions, re-identifications, outages, reconnects) are logged on
stderr as key=value pairs (or JSON lines).

Every key of the TOML file (--config) is also a flag --SECTION-KEY
(e.g. --mpc-u-max 0.65, --plant-drift-events 30,50); flags override the file.
See docs/service.md for the reference and examples/twin.toml.
"""

SERVE_EPILOG = """\
examples:
  kautztwin twin serve --plant hydraulic --speed 10 --out runs/live
  kautztwin plant serve --plant hydraulic --speed 10 --drift 0.4@30,50 &
  kautztwin twin serve --plant opc.tcp://127.0.0.1:4840 --out runs/opcua
  kautztwin twin serve --config examples/twin.toml --out runs/svc --logging-format json
"""


def _register_serve(actions: argparse._SubParsersAction,
                    common: argparse.ArgumentParser) -> None:
    from ..service.config import SCHEMA, SHORT_FLAGS

    s = actions.add_parser(
        "serve", parents=[common], allow_abbrev=False,
        help="run the twin as a long-lived service (until SIGTERM), resumable",
        description=SERVE_DESCRIPTION, epilog=SERVE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("--config", metavar="FILE", help="TOML service configuration")
    s.add_argument("--plant", metavar="PLANT",
                   help="hydraulic, tclab (in-process simulators), opc.tcp://HOST:PORT, "
                        "mqtt://HOST:PORT or replay:FILE")
    short = {v: k for k, v in SHORT_FLAGS.items()}
    for flag, (section, key) in SHORT_FLAGS.items():
        s.add_argument(flag, dest=f"cfg__{section}__{key}", metavar="VALUE",
                       help=f"same as --{section}-{key.replace('_', '-')}")
    group = s.add_argument_group("configuration keys (override the file)")
    for section, keys in SCHEMA.items():
        for key, (_, _default, text) in keys.items():
            extra = f" (short: {short[(section, key)]})" if (section, key) in short else ""
            group.add_argument(f"--{section}-{key.replace('_', '-')}",
                               dest=f"cfg__{section}__{key}", metavar="VALUE",
                               help=f"{text}{extra}")
    s.set_defaults(run=serve)


def serve(args: argparse.Namespace) -> int:
    """Run the ``twin serve`` command.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags.

    Returns
    -------
    int
        0 after a clean stop (signal, ``--duration`` or the end of the horizon).

    Raises
    ------
    KautzTwinError
        On a bad configuration (one line, exit 2) or an unreachable plant.
    """
    from ..service import TwinService, configure_logging, load_service_config

    overrides: dict[str, Any] = {}
    if args.plant is not None:
        text = args.plant.strip()
        if text.lower().startswith("opc.tcp://"):
            overrides.update({"plant.kind": "opcua", "plant.endpoint": text})
        else:
            overrides["plant.kind"] = text
    for name, value in vars(args).items():
        if name.startswith("cfg__") and value is not None:
            _, section, key = name.split("__")
            overrides[f"{section}.{key}"] = value
    config = load_service_config(args.config, overrides)
    log = config.values["logging"]
    configure_logging(log["level"], config.log_file, log["format"])
    import logging

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    config.out.mkdir(parents=True, exist_ok=True)
    service = TwinService(config)
    with stop_on_signals(service.request_stop):
        service.build()
        s = service.run()
    resumed = f" (resumed after {s['resume_k']})" if s["resumed"] else ""
    fit = s.get("sync_fit_mean")
    fit_text = "n/a" if fit is None else f"{fit:.1f} %"
    sys.stdout.write(
        f"twin serve {config.plant['kind']}: {s['n_samples']} samples{resumed}, "
        f"{s['reason']}; model version {s['version']}, sync fit mean {fit_text}, "
        f"{s['outages']} outages, {s['reconnects']} reconnects; store {config.history_path}\n")
    return 0


HISTORY_DESCRIPTION = """\
Read a twin's store back (DIR/history.sqlite, or the file itself): the
measured output y and input u, the twin's one-step prediction of each sample,
the set-point in force and the sample flags, with the run's model versions
and events.  Without --csv or --json it prints a summary and the samples of
the window as a table.
"""

HISTORY_EPILOG = """\
examples:
  kautztwin twin run --plant hydraulic --quick --no-plots --out runs/quick
  kautztwin twin history runs/quick --start 20 --end 20.1
  kautztwin twin history runs/quick --signals y,prediction --csv runs/quick/window.csv
  kautztwin twin history runs/quick --json --start 39.9
"""


def _register_history(actions: argparse._SubParsersAction,
                      common: argparse.ArgumentParser) -> None:
    h = actions.add_parser(
        "history", parents=[common], allow_abbrev=False,
        help="read a twin's store back (samples, predictions, versions, events)",
        description=HISTORY_DESCRIPTION, epilog=HISTORY_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    h.add_argument("dir", metavar="DIR", help="the run's folder (or its history.sqlite)")
    h.add_argument("--signals", metavar="LIST", default="y,u,prediction,setpoint",
                   help="comma-separated, among y, u, prediction, setpoint, flags "
                   "(default: %(default)s)")
    h.add_argument("--start", type=float, metavar="T", help="first time, s")
    h.add_argument("--end", type=float, metavar="T", help="last time, s")
    h.add_argument("--run", dest="run_id", type=int, metavar="ID",
                   help="run id (default: the last run)")
    fmt = h.add_mutually_exclusive_group()
    fmt.add_argument("--csv", metavar="FILE", help="write the samples to a CSV file")
    fmt.add_argument("--json", action="store_true",
                     help="print the run (samples, versions, events) as JSON")
    h.set_defaults(run=history)


def history(args: argparse.Namespace) -> int:
    """Run the ``twin history`` command.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags.

    Returns
    -------
    int
        Exit status (0).

    Raises
    ------
    CLIError
        On a folder without a store, an unknown signal or run, or a bad window.
    """
    from ..twin.history import SIGNALS, SQLiteHistory, read_run

    where = Path(args.dir)
    store = where / "history.sqlite" if where.is_dir() else where
    if not store.is_file():
        raise CLIError(f"{args.dir}: no twin history here (expected {store}); "
                       "'kautztwin twin run --out DIR' writes one")
    signals = tuple(s.strip() for s in args.signals.split(",") if s.strip())
    if not signals:
        raise CLIError(f"--signals: give at least one of {', '.join(SIGNALS)}")
    if args.csv and Path(args.csv).is_dir():
        raise CLIError(f"--csv {args.csv}: is a directory")
    h = SQLiteHistory(store)  # a file that is not SQLite: HistoryError, one line
    try:
        r = read_run(h, args.run_id, signals=signals, start=args.start, end=args.end)
    finally:
        h.close()
    if args.json:
        print_json(r.to_dict())
        return 0
    names = list(r.columns)
    n = int(r.columns["t"].size)
    if args.csv:
        import csv

        with open(args.csv, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(names)
            for i in range(n):
                w.writerow(["" if isinstance(v, float) and not math.isfinite(v) else v
                            for v in (r.columns[c][i].item() for c in names)])
        sys.stdout.write(f"twin history run {r.run_id} ({r.status}): wrote {n} samples "
                         f"({', '.join(names)}) to {args.csv}\n")
        return 0
    t = r.columns["t"]
    span = f"t {t[0]:g}..{t[-1]:g} s" if n else "no samples in the window"
    kinds: dict[str, int] = {}
    for e in r.events:
        kinds[e["kind"]] = kinds.get(e["kind"], 0) + 1
    ev = ", ".join(f"{v} {k}" for k, v in kinds.items()) or "none"
    lines = [f"run {r.run_id} ({r.status}) of {r.plant}: {r.n_committed} committed samples; "
             f"{n} in the window ({span}); {len(r.versions)} model versions; events: {ev}"]
    shown = range(n) if n <= 40 else [*range(20), -1, *range(n - 20, n)]
    lines.append("  ".join(f"{c:>11}" for c in names))
    for i in shown:
        if i < 0:
            lines.append(f"{'...':>11}  ({n - 40} more rows; --csv FILE writes them all)")
            continue
        cells = []
        for c in names:
            v = r.columns[c][i].item()
            cells.append(f"{v:>11d}" if isinstance(v, int) else f"{v:>11.5g}")
        lines.append("  ".join(cells))
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def _parse_drift(text: str | None, duration: float) -> tuple[float, tuple[float, ...]]:
    if text is None:
        return 0.0, ()
    value, _, times = text.partition("@")
    try:
        drift = float(value)
    except ValueError:
        raise CLIError(
            f"--drift must be FRACTION or FRACTION@T1,T2 (e.g. 0.4@30,60), got {text!r}"
        ) from None
    if not (math.isfinite(drift) and -0.9 < drift < 0.9):
        raise CLIError(f"--drift must be a fraction in (-0.9, 0.9), got {drift:g}")
    if times:
        try:
            events = tuple(float(x) for x in times.split(",") if x.strip())
        except ValueError:
            raise CLIError(f"--drift: cannot read the event times in {text!r}") from None
        if not events or any(not (0 < e < duration) for e in events):
            raise CLIError(f"--drift: event times must lie inside the run (0, {duration:g}) s")
    else:
        events = (duration / 3.0, 2.0 * duration / 3.0)
    return drift, tuple(sorted(events))


def run(args: argparse.Namespace) -> int:
    """Run the ``twin run`` command.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags.

    Returns
    -------
    int
        Exit status (0).
    """
    from ..twin.physical import Clock
    from ..twin.report import compute_metrics, write_report
    from ..twin.runtime import DigitalTwin, TwinConfig, make_plant

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise CLIError(f"--duration must be a positive number of seconds, got {args.duration:g}")
    if args.speedup is not None and not (math.isfinite(args.speedup) and args.speedup > 0):
        raise CLIError(f"--speedup must be a positive factor, got {args.speedup:g}")
    kind = args.plant.partition(":")[0].strip().lower()
    if kind not in ("hydraulic", "tclab", "replay"):
        raise CLIError(f"--plant must be hydraulic, tclab or replay:FILE, got {args.plant!r}")
    if kind != "hydraulic" and args.drift is not None:
        raise CLIError("--drift applies to the hydraulic plant only")
    if kind == "replay" and args.setpoints is not None:
        raise CLIError("--setpoints do not apply to a replay (the record fixes the input)")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {args.out}: exists and is not a directory")
    store = Path(args.store) if args.store else out / "history.sqlite"
    if kind != "replay":
        duration = args.duration if args.duration is not None else TwinConfig.for_plant(
            kind, quick=args.quick).duration
    else:
        duration = args.duration if args.duration is not None else math.inf
    drift, events = _parse_drift(args.drift, duration)
    plant = make_plant(args.plant, drift=drift, drift_events=events, seed=args.seed)
    if math.isfinite(duration):  # the size is known before any work: refuse what cannot fit
        n = duration / float(plant.dt)
        check_memory(n * _BYTES_PER_SAMPLE,
                     f"--duration {duration:g} s ({n:.3g} samples at dt {float(plant.dt):g} s)")
    config = TwinConfig.for_plant(
        plant, duration=args.duration, setpoints=args.setpoints, quick=args.quick,
        seed=args.seed, faults=args.faults, drift_events=events,
        static_twin=not args.no_static,
    )
    if events and events[0] <= config.ident_duration:
        raise CLIError(
            f"--drift: the first event ({events[0]:g} s) falls inside the identification phase "
            f"(first {config.ident_duration:g} s)"
        )
    clock = Clock.real_time(args.speedup, tolerance=config.dt) if args.speedup else None
    out.mkdir(parents=True, exist_ok=True)
    if not store.parent.is_dir():
        raise CLIError(f"--store {store}: directory {str(store.parent)!r} does not exist")
    stored_config = {"twin": config.to_dict(), "plant": plant.name}
    _settle_unfinished(store, stored_config, new=args.new)
    command = "kautztwin " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if (
        sys.argv and Path(sys.argv[0]).name in ("kautztwin", "__main__.py")) else None
    twin = DigitalTwin(plant, config, history=store, clock=clock, background=args.background)
    try:
        try:
            twin.start(resume=not args.new)
            if twin.k == 0 and twin.run_id is not None:
                twin.history.log_event(twin.run_id, "command", command or "(library call)",
                                       payload={"argv": _argv(args)})
            result = twin.run(progress=False if args.no_progress else None)
        except KeyboardInterrupt:
            if twin.run_id is not None:
                twin.finish()  # commits what is pending; the run stays resumable
            raise
        paths = write_report(result, out, command=command, plots=not args.no_plots)
    finally:
        twin.close()
    metrics = compute_metrics(result) if args.json else json.loads(
        paths["metrics"].read_text(encoding="utf-8"))
    if args.json:
        print_json(metrics)
        return 0
    sys.stdout.write(_summary(metrics, out, len(paths) - 2) + "\n")
    return 0


_KEPT = ("plant", "duration", "setpoints", "drift", "faults", "quick", "seed", "no_static",
         "store", "out")


def _argv(args: argparse.Namespace) -> dict[str, Any]:
    """The options of a ``twin run`` as given (stored with the run, for messages)."""
    return {k: getattr(args, k) for k in _KEPT if getattr(args, k, None) not in (None, False)}


def _command_line(argv: dict[str, Any]) -> str:
    """``kautztwin twin run ...`` from the stored options of a run."""
    words = ["kautztwin", "twin", "run"]
    for key in sorted(argv, key=lambda k: _KEPT.index(k) if k in _KEPT else len(_KEPT)):
        value = argv[key]
        value = f"{value:g}" if isinstance(value, float) else value
        flag = "--" + key.replace("_", "-")
        if value is True:
            words.append(flag)
        elif not (key == "seed" and value == 0):
            words += [flag, shlex.quote(str(value))]
    return " ".join(words)


def _config_diff(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """``name old, now new`` for the settings that differ (at most two)."""
    a, b = dict(old.get("twin", {})), dict(new.get("twin", {}))
    a["plant"], b["plant"] = old.get("plant"), new.get("plant")
    diff = []
    for key in sorted(set(a) | set(b)):
        if a.get(key) != b.get(key):
            x, y = (json.dumps(v, separators=(",", ":")) for v in (a.get(key), b.get(key)))
            x, y = (v if len(v) <= 24 else v[:21] + "..." for v in (x, y))
            diff.append(f"{key} {x}, now {y}")
    return diff[:2]


def _settle_unfinished(store: Path, config: dict[str, Any], *, new: bool) -> None:
    """Resume, abandon or refuse: what to do with the store's unfinished runs.

    An unfinished run started with the same options is resumed (nothing to do
    here); with ``new`` every unfinished run is marked ``'abandoned'``;
    otherwise an unfinished run started with other options is an error that
    says how to resume it or start over.
    """
    if not store.is_file():
        return
    from ..twin.history import SQLiteHistory

    try:
        history = SQLiteHistory(store)
    except Exception as exc:  # a file that is not a twin store
        raise CLIError(f"--store {store}: not a readable twin history ({exc})") from None
    try:
        unfinished = [r for r in history.runs() if r.status == "running"]
        if new:
            for info in unfinished:
                history.log_event(info.run_id, "abandoned",
                                  "abandoned: a new run was started with --new")
                history.finish_run(info.run_id, "abandoned")
            return
        if not unfinished or any(r.config == config for r in unfinished):
            return
        last = unfinished[-1]
        n = history.measurements(last.run_id).k.size
        total = int(round(last.config.get("twin", {}).get("duration", 0)
                          / max(last.config.get("twin", {}).get("dt", 1.0), 1e-12)))
        started = [e.payload for e in history.events(last.run_id, "command")]
    finally:
        history.close()
    argv = started[0].get("argv") if started and isinstance(started[0], dict) else None
    how = (f"resume it with '{_command_line(argv)}'" if isinstance(argv, dict) and argv
           else "resume it with the options it was started with")
    diff = "; ".join(_config_diff(last.config, config))
    raise CLIError(
        f"{store} holds an unfinished run (run {last.run_id}, {n} of {total} samples) started "
        f"with other options ({diff}): {how}, or add --new to start over (the old run is "
        "marked 'abandoned')"
    )


def _fit_note(*fits: Any) -> str:
    """A short explanation when a printed fit is negative (empty otherwise)."""
    if any(f is not None and math.isfinite(f) and f < 0 for f in fits):
        return (" (a fit below 0 % means the prediction is further from the output than the "
                "output's own mean)")
    return ""


def _f(x: Any, unit: str = "", digits: int = 1) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}{unit}"


def _summary(m: dict[str, Any], out: Path, n_plots: int) -> str:
    parts = [f"twin run {m['plant_name']}: {m['n_samples']} samples"]
    if m["resume"].get("resumed"):
        parts[0] += f" (resumed after {m['resume']['resume_k']})"
    parts.append(f"sync fit mean {_f(m['sync_fit_mean'], ' %')}"
                 + (f" (static twin {_f(m['static_twin_sync_fit_mean'], ' %')})"
                    if m.get("static_twin_sync_fit_mean") is not None else ""))
    if m["drift_events_s"]:
        parts.append(f"min {_f(m['sync_fit_min_after_recovery'], ' %')} outside "
                     f"{m['recovery_window_s']:g} s recovery windows")
    note = _fit_note(m.get("sync_fit_mean"), m.get("static_twin_sync_fit_mean"),
                     m.get("sync_fit_min_after_recovery") if m["drift_events_s"] else None)
    if note:
        parts[-1] += note
    parts.append(f"{m['reidentifications']} re-identifications")
    if m.get("tracking_iae") is not None:
        parts.append(f"tracking IAE {_f(m['tracking_iae'], '', 2)}, "
                     f"{m['constraint_violations']} constraint violations")
    parts.append(f"MPC {_f(m['mpc_solve_ms']['median'], ' ms', 3)}, "
                 f"update {_f(m['update_ms']['median'], ' ms', 3)} (median)")
    s = m["samples"]
    if s["dropouts"] or s["outliers"] or s["late"]:
        parts.append(f"{s['dropouts']} dropouts, {s['outliers']} outliers, {s['late']} late")
    plots = f", {n_plots} plots" if n_plots else ""
    return "; ".join(parts) + f"; wrote {out}/metrics.json, report.md{plots}"
