"""``coex vehicle --config FILE`` and ``coex config check FILE``."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from typing import Any

from coex_core.errors import CoexError

__all__ = ["register", "register_config", "run_vehicle"]


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "vehicle", help="run the vehicle node from a configuration file",
        description="Run the vehicle node: its modems, modalities, inputs from the vehicle's "
                    "middleware and the autonomy output for survey commands, all from one TOML "
                    "file (docs/deploy.md). SIGTERM or Ctrl-C stops it cleanly; the next start "
                    "resumes from its store.")
    p.add_argument("--config", required=True, metavar="FILE", help="the vehicle's configuration (TOML)")
    p.set_defaults(func=run_vehicle)


def register_config(subparsers: Any) -> None:
    p = subparsers.add_parser("config", help="check a vehicle or topside configuration file")
    sub = p.add_subparsers(dest="op", metavar="ACTION", required=True)
    c = sub.add_parser("check", help="report every problem of a configuration file, each with its key")
    c.add_argument("file", metavar="FILE")
    c.add_argument("--role", choices=["vehicle", "topside"], help="the role the file must configure")
    p.set_defaults(func=_check)


def _check(args: argparse.Namespace) -> int:
    from .config import check

    cfg, problems = check(args.file, args.role)
    if problems:
        for text in problems:
            print(f"{args.file}: {text}")
        print(f"{args.file}: {len(problems)} problem{'s' if len(problems) != 1 else ''}", file=sys.stderr)
        return 1
    assert cfg is not None
    parts = [f"{len(cfg.modems)} modem{'s' if len(cfg.modems) != 1 else ''}",
             "modalities " + ", ".join(m.name for m in cfg.modalities)]
    if cfg.role == "vehicle":
        parts.append(f"{len(cfg.inputs)} input{'s' if len(cfg.inputs) != 1 else ''}"
                     + (f" ({', '.join(i['type'] for i in cfg.inputs)})" if cfg.inputs else ""))
        parts.append(f"autonomy {cfg.autonomy.get('type')}")
    parts.append(f"store {cfg.store}" if cfg.store else "no store")
    parts.append("commands signed" if cfg.command_key else "commands NOT authenticated (no node.command_key_file)")
    print(f"{args.file}: ok: {cfg.role} node {cfg.node_id} (peer {cfg.peer}); " + "; ".join(parts))
    return 0


def run_vehicle(args: argparse.Namespace) -> int:
    from .config import load
    from .daemon import VehicleApp

    try:
        cfg = load(args.config, "vehicle")
        logging.basicConfig(level=cfg.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s",
                            force=True)  # a library may have configured logging on import
        app = VehicleApp(cfg)
    except (CoexError, OSError) as exc:
        print(f"coex vehicle: {exc}", file=sys.stderr)
        return 2
    st = app.store
    print(f"coex vehicle: node {cfg.node_id} on {', '.join(m.uri for m in cfg.modems)}; "
          f"modalities {', '.join(m.name for m in cfg.modalities)}; "
          f"{len(app.inputs)} input(s); autonomy {cfg.autonomy.get('type')}; "
          + (f"store {cfg.store} ({'resumed, ' + str(st.stats['replayed']) + ' journal rows replayed' if app.resumed else 'new'})"
             if st is not None else "no store"), flush=True)

    def terminate(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt  # SIGTERM stops like Ctrl-C: cleanly, the store saved

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        app.open()
        app.run()
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
        signal.signal(signal.SIGTERM, previous)
        print(f"coex vehicle: stopped ({', '.join(f'{k} {v}' for k, v in app.counts.items())})", flush=True)
    return 0
