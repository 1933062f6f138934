"""A survey plan flown or scanned (:mod:`.plans`): terrestrial stations, each a full
station of a terrestrial scanner, or drone and airborne flight lines following the ground;
every point in the stage's one frame (the stations registered by construction), with the
station or line it came from, and the tree table of the plot.

:func:`run_survey` computes; :func:`write_survey` writes the per-station or per-line LAS,
the merged cloud, the tree table and the plan's figures (expected and measured density).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from usdforest.atomic import atomic_path
from usdforest.errors import UsdForestError
from usdforest.seeds import stream
from usdforest.sensors.cast.raycast import SceneCaster
from usdforest.sensors.lidar.las import (
    FlightReturns,
    benchmark_tree_ids,
    gps_times,
    ground_height,
    stage_georeference,
    write_las,
)
from usdforest.sensors.lidar.patterns import TerrestrialScanner
from usdforest.sensors.lidar.ply import write_ply
from usdforest.sensors.lidar.scanners import LaserScanner, cast_pulses, observed
from usdforest.sensors.platforms.flight import Trajectory, fly_lidar
from usdforest.sensors.platforms.plans import (
    SurveyPlan,
    flight_lines,
    pulse_density,
    station_grid,
)
from usdforest.sensors.scene.scenetypes import Scene

BREAST = 1.3  # m: the tree table's position at breast height
CHUNK = 400_000  # pulses a terrestrial station casts at once (7 sub-rays each: 2.8 M rays)
WAYPOINT = 5.0  # m between a flight line's points that follow the ground
RELIEF = 2000.0  # m of ground relief a cluster task's scene allows for around its line
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True, eq=False)
class Survey:
    """A survey's clouds, one a station or line (``parts``, point source = its number from
    1), where each started (``starts``: stations (n, 3) or line ends (n, 2, 3)), the plan's
    pulse density (pulses/m², flights) and the one measured (first returns within the
    swath, where every swath that would cover the ground is flown), and the tree table."""

    plan: SurveyPlan
    lidar: LaserScanner
    parts: tuple[FlightReturns, ...]
    starts: np.ndarray
    expected_density: float | None
    measured_density: float | None
    trees: dict[str, np.ndarray]

    def merged(self) -> tuple[FlightReturns, np.ndarray]:
        """All parts as one cloud, and each point's part (1-based)."""
        if not self.parts:
            raise UsdForestError(
                "survey: no points here (a survey on workers keeps its lines' files)"
            )
        source = np.concatenate(
            [np.full(len(p), k + 1, np.uint16) for k, p in enumerate(self.parts)]
        )
        return FlightReturns.concat(list(self.parts)), source


def check_pairing(plan: SurveyPlan, lidar: LaserScanner) -> None:
    """The plan's kind and its scanner agree, and the scanner's settings are sound."""
    if (plan.kind == "tls") != isinstance(lidar, TerrestrialScanner):
        raise UsdForestError(
            f"survey.lidar: a {plan.kind} survey needs "
            + ("a terrestrial scanner (kind tls)" if plan.kind == "tls" else "an airborne one")
        )
    if plan.kind == "flight" and not hasattr(lidar, "firing"):
        raise UsdForestError(
            f"survey.lidar: {lidar.kind!r} has no swath; a flight survey flies a line, "
            "oscillating, conical or rosette scanner"
        )
    lidar.check()


def region_of(plan: SurveyPlan, scene: Scene) -> tuple[float, float, float, float]:
    """The plan's region, or the stage's bounds."""
    if plan.region:
        return tuple(float(v) for v in plan.region)
    lo, hi = scene.bounds
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def run_survey(
    stage: str | Path,
    plan: SurveyPlan,
    lidar: LaserScanner,
    *,
    progress: Progress | None = None,
) -> Survey:
    """Scan the plan's stations or fly its lines over ``stage`` (see the module)."""
    from usdforest.sensors.scene.extraction import extract_scene

    tick = progress or (lambda stage, done, total: None)
    check_pairing(plan, lidar)
    scene = extract_scene(stage, reflectors=False, progress=progress)
    caster = SceneCaster(scene)
    region = region_of(plan, scene)
    if plan.kind == "tls":
        xy = np.array(plan.stations, float) if plan.stations else station_grid(region, plan.spacing)
        z = ground_height(scene, xy) + plan.height
        starts = np.column_stack([xy, z])
        duration = lidar.station_pulses() / lidar.pulse_rate
        parts = []
        for k, at in enumerate(starts):
            parts.append(_station(scene, caster, lidar, at, k * duration, plan.seed, k, tick))
            tick("stations", k + 1, len(starts))
        trees = tree_table(stage, scene, parts)
        return Survey(plan, lidar, tuple(parts), starts, None, None, trees)
    lines = flight_lines(region, plan.heading, plan.spacing_between_lines)
    parts, ends, t0 = [], [], 0.0
    for j, (a, b) in enumerate(lines):
        traj = _following(scene, a, b, plan, t0)
        parts.append(fly_lidar(scene, lidar, traj, caster=caster, seed=plan.seed, key=(j,)))
        ends.append(traj.position[[0, -1]])
        t0 = float(traj.t[-1])
        tick("flight lines", j + 1, len(lines))
    survey = Survey(plan, lidar, tuple(parts), np.array(ends), pulse_density(plan, lidar),
                    None, tree_table(stage, scene, parts))  # fmt: skip
    return replace(survey, measured_density=_measured(survey, region))


def _station(scene, caster, lidar, at, t0, seed, k, tick) -> FlightReturns:
    """One terrestrial station at ``at``: its pulses cast in chunks of :data:`CHUNK`."""
    dirs = lidar.directions()
    az = lidar.grid()[0]
    times = t0 + lidar.times()
    rng = stream(seed, "tls", k)
    out = []
    for i in range(0, len(dirs), CHUNK):
        d = dirs[i : i + CHUNK]
        e = cast_pulses(caster, np.broadcast_to(at, d.shape), d, lidar)
        r, intensity = observed(e, lidar, rng)
        p = i + e.pulse
        n = len(p)
        out.append(FlightReturns(
            points=at + dirs[p] * r[:, None], gps_time=times[p], range=r,
            cls=e.cls.astype(np.uint8), tree=e.tree.astype(np.int32),
            path=e.path.astype(np.int32), paths=scene.paths, n_rays=len(d), sweeps=0,
            ring=np.zeros(n, np.uint16), azimuth=(az[p] + 180.0) % 360.0 - 180.0,
            intensity=intensity.astype(np.uint16),
            return_number=e.return_number.astype(np.uint8),
            number_of_returns=e.number_of_returns.astype(np.uint8),
            scan_angle=np.zeros(n),  # LAS's scan angle is an airborne one
            height=np.zeros(n), system=lidar.model or "OTHER",
        ))  # fmt: skip
        tick(f"station {k + 1}", min(i + CHUNK, len(dirs)), len(dirs))
    whole = FlightReturns.concat(out)
    height = whole.points[:, 2] - ground_height(scene, whole.points[:, :2])
    return replace(whole, sweeps=1, height=height)


def _following(scene, a, b, plan: SurveyPlan, t0) -> Trajectory:
    """A flight line from ``a`` to ``b`` (x, y) at the plan's height above the scene's
    ground and speed from ``t0``, facing along it (less its crab) at its roll and pitch."""
    length = float(np.hypot(*(np.asarray(b) - a)))
    n = max(2, math.ceil(length / WAYPOINT) + 1)
    s = np.linspace(0.0, 1.0, n)
    xy = np.asarray(a) + s[:, None] * (np.asarray(b) - a)
    z = ground_height(scene, xy) + plan.height
    track = math.degrees(math.atan2(b[1] - a[1], b[0] - a[0]))
    return Trajectory(
        t0 + s * length / plan.speed, np.column_stack([xy, z]),
        yaw=np.full(n, track + plan.crab), pitch=np.full(n, plan.pitch),
        roll=np.full(n, plan.roll),
    )  # fmt: skip


def _window(plan: SurveyPlan, starts: np.ndarray, region):
    """Where every swath that would cover the ground is flown: inside the region, across
    the track from a swath's half less a spacing inside the outermost lines (the lines
    beyond them, not flown, would have covered the rest): ``(lo, hi, area)`` along the
    across-track axis, or ``None`` where nothing is left."""
    h = math.radians(plan.heading)
    across = np.array([math.cos(h), -math.sin(h)])
    lines = starts[:, :, :2].mean(axis=1) @ across
    reach = plan.swath / 2 - plan.spacing_between_lines
    lo, hi = float(lines.min() + reach), float(lines.max() - reach)
    if hi <= lo:
        return None
    from shapely.geometry import Polygon, box

    x0, y0, x1, y1 = region
    along = np.array([math.sin(h), math.cos(h)])
    far = float(np.hypot(*np.abs([(x0, y0), (x1, y1)]).max(axis=0))) + 1.0  # past every corner
    strip = Polygon(
        [c * across + t * far * along for c, t in ((lo, -1), (lo, 1), (hi, 1), (hi, -1))]
    )
    area = float(box(x0, y0, x1, y1).intersection(strip).area)
    return (lo, hi, area, tuple(float(v) for v in region)) if area > 0 else None


def _first_in_window(p: FlightReturns, plan: SurveyPlan, window) -> int:
    """First returns of ``p`` within the plan's scan angle that land in ``window``."""
    if window is None:
        return 0
    lo, hi, _, (x0, y0, x1, y1) = window
    h = math.radians(plan.heading)
    c = p.points[:, :2] @ np.array([math.cos(h), -math.sin(h)])
    xy = p.points[:, :2]
    inside = (xy[:, 0] >= x0) & (xy[:, 0] < x1) & (xy[:, 1] >= y0) & (xy[:, 1] < y1)
    keep = (p.return_number == 1) & inside & (c > lo) & (c < hi)
    return int(np.count_nonzero(keep & (np.abs(p.scan_angle) <= plan.scan_angle)))


def _measured(survey: Survey, region) -> float | None:
    """First returns within the plan's scan angle per m² of :func:`_window` (``None``
    where nothing is left)."""
    window = _window(survey.plan, survey.starts, region)
    if window is None:
        return None
    return sum(_first_in_window(p, survey.plan, window) for p in survey.parts) / window[2]


def tree_table(stage, scene: Scene, parts) -> dict[str, np.ndarray]:
    """One row per tree of the scene: its treeID (``id + 1``), its ``trees.csv`` id, species,
    DBH and height where the forest's ``trees.csv`` has them, its position where its stem
    meets the ground and at breast height (1.3 m along its stem), its crown base (the lowest
    leaf, m above its base) and crown radius (its farthest leaf from the stem, horizontally),
    and the survey's points on it."""
    inst = scene.instances
    ids, first = np.unique(inst.tree[inst.tree >= 0], return_index=True)
    rows = np.flatnonzero(inst.tree >= 0)[first]
    m = inst.matrix[rows]
    base = m[:, 3, :3]
    up = m[:, 2, :3] / np.maximum(np.linalg.norm(m[:, 2, :3], axis=1, keepdims=True), 1e-12)
    crown_base = np.full(len(ids), np.nan)
    crown_radius = np.full(len(ids), np.nan)
    for j, (row, k) in enumerate(zip(rows, inst.proto[rows], strict=True)):
        leaves = scene.protos[k].leaf_instances
        if not len(leaves):
            continue
        w = leaves.matrix[:, 3, :3] @ inst.matrix[row, :3, :3] + inst.matrix[row, 3, :3]
        crown_base[j] = float(w[:, 2].min() - base[j, 2])
        crown_radius[j] = float(np.hypot(*(w[:, :2] - base[j, :2]).T).max())
    counts = np.zeros(len(ids), np.int64)
    for p in parts:
        on = p.tree[p.tree >= 0]
        at = np.searchsorted(ids, on)
        ok = (at < len(ids)) & (ids[np.minimum(at, len(ids) - 1)] == on)
        np.add.at(counts, at[ok], 1)
    species, dbh, height, offset = _inventory(stage, ids)
    # 1.3 m along the stem: trees.csv's breast-height point (a stem leans in its asset)
    bh = base + np.where(np.isfinite(offset), offset, BREAST * up)
    return {
        "treeID": benchmark_tree_ids(ids), "id": ids, "species": species,
        "x": base[:, 0], "y": base[:, 1], "z": base[:, 2],
        "x_1.3": bh[:, 0], "y_1.3": bh[:, 1], "z_1.3": bh[:, 2],
        "dbh": dbh, "height": height, "crown_base": crown_base, "crown_radius": crown_radius,
        "points": counts,
    }  # fmt: skip


def _inventory(stage, ids: np.ndarray):
    """Species, DBH, height and breast-height point (from the base) of trees ``ids`` from
    the forest's ``trees.csv`` (beside the stage as ``<stem>_assets/trees.csv``); empty and
    NaN where it has none."""
    path = Path(stage)
    table = path.parent / f"{path.stem}_assets" / "trees.csv"
    species = np.full(len(ids), "", dtype=object)
    dbh, height = np.full(len(ids), np.nan), np.full(len(ids), np.nan)
    offset = np.full((len(ids), 3), np.nan)
    if not table.is_file():
        return species, dbh, height, offset
    where = {int(i): j for j, i in enumerate(ids)}
    with open(table, newline="") as f:
        for row in csv.DictReader(f):
            j = where.get(int(row["id"]))
            if j is not None:
                species[j] = row.get("species", "")
                dbh[j] = float(row.get("dbh") or "nan")
                height[j] = float(row.get("height") or "nan")
                if row.get("x_bh"):  # where the stem passes 1.3 m up it, from its base
                    offset[j] = [float(row[f"{a}_bh"]) - float(row[a]) for a in "xyz"]
    return species, dbh, height, offset


def write_survey(survey: Survey, out: Path, *, crs=None, origin=None) -> list[Path]:
    """The survey's files in the folder ``out``: ``stations/station_NNN.las`` or
    ``lines/line_NNN.las``, the merged ``plot.las`` (tls) or ``survey.las`` with each
    point's station or line as its point source (``.laz`` with the plan's ``laz``; with its
    ``ply``, each of them also as FOR-instanceV2's PLY beside it,
    :func:`usdforest.sensors.lidar.ply.write_ply`), ``trees.csv`` and ``survey.json``."""
    plan = survey.plan
    start = plan.start_time or None
    if start is not None:
        gps_times(np.zeros(1), start)
    part = "station" if plan.kind == "tls" else "line"
    ext = ".laz" if plan.laz else ".las"
    files = []
    (out / f"{part}s").mkdir(parents=True, exist_ok=True)
    for k, r in enumerate(survey.parts):
        path = out / f"{part}s" / f"{part}_{k + 1:03d}{ext}"
        write_las(r, path, crs=crs, origin=origin, flight_line=k + 1, start_time=start,
                  labels=plan.labels)  # fmt: skip
        files.append(path)
        if plan.ply:
            files.append(write_ply(r, path.with_suffix(".ply"), origin=origin,
                                   point_source=np.full(len(r), k + 1)))  # fmt: skip
    merged, source = survey.merged()
    whole = out / (("plot" if plan.kind == "tls" else "survey") + ext)
    write_las(merged, whole, crs=crs, origin=origin, start_time=start, labels=plan.labels,
              point_source=source)  # fmt: skip
    files.append(whole)
    if plan.ply:
        files.append(write_ply(merged, whole.with_suffix(".ply"), origin=origin,
                               point_source=source))  # fmt: skip
    files.append(_write_trees(survey.trees, out / "trees.csv"))
    summary = survey_summary(survey)
    with atomic_path(out / "survey.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    files.append(out / "survey.json")
    return files


def _write_trees(trees: dict[str, np.ndarray], path: Path) -> Path:
    """The tree table as the forest's ``trees.csv`` is written (:mod:`usdforest.csvtext`:
    ids and counts whole, figures to 4 decimals, ``nan`` where there is none)."""
    from usdforest import csvtext

    def column(name: str, v: np.ndarray) -> np.ndarray:
        if name == "species":
            names, codes = np.unique(np.asarray(v, dtype=str), return_inverse=True)
            return csvtext.labels(codes, list(names))
        if np.issubdtype(np.asarray(v).dtype, np.integer):
            return csvtext.integers(v)
        return csvtext.fixed(np.asarray(v, dtype=float), 4)

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write((",".join(trees) + "\n").encode())
        if len(trees["id"]):
            f.write(csvtext.rows([column(k, v) for k, v in trees.items()]))
    return path


def survey_summary(survey: Survey, counts: tuple[int, int, int] | None = None) -> dict:
    """What a survey was and what it gave, as JSON-ready values; ``counts`` (parts, pulses,
    points) where its parts stayed in files (a survey on workers)."""
    plan = survey.plan
    parts, pulses, points = counts or (
        len(survey.parts),
        sum(p.n_rays for p in survey.parts),
        sum(len(p) for p in survey.parts),
    )
    return {
        "plan": asdict(plan),
        "lidar": asdict(survey.lidar),
        "kind": plan.kind,
        "parts": parts,
        "pulses": pulses,
        "points": points,
        "trees": len(survey.trees["id"]),
        "trees_seen": int(np.count_nonzero(survey.trees["points"])),
        "expected_pulse_density": survey.expected_density,
        "measured_first_return_density": survey.measured_density,
    }


def survey_folder(
    stage: str | Path,
    plan: SurveyPlan,
    lidar: LaserScanner,
    out: str | Path,
    *,
    force: bool = False,
    inputs: tuple = (),
    progress: Progress | None = None,
    workers: int = 0,
    scheduler: str | None = None,
) -> tuple[Survey, dict]:
    """:func:`run_survey` written to the folder ``out`` (:func:`write_survey`) as every
    writing command writes: ``out`` never one of the stage's layers or ``inputs`` (the plan's
    file), an existing one replaced only with ``force``, built beside it and moved into
    place whole, nothing left by an interrupted survey. With ``workers`` (1 or more) or a
    ``scheduler``, a flight survey's lines are Dask tasks (:func:`survey_on_cluster`: the
    survey's parts then stay in its files). Returns the survey and its summary."""
    from usdforest.atomic import interrupts_held, output_lock, publish, staging_folder
    from usdforest.paths import claim_outputs, require_output, stage_inputs

    check_pairing(plan, lidar)  # before anything is claimed or cast
    if workers or scheduler is not None:
        _check_on_workers(plan)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UsdForestError(f"{out}: the output must be a folder, and this is a file")
    require_output(out / "survey.json", "output folder")
    reads = stage_inputs(stage)
    claim_outputs([], inputs=lambda: [*reads(), *inputs], folders=[out], force=force)
    with output_lock(out), staging_folder(out) as tmp:
        claim_outputs([], inputs=lambda: [*reads(), *inputs], folders=[out], force=force)
        staged = tmp / out.name
        if workers or scheduler is not None:
            from usdforest.cluster import dask_client

            with dask_client(max(workers, 1), scheduler) as client:
                done, summary = survey_on_cluster(stage, plan, lidar, staged, client,
                                                  progress=progress)  # fmt: skip
        else:
            done = run_survey(stage, plan, lidar, progress=progress)
            crs, origin = stage_georeference(stage)
            write_survey(done, staged, crs=crs, origin=origin)
            summary = survey_summary(done)
        with interrupts_held():
            publish(tmp, out, staged, [], force=force)
    return done, summary


def _check_on_workers(plan: SurveyPlan) -> None:
    if plan.kind != "flight":
        raise UsdForestError(
            f"workers: a {plan.kind} survey runs here; workers fly a flight survey's lines"
        )


def survey_on_cluster(
    stage: str | Path,
    plan: SurveyPlan,
    lidar: LaserScanner,
    out: Path,
    client,
    *,
    progress: Progress | None = None,
) -> tuple[Survey, dict]:
    """A flight survey as Dask tasks, one flight line each (``client`` None: here, one after
    another, the same tasks): each task gathers the scene within reach of its line, flies
    it and writes its LAS into ``out/lines/``; only counts come back, so the client's memory
    stays flat however large the survey. ``out`` then holds the lines, ``trees.csv`` (the
    trees of every line's scene, their points summed) and ``survey.json``; no merged cloud
    (merge the lines with PDAL or lasmerge); with the plan's ``ply``, each line's PLY beside it."""
    from usdforest.cluster import run_tasks
    from usdforest.sensors.scene.extraction import extract_scene

    tick = progress or (lambda stage, done, total: None)
    _check_on_workers(plan)
    check_pairing(plan, lidar)
    frame = extract_scene(
        stage,
        instancing=True,
        leaf_triangles=False,
        reflectors=False,
        centre=np.zeros(3),
        radius=0.0,
    )  # the bounds and the ground only
    region = region_of(plan, frame)
    lines = flight_lines(region, plan.heading, plan.spacing_between_lines)
    lengths = np.hypot(*(lines[:, 1] - lines[:, 0]).T)
    starts = np.concatenate([[0.0], np.cumsum(lengths / plan.speed)[:-1]])
    ends = [np.column_stack([ln, ground_height(frame, ln) + plan.height]) for ln in lines]
    window = _window(plan, np.array(ends), region)
    out.mkdir(parents=True, exist_ok=True)
    (out / "lines").mkdir(exist_ok=True)
    crs, origin = stage_georeference(stage)
    # absolute: a worker's current folder need not be this process's
    shared = (str(Path(stage).resolve()), plan, lidar, str(out.resolve()), window, crs, origin)
    jobs = [(j, lines[j], float(starts[j])) for j in range(len(lines))]
    done = run_tasks(client, _line_task, jobs, shared, tick, "flight lines")
    trees: dict[int, dict] = {}
    for d in done:
        for row in d["trees"]:
            kept = trees.setdefault(row["id"], {**row, "points": 0})
            kept["points"] += row["points"]
    ids = sorted(trees)
    columns = next(iter(trees.values())) if trees else {"id": 0, "points": 0}
    table = {k: np.array([trees[i][k] for i in ids], dtype=object if k == "species" else None)
             for k in columns}  # fmt: skip
    if trees:
        _write_trees(table, out / "trees.csv")
    area = window[2] if window else 0.0
    survey = Survey(plan, lidar, (), np.array(ends), pulse_density(plan, lidar),
                    sum(d["first"] for d in done) / area if area else None, table)  # fmt: skip
    counts = (len(done), sum(d["pulses"] for d in done), sum(d["points"] for d in done))
    summary = survey_summary(survey, counts) | {"merged": False}
    with atomic_path(out / "survey.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    return survey, summary


def _line_task(j: int, line: np.ndarray, t0: float, shared) -> dict:
    """One flight line: its scene (everything within its length and its reach), flown,
    written; its counts."""
    from usdforest.sensors.scene.extraction import extract_scene

    stage, plan, lidar, out, window, crs, origin = shared
    mid = line.mean(axis=0)
    half = float(np.hypot(*(line[1] - line[0]))) / 2
    # what the line's rays can reach, from any height over any relief (RELIEF)
    reach = half + lidar.max_range + plan.height + RELIEF
    scene = extract_scene(stage, centre=np.array([mid[0], mid[1], 0.0]), radius=reach,
                          reflectors=False)  # fmt: skip
    traj = _following(scene, line[0], line[1], plan, t0)
    r = fly_lidar(scene, lidar, traj, seed=plan.seed, key=(j,))
    ext = ".laz" if plan.laz else ".las"
    name = Path(out) / "lines" / f"line_{j + 1:03d}{ext}"
    write_las(r, name, crs=crs, origin=origin, flight_line=j + 1,
              start_time=plan.start_time or None, labels=plan.labels)  # fmt: skip
    if plan.ply:
        write_ply(r, name.with_suffix(".ply"), origin=origin,
                  point_source=np.full(len(r), j + 1))  # fmt: skip
    table = tree_table(stage, scene, [r])
    rows = [{k: (v[i].item() if hasattr(v[i], "item") else v[i]) for k, v in table.items()}
            for i in range(len(table["id"]))]  # fmt: skip
    return {
        "pulses": r.n_rays, "points": len(r), "trees": rows,
        "first": _first_in_window(r, plan, window),
    }  # fmt: skip
