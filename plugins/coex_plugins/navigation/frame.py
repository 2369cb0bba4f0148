"""The local frame: metres east (x) and north (y) of ``node.origin``, through pyproj.

An azimuthal equidistant projection centred on the origin (distances and bearings from the
origin are true), the frame the map, the vehicle's navigation and the USBL fixes share
(``docs/navigation.md``). :meth:`LocalFrame.to_utm` / :meth:`LocalFrame.from_utm` give the UTM
coordinates a tracking system may report (Kongsberg's ``$PSIMSSB`` in UTM), in the origin's zone
unless another is named.
"""

from __future__ import annotations

import math
import re

from pyproj import CRS, Transformer

__all__ = ["LocalFrame", "utm_crs"]

_ZONE = re.compile(r"^(\d{1,2})\s*([NSns])$")


def utm_crs(zone: str) -> CRS:
    """The WGS 84 UTM CRS of a zone written ``"31N"`` or ``"18S"`` (ValueError otherwise)."""
    m = _ZONE.match(zone.strip())
    if m is None or not 1 <= int(m.group(1)) <= 60:
        raise ValueError(f"a UTM zone is a number 1-60 and N or S, like '31N', got {zone!r}")
    return CRS.from_epsg((32600 if m.group(2).upper() == "N" else 32700) + int(m.group(1)))


class LocalFrame:
    """x metres east, y metres north of ``(lat, lon)`` (see the module docstring)."""

    def __init__(self, lat: float, lon: float, utm_zone: str | None = None) -> None:
        self.lat, self.lon = float(lat), float(lon)
        self.crs = CRS.from_proj4(f"+proj=aeqd +lat_0={self.lat} +lon_0={self.lon} +datum=WGS84 +units=m +no_defs")
        self._to_geo = Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)
        self._from_geo = Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)
        zone = math.floor((self.lon + 180.0) / 6.0) % 60 + 1
        self.utm_zone = utm_zone or f"{zone}{'N' if self.lat >= 0 else 'S'}"
        utm = utm_crs(self.utm_zone)
        self._to_utm = Transformer.from_crs(self.crs, utm, always_xy=True)
        self._from_utm = Transformer.from_crs(utm, self.crs, always_xy=True)

    def local(self, lat: float, lon: float) -> tuple[float, float]:
        """Metres east and north of the origin of a latitude and longitude (degrees)."""
        x, y = self._from_geo.transform(lon, lat)
        return float(x), float(y)

    def geodetic(self, x: float, y: float) -> tuple[float, float]:
        """Latitude and longitude (degrees) of a local point."""
        lon, lat = self._to_geo.transform(x, y)
        return float(lat), float(lon)

    def to_utm(self, x: float, y: float) -> tuple[float, float]:
        """UTM easting and northing (in :attr:`utm_zone`) of a local point."""
        e, n = self._to_utm.transform(x, y)
        return float(e), float(n)

    def from_utm(self, easting: float, northing: float) -> tuple[float, float]:
        """The local point of a UTM easting and northing in :attr:`utm_zone`."""
        x, y = self._from_utm.transform(easting, northing)
        return float(x), float(y)
