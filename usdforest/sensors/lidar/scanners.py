"""Lidar: laser scanners (their beam and receiver; spinning multi-channel scanners here, the
survey patterns in :mod:`.patterns`) and pinhole depth cameras.

A spinning lidar's pulse is a diverging beam sampled as sub-rays (:mod:`.returns`): a pulse
whose footprint falls partly on a leaf and partly on what lies behind gives several returns,
reported first, last, strongest, dual or up to N as the sensor is set. A depth camera has one
ray per pixel. Every return carries its range, intensity, semantic class (trunk, branch,
leaf), tree id and prim path: ground truth for segmentation. Ranges may get Gaussian noise
from a seeded generator.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from usdforest.atomic import atomic_path, save_npz
from usdforest.errors import UsdForestError
from usdforest.seeds import stream
from usdforest.sensors.cast.raycast import SceneCaster
from usdforest.sensors.lidar.returns import (
    MODES,
    Echoes,
    beam_pattern,
    merge_echoes,
    subray_directions,
)
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.scenetypes import CLASSES, Scene

# Leaves and needles transmit near 905 nm: broadleaves 0.40-0.49 (PROSPECT-D), Norway spruce
# needles 0.364 (RAMI-V Järvselja); one value for both, as REFLECTANCE has (0.47), 0.42
# (docs/notes/lidar-radiometry.md). Light is followed through one leaf: beyond a second, a
# return keeps T^4 = 3 % of its power, and each pass costs a cast of the rays that hit leaves.
LEAF_TRANSMITTANCE = 0.42
LEAF_PASSES = 1


@dataclass(frozen=True)
class LaserScanner:
    """What every laser scanner shares: its beam, its receiver and its noise; the scan pattern
    is the subclass's (:class:`SpinningLidar`, and the survey scanners' kinds in
    :mod:`.patterns`).

    ``divergence`` (mrad, full angle at 1/e^2; 0: an ideal thin ray) is sampled by
    ``beam_rings`` rings of sub-rays (1: 7 sub-rays, 2: 19); hits closer in range than
    ``return_separation`` metres are one echo; ``returns`` picks the echoes reported:
    ``first``, ``last``, ``strongest``, ``dual`` (strongest and last) or ``all`` (up to
    ``max_returns``). ``leaf_transmittance``: the share of the light a leaf lets through
    (0: opaque leaves); a sub-ray that hits a leaf goes on through :data:`LEAF_PASSES`
    leaves, what it then hits returning through them (``T²`` per leaf, there and back).

    What the receiver detects and how exactly (the presets' figures from their datasheets):
    no echo nearer than ``min_range``; none weaker than a Lambertian target of reflectance
    ``detect_reflectance`` facing the sensor at ``detect_range`` metres (0: no limit), so
    a darker target or one seen obliquely is lost sooner; ranges with Gaussian noise of
    ``range_noise`` metres (standard deviation) and intensities with relative Gaussian noise
    ``intensity_noise``, from the scan's seed. ``noise = False`` turns all four off: the exact
    cloud, for ground truth. ``max_range`` is how far the rays are followed. ``model`` names
    the sensor (a flight's LAS system identifier). ``wavelength`` (nm) picks the targets'
    reflectances (:func:`reflectances`: near 905 nm or near 1550 nm).

    ``pulse_width`` (ns, full width at half maximum of the emitted pulse): echoes are the peaks
    of each pulse's return waveform (:func:`.returns.merge_echoes`), so two surfaces a pulse
    length apart give two returns at their ranges and an oblique one a peak, not a mean; 0:
    hits within ``return_separation`` are one echo at their energy-weighted range.
    """

    max_range: float = 100.0
    range_noise: float = 0.0
    kind: str = ""
    divergence: float = 0.0
    beam_rings: int = 1
    returns: str = "strongest"
    max_returns: int = 4
    return_separation: float = 1.0
    leaf_transmittance: float = LEAF_TRANSMITTANCE
    min_range: float = 0.0
    detect_range: float = 0.0
    detect_reflectance: float = 0.8
    intensity_noise: float = 0.0
    noise: bool = True
    model: str = ""
    pulse_width: float = 0.0
    wavelength: float = 905.0

    def check(self) -> None:
        if not (np.isfinite(self.pulse_width) and 0 <= self.pulse_width <= 100):
            raise UsdForestError("lidar.pulse_width: must be 0 to 100 ns (0: no waveform)")
        if len(self.model.encode()) > 32:
            raise UsdForestError("lidar.model: at most 32 bytes (the LAS system identifier)")
        if not (np.isfinite(self.min_range) and 0 <= self.min_range < self.max_range):
            raise UsdForestError("lidar.min_range: must be >= 0 m and below max_range")
        if not (np.isfinite(self.detect_range) and self.detect_range >= 0):
            raise UsdForestError("lidar.detect_range: must be >= 0 m (0: no detection limit)")
        if not (np.isfinite(self.detect_reflectance) and 0 < self.detect_reflectance <= 1):
            raise UsdForestError("lidar.detect_reflectance: must be in (0, 1]")
        if not (np.isfinite(self.intensity_noise) and 0 <= self.intensity_noise <= 1):
            raise UsdForestError("lidar.intensity_noise: must be in [0, 1] (relative)")
        if not (np.isfinite(self.leaf_transmittance) and 0 <= self.leaf_transmittance < 1):
            raise UsdForestError("lidar.leaf_transmittance: must be in [0, 1)")
        if not (np.isfinite(self.divergence) and 0 <= self.divergence <= 100):
            raise UsdForestError("lidar.divergence: must be in [0, 100] milliradians")
        if not 0 <= self.beam_rings <= 8:
            raise UsdForestError("lidar.beam_rings: must be 0 to 8 (1: 7 sub-rays, 8: 217)")
        if self.returns not in MODES:
            raise UsdForestError(
                f"lidar.returns: {self.returns!r} is not one of {', '.join(MODES)}"
            )
        if not 1 <= self.max_returns <= 15:
            raise UsdForestError("lidar.max_returns: must be 1 to 15 (LAS 1.4 holds 15)")
        if not (np.isfinite(self.return_separation) and self.return_separation > 0):
            raise UsdForestError("lidar.return_separation: must be a finite number of metres > 0")
        reflectances(self.wavelength)
        _check_common(self.max_range, self.range_noise)

    def sub_rays(self) -> int:
        """Sub-rays cast per pulse (the beam's rings of :func:`.returns.beam_pattern`)."""
        k = self.beam_rings
        return 1 + 3 * k * (k + 1)


def check_vfov(lo: float, hi: float) -> None:
    """Elevations from ``lo`` to ``hi`` degrees, within the sphere's."""
    if not -90 <= lo <= hi <= 90:
        raise UsdForestError("lidar.vfov_min/vfov_max: need -90 <= min <= max <= 90")


@dataclass(frozen=True)
class SpinningLidar(LaserScanner):
    """Channels evenly spread over [vfov_min, vfov_max] degrees, a full turn in azimuth
    (robot-mounted scanners: Velodyne, Ouster); the beam and receiver as
    :class:`LaserScanner`'s. A flight turns it ``rate`` times a second, each pulse firing at
    its azimuth's share of the turn."""

    kind: str = "spinning"
    channels: int = 16
    vfov_min: float = -15.0
    vfov_max: float = 15.0
    azimuth_step: float = 0.2

    def check(self) -> None:
        super().check()
        if not 1 <= self.channels <= 1024:
            raise UsdForestError("lidar.channels: must be 1 to 1024")
        if not 0.01 <= self.azimuth_step <= 360:
            raise UsdForestError("lidar.azimuth_step: must be in [0.01, 360] degrees")
        check_vfov(self.vfov_min, self.vfov_max)

    def angles(self) -> tuple[np.ndarray, np.ndarray]:
        """Azimuth and elevation (degrees) of every ray, azimuth-major (firing order)."""
        az = np.arange(0.0, 360.0, self.azimuth_step)
        el = (
            np.linspace(self.vfov_min, self.vfov_max, self.channels)
            if self.channels > 1
            else np.array([(self.vfov_min + self.vfov_max) / 2])
        )
        a, e = np.meshgrid(az, el, indexing="ij")
        return a.ravel(), e.ravel()

    def directions(self) -> np.ndarray:
        a, e = (np.radians(v) for v in self.angles())
        return np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])

    def pulses(self, duration: float, rate: float) -> int:
        """Pulses fired in ``duration`` seconds turning ``rate`` times a second."""
        return math.ceil(duration * rate) * self.channels * math.ceil(360.0 / self.azimuth_step)


# what a camera's settings may be (read noise in 8-bit counts, a sensor's full-well
# capacity, a stereo rig's baseline): beyond these an image is all noise or all saturated
CAMERA_LIMITS = {"noise": (255.0, "counts of 255"), "full_well": (1e7, "electrons"),
                 "baseline": (10.0, "m")}  # fmt: skip


@dataclass(frozen=True)
class DepthCamera:
    """A pinhole camera looking along +X: ``width`` x ``height`` rays, horizontal FOV.

    As ``kind = "camera"`` (:mod:`usdforest.sensors.optics.camera`) it also has a lens with
    Brown-Conrady distortion under OpenCV's names (``k1``, ``k2``, ``p1``, ``p2``, ``k3``),
    image noise (``noise``: Gaussian read noise, standard deviation in 8-bit counts;
    ``full_well``: electrons at full scale, for shot noise, 0 for none), an ``exposure``
    (EV: a white surface facing the renderer's sun is full scale at 0), ``auto_exposure``
    (metered: the frame's mean luminance made 18 % grey, ``exposure`` then compensating),
    ``shadows`` (the sun's light cast: a shadow ray per sunlit pixel) and, for a rectified
    stereo pair, a ``baseline`` (m) to its right camera."""

    width: int = 640
    height: int = 480
    hfov: float = 87.0
    max_range: float = 10.0
    range_noise: float = 0.0
    kind: str = "depth-camera"
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    noise: float = 0.0
    full_well: float = 0.0
    exposure: float = 0.0
    auto_exposure: bool = False
    shadows: bool = False
    baseline: float = 0.0

    def check(self) -> None:
        table = "camera" if self.kind == "camera" else "lidar"
        lens = {k: getattr(self, k) for k in CAMERA_ONLY}
        for key, value in lens.items():
            if not math.isfinite(value):
                raise UsdForestError(f"{table}.{key}: must be a finite number")
            if self.kind != "camera" and value != 0:
                raise UsdForestError(f"lidar.{key}: a camera setting, not a depth camera's")
        for key, (top, unit) in CAMERA_LIMITS.items():
            if not 0 <= getattr(self, key) <= top:
                raise UsdForestError(
                    f"{table}.{key}: {getattr(self, key):g} is outside 0 to {top:g} {unit}"
                )
        if self.baseline > 0 and any(getattr(self, k) for k in DISTORTION):
            raise UsdForestError(
                f"{table}.baseline: a stereo pair is rectified (its images undistorted): set "
                "k1, k2, p1, p2 and k3 to 0"
            )
        if abs(self.exposure) > 20:
            raise UsdForestError(f"{table}.exposure: {self.exposure:g} EV is beyond +-20")
        if self.width < 1 or self.height < 1:
            raise UsdForestError(f"{table}.width/height: the image needs at least one pixel")
        if self.width * self.height > 50_000_000:
            raise UsdForestError(
                f"{table}.width/height: {self.width} x {self.height} is over 50 megapixels"
            )
        if not 0 < self.hfov < 180:
            raise UsdForestError(f"{table}.hfov: must be in (0, 180) degrees")
        _check_common(self.max_range, self.range_noise, table)

    def directions(self) -> np.ndarray:
        f = (self.width / 2) / np.tan(np.radians(self.hfov) / 2)
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        d = np.column_stack(
            [np.full(u.size, f), -(u.ravel() - self.width / 2), -(v.ravel() - self.height / 2)]
        )
        return d / np.linalg.norm(d, axis=1, keepdims=True)


DISTORTION = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's distCoeffs, in its order
CAMERA_ONLY = (
    *DISTORTION,
    "noise",
    "full_well",
    "exposure",
    "auto_exposure",
    "shadows",
    "baseline",
)


MAX_RANGE = 1e5  # m: beyond any laser or camera in forest sensing (airborne: a few km)
MAX_RANGE_NOISE = 10.0  # m, one standard deviation


def _check_common(max_range: float, noise: float, table: str = "lidar") -> None:
    if not (np.isfinite(max_range) and 0 < max_range <= MAX_RANGE):
        raise UsdForestError(f"{table}.max_range: must be a number in (0, {MAX_RANGE:g}] m")
    if not (np.isfinite(noise) and 0 <= noise <= MAX_RANGE_NOISE):
        raise UsdForestError(f"{table}.range_noise: must be within 0 and {MAX_RANGE_NOISE:g} m")


# Hemispherical reflectance near 905 nm (the VLP-16's 903 nm; leaves differ by under 0.01 at
# the OS1's 865 nm) per class, from docs/notes/lidar-radiometry.md: Norway spruce needles
# 0.487 (RAMI-V Järvselja, Tartu Observatory) and broadleaves 0.44-0.51 (PROSPECT-D), so 0.47
# for leaves and shoots; spruce and hardwood bark 0.34-0.36 (RAMI-V), so 0.35 for wood
# (birch bark is brighter, 0.44-0.46); the forest floor between PROSAIL's wet (0.08) and dry
# (0.43) soil, 0.25 (no measured figure: a guess); anything unlabelled 0.5.
REFLECTANCE = {
    "unknown": 0.5,
    "trunk": 0.35,
    "branch": 0.35,
    "leaf": 0.47,
    "ground": 0.25,
    "dead_wood": 0.35,  # bare wood 0.34-0.36 at 905 nm (docs/notes/lidar-radiometry.md), as bark
    "ground_vegetation": 0.47,  # green leaves of herbs, grasses and ferns: as the trees' leaves
}
# Near 1550 nm (most airborne and many terrestrial scanners) leaf water absorbs: green leaves
# reflect about half what they do at 905 nm. ASTER/JHU spectra (Baldridge et al. 2009, as
# HELIOS++ ships them in assets/spectra): deciduous leaves 0.554 at 905 nm and 0.253 at
# 1550 nm, green grass 0.509 and 0.243; the 905 nm values above scaled by those ratios
# (leaves 0.47 x 0.457, ground vegetation 0.47 x 0.477). Stems absorb less than leaves at
# 1548 nm (Douglas et al. 2015, the dual-wavelength Echidna lidar): wood, dead wood and the
# floor kept at their 905 nm values (no measured 1550 nm figure for bark or litter: a stated
# choice).
REFLECTANCE_1550 = {
    **REFLECTANCE,
    "leaf": 0.215,
    "ground_vegetation": 0.224,
}
# the bands whose reflectances are known: the near-infrared plateau of leaves (800-1100 nm,
# where PROSPECT's leaves change by a few hundredths: 865, 905 and 1064 nm scanners) and the
# short-wave infrared near 1550 nm
BANDS = ((800.0, 1100.0, REFLECTANCE), (1500.0, 1600.0, REFLECTANCE_1550))


def reflectances(wavelength: float) -> np.ndarray:
    """Each class's reflectance (by class index) at ``wavelength`` nm."""
    for lo, hi, table in BANDS:
        if np.isfinite(wavelength) and lo <= wavelength <= hi:
            return np.array([table[c] for c in CLASSES])
    raise UsdForestError(
        f"lidar.wavelength: {wavelength:g} nm is not modelled; the reflectances known are "
        "for 800-1100 nm and 1500-1600 nm (905, 1064 or 1550 nm scanners)"
    )


_RHO = reflectances(905.0)  # by class index, at 905 nm
# what lets light through: the trees' leaves and the ground vegetation's blades
_GREEN = np.array([CLASSES.index("leaf"), CLASSES.index("ground_vegetation")], np.uint8)
LEAF_STEP = 1e-4  # m: a ray through a leaf starts again this far past it
# the intensity of a Lambertian target of reflectance 1 facing the sensor 1 m away
INTENSITY_GAIN = 65535.0


def reflected(cls: np.ndarray, cos_incidence: np.ndarray, rng: np.ndarray) -> np.ndarray:
    """Reflectance (of each hit's class) x |cos incidence| / range^2 (metres): the power an
    extended Lambertian target returns, relative to a white one facing the sensor at 1 m."""
    rho = _RHO[np.asarray(cls, dtype=np.int64)]
    r = np.maximum(np.asarray(rng, dtype=float), 1e-6)
    return rho * np.abs(cos_incidence) / (r * r)


def counts(energy: np.ndarray) -> np.ndarray:
    """``uint16`` intensities: ``INTENSITY_GAIN`` x ``energy`` (:func:`reflected`, summed over
    a return's share of the beam), rounded and saturated at 65,535."""
    return np.minimum(np.round(INTENSITY_GAIN * np.asarray(energy)), 65535).astype(np.uint16)


def cast_pulses(
    caster: SceneCaster,
    origins: np.ndarray,
    dirs: np.ndarray,
    sensor: LaserScanner | DepthCamera,
) -> Echoes:
    """The returns of pulses fired from ``origins`` along unit ``dirs`` (n, 3): every sub-ray
    of a laser scanner's beam cast in one batch, then merged (:func:`.returns.merge_echoes`);
    a depth camera's rays are thin and give their first hit."""
    from usdforest.sensors.lidar import returns_kernels

    near = least = sigma = 0.0
    rho = _RHO
    if isinstance(sensor, LaserScanner):
        rho = reflectances(sensor.wavelength)
        # the pulse's standard deviation in range: c/2 x FWHM / 2 sqrt(2 ln 2)
        sigma = 0.299792458 / 2 * sensor.pulse_width / (2 * np.sqrt(2 * np.log(2)))
        beam = beam_pattern(sensor.divergence, sensor.beam_rings)
        mode, most, apart = sensor.returns, sensor.max_returns, sensor.return_separation
        if sensor.noise:
            near = sensor.min_range
            if sensor.detect_range > 0:  # what that target returns head-on (reflected())
                least = sensor.detect_reflectance / sensor.detect_range**2
    else:
        beam, mode, most, apart = beam_pattern(0.0, 0), "first", 1, 1.0
    n, s = len(dirs), len(beam)
    sub = subray_directions(dirs, beam)
    start = np.repeat(origins, s, axis=0)
    weights = np.asarray(beam.weights, float)
    h = caster.first_hit(start, sub, sensor.max_range, group=s)
    energy, spread = returns_kernels.subray_energy(
        sub, h.normal, h.t, h.cls, rho, weights, float(beam.cell)
    )
    columns = [(h.t, energy, spread, h.cls, h.tree, h.path)]
    trans = getattr(sensor, "leaf_transmittance", 0.0)
    travelled, carry, met = h.t, np.ones(n * s), h.cls
    for _ in range(LEAF_PASSES if trans > 0 else 0):
        # the light a leaf lets through goes on; what it meets returns through the leaf again
        through = np.flatnonzero(np.isin(met, _GREEN) & np.isfinite(travelled))
        if not through.size:
            break
        past = travelled[through] + LEAF_STEP
        nxt = caster.first_hit(start[through] + sub[through] * past[:, None], sub[through],
                               sensor.max_range)  # fmt: skip
        t = np.full(n * s, np.inf)
        t[through] = np.where(past + nxt.t <= sensor.max_range, past + nxt.t, np.inf)
        normal, cls = np.zeros((n * s, 3)), np.zeros(n * s, np.uint8)
        tree, path = np.full(n * s, -1, np.int64), np.full(n * s, -1, np.int64)
        normal[through], cls[through] = nxt.normal, nxt.cls
        tree[through], path[through] = nxt.tree, nxt.path
        carry = carry * trans * trans
        e, sp = returns_kernels.subray_energy(sub, normal, t, cls, rho, weights, float(beam.cell))
        columns.append((t, e * carry, sp, cls, tree, path))
        travelled, met = t, cls
    t, e, sp, cls, tree, path = (
        np.stack([c[k].reshape(n, s) for c in columns], axis=2).reshape(n, -1) for k in range(6)
    )
    return merge_echoes(
        t, e, (cls, tree, path), spread=sp, separation=apart, mode=mode, max_returns=most,
        min_range=near, threshold=least, pulse_sigma=sigma,
    )  # fmt: skip


def observed(
    e: Echoes, sensor: LaserScanner | DepthCamera, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The ranges and intensities (:func:`counts`) the sensor reports for echoes ``e``: with
    its range noise (Gaussian, metres) and a spinning lidar's relative intensity noise drawn
    from ``rng``, unless its ``noise`` is off."""
    on = getattr(sensor, "noise", True)
    rng_, energy = e.range, e.energy
    if on and sensor.range_noise > 0:
        rng_ = rng_ + rng.normal(0.0, sensor.range_noise, len(e))
    relative = getattr(sensor, "intensity_noise", 0.0)
    if on and relative > 0:
        energy = energy * np.maximum(1.0 + rng.normal(0.0, relative, len(e)), 0.0)
    return rng_, counts(energy)


@dataclass(frozen=True, eq=False)
class Returns:
    """Returns of one scan: world points, ranges, pulse (ray) index, class, tree id, prim path,
    intensity (see :func:`counts`), and each return's number among its pulse's."""

    points: np.ndarray
    range: np.ndarray
    ray: np.ndarray
    cls: np.ndarray
    tree: np.ndarray
    path: np.ndarray
    paths: tuple[str, ...]
    n_rays: int
    sensor: dict
    intensity: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray

    def __len__(self) -> int:
        return int(self.range.shape[0])


def scan(
    scene: Scene,
    sensor: LaserScanner | DepthCamera,
    pose: Pose,
    *,
    seed: int = 0,
    caster: SceneCaster | None = None,
) -> Returns:
    """Fire every pulse of ``sensor`` at ``pose`` into ``scene``; its returns (one per pulse
    for a depth camera, as the sensor's ``returns`` mode says for a spinning lidar)."""
    sensor.check()
    dirs = sensor.directions() @ pose.rotation().T
    origins = np.broadcast_to(pose.position, dirs.shape)
    caster = caster or SceneCaster(scene)
    e = cast_pulses(caster, origins, dirs, sensor)
    rng_, intensity = observed(e, sensor, stream(seed, "lidar-noise"))
    pts = pose.position + dirs[e.pulse] * rng_[:, None]
    return Returns(
        pts,
        rng_,
        e.pulse.astype(np.int64),
        e.cls,
        e.tree,
        e.path,
        scene.paths,
        len(dirs),
        {**asdict(sensor), "pose": asdict(pose)},
        intensity,
        e.return_number,
        e.number_of_returns,
    )


def write_returns(r: Returns, out: str | Path) -> None:
    """``.npz`` (all arrays, path table, sensor) or ``.ply`` (binary; class, tree, path index)."""
    out = Path(out)
    if out.suffix == ".npz":
        save_npz(
            out,
            points=r.points,
            range=r.range,
            ray=r.ray,
            cls=r.cls,
            tree=r.tree,
            path=r.path,
            intensity=r.intensity,
            return_number=r.return_number,
            number_of_returns=r.number_of_returns,
            paths=np.array(r.paths, dtype=str),
            classes=np.array(CLASSES),
            n_rays=r.n_rays,
            sensor=json.dumps(r.sensor),
        )
        return
    if out.suffix != ".ply":
        raise UsdForestError(f"{out}: lidar output must end in .ply or .npz")
    n = len(r)
    rec = np.empty(
        n,
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("range", "<f4"),
            ("class", "u1"),
            ("tree", "<i4"),
            ("path", "<i4"),
            ("ray", "<i4"),
            ("intensity", "<u2"),
            ("return_number", "u1"),
            ("number_of_returns", "u1"),
        ],
    )
    rec["x"], rec["y"], rec["z"] = r.points.T
    rec["range"], rec["class"], rec["tree"] = r.range, r.cls, r.tree
    rec["path"], rec["ray"], rec["intensity"] = r.path, r.ray, r.intensity
    rec["return_number"], rec["number_of_returns"] = r.return_number, r.number_of_returns
    header = "\n".join(
        [
            "ply",
            "format binary_little_endian 1.0",
            "comment usdforest lidar scan; class: "
            + ", ".join(f"{i}={c}" for i, c in enumerate(CLASSES)),
            f"comment rays {r.n_rays}; path indexes the table in the .npz output",
            f"element vertex {n}",
            "property float x",
            "property float y",
            "property float z",
            "property float range",
            "property uchar class",
            "property int tree",
            "property int path",
            "property int ray",
            "property ushort intensity",
            "property uchar return_number",
            "property uchar number_of_returns",
            "end_header",
            "",
        ]
    ).encode()
    with atomic_path(out) as tmp:
        tmp.write_bytes(header + rec.tobytes())
