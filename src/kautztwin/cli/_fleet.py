"""``kautztwin fleet run`` and ``fleet serve``: a simulated fleet's twins stepped together."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ._common import CLIError, print_json

__all__ = ["register", "run"]

DESCRIPTION = """\
Run the digital twins of a simulated fleet: N hydraulic drives with individual
parameter spread, oil temperature and drift of the dominant pole, each with
its own twin (identification, closed-loop Kautz/Laguerre MPC, recursive
updates, re-identification on desynchronisation), all stepped together as
array operations (docs/fleet.md).  The plants are one array simulation; the
identifications, re-identifications and controller builds run in a worker
pool; every asset's samples go to one SQLite history.

Writes DIR/summary.json (per-asset sync fit distribution, desync events,
re-identifications, constraint violations, tracking error, timings),
DIR/fleet.png and DIR/history.sqlite.
"""

EPILOG = """\
examples:
  kautztwin fleet run --assets 20 --plant hydraulic --out runs/fleet
  kautztwin fleet run --assets 200 --plant hydraulic --drift-spread 0.4 --duration 60 \\
      --workers 2 --out runs/fleet200
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``fleet`` command (with its ``run`` action) to the command-line parser.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``kautztwin`` command's subparsers.
    common : argparse.ArgumentParser
        Parent parser with the flags every command shares (``--debug``).
    """
    p = subparsers.add_parser(
        "fleet", parents=[common], allow_abbrev=False,
        help="run the twins of a simulated fleet of plants together (batched)",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = p.add_subparsers(dest="action", title="actions", metavar="ACTION", required=True)
    r = actions.add_parser(
        "run", parents=[common], allow_abbrev=False, help="run a simulated fleet",
        description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    r.add_argument("--assets", required=True, type=int, metavar="N", help="number of assets")
    r.add_argument("--plant", default="hydraulic", choices=("hydraulic",),
                   help="plant type of the fleet (default: %(default)s)")
    r.add_argument("--duration", type=float, default=None, metavar="S",
                   help="run length in seconds (default: the quick profile's 40 s)")
    r.add_argument("--spread", type=float, default=0.05,
                   help="log-normal spread of the physical parameters (default: %(default)s)")
    r.add_argument("--drift-spread", type=float, default=0.3, metavar="F",
                   help="largest drift of an asset's dominant pole, a fraction; each asset "
                   "draws its own in [0, F] (default: %(default)s)")
    r.add_argument("--noise", type=float, default=0.01,
                   help="sensor noise, rad/s (default: %(default)s)")
    r.add_argument("--seed", type=int, default=0, help="seed of the fleet (default: 0)")
    r.add_argument("--workers", type=int, default=1,
                   help="worker processes for identification and re-identification "
                   "(default: %(default)s)")
    r.add_argument("--shards", type=int, default=1, metavar="S",
                   help="split the fleet into S shards, each a Ray actor (needs ray; "
                   "default: %(default)s, no Ray)")
    r.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="Ray cluster to join with --shards ('auto', 'HOST:6379'); a local "
                   "Ray instance when omitted")
    r.add_argument("--estimator", metavar="DIR", default=None,
                   help="a trained DNN estimator of step responses (kautztwin train): the due "
                   "re-identifications use it, one call per sample (not with --shards)")
    r.add_argument("--no-record", action="store_true",
                   help="keep no per-sample arrays in memory (no output plot, less memory)")
    r.add_argument("--out", required=True, metavar="DIR", help="output folder")
    r.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="progress bar on stderr (default: only on a terminal)")
    r.add_argument("--json", action="store_true", help="print the summary as JSON")
    r.set_defaults(run=run)
    _register_serve(actions, common)


SERVE_DESCRIPTION = """\
Serve the twins of a simulated fleet (docs/fleet.md): the batched fleet is
stepped on the wall clock, --speed plant seconds per wall-clock second, until
SIGTERM/SIGINT, --wall-duration or the horizon (--duration plant seconds), and
one HTTP API serves every asset: GET /assets, /assets/{id}/state,
/assets/{id}/history, /fleet/metrics, POST /assets/{id}/setpoint
(docs/api-http.md, Fleet).  The history is DIR/history.sqlite; a restart with
the same options resumes the run.  A bind off 127.0.0.1 needs --token (or
KAUTZTWIN_HTTP_TOKEN), which the writes then need as a bearer token.
"""

SERVE_EPILOG = """\
examples:
  kautztwin fleet serve --assets 20 --plant hydraulic --speed 1 --out runs/fleet \\
      --http 127.0.0.1:8000
  curl -s http://127.0.0.1:8000/assets/3/state
"""


def _register_serve(actions: argparse._SubParsersAction,
                    common: argparse.ArgumentParser) -> None:
    s = actions.add_parser(
        "serve", parents=[common], allow_abbrev=False,
        help="serve a simulated fleet's twins on the wall clock over one HTTP API",
        description=SERVE_DESCRIPTION, epilog=SERVE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--assets", required=True, type=int, metavar="N", help="number of assets")
    s.add_argument("--plant", default="hydraulic", choices=("hydraulic",),
                   help="plant type of the fleet (default: %(default)s)")
    s.add_argument("--speed", type=float, default=1.0, metavar="S",
                   help="plant seconds per wall-clock second (default: %(default)s)")
    s.add_argument("--duration", type=float, default=None, metavar="S",
                   help="horizon of the run, plant seconds (default: 600)")
    s.add_argument("--wall-duration", type=float, default=None, metavar="S",
                   help="stop after S wall-clock seconds (default: at the horizon or a signal)")
    s.add_argument("--http", default=None, metavar="HOST:PORT",
                   help="serve the HTTP API there (PORT alone: on 127.0.0.1)")
    s.add_argument("--token", default=None,
                   help="API token (bearer) the writes need; default: KAUTZTWIN_HTTP_TOKEN")
    s.add_argument("--rate-limit", type=float, default=60.0, metavar="N",
                   help="writes a minute per client, 0: no limit (default: %(default)s)")
    s.add_argument("--spread", type=float, default=0.05,
                   help="log-normal spread of the physical parameters (default: %(default)s)")
    s.add_argument("--drift-spread", type=float, default=0.3, metavar="F",
                   help="largest drift of an asset's dominant pole (default: %(default)s)")
    s.add_argument("--noise", type=float, default=0.01,
                   help="sensor noise, rad/s (default: %(default)s)")
    s.add_argument("--seed", type=int, default=0, help="seed of the fleet (default: 0)")
    s.add_argument("--workers", type=int, default=1,
                   help="worker processes for identification and re-identification "
                   "(default: %(default)s)")
    s.add_argument("--estimator", metavar="DIR", default=None,
                   help="a trained DNN estimator of step responses for the update module")
    s.add_argument("--new", action="store_true",
                   help="start a new run instead of resuming an unfinished one")
    s.add_argument("--logging-format", choices=("kv", "json"), default="kv",
                   help="log lines as key=value or JSON (default: %(default)s)")
    s.add_argument("--out", required=True, metavar="DIR", help="output folder")
    s.set_defaults(run=serve)


def serve(args: argparse.Namespace) -> int:
    """Run ``kautztwin fleet serve``.

    Parameters
    ----------
    args : argparse.Namespace

    Returns
    -------
    int
        0 after a clean stop (signal, ``--wall-duration`` or the horizon).
    """
    from ..service import configure_logging
    from ..service.fleet_service import FleetService
    from ._common import stop_on_signals

    if args.assets <= 0:
        raise CLIError(f"--assets must be a positive number of assets, got {args.assets}")
    configure_logging("info", None, args.logging_format)
    service = FleetService(
        args.assets, args.out, plant=args.plant, speed=args.speed, duration=args.duration,
        wall_duration=args.wall_duration, http=args.http, token=args.token,
        rate_limit=args.rate_limit, seed=args.seed, spread=args.spread,
        drift_spread=args.drift_spread, noise=args.noise, workers=args.workers,
        resume=not args.new, estimator=_estimator(args.estimator))
    with stop_on_signals(service.request_stop):
        service.build()
        s = service.run()
    f = s.get("sync_fit_last", {})
    sys.stdout.write(
        f"fleet serve of {args.assets}: {s['n_samples']} samples, {s['reason']}; median last "
        f"sync fit {f.get('median', float('nan')):.1f} %, re-identifications "
        f"{s['reidentification']['accepted']}/{s['reidentification']['attempts']} accepted; "
        f"store {s['store']}\n")
    return 0


def run(args: argparse.Namespace) -> int:
    """Run ``kautztwin fleet run``.

    Parameters
    ----------
    args : argparse.Namespace

    Returns
    -------
    int
        Exit status.
    """
    from ..twin.fleet import Fleet, FleetStore
    from ..twin.fleet.simulate import hydraulic_fleet, summarize
    from ..twin.runtime import TwinConfig

    if args.assets <= 0:
        raise CLIError(f"--assets must be a positive number of assets, got {args.assets}")
    if args.workers <= 0:
        raise CLIError(f"--workers must be >= 1, got {args.workers}")
    if args.duration is not None and not args.duration > 0:
        raise CLIError(f"--duration must be a positive number of seconds, got {args.duration}")
    if not 1 <= args.shards <= max(args.assets, 1):
        raise CLIError(f"--shards must lie in [1, --assets = {args.assets}], got {args.shards}")
    cfg = TwinConfig.for_plant("hydraulic", duration=args.duration, quick=True,
                               static_twin=False, retune=False, seed=args.seed)
    record = not args.no_record
    if args.shards > 1 or args.ray_address:
        if args.estimator:
            raise CLIError("--estimator runs in one process: leave out --shards/--ray-address")
        return _run_sharded(args, cfg)
    estimator = _estimator(args.estimator)
    plant, assets = hydraulic_fleet(args.assets, cfg, spread=args.spread,
                                    drift_spread=args.drift_spread, noise=args.noise,
                                    seed=args.seed, record=record)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    db = out / "history.sqlite"
    if db.exists():
        db.unlink()
    store = FleetStore(str(db))
    with Fleet(plant, cfg, store=store, workers=args.workers, record=record,
               estimator=estimator) as fleet:
        result = fleet.run(progress=args.progress)
        summary: dict[str, Any] = summarize(result, assets)
        summary["memory_bytes_per_asset_state"] = fleet.nbytes_per_asset
    summary["store"] = {"path": str(db), "rows": store.rows_written}
    summary["options"] = {"assets": args.assets, "plant": args.plant, "duration": cfg.duration,
                          "spread": args.spread, "drift_spread": args.drift_spread,
                          "noise": args.noise, "seed": args.seed, "workers": args.workers}
    _write(args, out, summary, result if record else None)
    return 0


def _estimator(path: str | None) -> Any:
    """The estimator of ``--estimator DIR`` (``None`` without one)."""
    if not path:
        return None
    from ..service import load_estimator

    return load_estimator(path)


def _run_sharded(args: argparse.Namespace, cfg: Any) -> int:
    """``--shards S``: the fleet over Ray actors, one store per shard."""
    from .._validation import check_memory
    from ..twin.fleet.shards import run_sharded
    from ..twin.fleet.simulate import bytes_per_asset, summarize

    try:
        import ray  # noqa: F401
    except ImportError:
        raise CLIError("--shards needs ray: pip install 'ray==2.60.0'") from None

    check_memory(args.assets * bytes_per_asset(cfg, record=True), f"--assets {args.assets}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    store_dir = out / "shards"
    result, assets = run_sharded(
        args.assets, cfg, n_shards=args.shards, store_dir=str(store_dir),
        address=args.ray_address, workers_per_shard=args.workers, spread=args.spread,
        drift_spread=args.drift_spread, noise=args.noise, seed=args.seed)
    summary: dict[str, Any] = summarize(result, assets)
    summary["store"] = {"path": str(store_dir), "shards": args.shards}
    summary["resume"] = dict(result.resume)
    summary["options"] = {"assets": args.assets, "plant": args.plant, "duration": cfg.duration,
                          "spread": args.spread, "drift_spread": args.drift_spread,
                          "noise": args.noise, "seed": args.seed, "workers": args.workers,
                          "shards": args.shards, "ray_address": args.ray_address}
    _write(args, out, summary, result)
    return 0


def _write(args: argparse.Namespace, out: Path, summary: dict[str, Any], result: Any) -> None:
    from ..twin.fleet.simulate import plot_fleet

    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False,
                                                 default=str))
    if result is not None:
        plot_fleet(result, str(out / "fleet.png"))
    if args.json:
        print_json(summary)
    else:
        f = summary["sync_fit_last"]
        sys.stdout.write(
            f"fleet of {args.assets}: median last sync fit {f.get('median', float('nan')):.1f} % "
            f"(p5 {f.get('p5', float('nan')):.1f} %), re-identifications "
            f"{summary['reidentification']['accepted']}/{summary['reidentification']['attempts']}"
            f" accepted, MPC failures {summary['mpc']['failures']}; wrote {out}\n")
