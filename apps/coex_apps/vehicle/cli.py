"""``coex vehicle --config FILE`` and ``coex config check FILE``."""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

from coex import CoexError

__all__ = ["register", "register_config", "run_vehicle", "summary_text"]


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "vehicle", help="run the vehicle node from a configuration file",
        description="Run the vehicle node: its modems, modalities, inputs from the vehicle's "
                    "middleware and the autonomy output for survey commands, all from one TOML "
                    "file (docs/deploy.md), or as the MOOS application pCoex from a mission file's "
                    "ProcessConfig block (docs/moos.md). SIGTERM or Ctrl-C stops it cleanly; the "
                    "next start resumes from its store.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", metavar="FILE", help="the vehicle's configuration (TOML)")
    src.add_argument("--moos", metavar="MISSION", help="a MOOS mission file (.moos) with a ProcessConfig block "
                                                       "for this process")
    p.add_argument("--process-name", default="pCoex", metavar="NAME",
                   help="with --moos: the ProcessConfig block to read (default pCoex)")
    p.add_argument("--moos-host", "--moos_host", metavar="HOST",
                   help="with --moos: the MOOSDB host instead of the mission's ServerHost")
    p.add_argument("--moos-port", "--moos_port", type=int, metavar="PORT",
                   help="with --moos: the MOOSDB port instead of the mission's ServerPort")
    p.set_defaults(func=run_vehicle)


def register_config(subparsers: Any) -> None:
    p = subparsers.add_parser("config", help="check a vehicle or topside configuration file")
    sub = p.add_subparsers(dest="op", metavar="ACTION", required=True)
    c = sub.add_parser("check", help="report every problem of a configuration file, each with its key")
    c.add_argument("file", metavar="FILE")
    c.add_argument("--role", choices=["vehicle", "topside"], help="the role the file must configure")
    c.add_argument("--process-name", default="pCoex", metavar="NAME",
                   help="a .moos mission file: the ProcessConfig block to read (default pCoex)")
    p.set_defaults(func=_check)


def _check(args: argparse.Namespace) -> int:
    from .config import check

    if str(args.file).endswith(".moos"):
        from .mission import check_mission

        cfg, problems = check_mission(args.file, args.process_name)
        if args.role == "topside" and not problems:
            problems = ["a MOOS mission's pCoex block configures the vehicle"]
    else:
        cfg, problems = check(args.file, args.role)
    for text in cfg.warnings if cfg is not None else ():
        print(f"{args.file}: warning: {text}")
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
    if cfg.ros is not None:
        parts.append(f"products on ROS under {cfg.ros.get('prefix', '/coex')} "
                     f"({cfg.ros.get('master') or 'ROS_MASTER_URI'})")
    parts.append("commands signed" if cfg.command_key else "commands NOT authenticated (no node.command_key_file)")
    if cfg.fleet:
        parts.append("keys per vehicle: " + ", ".join(v.name for v in cfg.vehicles if v.command_key)
                     if any(v.command_key for v in cfg.vehicles) else "one key for every vehicle"
                     if cfg.command_key else "")
        who = "vehicles " + ", ".join(f"{v.name} ({v.id})" for v in cfg.vehicles)
    else:
        who = f"peer {cfg.peer}"
    print(f"{args.file}: ok: {cfg.role} node {cfg.node_id} ({who}); " + "; ".join(p for p in parts if p))
    return 0


def summary_text(summary: dict[str, Any]) -> str:
    """The shutdown line's words: "points 400, images 3, ..., skipped 6, plans 1, reports 2;
    skipped by input: inputs[0] (directory) 4, inputs[1] (lcm) 2" (every input, zeros too)."""
    by_input = summary.get("skipped_by_input") or {}
    text = ", ".join(f"{k} {v}" for k, v in summary.items() if k != "skipped_by_input")
    if by_input:
        text += "; skipped by input: " + ", ".join(f"{k} {v}" for k, v in by_input.items())
    return text


def run_vehicle(args: argparse.Namespace) -> int:
    from .config import load
    from .daemon import VehicleApp

    try:
        if args.moos is not None:
            from .mission import load_mission

            cfg = load_mission(args.moos, args.process_name, host=args.moos_host, port=args.moos_port)
        else:
            if args.moos_host is not None or args.moos_port is not None:
                raise CoexError("--moos-host and --moos-port go with --moos MISSION")
            cfg = load(args.config, "vehicle")
        logging.basicConfig(level=cfg.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s",
                            force=True)  # a library may have configured logging on import
        app = VehicleApp(cfg)
    except (CoexError, OSError) as exc:
        print(f"coex vehicle: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # what no check foresaw: named, never a traceback (exit 2, as above)
        print(f"coex vehicle: cannot start: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    st = app.store
    waiting = [f"link {lid} waiting for its modem" for lid, tr in app.transports.items() if not tr.up]
    print(f"coex vehicle: node {cfg.node_id} on {', '.join(m.uri for m in cfg.modems)}"
          + (f" ({', '.join(waiting)})" if waiting else "") + "; "
          f"modalities {', '.join(m.name for m in cfg.modalities)}; "
          f"{len(app.inputs)} input(s); autonomy {cfg.autonomy.get('type')}; "
          + (f"store {cfg.store} ({'resumed, ' + str(st.stats['replayed']) + ' journal rows replayed' if app.resumed else 'new'})"
             if st is not None else "no store"), flush=True)

    from coex_runtime.runner import sigterm_as_interrupt

    with sigterm_as_interrupt():  # SIGTERM stops like Ctrl-C: cleanly, the store saved
        try:
            app.open()
            app.run()
        except KeyboardInterrupt:
            pass
        finally:
            app.close()
            from coex_transports.recovery import describe_seconds

            modems = [f"link {lid}: {h.outages} outage{'s' if h.outages != 1 else ''}, down "
                      f"{describe_seconds(h.down_total)}" for lid, h in app.link_health().items() if h.outages]
            print(f"coex vehicle: stopped ({summary_text(app.summary())})"
                  + (f"; {'; '.join(modems)}" if modems else ""), flush=True)
    return 0
