"""The demo's options, its result and its fixed numbers (node ids, the dive's clock, altitudes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from coex import ConfigError

from .scenario import Scenario, preset

# the vehicle's data sheet (what the operator knows too), here as before
from .specs import CAMERA_PERIOD as CAMERA_PERIOD
from .specs import CAMERA_SPEED as CAMERA_SPEED
from .specs import TRANSIT_ALTITUDE as TRANSIT_ALTITUDE
from .specs import TRANSIT_SPEED as TRANSIT_SPEED

#: The seeds the eye, the operator and the scenes were developed and tuned on (``bench/eye.py``
#: and development dives). Reported results use other seeds, drawn fresh per run.
DEVELOPMENT_SEEDS = range(1000, 1100)

TOPSIDE, VEHICLE = 1, 2
#: the camera vehicle of a fleet dive (preset ``fleet``: TDMA slots ``"camera"``); ``VEHICLE`` is
#: then the mapping AUV
CAMERA = 3
EPOCH = 1_656_633_600.0  # 2022-07-01T00:00:00Z: the dive's clock (simulated)
HOLD_ALTITUDE = 50.0
#: the vehicle modem's statistics for the console (the demo's own stream; the modalities' streams
#: are the deployment's, ``coex_apps.vehicle.config.STREAM_DEFAULTS``)
LINK_STREAM = 6
#: the lowest altitude (m) the vehicle's geofence lets a survey ask for
MIN_ALTITUDE = 2.0
#: the demo's quality marks (``layer_psnr``, dB): the imagery default (25, 30, 35, 40) with a
#: 20 dB preview mark first, because every frame of the camera pass goes up as a preview
LAYER_PSNR = (20.0, 25.0, 30.0, 35.0, 40.0)
#: the vehicle's default set-point for every image (``default_goal``: the first quality mark, 20 dB, a few tens of bytes)
DEFAULT_LAYERS = 1
#: a target is identifiable at 1 m when a car-like candidate of the received 1 m map lies this
#: close to it (m)
IDENTIFY_RADIUS = 3.5
OPERATORS = ("script", "none")


#: The demo's embedded command key (not a secret: real deployments configure their own).
DEMO_COMMAND_KEY = b"coex-demo-command-key-not-secret"


@dataclass
class DemoConfig:
    """Options of ``coex demo`` (see ``coex demo --help``)."""

    out: Path = Path("coex-demo-out")
    #: frame loss; ``None`` keeps the scenario's loss model (``--loss``)
    loss: float | None = None
    seed: int = 1
    images: Path | None = None
    gui: bool = False
    http: str = "127.0.0.1:8080"
    quick: bool = False
    progress: bool = True
    #: bursty (Gilbert-Elliott) loss at ``loss`` (or the scenario's rate) instead of independent
    burst: bool = False
    #: with ``gui``: simulated seconds per wall-clock second, so that a person can act
    speed: float = 20.0
    #: with ``gui``: keep serving the console after the dive until interrupted
    linger: bool = True
    #: shared command key (spec section 10): topside signs every command, the vehicle checks
    #: them; ``None`` turns authentication off
    command_key: bytes | None = DEMO_COMMAND_KEY
    #: the dive (``--scenario FILE`` / ``--preset NAME``); ``None`` is preset ``default``
    scenario: Scenario | None = None
    #: ``"script"`` or ``"none"``; ``None``: the script, unless a person has the console (``gui``)
    operator: str | None = None
    #: with ``gui``: the console's operators file (everyone signs in; required beyond loopback)
    operators: Path | None = None
    #: with ``gui``: serve beyond loopback without sign-in
    insecure_open: bool = False
    #: OpenJPEG threads for the dive's image coding (:func:`coex_plugins.imagery.codec.set_threads`;
    #: the same images either way); ``None``: one per CPU, up to 4 (a dive alone on a machine).
    #: A sweep runs one dive per core with 0
    codec_threads: int | None = None
    #: the vehicle's geofence for survey commands (:class:`~coex_plugins.survey.plan.Geofence`
    #: keys); ``None``: the site with a margin of a quarter of its side, and
    #: :data:`MIN_ALTITUDE`
    geofence: dict[str, Any] | None = None
    #: the check that only the referee reads the simulator's per-pixel labels: they are zeros
    #: wherever the renderer makes them (the frames unchanged); the referee then sees no object
    #: and judges nothing, but the operator must decide exactly as with them (docs/demo.md)
    zero_labels: bool = False
    #: issue 56: topside applies its estimate of the vehicle's drift (the map, images and
    #: detections corrected, survey commands put into the vehicle's frame); False
    #: (``--no-correction``) keeps estimating but shows and sends everything in the vehicle's frame
    correction: bool = True

    def resolved(self) -> tuple[Scenario, str]:
        """The scenario with ``--quick``, ``--loss`` and ``--burst`` applied, and the operator."""
        scn = self.scenario or preset("default")
        scn = scn.with_loss(self.loss, self.burst)
        if self.quick:
            scn = scn.quick()
        op = self.operator or ("none" if self.gui else "script")
        if op not in OPERATORS:
            raise ConfigError(f"operator must be one of {', '.join(OPERATORS)}, got {op!r}")
        return scn, op


@dataclass
class Decision:
    t: float
    kind: str
    text: str
    #: ``"script"`` (the scripted operator), ``"person"`` (an action in the console) or ``"system"``
    who: str = "script"


@dataclass
class DemoResult:
    out: Path
    metrics: dict[str, Any]
    decisions: list[Decision] = field(default_factory=list)
