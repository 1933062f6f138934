"""Sensor commands: ``scan`` and ``fly`` (thin layers over
:mod:`usdforest.sensors.platforms.survey`)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from usdforest import arguments
from usdforest.atomic import move_into_place, output_lock, staging_folder
from usdforest.cli.app import (
    MAX_SEED,
    Command,
    DeviceOption,
    ForceOption,
    QuietOption,
    SummaryJsonOption,
    app,
    err,
    handles_errors,
    out,
    progress_bars,
)
from usdforest.errors import UsdForestError
from usdforest.paths import claim_outputs, require_output, stage_inputs

LAS_LABELS = ("asprs", "for-instance")  # usdforest.sensors.lidar.las.LABELS, not imported here


@app.command("scan", cls=Command)
@handles_errors
def scan_cmd(
    stage: Annotated[Path, typer.Argument(help="Any stage that composes trees or forests.")],
    sensor: Annotated[str, typer.Option(help="lidar, sonar or camera.")],
    pose: Annotated[
        str, typer.Option(help="x,y,z[,yaw,pitch,roll] (the stage's units and axes, degrees).")
    ],
    output: Annotated[
        Path,
        typer.Option(
            "--output",
            "-o",
            help="lidar: .ply or .npz; sonar: .npz (+ .wav, .png); camera: .npz "
            "(+ _rgb, _depth, _semantic, _instance .png)",
        ),
    ],
    preset: Annotated[
        str | None,
        typer.Option(
            help="lidar: vlp-16, hdl-32, os1-64, depth-camera (robotics), vz-400 (terrestrial), "
            "vux-1uav, livox-mid-40 (drone), vq-780i, als50-ii (airborne); sonar: bat-fm, "
            "paper, narrow, wide; camera: pinhole-640, d435, d435-stereo, fpv-1280."
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="TOML with a \\[lidar], \\[sonar] or \\[camera] table of settings."),
    ] = None,
    occlusion: Annotated[
        bool,
        typer.Option(
            "--occlusion", help="sonar: drop leaves, wood and ground hidden by anything in front."
        ),
    ] = False,
    seed: Annotated[
        int, typer.Option(min=0, max=MAX_SEED, help="Seed for range noise and ground roughness.")
    ] = 0,
    device: DeviceOption = "cpu",
    at: Annotated[
        float | None,
        typer.Option(
            "--time",
            help="Seconds into the stage's animation (a forest's wind): the trees where they "
            "sway then. Default: the still forest.",
        ),
    ] = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
    as_json: SummaryJsonOption = False,
) -> None:
    """Scan a stage with a lidar (ray casting), a bat-like sonar (echoes of leaves, wood and
    ground) or a camera (depth, semantic and instance images, shaded RGB)."""
    import time

    from usdforest.sensors.platforms.survey import SENSORS, scan
    from usdforest.sensors.pose import parse_pose

    require_output(output)
    if sensor not in SENSORS:
        raise UsdForestError(f"--sensor: {sensor!r} is not lidar, sonar or camera")
    reads = stage_inputs(stage)
    claim_outputs(
        [output, *_scan_outputs(sensor, output)],
        inputs=lambda: [*reads(), config],
        force=force,
    )
    p = parse_pose(pose)
    if at is not None:
        arguments.number(at, "--time")
    settings = _scan_settings(sensor, preset, config, occlusion)
    t0 = time.perf_counter()
    with progress_bars(not (quiet or as_json), t0) as tick:
        done = scan(
            stage, sensor, p, settings=settings, seed=seed, device=device, progress=tick, time=at
        )
    for w in done.warnings:
        err.print(f"warning: {w}", highlight=False)
    summary, text = _write_scan(sensor, done, settings, output)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        out.print(text, highlight=False)


def _scan_outputs(sensor: str, output: Path) -> list[Path]:
    """The files a scan writes beside ``output``, whose suffix is checked for ``sensor``."""
    suffixes = (".ply", ".npz") if sensor == "lidar" else (".npz",)
    if output.suffix.lower() not in suffixes:
        raise UsdForestError(f"{output}: a {sensor} scan is written as {' or '.join(suffixes)}")
    return {
        "sonar": [output.with_suffix(x) for x in (".wav", ".png")],  # OUT.npz -> OUT.wav
        "camera": [
            output.with_name(f"{output.stem}_{k}.png")
            for k in ("rgb", "depth", "semantic", "instance")
        ],
    }.get(sensor, [])


def _scan_settings(sensor: str, preset: str | None, config: Path | None, occlusion: bool):
    """The ``sensor``'s settings: its ``preset`` (or the default) with ``config``'s table."""
    from usdforest.config import check_keys, load_toml
    from usdforest.sensors.platforms.survey import SENSORS, sensor_settings, sensor_table

    presets, default = SENSORS[sensor]
    name = preset or default
    if name not in presets:
        raise UsdForestError(
            f"--preset: unknown {sensor} preset {name!r}; known: " + ", ".join(presets)
        )
    table: dict = {}
    if config is not None:
        data = load_toml(config)
        check_keys(data, {sensor}, str(config))
        table = sensor_table(data.get(sensor), sensor, str(config))
    if occlusion and sensor == "sonar":
        table["occlusion"] = True
    return sensor_settings(sensor, name, table, where=str(config) if config else "")


def _write_scan(sensor: str, done, settings, output: Path) -> tuple[dict, str]:
    """Write a finished scan's files; its summary (for ``--json``) and its line of text."""
    import numpy as np

    from usdforest.sensors.lidar import scanners as lidar
    from usdforest.sensors.optics import camera
    from usdforest.sensors.scene.scenetypes import class_counts
    from usdforest.sensors.sonar import model as sonar

    if sensor == "lidar":
        r = done.result
        lidar.write_returns(r, output)
        summary = {
            "output": str(output),
            "rays": r.n_rays,
            "returns": len(r),
            "pulses_with_several_returns": int(np.count_nonzero(r.return_number == 2)),
            "returns_by_class": class_counts(r.cls),
            "trees_hit": int(np.unique(r.tree[r.tree >= 0]).size),
            "triangles": done.triangles,
        }
        text = (
            f"{output}: {len(r):,} returns from {r.n_rays:,} pulses "
            f"({summary['pulses_with_several_returns']:,} with several; "
            + ", ".join(f"{k} {v:,}" for k, v in summary["returns_by_class"].items() if v)
            + f"), {summary['trees_hit']} trees, {done.triangles:,} triangles in range"
        )
        return summary, text
    if sensor == "camera":
        frame = done.result
        files = camera.write_frame(frame, settings, output)
        summary = {
            "output": [str(f) for f in files],
            "pixels": int(frame.depth.size),
            "pixels_by_class": class_counts(frame.semantic.ravel()),
            "trees_seen": int(np.unique(frame.instance[frame.instance >= 0]).size),
        }
        seen = summary["pixels_by_class"]
        text = (
            f"{output} (+ {len(files) - 1} PNGs): {settings.width} x {settings.height} pixels ("
            + ", ".join(f"{k} {v:,}" for k, v in seen.items() if v and k != "unknown")
            + f"), {summary['trees_seen']} trees in view"
        )
        return summary, text
    e = done.result
    files = sonar.write_echo(e, output)
    env = np.abs(e.impulse)
    peak = float(e.t[np.argmax(env)]) * settings.speed_of_sound / 2 if env.max() > 0 else None
    summary = {
        "output": [str(f) for f in files],
        "leaves_in_range": e.leaves_in_range,
        "leaves_used": e.leaves_used,
        "reflectors": e.reflectors,
        "strongest_echo_range_m": peak,
    }
    heard = {
        "trunk": "trunk cylinders",
        "branch": "branch cylinders",
        "dead_wood": "dead-wood cylinders",
        "ground_vegetation": "ground-vegetation blades",
        "ground": "ground facets",
    }
    text = (
        f"{', '.join(map(str, files))}: echo of {e.leaves_used:,} leaves "
        f"(of {e.leaves_in_range:,} within {settings.max_range:g} m)"
        + "".join(f", {n:,} {heard[k]}" for k, n in e.reflectors.items() if k in heard and n)
        + (f", strongest at {peak:.2f} m" if peak is not None else "")
    )
    return summary, text


@app.command("fly", cls=Command)
@handles_errors
def fly_cmd(
    stage: Annotated[Path, typer.Argument(help="Any stage that composes trees or forests.")],
    output: Annotated[
        Path,
        typer.Option(
            "--output",
            "-o",
            help="Output stem: writes STEM.las and STEM_trajectory.csv, STEM_sonar.npz/.wav/.png "
            "and STEM_camera.npz/.png.",
        ),
    ],
    path: Annotated[
        Path | None,
        typer.Option(
            help="CSV of poses: t,x,y,z[,yaw,pitch,roll] (s, stage units, deg); t is also the "
            "time in the stage's animation (a forest's wind, wrapped over its loop)."
        ),
    ] = None,
    line: Annotated[
        str | None,
        typer.Option(
            help="x0,y0,z0:x1,y1,z1 in the stage's units, flown at --speed from t = 0 (a "
            "forest's wind from its start; --path starts elsewhere)."
        ),
    ] = None,
    speed: Annotated[float, typer.Option(help="m/s along --line.")] = 2.0,
    lidar_preset: Annotated[
        str,
        typer.Option(
            "--lidar",
            help="vlp-16, hdl-32, os1-64 (robotics), vux-1uav, livox-mid-40 (drone), vq-780i, "
            "als50-ii (airborne) or none.",
        ),
    ] = "vlp-16",
    lidar_rate: Annotated[float, typer.Option(help="Lidar sweeps per second.")] = 10.0,
    sonar_preset: Annotated[
        str,
        typer.Option(
            "--sonar",
            help="paper, bat-fm, narrow, wide or none (a pulse takes seconds in a closed canopy).",
        ),
    ] = "none",
    camera_preset: Annotated[
        str,
        typer.Option(
            "--camera",
            help="pinhole-640, d435, d435-stereo (its left camera), fpv-1280 or none.",
        ),
    ] = "none",
    camera_rate: Annotated[float, typer.Option(help="Camera frames per second.")] = 2.0,
    config: Annotated[
        Path | None,
        typer.Option(help="TOML with \\[lidar], \\[sonar] and/or \\[camera] settings."),
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, max=MAX_SEED, help="Seed for range noise and ground roughness.")
    ] = 0,
    start_time: Annotated[
        str | None,
        typer.Option(
            help="UTC time of the path's t = 0 (ISO 8601, e.g. 2026-06-21T10:00:00Z): the LAS "
            "and trajectory then carry Adjusted Standard GPS Time; without it, GPS week time "
            "from 0. The wind's time is t, not this."
        ),
    ] = None,
    labels: Annotated[
        str,
        typer.Option(
            help="The LAS classification: asprs (ground 2, vegetation 3-5 by height) or "
            "for-instance (the tree-segmentation benchmarks': 1 low vegetation, 2 terrain, "
            "4 stem, 5 live branches, 6 woody branches). Both write treeID (0: no tree)."
        ),
    ] = "asprs",
    device: DeviceOption = "cpu",
    force: Annotated[bool, typer.Option("--force", help="Overwrite the outputs.")] = False,
    long: Annotated[
        bool,
        typer.Option(
            "--long",
            help="Fly beyond the work limits (5e9 lidar rays, 20,000 sonar pulses or camera "
            "frames).",
        ),
    ] = False,
    quiet: QuietOption = False,
    as_json: SummaryJsonOption = False,
) -> None:
    """Fly a lidar, a sonar and a camera through a stage: LAS 1.4 returns with GPS time,
    class and tree id; sonar pulses with Doppler (leaves, wood, ground), a WAV of the flight
    and an echogram; camera frames (depth, semantic, instance, RGB) and a contact sheet.
    Every output appears at the end, together: an interrupted flight leaves none."""
    import time

    import numpy as np

    from usdforest.config import check_keys, load_toml
    from usdforest.sensors.lidar.las import gps_times
    from usdforest.sensors.optics import camera
    from usdforest.sensors.platforms.survey import (
        check_work,
        flight_settings,
        fly,
        planned_work,
        trajectory,
    )

    if (path is None) == (line is None):
        raise UsdForestError("give the flight as --path CSV or as --line x0,y0,z0:x1,y1,z1")
    if labels not in LAS_LABELS:
        raise UsdForestError(f"--labels: {labels!r} is not one of {', '.join(LAS_LABELS)}")
    ends = _line_ends(line) if line is not None else None
    require_output(output, "output stem")
    if start_time is not None:
        gps_times(np.zeros(1), start_time.strip())  # a bad time fails before any work
        start_time = start_time.strip()
    traj = trajectory(stage, path=path, line=ends, speed=speed)
    tables = {}
    if config is not None:
        tables = load_toml(config)
        check_keys(tables, {"lidar", "sonar", "camera"}, str(config))
    lidar_cfg, sonar_cfg, camera_cfg = flight_settings(
        lidar_preset, sonar_preset, camera_preset, tables, where=str(config) if config else ""
    )
    check_work(planned_work(traj, lidar_cfg, sonar_cfg, camera_cfg, lidar_rate, camera_rate), long)
    if camera_cfg is not None:
        camera.frame_times(camera_cfg, traj, camera_rate)  # checks the memory
    files = _FlightFiles(output)
    outs = files.written(lidar_cfg is not None, sonar_cfg is not None, camera_cfg is not None)
    for o in outs:
        require_output(o)
    reads = stage_inputs(stage)
    claim_outputs(outs, inputs=lambda: [*reads(), path, config], force=force)
    t0 = time.perf_counter()
    summary: dict = {"duration_s": traj.duration, "outputs": [str(o) for o in outs]}
    with (
        output_lock(output),
        progress_bars(not (quiet or as_json), t0) as tick,
        staging_folder(output) as tmp,
    ):
        # again, now that no other flight can write them
        claim_outputs(outs, inputs=lambda: [*reads(), path, config], force=force)
        done = fly(
            stage, path=traj, lidar=lidar_cfg, sonar=sonar_cfg, camera=camera_cfg,
            lidar_rate=lidar_rate, camera_rate=camera_rate, seed=seed, progress=tick,
            warn=lambda w: err.print(f"warning: {w}", highlight=False), long=long,
            device=device,
        )  # fmt: skip
        summary |= _write_flight(done, traj, files, tmp, start_time, tick, labels)
        move_into_place([(tmp / o.name, o) for o in outs], force=force)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
        return
    out.print(_flight_text(traj, summary, files), highlight=False)


def _line_ends(line: str) -> tuple[list[float], list[float]]:
    """``--line x0,y0,z0:x1,y1,z1`` as its two ends."""
    try:
        ends = tuple([float(v) for v in end.split(",")] for end in line.split(":"))
        if len(ends) != 2 or any(len(e) != 3 for e in ends):
            raise ValueError
    except ValueError:
        raise UsdForestError(f"--line: expected x0,y0,z0:x1,y1,z1, got {line!r}") from None
    return ends


class _FlightFiles:
    """The files a flight with the output stem ``output`` writes, beside it."""

    def __init__(self, output: Path):
        self.las = output.with_name(output.name + ".las")
        self.trajectory = output.with_name(output.name + "_trajectory.csv")
        self.echo = output.with_name(output.name + "_sonar")
        self.frames = output.with_name(output.name + "_camera")

    def written(self, lidar: bool, sonar: bool, camera: bool) -> list[Path]:
        """Those the flight's sensors write, in the order they are written."""
        return (
            ([self.las, self.trajectory] if lidar else [])
            + ([self.echo.with_name(self.echo.name + x) for x in (".npz", ".wav", ".png")]
               if sonar else [])
            + ([self.frames.with_name(self.frames.name + x) for x in (".npz", ".png")]
               if camera else [])
        )  # fmt: skip


def _write_flight(
    done, traj, files: _FlightFiles, tmp: Path, start_time, tick, labels: str = "asprs"
) -> dict:
    """Write a finished flight's files into the staging folder ``tmp``; each sensor's
    summary (for ``--json``)."""
    import numpy as np

    from usdforest.sensors.lidar.las import write_las
    from usdforest.sensors.optics import camera
    from usdforest.sensors.platforms import flight
    from usdforest.sensors.scene.scenetypes import class_counts

    summary: dict = {}
    writes = sum(x is not None for x in (done.lidar, done.sonar, done.camera))
    tick("writing outputs", 0, writes)
    if (r := done.lidar) is not None:
        write_las(r, tmp / files.las.name, crs=done.crs, origin=done.origin,
                  start_time=start_time, labels=labels)  # fmt: skip
        flight.write_trajectory(traj, tmp / files.trajectory.name, origin=done.origin,
                                start_time=start_time)  # fmt: skip
        tick("writing outputs", 1, writes)
        summary["lidar"] = {
            "sweeps": r.sweeps,
            "rays": r.n_rays,
            "returns": len(r),
            "returns_by_class": class_counts(r.cls),
        }
    if (f := done.sonar) is not None:
        flight.write_flight_echo(f, tmp / files.echo.name)
        tick("writing outputs", (done.lidar is not None) + 1, writes)
        summary["sonar"] = {
            "pulses": len(f.t),
            "max_leaves_in_range": int(f.leaves.max()),
            "classes_heard": sorted(k for k, v in f.parts.items() if np.any(v)),
        }
    if (frames := done.camera) is not None:
        camera.write_frames(frames, tmp / files.frames.name)
        tick("writing outputs", writes, writes)
        summary["camera"] = {
            "frames": len(frames),
            "trees_seen": int(np.unique(frames.instance[frames.instance >= 0]).size),
        }
    return summary


def _flight_text(traj, summary: dict, files: _FlightFiles) -> str:
    """A flight's line of text: its length and each sensor's files and counts."""
    parts = [f"{traj.duration:.1f} s flight"]
    if "lidar" in summary:
        parts.append(
            f"{files.las}: {summary['lidar']['returns']:,} returns in "
            f"{summary['lidar']['sweeps']} sweeps (trajectory in {files.trajectory.name})"
        )
    if "sonar" in summary:
        parts.append(f"{files.echo}.npz/.wav/.png: {summary['sonar']['pulses']} sonar pulses")
    if "camera" in summary:
        parts.append(f"{files.frames}.npz/.png: {summary['camera']['frames']} camera frames")
    return "; ".join(parts) + f" ({summary['seconds']:.1f} s)"
