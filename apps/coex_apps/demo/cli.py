"""``coex demo [--preset NAME | --scenario FILE.toml] [--loss P] [--burst] [--seed S] [--operator none|script]
[--out DIR] [--images DIR] [--gui | --no-gui] [--quick]``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

DEFAULT_IMAGES = Path("../shared/data/nui040")


def register(sub: Any) -> None:
    p = sub.add_parser(
        "demo",
        help="replay a nested survey (sonar map, then camera pass) through simulated modems",
        description="Replays a two-hour nested survey through the whole CoEx stack and two simulated "
        "Micromodems (rate 5, 6 x 20 s TDMA by default), time-compressed, with a scripted operator. "
        "Writes maps, images, time series, the link log, truth.json, metrics.json and report.html to "
        "--out; the goals are judged against the simulation's truth.",
    )
    p.add_argument("--out", type=Path, default=Path("coex-demo-out"), help="output directory (default ./coex-demo-out)")
    scn = p.add_mutually_exclusive_group()
    scn.add_argument("--preset", default=None, metavar="NAME",
                     help="a built-in scenario: default (today's dive), dive040 (the ship 1.5 water depths "
                          "away, range-dependent loss), harsh (Micromodem rate 3, bursty loss), lowrate (rate 1, "
                          "far from the site), fleet (a mapping AUV and a camera vehicle on one network), "
                          "container-hull-car (a 20-ft container, a 7 m boat hull and a small pale car)")
    scn.add_argument("--scenario", type=Path, default=None, metavar="FILE.toml",
                     help="a scenario file (site, survey, targets and decoys, modem, TDMA, loss model, ship; "
                          "see docs/demo.md)")
    p.add_argument("--loss", type=float, default=None,
                   help="frame loss probability, overriding the scenario's loss model (default: the scenario's, "
                        "0.3 independent for the default preset)")
    p.add_argument("--burst", action="store_true",
                   help="bursty (Gilbert-Elliott, mean burst 4 frames) loss at --loss instead of independent")
    p.add_argument("--seed", type=int, default=1, help="seed of the scenario and the channel (default 1)")
    p.add_argument("--operator", choices=("none", "script"), default=None,
                   help="who operates topside: the scripted operator (default without --gui) or nobody but a "
                        "person at the console (default with --gui)")
    p.add_argument("--images", type=Path, default=None,
                   help="build the simulated sand from real seafloor frames in DIR (e.g. ../shared/data/nui040) "
                        "instead of the generated texture")
    gui = p.add_mutually_exclusive_group()
    gui.add_argument("--gui", action="store_true", help="serve the live web console during the dive")
    gui.add_argument("--no-gui", dest="gui", action="store_false", help="no web console (default)")
    p.add_argument("--http", default="127.0.0.1:8080", help="address of the web console with --gui")
    p.add_argument("--operators", type=Path, default=None, metavar="FILE",
                   help="with --gui: everyone signs in to the console (coex operators); required for "
                        "an --http address beyond loopback")
    p.add_argument("--insecure-open", action="store_true",
                   help="with --gui: serve beyond loopback without sign-in (a trusted network only)")
    p.add_argument("--speed", type=float, default=20.0,
                   help="with --gui: simulated seconds per second (default 20: the dive takes 6 minutes)")
    p.add_argument("--quick", action="store_true", help="a short, small scenario (for tests)")
    p.add_argument("--command-key-file", type=Path, default=None, metavar="PATH",
                   help="shared command key (hex, or at least 16 raw bytes) instead of the demo's "
                        "embedded one")
    p.add_argument("--no-auth", action="store_true", help="commands unauthenticated")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="threads for the image coding (OpenJPEG; the same images either way; default: one per "
                        "CPU, up to 4; 0: in the dive's own thread)")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no decision log")
    p.add_argument("--zero-labels", action="store_true",
                   help="a check: the simulator's per-pixel labels are zeros (frames unchanged), so the referee "
                        "sees nothing; the operator's decisions must not change (metrics.json verdicts)")
    p.add_argument("--no-correction", dest="correction", action="store_false",
                   help="topside estimates the vehicle's drift from the USBL fixes but does not apply it: the map, "
                        "images and survey commands stay in the vehicle's drifting frame (docs/navigation.md)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from coex import ConfigError

    from .dive import Decision, DemoConfig, run_demo

    if args.loss is not None and not 0.0 <= args.loss < 1.0:
        raise ConfigError("--loss must be in [0, 1)")
    if args.speed <= 0:
        raise ConfigError("--speed must be positive")
    if args.threads is not None and args.threads < 0:
        raise ConfigError("--threads must be >= 0")
    if args.images is not None and not args.images.is_dir():
        raise ConfigError(f"--images {args.images} is not a directory")

    def say(d: Decision) -> None:
        if not args.quiet:
            who = "" if d.who == "script" else f"[{d.who}] "
            sys.stderr.write(f"\r{d.t:7.0f} s  {d.kind:<16} {who}{d.text}\n")

    from coex_core.auth import parse_key

    from .dive import DEMO_COMMAND_KEY

    key: bytes | None = DEMO_COMMAND_KEY
    if args.no_auth:
        key = None
    elif args.command_key_file is not None:
        try:
            key = parse_key(args.command_key_file.read_bytes())
        except OSError as exc:
            raise ConfigError(f"cannot read --command-key-file: {exc}") from exc
    from .scenario import load_scenario, preset

    scenario = load_scenario(args.scenario) if args.scenario is not None else preset(args.preset or "default")
    cfg = DemoConfig(out=args.out, loss=args.loss, seed=args.seed, images=args.images, gui=args.gui,
                     http=args.http, quick=args.quick, progress=not args.quiet, burst=args.burst,
                     speed=args.speed, command_key=key, scenario=scenario, operator=args.operator,
                     operators=args.operators, insecure_open=args.insecure_open, codec_threads=args.threads,
                     correction=args.correction, zero_labels=args.zero_labels)
    result = run_demo(cfg, on_decision=say)
    m = result.metrics
    print(f"scenario {m['scenario']['name']}: {m['scenario']['loss_description']}; operator {m['operator']}")
    for name, goal in m["goals"].items():
        verdict = "MET" if goal["met"] else "NOT MET"
        print(f"{verdict:8} {name}: {goal['detail']}")
    print(f"outputs in {result.out}/ (report.html, metrics.json); {m['wall_seconds']} s wall time")
    return 0
