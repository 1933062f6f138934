"""The scan patterns of survey laser scanners, as their datasheets state them: a pulse rate,
a scan rate and a field of view (and, for a terrestrial scanner, an angular step).

Every pattern here fires its pulses at ``k / pulse_rate`` seconds (``k`` = 0, 1, ...), each
along the direction its mechanism points then, so a pattern continues from one batch of
pulses to the next and a flight's pulses each have their own time and pose. Directions are
in the sensor's frame (+X forward, +Y left, +Z up). The airborne and drone patterns look
down (-Z) from a level platform, their angles positive to the right; a sensor mounted
otherwise is turned by its pose (pitch, roll).

* ``line``: a rotating mirror or polygon; the beam sweeps the field of view across the track
  at a constant angular speed, one line after another (``scan_rate`` lines a second). The
  ``pulse_rate`` is the effective rate: the pulses fired within the field of view (what
  Riegl's datasheets call the effective measurement rate).
* ``oscillating``: a mirror swinging to and fro: a zig-zag of lines (a triangle wave, one
  line each way, ``scan_rate`` lines a second; the mirror's turnarounds taken as instant).
* ``conical``: a Palmer scanner; the beam on a cone of full angle ``fov`` about the nadir,
  ``scan_rate`` turns a second.
* ``rosette``: two Risley prisms turning at ``prism_rates`` (Hz, opposite signs for the
  Livox rosette), each deflecting the beam by a quarter of ``fov``: the pointing is the
  sum of the two rotating vectors (the first-order Risley equation: Li, Appl. Opt. 50, 679,
  2011, after Marshall, Proc. SPIE 3787, 1999), a pattern that fills the circle without
  repeating for seconds.
* ``tls``: a terrestrial scanner; a vertical line from ``vfov_min`` to ``vfov_max``
  (elevation, degrees) at ``elevation_step``, the head turning by ``azimuth_step`` through
  ``hfov`` degrees after each line: one station.

A static scan (``usdforest scan``) fires a pattern for ``frame_time`` seconds (a terrestrial
scanner: its whole station).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.sensors.lidar.scanners import LaserScanner, check_vfov

MAX_PULSE_RATE = 1e7  # Hz: beyond any scanner's (the fastest airborne ones fire 2-4 MHz)
MAX_SCAN_RATE = 1e4  # lines or turns a second
MAX_STATION = 1e9  # pulses of one terrestrial station (0.0007 deg over a sphere is 2.6e11)


@dataclass(frozen=True)
class Firing:
    """Pulses of a pattern: their times (s), unit directions in the sensor's frame (n, 3),
    laser channel and the pattern's own angle (degrees: the scan angle of a line, the
    cone's or the head's azimuth)."""

    t: np.ndarray
    dirs: np.ndarray
    channel: np.ndarray
    angle: np.ndarray


def _check_pulse_rate(rate: float) -> None:
    if not (np.isfinite(rate) and 0 < rate <= MAX_PULSE_RATE):
        raise UsdForestError(f"lidar.pulse_rate: must be in (0, {MAX_PULSE_RATE:g}] Hz")


def pulse_indices(t0: float, t1: float, rate: float) -> np.ndarray:
    """The ``k`` of the pulses fired in ``[t0, t1)`` at ``k / rate`` seconds."""
    k0 = math.ceil(t0 * rate - 1e-9)
    k1 = math.ceil(t1 * rate - 1e-9)
    return np.arange(k0, max(k0, k1), dtype=np.int64)


def across_track(theta_deg: np.ndarray) -> np.ndarray:
    """Directions in the plane across the track at ``theta_deg`` from the nadir, positive to
    the right (-Y)."""
    th = np.radians(theta_deg)
    return np.column_stack([np.zeros(len(th)), -np.sin(th), -np.cos(th)])


def off_nadir(angle_rad: np.ndarray, azimuth_rad: np.ndarray) -> np.ndarray:
    """Directions ``angle_rad`` from the nadir towards ``azimuth_rad`` (0: forward, +X)."""
    s = np.sin(angle_rad)
    return np.column_stack([s * np.cos(azimuth_rad), s * np.sin(azimuth_rad), -np.cos(angle_rad)])


@dataclass(frozen=True)
class _Timed(LaserScanner):
    """A pattern of pulses at ``pulse_rate`` Hz (see the module)."""

    pulse_rate: float = 100_000.0
    scan_rate: float = 100.0
    fov: float = 60.0
    frame_time: float = 0.1

    def check(self) -> None:
        super().check()
        _check_pulse_rate(self.pulse_rate)
        if not (np.isfinite(self.scan_rate) and 0 < self.scan_rate <= MAX_SCAN_RATE):
            raise UsdForestError(f"lidar.scan_rate: must be in (0, {MAX_SCAN_RATE:g}] a second")
        if not (np.isfinite(self.fov) and 0 < self.fov <= 360):
            raise UsdForestError("lidar.fov: must be in (0, 360] degrees")
        if not (np.isfinite(self.frame_time) and 0 < self.frame_time <= 60):
            raise UsdForestError("lidar.frame_time: must be in (0, 60] seconds")

    def pulses(self, duration: float, rate: float = 0.0) -> int:
        """Pulses fired in ``duration`` seconds (``rate``: unused, as a spinning lidar's)."""
        return math.ceil(duration * self.pulse_rate)

    def firing(self, t0: float, t1: float) -> Firing:
        """The pulses fired in ``[t0, t1)`` seconds."""
        k = pulse_indices(t0, t1, self.pulse_rate)
        t = k / self.pulse_rate
        dirs, angle = self._point(k)
        return Firing(t, dirs, np.zeros(len(k), np.uint16), angle)

    def directions(self) -> np.ndarray:
        """Directions of a static scan's pulses: those of its first ``frame_time`` seconds."""
        return self.firing(0.0, self.frame_time).dirs

    def _phase(self, k: np.ndarray, rate: float) -> np.ndarray:
        """``rate`` turns a second at pulse ``k``: the fraction of the turn, in [0, 1) (exact
        where the rates are whole numbers: ``k rate`` is then an integer)."""
        return np.mod(k * rate / self.pulse_rate, 1.0)

    def _point(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


@dataclass(frozen=True)
class LineScanner(_Timed):
    """A rotating mirror or polygon: lines across the track (see the module)."""

    kind: str = "line"

    def _point(self, k):
        theta = self.fov * (self._phase(k, self.scan_rate) - 0.5)
        return across_track(theta), theta


@dataclass(frozen=True)
class OscillatingScanner(_Timed):
    """A swinging mirror: a zig-zag of lines across the track (see the module)."""

    kind: str = "oscillating"

    def _point(self, k):
        u = 2.0 * self._phase(k, self.scan_rate / 2.0)  # two lines a period
        theta = self.fov * (np.where(u < 1.0, u, 2.0 - u) - 0.5)
        return across_track(theta), theta


@dataclass(frozen=True)
class ConicalScanner(_Timed):
    """A Palmer scanner: the beam on a cone about the nadir (see the module)."""

    kind: str = "conical"
    fov: float = 40.0

    def check(self) -> None:
        super().check()
        if self.fov >= 180:
            raise UsdForestError("lidar.fov: a cone's full angle must be below 180 degrees")

    def _point(self, k):
        phi = 2 * np.pi * self._phase(k, self.scan_rate)
        alpha = np.full(len(k), np.radians(self.fov) / 2)
        return off_nadir(alpha, phi), np.degrees(phi)


@dataclass(frozen=True)
class RosetteScanner(_Timed):
    """Two Risley prisms: the rosette of the Livox and DJI drone scanners (see the
    module). ``scan_rate`` is unused; ``prism_rate_1`` and ``prism_rate_2`` are the prisms'
    turns a second."""

    kind: str = "rosette"
    fov: float = 38.4
    prism_rate_1: float = 121.567
    prism_rate_2: float = -77.733

    def check(self) -> None:
        super().check()
        if self.fov >= 180:
            raise UsdForestError("lidar.fov: a rosette's full angle must be below 180 degrees")
        for key in ("prism_rate_1", "prism_rate_2"):
            v = getattr(self, key)
            if not (np.isfinite(v) and 0 < abs(v) <= MAX_SCAN_RATE):
                raise UsdForestError(f"lidar.{key}: must be a non-zero rate within +-1e4 Hz")
        if self.prism_rate_1 == self.prism_rate_2:
            raise UsdForestError("lidar.prism_rate_1/prism_rate_2: equal rates draw one point")

    def pointing(self, k: np.ndarray) -> np.ndarray:
        """The Risley equation's pointing (radians, forward and left components) at pulse
        ``k``: ``delta (cos w1 t, sin w1 t) + delta (cos w2 t, sin w2 t)``, ``delta`` a quarter
        of the field of view."""
        delta = np.radians(self.fov) / 4
        a1 = 2 * np.pi * self._phase(k, self.prism_rate_1)
        a2 = 2 * np.pi * self._phase(k, self.prism_rate_2)
        return delta * np.column_stack([np.cos(a1) + np.cos(a2), np.sin(a1) + np.sin(a2)])

    def _point(self, k):
        p = self.pointing(k)
        azimuth = np.arctan2(p[:, 1], p[:, 0])
        return off_nadir(np.hypot(p[:, 0], p[:, 1]), azimuth), np.degrees(azimuth)


@dataclass(frozen=True)
class TerrestrialScanner(LaserScanner):
    """A terrestrial laser scanner on a tripod: vertical lines from ``vfov_min`` to
    ``vfov_max`` degrees of elevation at ``elevation_step``, the head turning by
    ``azimuth_step`` through ``hfov`` degrees (see the module); ``pulse_rate`` times the
    pulses. One scan is one station."""

    kind: str = "tls"
    pulse_rate: float = 300_000.0
    vfov_min: float = -40.0
    vfov_max: float = 60.0
    hfov: float = 360.0
    azimuth_step: float = 0.1
    elevation_step: float = 0.1

    def check(self) -> None:
        super().check()
        _check_pulse_rate(self.pulse_rate)
        check_vfov(self.vfov_min, self.vfov_max)
        if not 0 < self.hfov <= 360:
            raise UsdForestError("lidar.hfov: must be in (0, 360] degrees")
        for key in ("azimuth_step", "elevation_step"):
            if not 0.0005 <= getattr(self, key) <= 45:
                raise UsdForestError(f"lidar.{key}: must be in [0.0005, 45] degrees")
        if self.station_pulses() > MAX_STATION:
            raise UsdForestError(
                f"lidar.azimuth_step/elevation_step: {self.station_pulses():,} pulses a "
                f"station, more than {MAX_STATION:,.0f}"
            )

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Azimuth and elevation (degrees) of each pulse of the station, in firing order:
        line by line (azimuth-major), each line rising."""
        n_az, n_el = self.lines()
        az = np.arange(n_az) * self.azimuth_step
        el = self.vfov_min + np.arange(n_el) * self.elevation_step
        a, e = np.meshgrid(az, el, indexing="ij")
        return a.ravel(), e.ravel()

    def lines(self) -> tuple[int, int]:
        """The station's vertical lines, and the pulses in each."""
        n_az = max(1, math.floor(self.hfov / self.azimuth_step + 1e-9))
        n_el = math.floor((self.vfov_max - self.vfov_min) / self.elevation_step + 1e-9) + 1
        return n_az, n_el

    def station_pulses(self) -> int:
        n_az, n_el = self.lines()
        return n_az * n_el

    def pulses(self, duration: float = 0.0, rate: float = 0.0) -> int:
        """Pulses of one station (a terrestrial scanner does not fly)."""
        return self.station_pulses()

    def directions(self) -> np.ndarray:
        a, e = (np.radians(v) for v in self.grid())
        return np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])

    def times(self) -> np.ndarray:
        """Each pulse's time from the station's start (s)."""
        return np.arange(self.station_pulses()) / self.pulse_rate


KINDS: dict[str, type[LaserScanner]] = {
    "line": LineScanner,
    "oscillating": OscillatingScanner,
    "conical": ConicalScanner,
    "rosette": RosetteScanner,
    "tls": TerrestrialScanner,
}
