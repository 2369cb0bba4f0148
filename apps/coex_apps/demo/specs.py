"""What topside knows of the vehicle and its camera without being told by the simulation: the
figures of the vehicle's and the camera's data sheets, which an operator plans with.

The scripted operator and its eye import these (and nothing of the simulator's truth); the
simulated vehicle flies and the renderer draws by the same figures, as a real vehicle's would
match its data sheet.
"""

from __future__ import annotations

__all__ = ["CAMERA_ASPECT", "CAMERA_HFOV_DEG", "CAMERA_PERIOD", "CAMERA_SPEED", "TRANSIT_ALTITUDE",
           "TRANSIT_SPEED"]

#: the vehicle's speeds (m/s): between the camera lines, and along them
TRANSIT_SPEED = 1.0
CAMERA_SPEED = 0.5
#: the altitude (m) the vehicle transits at between camera lines
TRANSIT_ALTITUDE = 10.0
#: seconds between camera frames on a transect
CAMERA_PERIOD = 6.0
#: the camera's horizontal field of view (degrees) and its frame's height over its width
CAMERA_HFOV_DEG = 62.0
CAMERA_ASPECT = 0.75
