"""Several returns per lidar pulse: a diverging Gaussian beam sampled as sub-rays, their hits
merged into echoes by range, and the echoes a sensor reports (first, last, strongest, dual, or
up to N).

The beam's irradiance falls as exp(-2 (theta / w)^2) off its axis, ``w`` half the full
divergence angle (the 1/e^2 width, as datasheets quote it). It is sampled in rings as
HELIOS++ does (Winiwarter et al. 2022): the axis, then ring ``k`` of ``6 k`` sub-rays at
``k w / rings``; each sub-ray carries the beam energy of its cell (the disk or annulus
sector around it, the outermost annulus reaching to infinity), so the weights sum to 1 and
a target that fills the footprint returns the single-ray intensity.

Each sub-ray's hit contributes reflectance x |cos incidence| / range^2 x its weight (the
lidar equation for an extended Lambertian target) and stands for a patch of the footprint,
which spans ``range x cell x tan(incidence)`` either side in range on a surface seen
obliquely. Hits of one pulse whose patches are closer in range than ``separation`` (about
the pulse length: 1 m for Velodyne's dual mode) merge into one echo (a wall seen at grazing
incidence stays one long echo)
at their energy-weighted mean range, labelled by its strongest sub-ray (class, tree, prim),
its intensity the sum. Light a leaf transmits is followed by
:func:`usdforest.sensors.lidar.scanners.cast_pulses` (a later echo from behind the leaf, ``T²`` as
strong), so a pulse's later echoes come from the gaps in its footprint and through leaves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MODES = ("first", "last", "strongest", "dual", "all")


@dataclass(frozen=True, eq=False)
class Beam:
    """Sub-ray directions relative to a pulse's axis and their share of its energy."""

    offsets: np.ndarray  # (s, 2) angular offsets (radians) along the axis' two normals
    weights: np.ndarray  # (s,) sum 1
    cell: float = 0.0  # angular half-width (radians) of the patch each sub-ray stands for

    def __len__(self) -> int:
        return len(self.weights)


def beam_pattern(divergence: float, rings: int) -> Beam:
    """The sub-rays of a Gaussian beam of full divergence ``divergence`` (milliradians, at
    1/e^2) in ``rings`` rings (1 + 3 rings (rings + 1) sub-rays); one ray when either is 0.

    Examples
    --------
    >>> b = beam_pattern(3.0, 1)
    >>> len(b), round(float(b.weights.sum()), 12), round(float(b.weights[0]), 4)
    (7, 1.0, 0.3935)
    """
    if divergence <= 0 or rings <= 0:
        return Beam(np.zeros((1, 2)), np.ones(1))
    w = divergence * 1e-3 / 2

    def inside(r: float) -> float:  # share of the energy within angle r of the axis
        return 1.0 - np.exp(-2.0 * (r / w) ** 2) if np.isfinite(r) else 1.0

    offsets, weights = [np.zeros(2)], [inside(0.5 * w / rings)]
    for k in range(1, rings + 1):
        inner = (k - 0.5) * w / rings
        outer = (k + 0.5) * w / rings if k < rings else np.inf
        phi = 2 * np.pi * np.arange(6 * k) / (6 * k)
        offsets += list(k * w / rings * np.column_stack([np.cos(phi), np.sin(phi)]))
        weights += [(inside(outer) - inside(inner)) / (6 * k)] * (6 * k)
    return Beam(np.array(offsets), np.array(weights), 0.5 * w / rings)


def subray_directions(dirs: np.ndarray, beam: Beam) -> np.ndarray:
    """Unit directions of every sub-ray of pulses along unit ``dirs`` (n, 3): (n * s, 3),
    pulse-major (pulse ``i``'s sub-rays are rows ``i s`` to ``i s + s - 1``)."""
    dirs = np.ascontiguousarray(dirs, dtype=float)
    if len(beam) == 1:
        return dirs.copy()
    from usdforest.sensors.lidar import returns_kernels

    # about each axis, a normal to it (its cross product with the coordinate axis it is least
    # aligned with) and the axis crossed with that: the beam's offsets along the two
    return returns_kernels.subrays(dirs.reshape(-1, 3), np.ascontiguousarray(np.tan(beam.offsets)))


@dataclass(frozen=True, eq=False)
class Echoes:
    """The returns a sensor reports, ordered by pulse then range: pulse index, range, energy
    (sum of weight x reflectance x |cos| / range^2), class, tree, path, return number
    (1-based) and number of returns of the pulse."""

    pulse: np.ndarray
    range: np.ndarray
    energy: np.ndarray
    cls: np.ndarray
    tree: np.ndarray
    path: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray

    def __len__(self) -> int:
        return len(self.pulse)


def merge_echoes(
    t: np.ndarray,
    energy: np.ndarray,
    labels: tuple[np.ndarray, np.ndarray, np.ndarray],
    *,
    spread: np.ndarray | None = None,
    separation: float,
    mode: str,
    max_returns: int = 1,
    min_range: float = 0.0,
    threshold: float = 0.0,
    pulse_sigma: float = 0.0,
) -> Echoes:
    """Echoes of pulses from their sub-rays' hits.

    Parameters
    ----------
    t, energy
        (n, s): each sub-ray's hit distance (inf: none) and energy.
    labels
        (class, tree, path), each (n, s).
    spread
        (n, s): half the range interval each hit stands for (its patch of the footprint on
        a surface seen obliquely, ``range x cell x tan(incidence)``); 0 when not given.
    separation
        Hits of one pulse closer in range than this (metres) are one echo.
    mode
        ``first``, ``last``, ``strongest``, ``dual`` (the strongest and the last; the
        second strongest and the last when the strongest is last, as Velodyne's dual mode)
        or ``all`` (the nearest ``max_returns``), chosen among the detected echoes.
    min_range, threshold
        An echo nearer than ``min_range`` metres, or with less energy than ``threshold``,
        is not detected: the sensor never sees it (0, 0: every echo is).
    pulse_sigma
        > 0: the echoes are the peaks of each pulse's return waveform, its hits seen
        through a Gaussian pulse of this standard deviation in range (metres), each peak at
        its own range, peaks closer than ``separation`` one echo at the stronger's; 0: hits
        closer than ``separation`` are one echo at their energy-weighted mean range.
    """
    if mode not in MODES:
        raise ValueError(f"mode {mode!r} is not one of {MODES}")
    from usdforest.sensors.lidar import returns_kernels

    t = np.ascontiguousarray(t, dtype=np.float64)
    spread = np.zeros_like(t) if spread is None else np.ascontiguousarray(spread, np.float64)
    cls, tree, path = (np.ascontiguousarray(x) for x in labels)
    out = returns_kernels.merge(
        t, np.ascontiguousarray(energy, np.float64), spread, cls, tree, path,
        float(separation), MODES.index(mode), int(max_returns), float(min_range),
        float(threshold), float(pulse_sigma),
    )  # fmt: skip
    return Echoes(*out)
