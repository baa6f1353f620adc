"""The ``o3dsoft`` command line: thin click commands over the library."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
import shlex
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import List, Optional, Sequence

import click

from .. import __version__
from ..errors import InputError, O3dsoftError, terminate_as_interrupt

# The values of RegisterConfig.search.mode (o3dsoft.config.SEARCH_MODES) and the bench's methods
# (o3dsoft.bench.METHODS), not imported here: that would load torch and Open3D before --help;
# a test keeps them equal.
SEARCH_MODES = ("auto", "always", "off", "quick")
METHOD_NAMES = ("oracle", "o3dsoft-coarse", "o3dsoft", "icp", "fpfh-ransac", "fpfh-ransac+icp", "fgr", "fgr+icp", "kiss-matcher", "kiss-matcher+gicp")
WEIGHTS_HELP = (
    "TorchScript model file, or a shipped model by name: default, paper, partial, incongruent (default: default; "
    "partial is the search network, trained on cropped, noisy clouds; incongruent the second network, trained on clouds that share no point)."
)
MAX_ROTATION_HELP = (
    "The clouds are given within this many degrees of their true relative rotation (e.g. from odometry): "
    "estimates beyond it are not trusted and the search goes on (default: any rotation)."
)


def _friendly_errors(fn):
    """Print o3dsoft's own errors as one line on stderr and exit 1 (failure) or 2 (usage); Ctrl-C
    and SIGTERM stop the command the same way (outputs not yet complete are not left behind). Any
    other error (a bug, or a library failing on an input o3dsoft does not check for) is one line
    too, exit 1, unless O3DSOFT_TRACEBACK is set (then its traceback)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            with terminate_as_interrupt():
                return fn(*args, **kwargs)
        except O3dsoftError as e:
            click.echo(f"Error: {e}", err=True)
            sys.exit(e.exit_code)
        except KeyboardInterrupt:
            click.echo("Interrupted.", err=True)
            sys.exit(130)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except Exception as e:
            if os.environ.get("O3DSOFT_TRACEBACK"):
                raise
            click.echo(f"Error: {_unexpected(e)} (please report it with the command; O3DSOFT_TRACEBACK=1 shows where it happened)", err=True)
            sys.exit(1)

    return wrapper


def _unexpected(e: Exception) -> str:
    """`e` as 'Type: first line of its message', without terminal colour codes (Open3D's)."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(e)).strip()
    return f"{type(e).__name__}: {text.splitlines()[0]}" if text else type(e).__name__


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="o3dsoft")
def main() -> None:
    """o3dsoft: rigid registration of 3D point clouds (learned coarse stage + Open3D ICP)."""
    warnings.showwarning = _one_line_warning


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line on stderr, without Python's source location."""
    click.echo(f"Warning: {message}", err=True)


def _apply_options(options, fn):
    """Decorate `fn` with click `options`, listed in --help in their order."""
    for option in reversed(options):
        fn = option(fn)
    return fn


def _a_number(ctx, param, value):
    """A float option's value, refused where it is NaN or infinite (click's ranges let them through)."""
    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"{value} is not a finite number")
    return value


def _pipeline_options(fn):
    """o3dsoft's pipeline settings, declared once for `register` and every bench command (each
    a field of RegisterConfig, see :func:`_register_config`)."""
    return _apply_options(
        [
            click.option("--weights", type=click.Path(path_type=Path), help=WEIGHTS_HELP),
            click.option("--device", default="cpu", show_default=True, help="Torch device of the network: cpu, cuda, cuda:1..."),
            click.option(
                "--voxel",
                type=click.FloatRange(min=0),
                default=None,
                callback=_a_number,
                help="Register both clouds on a voxel grid of this size (their units); default: 1 % of the scene's size for clouds of over 10,000 points denser than half of that; 0: every point.",
            ),
            click.option(
                "--coarse-iterations",
                type=click.IntRange(min=1),
                default=1,
                show_default=True,
                help="Network passes, each on the source moved by the estimate so far (more: closer start for ICP, slower).",
            ),
            click.option(
                "--icp-distance",
                type=click.FloatRange(min=0, min_open=True),
                default=None,
                callback=_a_number,
                show_default="0.1",
                help="ICP max correspondence distance, relative to the clouds' radius unless --icp-absolute (the confidence measures at 0.1 of the radius whatever this).",
            ),
            click.option("--icp-absolute", is_flag=True, help="--icp-distance is in the clouds' units."),
            click.option(
                "--icp-method",
                type=click.Choice(["auto", "point", "plane"]),
                default="auto",
                show_default=True,
                help="ICP's error: point-to-point, point-to-plane, or auto (point-to-plane on scans: clouds registered on a voxel grid, or of more than 4,096 points).",
            ),
            click.option(
                "--search",
                type=click.Choice(SEARCH_MODES),
                default="auto",
                show_default=True,
                help="Global search, for clouds with no rough alignment (a feature match's estimates in turn, then the search network from 15 starting rotations; without the feature match, the networks from 39): auto = when the first result looks wrong, and first of all on clouds that look like a partial overlap; quick = only the feature match that goes first on a partial overlap (a flagged result stays flagged).",
            ),
            click.option(
                "--search-features/--no-search-features",
                default=True,
                show_default=True,
                help="The search starts with FPFH features matched by RANSAC (for partial scans, any rotation).",
            ),
            click.option(
                "--search-restart",
                is_flag=True,
                help="End a search that found nothing confident by refining every distinct start again with ICP's tight stages (partial overlap; see docs/pipeline.md).",
            ),
            click.option(
                "--search-feature-stop",
                type=click.FloatRange(0.5, 1.0),
                default=0.5,
                show_default=True,
                help="The search's feature match goes on until an estimate reaches this confidence (0.9: doubtful results, 0.5-0.9, are searched further; see docs/pipeline.md).",
            ),
            click.option(
                "--search-replace-odds",
                type=click.FloatRange(min=1),
                default=30.0,
                show_default=True,
                help="An estimate of the search replaces the first one (the network's) only when its odds of being right are this many times higher (1: the most trusted wins; see docs/incongruent.md).",
            ),
            click.option(
                "--search-min-contact",
                type=click.FloatRange(0, 1),
                default=0.5,
                show_default=True,
                help="An estimate is chosen only if it brings at least this share as many points into close contact as the estimate that brings most (0: any; see docs/incongruent.md).",
            ),
            click.option(
                "--second-weights",
                default="incongruent",
                show_default=True,
                help="A second network, for clouds that share no point, run when the first network's result is flagged (not on scans, where it was never right): a model file or a shipped model's name; 'none': off.",
            ),
            click.option(
                "--second-turns",
                type=click.IntRange(0, 23),
                default=0,
                show_default=True,
                help="For clouds that share no point and may be turned by any rotation: where the second network's pose is flagged on two complete-looking clouds, run it from this many of the other 23 rotations of a cube too (4: the measured setting; see docs/incongruent.md); 0: off.",
            ),
            click.option("--max-rotation", type=click.FloatRange(min=0, max=180, min_open=True), default=None, callback=_a_number, help=MAX_ROTATION_HELP),
        ],
        fn,
    )


def _register_config(
    *,
    weights,
    device,
    voxel,
    coarse_iterations,
    search,
    search_features,
    search_restart,
    search_feature_stop,
    search_replace_odds,
    search_min_contact,
    second_weights,
    second_turns,
    max_rotation,
    icp_distance,
    icp_absolute,
    icp_method,
    **more,
):
    """RegisterConfig from the values of :func:`_pipeline_options` and further fields (`more`)."""
    from ..coarse import weights_file
    from ..config import FeatureSearchConfig, RegisterConfig, RestartConfig, SearchConfig, SecondNetworkConfig
    from ..refine import ICPConfig

    if icp_absolute and icp_distance is None:
        raise click.UsageError("--icp-absolute needs --icp-distance, in the clouds' units")

    second = None if second_weights.lower() == "none" else second_weights
    if second is not None:
        weights_file(second)  # a misspelt name fails now, not at the first flagged pair

    search_config = SearchConfig(
        mode=search,
        features=FeatureSearchConfig(enabled=search_features, stop=search_feature_stop),
        restart=RestartConfig(enabled=search_restart),
        replace_odds=search_replace_odds,
        min_contact=search_min_contact,
    )
    return RegisterConfig(
        weights=str(weights) if weights else None,
        device=device,
        voxel=voxel,
        coarse_iterations=coarse_iterations,
        search=search_config,
        second_network=SecondNetworkConfig(weights=second, turns=second_turns),
        max_rotation=max_rotation,
        icp=ICPConfig(distance=icp_distance, absolute=icp_absolute, method=icp_method),
        **more,
    )


@main.command()
@click.argument("source", type=click.Path(path_type=Path), required=False)
@click.argument("target", type=click.Path(path_type=Path), required=False)
@click.option(
    "--pairs",
    "pairs_path",
    type=click.Path(path_type=Path),
    help="Register every pair of this file instead (lines 'source target [ground truth] [init=initial guess]', paths relative to it); --out: the CSV.",
)
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True, help="--pairs: pairs registered at once, each in its own process.")
@click.option("--ray", "ray_address", help="--pairs: run on a Ray cluster: local (start one here), auto (the one `ray start` set up) or its address.")
@click.option("--no-progress", is_flag=True, help="--pairs: no progress bar.")
@click.option("--gt", "gt_path", type=click.Path(path_type=Path), help="Ground-truth T_target_source (4x4 or 3x4 text, or .npy): print the errors against it.")
@click.option(
    "--init",
    "init_path",
    type=click.Path(path_type=Path),
    help="Initial guess of T_target_source (4x4 or 3x4 text, or .npy; odometry, a previous pose): the source starts there, ICP from it is tried first, "
    "and where it is trusted neither the feature match nor the network runs; --max-rotation then bounds the turn away from it.",
)
@click.option(
    "--out",
    "out_path",
    type=click.Path(path_type=Path),
    help="Write the transformed source here (.ply .pcd .xyz .xyzn .pts .csv .npy .las); the colours and normals of a point-cloud source "
    "(PLY, PCD, XYZN, XYZRGB, PTS, LAS, E57; not a mesh's sampled points) go with it (colours into .ply, .pcd, .las, .pts; normals into .ply, .pcd, .xyzn; .xyzn estimates normals, their sign arbitrary, where the source has none), "
    "and a LAS/LAZ source's every dimension into .las.",
)
@click.option("--save-transform", type=click.Path(path_type=Path), help="Write the 4x4 result here (text, or .npy).")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON instead of a table.")
@click.option(
    "--no-refine",
    is_flag=True,
    help="Skip ICP: every estimate as proposed (the network's, and the search's where it runs; with --search off, the network's alone).",
)
@click.option("--points", "num_points", type=click.IntRange(min=1), default=1024, show_default=True, help="Points sampled from each cloud for the network.")
@click.option("--mesh-points", type=click.IntRange(min=1), default=20000, show_default=True, help="Points sampled on the faces of mesh inputs.")
@click.option(
    "--render",
    "render_path",
    type=click.Path(path_type=Path),
    help="Write a PNG of the pair (input, after the network, after ICP), seen onto its principal plane, the source coloured by its distance to the target.",
)
@click.option(
    "--strict",
    is_flag=True,
    help="Exit with code 3 when the result is flagged as likely failed, writing neither --out nor --save-transform (--render still shows it).",
)
@_pipeline_options
@_friendly_errors
def register(
    source,
    target,
    pairs_path,
    workers,
    ray_address,
    no_progress,
    gt_path,
    init_path,
    out_path,
    save_transform,
    as_json,
    no_refine,
    num_points,
    mesh_points,
    render_path,
    strict,
    **pipeline,
):
    """Register SOURCE onto TARGET; print T_target_source and how well it fits.

    SOURCE and TARGET are point clouds (PLY, PCD, XYZ, XYZN, XYZRGB, PTS, NPY, LAS, LAZ, E57 of one
    scan, CSV/TXT with x, y, z columns) or meshes (OFF, OBJ, STL, GLB, GLTF, FBX, PLY with faces),
    sampled on their faces. With --pairs, every
    pair of a file, one CSV row each (a run stopped half-way resumes from its --out file).
    """
    if pairs_path is not None:
        given = [
            name
            for name, v in (
                ("SOURCE", source),
                ("--gt", gt_path),
                ("--init", init_path),
                ("--save-transform", save_transform),
                ("--render", render_path),
                ("--json", as_json),
            )
            if v
        ]
        if given:
            raise click.UsageError(f"--pairs registers the pairs of a file; {', '.join(given)} belong(s) to a single pair")
        if out_path is None:
            raise click.UsageError("--pairs needs --out RESULTS.csv")
        if out_path.is_dir() or out_path.suffix.lower() != ".csv":
            raise click.UsageError(f"--out {out_path}: --pairs writes a CSV file; give --out RESULTS.csv")
        _register_pairs(pairs_path, out_path, workers, ray_address, no_progress, num_points, no_refine, pipeline)
        return
    if source is None or target is None:
        raise click.UsageError("give SOURCE and TARGET, or --pairs FILE")
    if workers > 1 or ray_address:
        raise click.UsageError("--workers and --ray go with --pairs")
    from .. import io
    from ..coarse import load_model
    from ..metrics import pair_errors
    from ..pipeline import register as run_register
    from ..preprocess import local_origin

    for opt, p in (("--out", out_path), ("--render", render_path)):
        if p is not None and (p.suffix == "" or p.is_dir()):
            raise click.UsageError(f"{opt} {p}: {'is a folder; ' if p.is_dir() else ''}give a file name with an extension")
    if render_path is not None and render_path.suffix.lower() != ".png":
        raise click.UsageError(f"--render {render_path}: give a .png file name")
    if save_transform is not None and save_transform.suffix.lower() in set(io.READ_EXTENSIONS + (".png", ".json")) - {".txt", ".csv", ".npy"}:
        raise click.UsageError(
            f"--save-transform {save_transform}: a transform is written as text (.txt) or .npy, not as {save_transform.suffix}"
            + (" (--json prints the whole result as JSON)" if save_transform.suffix.lower() == ".json" else "")
        )
    if out_path is not None:
        io.check_extension(out_path, io.WRITE_EXTENSIONS, "--out")
    io.check_outputs_apart(
        {"--out": out_path, "--save-transform": save_transform, "--render": render_path},
        {"SOURCE": source, "TARGET": target, "--gt": gt_path, "--init": init_path},
    )
    for p in (out_path, save_transform, render_path):  # before the work, which can take minutes
        if p is not None:
            io.check_writable(p)
    t0 = time.perf_counter()
    src = io.read_points(source, mesh_points=mesh_points)
    tgt = io.read_points(target, mesh_points=mesh_points)
    _warn_float32(source, src)
    _warn_float32(target, tgt)
    moved = local_origin(src)  # a rounded rotation, made exact, still moves the source where the file's does
    T_gt = io.read_transform(gt_path, moved) if gt_path is not None else None
    T_init = io.read_transform(init_path, moved) if init_path is not None else None
    read_ms = (time.perf_counter() - t0) * 1000.0
    config = _register_config(**pipeline, num_points=num_points, refine=not no_refine)
    t0 = time.perf_counter()
    model = load_model(config.weights, config.device)
    load_ms = (time.perf_counter() - t0) * 1000.0
    result = run_register(src, tgt, config, model=model, source_name=str(source), target_name=str(target), init=T_init)
    timings_ms = {"read": read_ms, "load_model": load_ms, **result.timings_ms}
    timings_ms["total"] += read_ms + load_ms
    result = dataclasses.replace(result, timings_ms=timings_ms)

    errors = None
    if T_gt is not None:
        origin = local_origin(tgt)  # georeferenced scans: their errors about the target, not the frame's origin
        errors = {"final": pair_errors(result.transformation, T_gt, origin), "coarse": pair_errors(result.coarse_transformation, T_gt, origin)}
    model_info = {"path": str(model.path), "trained": model.meta.get("info", {})}
    if as_json:
        payload = {"source": str(source), "target": str(target), "model": model_info, **result.to_dict()}
        if T_init is not None:
            payload["init"] = T_init.tolist()
        if errors is not None:
            payload["errors"] = {k: _errors_dict(e) for k, e in errors.items()}
        click.echo(json.dumps(payload, indent=2))
    else:
        click.echo(_format_result(source, target, result, errors, model_info, config, (len(src), len(tgt))))
    if result.likely_failed:
        click.echo(
            f"Warning: the alignment is likely wrong (confidence {result.confidence:.2f}: {result.failure_reason}). Check it visually (--render).", err=True
        )
    if errors is not None and errors["final"].rotation_deg > SWAPPED_GT_DEG:
        from ..transforms import rotation_angle_deg

        inverse = rotation_angle_deg(T_gt[:3, :3] @ result.transformation[:3, :3])  # the turn from the inverse's rotation, R_gt^T
        if inverse < SWAPPED_GT_DEG / 5:  # a ground truth the other way round: the error is twice its turn
            click.echo(
                f"Note: the result turns {inverse:.2g} deg from the inverse of --gt: it may map the target onto the source; --gt takes T_target_source "
                "(or the clouds are given the other way round)",
                err=True,
            )
    # The outputs last, so that a failed write still leaves the result on screen.
    if strict and result.likely_failed:  # a failed run leaves no result for a pipeline to pick up
        held = [opt for opt, p in (("--out", out_path), ("--save-transform", save_transform)) if p is not None]
        if held:
            click.echo(f"Not written (--strict, the result is flagged): {', '.join(held)}", err=True)
        out_path = save_transform = None
    if out_path is not None:
        t0 = time.perf_counter()
        io.write_moved(out_path, source, src, result.transformation)  # with the source's colours, normals, LAS dimensions
        click.echo(f"Aligned source: {out_path} ({_ms_since(t0)})", err=as_json)
        if out_path.suffix.lower() == ".pcd" and io.pcd_needs_doubles(src):
            click.echo(
                f"Note: {out_path} holds x, y, z as float64 (float32 would round them this far from the origin); PCL and CloudCompare read it, Open3D 0.20 reads zeros: use .ply for it",
                err=True,
            )
    if save_transform is not None:
        io.write_transform(save_transform, result.transformation)
        click.echo(f"Transform: {save_transform}", err=as_json)
    if render_path is not None:
        from ..render import render_registration

        panels = [("input", None), ("coarse estimate", result.coarse_transformation)]
        if config.refine:
            panels.append(("after ICP", result.transformation))
        caption = f"Confidence {result.confidence:.2f} (0-1, higher is better){', LIKELY FAILED' if result.likely_failed else ''}."
        if errors is not None:
            e = errors["final"]
            caption += f" Error against the ground truth: {e.rotation_deg:.3g} deg, {e.translation:.3g} units (lower is better)."
        # Colours up to three grid cells (scans), or the confidence's tight distance.
        scale = 3 * result.voxel if result.voxel is not None else result.tight_distance
        t0 = time.perf_counter()
        render_registration(render_path, src, tgt, panels, scale, caption)
        click.echo(f"Picture: {render_path} ({_ms_since(t0)})", err=as_json)
    if result.likely_failed and strict:
        sys.exit(3)


def _register_pairs(pairs_path, out_path, workers, ray_address, no_progress, num_points, no_refine, pipeline) -> None:
    """`register --pairs`: every pair of the file, rows into the CSV `out_path`; exit 3 when a pair
    failed to run."""
    from tqdm import tqdm

    from ..batch import check_results_belong, done_lines, model_for, read_pair_jobs, resume_counts, run_jobs

    jobs = read_pair_jobs(pairs_path)
    config = _register_config(**pipeline, num_points=num_points, refine=not no_refine)
    model_for(config)  # a bad --weights fails here, once, not on every row; a run in this process reuses it
    done = done_lines(out_path)
    check_results_belong(jobs, done, out_path)
    skipped, again, dropped = resume_counts(jobs, done, out_path)
    if skipped or again or dropped:
        rerun = f"; {again} run again (they failed, or a line or a file they name changed since)" if again else ""
        gone = f"; {dropped} rows of pairs the pairs file no longer lists are dropped" if dropped else ""
        click.echo(f"Resuming: {skipped} of {len(jobs)} pairs already in {out_path}{rerun}{gone}", err=True)
    bar = tqdm(total=len(jobs) - skipped, unit="pair", disable=True if no_progress else None, dynamic_ncols=True)
    try:
        rows = run_jobs(jobs, config, out_path, workers=workers, ray=ray_address, progress=lambda row: bar.update(1), done=done)
    except KeyboardInterrupt:
        bar.close()
        click.echo(f"Stopped: the pairs done so far are in {out_path}; the same command goes on from there.", err=True)
        raise
    finally:
        bar.close()
    failed = [r for r in rows if r["status"] != "ok"]
    flagged = [r for r in rows if r["status"] == "ok" and str(r["likely_failed"]) == "True"]
    seconds = [float(r["seconds"]) for r in rows if r["status"] == "ok"]
    median = f"; median {statistics.median(seconds):.2f} s per pair (lower is better)" if seconds else ""
    click.echo(
        f"{len(rows)} pairs: {len(rows) - len(failed) - len(flagged)} trusted, {len(flagged)} flagged likely failed, {len(failed)} could not run{median}."
    )
    for r in failed:
        click.echo(f"  line {r['line']}: {r['error']}", err=True)
    click.echo(f"Results: {out_path}")
    if failed:
        sys.exit(3)


def _errors_dict(e) -> dict:
    d = e._asdict()
    d["euler_abs_deg"] = e.euler_abs_deg.tolist()
    d["translation_abs"] = e.translation_abs.tolist()
    return d


def _cleaning_lines(removed: dict, isolated: str) -> list:
    """The lines saying how many rows without finite coordinates, repeated points and stray far
    points cleaning dropped and how many isolated points were left out (`isolated`: within what,
    in words), where there were any."""
    from ..preprocess import STRAY_PERCENTILE, STRAY_REACH

    reach = f"over {STRAY_REACH * 2:,.0f} times farther from the median than {STRAY_PERCENTILE:.0f} % of the cloud"
    kinds = (
        ("non_finite", "rows dropped (a NaN or infinite coordinate)"),
        ("duplicates", "repeated points dropped (kept once)"),
        ("strays", f"points dropped ({reach})"),
        ("isolated", f"points left out (fewer than two other points within {isolated}: scattered outliers, or the sparsest far returns)"),
    )
    lines = []
    for key, what in kinds:
        n, m = removed.get(f"source_{key}", 0), removed.get(f"target_{key}", 0)
        if n or m:
            lines.append(f"  {key.replace('_', '-')}: source {n}, target {m} {what}")
    return lines


def _matrix_lines(T) -> List[str]:
    """The rows of a (4, 4) transform with 12 decimals, aligned: enough to apply it to
    georeferenced clouds (millions of units from the origin) to 1e-5 units."""
    cells = [[f"{_tidy(float(v)):.12f}" for v in row] for row in T]
    width = max(len(cell) for row in cells for cell in row)
    return ["  " + " ".join(cell.rjust(width) for cell in row) for row in cells]


def _tidy(value: float) -> float:
    """0 for a value within float rounding of it (the world scan's pose is the identity up to 1e-20)."""
    return 0.0 if abs(value) < 1e-12 else value


def _ms_since(t0: float) -> str:
    """The time since perf_counter() read `t0`, in milliseconds, for a line of output: "950 ms"."""
    return f"{(time.perf_counter() - t0) * 1000.0:.0f} ms"


def _format_result(source, target, result, errors, model_info, config, read=None) -> str:
    """register's text output; `read`: (source, target) points read from the files."""
    from ..coarse import weights_file

    refined = config.refine
    grid = f" and a {result.voxel:.3g}-unit voxel grid" if result.voxel is not None else ""
    without = ", without their isolated points" if result.removed.get("source_isolated") or result.removed.get("target_isolated") else ""
    T = result.transformation
    lines = [
        f"o3dsoft register {source} -> {target}",
        f"  points: source {result.num_source}, target {result.num_target} (after cleaning{grid}{without}"
        + ("" if read is None else f"; {read[0]} and {read[1]} read")
        + f"); scale {result.scale:.4g} units (the clouds' radius, which --icp-distance is relative to); ICP point-to-{result.icp_method}",
        "  points per stage (source / target): " + ", ".join(f"{stage} {n} / {m}" for stage, (n, m) in result.points_used.items()),
        *_cleaning_lines(
            result.removed,
            f"{config.isolated_radius:g} voxels" if result.voxel is not None else f"{config.isolated_spacings:g} times each cloud's median point spacing",
        ),
        f"  model:  {model_info['path']}"
        + (f"; second network: {weights_file(config.second_network.weights)}" if "second_network" in result.timings_ms else ""),
        "",
        "T_target_source (maps the source onto the target):",
        *_matrix_lines(T),
        "",
        f"  fitness      {result.fitness:.4f}   share of source points within {result.correspondence_distance:.4g} units of the target (0-1, higher is better)",
        f"  inlier RMSE  {result.inlier_rmse:.4g}   units, over those points (lower is better)",
        f"  confidence   {result.confidence:.4f}   trust in the alignment (0-1, higher is better; flagged below 0.5)"
        + ("  LIKELY FAILED" if result.likely_failed else ""),
        *(
            [
                f"  constraint   {result.constraint:<6.3g}   how firmly the surfaces fix the pose (0-1, higher is better; below {config.degeneracy.min_constraint:g}: not determined)",
                f"  flatness     {result.flatness:.3f}   fit {config.degeneracy.turn_deg:g} degrees away over the result's (0-1, lower is better; from {config.degeneracy.max_flatness:g}: not determined)",
            ]
            if result.constraint is not None
            else ["  constraint   not measured: the clouds share their points, which fix the pose"]
        ),
        *(
            [
                f"  copy fit     {result.copy_fit:.3f}   the best half-turned copy's Chamfer distance over the result's (higher is better; at most {config.symmetry.max_ratio:g}: ambiguous)"
            ]
            if result.copy_fit is not None
            else []
        ),
        f"  estimate     from {'' if result.estimate_from == 'KISS-Matcher' else 'the '}{result.estimate_from}" + (", refined by ICP" if refined else ""),
    ]
    if result.sparser_moved:
        lines.append("  roles        the target is much sparser: it was registered onto the source, and the result inverted")
    if result.searched:
        why = result.search_reason
        screened = f" ({result.screened} screened on at most {config.search.screen.points:,} points per cloud first)" if result.screened else ""
        tried = f"{result.attempts} estimate{'' if result.attempts == 1 else 's'} refined"
        reached = "it reached" if result.attempts == result.agreeing == 1 else f"{result.agreeing} of them reached"
        lines.append(f"  search       ran ({why}); {tried}{screened}, {reached} the result's pose")
    if errors is not None:
        f, c = errors["final"], errors["coarse"]
        estimate = result.estimate_from
        lines += [
            "",
            "Errors against the ground truth (lower is better):",
            f"  {'':24s} {'rotation':>12s} {'translation':>14s} {'|R-Rgt|_1':>10s} {'|R-Rgt|_2':>10s} {'|t-tgt|_1':>10s} {'|t-tgt|_2':>10s}",
        ]
        rows = [(estimate, c)] + ([(f"{estimate} + ICP", f)] if refined else [])
        for name, e in rows:
            lines.append(
                f"  {name:24s} {e.rotation_deg:>8.4f} deg {e.translation:>8.3g} units {e.rotation_l1:>10.6f} {e.rotation_l2:>10.6f} {e.translation_l1:>10.6f} {e.translation_l2:>10.6f}"
            )
        lines.append("  (|R-Rgt|_1, |R-Rgt|_2: entrywise L1 and Frobenius norms of the rotation matrices' difference, no unit; |t-tgt|_1, |t-tgt|_2: units)")
    t = result.timings_ms
    lines += [
        "",
        "Time per stage (ms, lower is better): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()),
        "  (not counted: the program's start-up and imports; the outputs asked for are timed on their own lines)",
    ]
    return "\n".join(lines)


@main.command()
@click.argument("scans", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Folder for poses.json and merged.ply (created if missing).")
@click.option(
    "--neighbours",
    type=click.Choice(["auto", "all", "sequence", "near"]),
    default="auto",
    show_default=True,
    help="Pairs registered: all, each scan with the next --window (scans in order), each with its --near nearest by centroid (scans roughly placed, or placed by --init); auto: all up to 12 scans, else near where --init places every scan, sequence otherwise.",
)
@click.option("--window", type=click.IntRange(min=1), default=3, show_default=True, help="sequence: following scans each scan is paired with.")
@click.option("--near", type=click.IntRange(min=1), default=4, show_default=True, help="near: nearest scans each scan is paired with.")
@click.option(
    "--merge-voxel", type=click.FloatRange(min=0, min_open=True), default=None, help="Grid of merged.ply (scan units); default: the pairs' registration grid."
)
@click.option(
    "--init",
    "init_path",
    type=click.Path(path_type=Path),
    help="Initial poses world_T_scan (odometry, an earlier run): a poses.json as multiway writes, a Stanford .conf, or text with one pose per scan, in order, 12 numbers (KITTI's 3x4) or 16. "
    "Each pair is then held within 45 degrees of the turn between its poses (--max-rotation sets another bound).",
)
@click.option("--render", "render_path", type=click.Path(path_type=Path), help="Write a PNG of the merged cloud, one colour per scan.")
@click.option("--json", "as_json", is_flag=True, help="Print the result (poses, edges) as JSON instead of a table.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@_pipeline_options
@_friendly_errors
def multiway(scans, out_dir, neighbours, window, near, merge_voxel, init_path, render_path, as_json, no_progress, **pipeline):
    """Register SCANS (two or more files; every scan of an E57) into the frame of the first (of
    the largest group of scans that trusted alignments join, where they do not all join).

    Writes OUT/poses.json (world_T_scan per scan, each edge's transform, confidence and whether it
    was pruned) and OUT/merged.ply. With --init, pairs start from their initial poses and the
    result stays in their frame; scans that no trusted alignment joins to the world scan are then
    placed by their initial poses (relative to the nearest joined scan) in poses.json, not in
    merged.ply. Exit status 3 when a scan is not joined to the world scan, or when a quarter or
    more of the trusted alignments disagreed with the others (pruned): the poses may be wrong.
    """
    from tqdm import tqdm

    from .. import io
    from ..coarse import load_model
    from ..multiway import MultiwayConfig, merged_cloud, units_note
    from ..multiway import multiway as run_multiway
    from ..preprocess import local_origin

    _each_once(scans, "scan")
    if render_path is not None and render_path.suffix.lower() != ".png":
        raise click.UsageError(f"--render {render_path}: give a .png file name")
    names, clouds, files = [], [], []
    for p in scans:
        found = io.read_scans(p)
        if len(found) == 1:
            _warn_float32(p, found[0][1])
        first = len(files)
        for name, points in found:
            names.append(name)
            clouds.append(points)
            files.append((p, None if len(found) == 1 else len(files) - first))  # the file, and the scan's index in an E57 of several
    if len(clouds) < 2:
        raise click.UsageError(f"{scans[0]}: one scan; multiway needs at least two")
    units = units_note(clouds, names)
    if units:
        click.echo(f"Warning: {units}.", err=True)
    if init_path is not None and init_path.suffix.lower() not in (".json", ".conf"):  # its lines are taken in the scans' order
        _warn_name_order([str(p) for p in scans], "scans", f"{init_path}'s lines are read in the order the scans are given; give them in its order")
    init_poses = io.read_poses(init_path, names, [local_origin(c) for c in clouds]) if init_path is not None else None
    without = [n for n, pose in zip(names, init_poses or ()) if pose is None]
    if without:
        click.echo(f"Note: {init_path} gives no initial pose for {len(without)} scan(s), registered without one: {', '.join(without)}", err=True)
    io.check_outputs_apart(
        {"--out's poses": out_dir / "poses.json", "--out's merged cloud": out_dir / "merged.ply", "--render": render_path},
        {**{f"the scan {p}": p for p in scans}, "--init": init_path},
    )
    io.make_folder(out_dir)  # after the scans are read: a bad file leaves no folder behind
    for p in (out_dir / "poses.json", out_dir / "merged.ply", render_path):
        if p is not None:
            io.check_writable(p)
    config = MultiwayConfig(neighbours=neighbours, window=window, near=near, voxel=merge_voxel, register=_register_config(**pipeline))
    model = load_model(config.register.weights, config.register.device)
    bar = tqdm(unit="pair", disable=True if no_progress else None, dynamic_ncols=True, desc="pairs")

    def progress(done, total):
        bar.total = total
        bar.update(done - bar.n)

    try:
        result = run_multiway(clouds, config, names=names, model=model, progress=progress, init_poses=init_poses)
    finally:
        bar.close()
    payload = result.to_dict()
    with io.atomic_output(out_dir / "poses.json") as tmp:
        tmp.write_text(json.dumps(payload, indent=2))
    colors = [io.read_attributes(f, len(c), scan).colors if joined else None for (f, scan), c, joined in zip(files, clouds, result.joined)]
    merged = merged_cloud(clouds, result, result.voxel, colors)
    io.write_points(out_dir / "merged.ply", merged.points, merged.colors)
    if as_json:
        click.echo(json.dumps(payload, indent=2))
    else:
        placed = init_path if init_poses is not None and init_poses[result.world] is not None else None
        click.echo(_format_multiway(result, out_dir, len(merged.points), placed))
    if render_path is not None:
        from ..render import render_merged

        joined = sum(result.joined)
        render_merged(render_path, merged.points, merged.scans, names, f"{joined} of {len(names)} scans joined.")
        click.echo(f"Picture: {render_path}", err=as_json)
    trusted = [e for e in result.edges if not e.likely_failed]
    pruned = [e for e in trusted if e.pruned]
    disagree = bool(trusted) and len(pruned) >= PRUNED_WARNING * len(trusted)  # one wrong loop closure is pruned as designed; many say the poses disagree
    if disagree:
        click.echo(
            f"Warning: {len(pruned)} of {len(trusted)} trusted alignments disagreed with the others and were pruned: the scans' poses may be wrong "
            "(a symmetric or repeated shape fits several ways); check them (--render)",
            err=True,
        )
    left_out = [n for n, j in zip(names, result.joined) if not j]
    if left_out:
        kept = [n for n, by in zip(names, result.placed_by) if by == "initial pose"]
        also = f"; {', '.join(kept)} placed by the initial poses in poses.json (unverified)" if kept else ""
        click.echo(
            f"Warning: {len(left_out)} scan(s) that no trusted alignment joins to {names[result.world]} were left out of the merged cloud: {', '.join(left_out)}{also}",
            err=True,
        )
    if left_out or disagree:  # written, but not a result to pick up unchecked
        sys.exit(3)


# multiway warns where at least this share of the trusted alignments was pruned as inconsistent
# (none is, on the bunny's, 3DMatch's or odometry's scans; 7 to 15 of 18 to 24 on turntable views
# of symmetric objects whose poses came out 60 to 180 degrees off).
PRUNED_WARNING = 0.25
# Over this rotation error (degrees), a result within a fifth of it of the inverse of --gt is named.
SWAPPED_GT_DEG = 5.0


def _each_once(paths: Sequence[Path], what: str) -> None:
    """Refuse a file given twice among `paths` (under any name), calling each a `what`."""
    seen: dict = {}
    for p in paths:
        key = p.resolve()
        if key in seen:
            raise click.UsageError(f"{p}: given twice (as {seen[key]} too); each {what} once")
        seen[key] = p


@main.command()
@click.argument("sweeps", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Folder for poses.json and poses.txt (created if missing).")
@click.option(
    "--map-sweeps",
    type=click.IntRange(min=1),
    default=10,
    show_default=True,
    help="Sweeps in the local map each sweep is registered onto (1: the previous one alone, frame to frame).",
)
@click.option(
    "--gt",
    "gt_path",
    type=click.Path(path_type=Path),
    help="Reference poses world_T_sweep (a poses.json, a Stanford .conf, or text with one pose per sweep, 12 numbers (KITTI's 3x4) or 16): print the steps' errors and the drift.",
)
@click.option(
    "--grid-per-step",
    is_flag=True,
    help="Register every step on a voxel grid of its own, cleaning the raw sweep and map each time (about twice as slow), instead of every sweep "
    "cleaned once and every step on the first step's grid: for a sequence whose scale changes much (a room, then a close-up).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the result (poses, each step's confidence) as JSON instead of a summary.")
@click.option("--strict", is_flag=True, help="Exit with status 3 when a step is flagged likely failed.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@_pipeline_options
@_friendly_errors
def odometry(sweeps, out_dir, map_sweeps, gt_path, grid_per_step, as_json, strict, no_progress, **pipeline):
    """The poses of SWEEPS (files in the order they were taken, e.g. a LiDAR's or a depth camera's
    frames; a shell glob sorts them by name) in the frame of the first: each sweep registered onto
    the last --map-sweeps sweeps from a constant-velocity guess, and held within 45 degrees of it
    (--max-rotation sets another bound, for every step, the first included).

    Writes OUT/poses.json (world_T_sweep per sweep, each step's confidence) and OUT/poses.txt (one
    3x4 pose per line, as KITTI's files; multiway --init reads either to close loops). A flagged
    step is named on stderr (exit status 3 with --strict), and later sweeps are registered
    without its sweep.
    """
    from tqdm import tqdm

    from .. import io
    from ..odometry import OdometryConfig
    from ..odometry import odometry as run_odometry
    from ..preprocess import local_origin

    _each_once(sweeps, "sweep")
    for p in sweeps:
        io.check_readable(p)
    if len(sweeps) < 2:
        raise click.UsageError(f"{sweeps[0]}: one sweep; odometry needs at least two")
    names = [str(p) for p in sweeps]
    _warn_name_order(names, "sweeps", "give them in the order taken")
    clouds = [io.read_points(p) for p in sweeps]
    for p, c in zip(sweeps, clouds):
        _warn_float32(p, c)
    # A rounded rotation made exact about each sweep's own points, as register --gt does about its clouds' (georeferenced sweeps).
    reference = io.read_poses(gt_path, names, [local_origin(c) for c in clouds], what="sweeps") if gt_path is not None else None
    missing = [n for n, pose in zip(names, reference or ()) if pose is None]
    if missing:
        raise click.UsageError(f"--gt {gt_path}: no pose for {len(missing)} sweep(s): {', '.join(missing[:5])}")
    io.check_outputs_apart(
        {"--out's poses": out_dir / "poses.json", "--out's KITTI poses": out_dir / "poses.txt"}, {**{f"the sweep {p}": p for p in sweeps}, "--gt": gt_path}
    )
    config = OdometryConfig(map_sweeps=map_sweeps, one_grid=not grid_per_step, register=_register_config(**pipeline))
    bar = tqdm(total=len(clouds), unit="sweep", disable=True if no_progress else None, dynamic_ncols=True)

    def progress(done: int, total: int) -> None:
        if done == 1:  # the sweeps are checked: a bad one has left no folder behind
            io.make_folder(out_dir)
            for p in (out_dir / "poses.json", out_dir / "poses.txt"):
                io.check_writable(p)
        bar.update(done - bar.n)

    try:
        result = run_odometry(clouds, config, names=names, progress=progress)
    finally:
        bar.close()
    payload = result.to_dict()
    with io.atomic_output(out_dir / "poses.json") as tmp:
        tmp.write_text(json.dumps(payload, indent=2))
    with io.atomic_output(out_dir / "poses.txt") as tmp:
        tmp.write_text("".join(" ".join(f"{v:.17g}" for v in pose[:3].reshape(-1)) + "\n" for pose in result.poses))  # every bit, as poses.json
    click.echo(json.dumps(payload, indent=2) if as_json else _format_odometry(result, out_dir, reference))
    flagged = [
        f"{n} (confidence {s.confidence:.3f}: {s.failure_reason}; "
        + ("kept in the map: it fits it and lies near the motion guessed, so the sweeps after it build on it)" if m else "left out of the map)")
        for n, s, f, m in zip(names, result.steps, result.flagged, result.mapped)
        if f
    ]
    if flagged:
        click.echo(
            f"Warning: {len(flagged)} step(s) flagged likely failed; their poses may be off (the sweeps after a step left out of the map are registered "
            "without it): " + "; ".join(flagged),
            err=True,
        )
        if strict:
            sys.exit(3)


def _warn_float32(path: Path, points) -> None:
    """Warn where the file `path` stores its points' coordinates as float32 so far from its
    frame's origin that they were rounded by more than a millionth of the cloud's extent."""
    import numpy as np

    from .. import io

    rounding = io.float32_rounding(path, points)
    if rounding is not None:
        far = float(abs(points[np.isfinite(points).all(axis=1)]).max())
        click.echo(
            f"Warning: {path} stores x, y, z as float32, which {far:,.0f} units from the origin rounds them by up to {rounding:.3g} units: "
            "the file lost that precision when it was written (write float64 coordinates, or coordinates about a point near the cloud)",
            err=True,
        )


def _warn_name_order(names: "list[str]", what: str, advice: str) -> None:
    """Warn where `names` come in name order but not in number order (a shell glob's: frame_10
    before frame_2), which is seldom the order they were taken in."""
    numbered = sorted(names, key=lambda n: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", n)])
    if names == sorted(names) and numbered != names:
        early, late = next((a, b) for a, b in zip(names, numbered) if a != b)
        click.echo(f"Warning: the {what} are in name order, so {early} comes before {late}: {advice} (`ls -v`, or names with leading zeros)", err=True)


def _format_odometry(result, out_dir: Path, reference=None) -> str:
    """A summary: the sweeps, the flagged steps, the path and the time; against `reference` poses
    (world_T_sweep per sweep) the steps' errors and the final drift."""
    import numpy as np

    from ..odometry import errors_against

    seconds = [step.timings_ms.get("total", 0.0) / 1000.0 for step in result.steps[1:]]
    lines = [
        f"o3dsoft odometry {len(result.names)} sweeps, world frame: {result.names[0]}",
        f"Path: {_tidy(result.path):.4g} units in all (the motions' lengths summed); the last sweep {_tidy(result.last_from_first):.4g} units from the first.",
        f"Steps flagged likely failed: {sum(result.flagged)} of {len(result.steps) - 1}.",
    ]
    if reference is not None:
        rotation, translation, drift, travelled = errors_against(result, reference)
        lines.append(
            f"Against --gt (lower is better): step errors median {np.median(rotation):.3g} deg / {np.median(translation):.3g} units, "
            f"largest {rotation.max():.3g} deg / {translation.max():.3g} units; the last sweep {drift.rotation_deg:.3g} deg / {drift.translation:.3g} units off"
            + (f" ({100 * drift.translation / travelled:.2g} % of the reference path, {travelled:.4g} units)" if travelled > 0 else "")
            + "."
        )
    lines += [
        f"Time (s, lower is better): {result.timings_s['total']:.1f} in all, {np.median(seconds):.3f} per step (median, a sweep registered onto its map).",
        f"Wrote {out_dir / 'poses.json'} and {out_dir / 'poses.txt'} (one 3x4 pose per line).",
    ]
    return "\n".join(lines)


def _format_multiway(result, out_dir: Path, merged_points: int, frame_file: Optional[Path] = None) -> str:
    """The result as a table; `frame_file`: the --init file that holds the world scan's pose."""
    import numpy as np

    from ..transforms import rotation_angle_deg

    world = result.names[result.world]
    frame = f"that of {frame_file} ({world} held at its pose there)" if frame_file is not None else world
    lines = [f"o3dsoft multiway {len(result.names)} scans, world frame: {frame}", "", "Scans:"]
    for name, pose, by in zip(result.names, result.poses, result.placed_by):
        if by is None:
            lines.append(f"  {name}: not joined (no trusted alignment reaches {world})")
        elif by == "initial pose":
            lines.append(f"  {name}: not joined (no trusted alignment reaches {world}); placed by the initial poses, unverified")
        else:
            lines.append(
                f"  {name}: joined; world_T_scan turns {rotation_angle_deg(pose[:3, :3]):.2f} deg and moves {_tidy(np.linalg.norm(pose[:3, 3])):.4g} units"
            )
    used = [e for e in result.edges if e.used]
    lines += [
        "",
        f"Pairs: {len(result.edges)} registered, {len(used)} trusted (confidence >= 0.5, higher is better), "
        f"{sum(e.in_tree for e in result.edges)} in the spanning tree, {sum(e.pruned for e in result.edges)} pruned by the optimisation.",
    ]
    for e in result.edges:
        state = "pruned" if e.pruned else "tree" if e.in_tree else "loop" if e.used else "left out (flagged likely failed)"
        lines.append(f"  {result.names[e.source]} -> {result.names[e.target]}: confidence {e.confidence:.3f}, {state}, {e.seconds:.2f} s")
    t = result.timings_s
    lines += [
        "",
        f"Time (s, lower is better): cleaning {t['clean']:.1f}, pairs {t['pairs']:.1f}, optimisation {t['optimise']:.2f}, total {t['total']:.1f}",
        f"Wrote {out_dir / 'poses.json'} and {out_dir / 'merged.ply'} ({merged_points:,} points"
        + ("" if result.voxel is not None else ": every scan's, overlaps included; --merge-voxel thins them onto a grid")
        + ").",
    ]
    return "\n".join(lines)


# Command-line options of `train` that are TrainConfig fields of the same name; given on the
# command line, they override the --config file, which overrides TrainConfig's defaults.
def _loss_weight(flag: str, help: str):
    """A training loss's weight option (0, the default: that loss is not added)."""
    return click.option(flag, type=click.FloatRange(min=0), default=0.0, show_default=True, help=help)


_TRAIN_FIELDS = (
    "data",
    "protocol",
    "epochs",
    "batch_size",
    "lr",
    "lr_schedule",
    "lr_min",
    "grad_clip",
    "point_loss",
    "match_loss",
    "overlap_loss",
    "only_overlap",
    "init_temperature",
    "init",
    "seed",
    "device",
    "out",
    "checkpoint_minutes",
    "eval_pairs",
    "max_steps",
    "max_minutes",
    "limit_train",
    "points_per_shape",
    "extra_data",
    "extra_protocol",
    "extra_share",
    "extra_points_per_shape",
    "workers",
)


@main.command()
@click.option(
    "--config",
    "config_file",
    type=click.Path(path_type=Path),
    help="YAML file of settings (the keys of config.yaml in a run folder); command-line options override it.",
)
@click.option("--data", help="ModelNet40 folder (official HDF5 layout or OFF meshes); default $O3DSOFT_DATA.")
@click.option(
    "--protocol",
    default="paper",
    show_default=True,
    help="Pair protocol (paper, dcp, wide45, so3, incongruent, ...) or mixture (incongruent-mix, incongruent-view-mix).",
)
@click.option("--epochs", type=click.IntRange(min=1), default=5, show_default=True, help="Passes over the training pairs.")
@click.option("--batch-size", type=click.IntRange(min=1), default=10, show_default=True, help="Pairs per step (per process under torchrun).")
@click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=1e-3, show_default=True, help="Adam's learning rate.")
@click.option(
    "--lr-schedule",
    type=click.Choice(["constant", "cosine"]),
    default="constant",
    show_default=True,
    help="Learning rate: constant, or cosine from --lr to --lr-min.",
)
@click.option("--lr-min", type=click.FloatRange(min=0), default=1e-5, show_default=True, help="Final learning rate of the cosine schedule.")
@click.option("--grad-clip", type=click.FloatRange(min=0, min_open=True), default=None, help="Clip the gradients' L2 norm (default: no clipping).")
@_loss_weight("--point-loss", "Weight of a loss on each source point's soft partner (where it truly lies), added to the paper's transform loss.")
@_loss_weight("--match-loss", "Weight of the soft assignment's cross-entropy against each source point's true neighbourhood, added to the loss.")
@_loss_weight("--overlap-loss", "Weight of the overlap head's cross-entropy against which points lie in the overlap, added to the loss (needs --overlap).")
@click.option("--only-overlap", is_flag=True, default=False, help="Train the overlap head alone; the rest of the network stays as --init gave it.")
@click.option(
    "--init-temperature",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Set the softmax temperature tau to this value before training (default: the initial weights' own).",
)
@click.option(
    "--init",
    type=click.Path(),
    default=None,
    help="Start from these weights (fine-tuning): a run's checkpoint.pt, a model file, or a shipped model by name (default, paper, partial, incongruent).",
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of the pairs drawn and of the network's first weights.")
@click.option("--device", default="cpu", show_default=True, help="Torch device: cpu, cuda, cuda:1, mps... (under torchrun: one GPU per process).")
@click.option(
    "--radius", type=click.FloatRange(min=0, min_open=True), default=None, help="Neighbourhood radius (normalised units); default from the network config."
)
@click.option("--k", "k", type=click.IntRange(min=1), default=None, help="Neighbourhood size K; default 32.")
@click.option("--separate-encoders", is_flag=True, default=None, help="One encoder per cloud instead of a shared one.")
@click.option(
    "--relative",
    is_flag=True,
    default=None,
    help="First layer on neighbour offsets instead of coordinates: descriptors that do not move with a cropped cloud's centroid.",
)
@click.option(
    "--overlap",
    type=click.IntRange(min=0),
    default=None,
    help="Width of an overlap head (attention between the two clouds that predicts which points lie in the overlap; default 0: none).",
)
@click.option("--out", default="runs/train", show_default=True, help="Output folder: checkpoint, config, model, model card.")
@click.option(
    "--checkpoint-minutes",
    type=click.FloatRange(min=0, min_open=True),
    default=5.0,
    show_default=True,
    help="Minutes between checkpoints (one is also written each epoch).",
)
@click.option(
    "--resume",
    is_flag=True,
    help="Continue from OUT/checkpoint.pt exactly where it stopped, with the settings of OUT/config.yaml. Options given here override them "
    "(e.g. --epochs, --max-steps, --lr); those that decide which pairs are drawn or the network (the data, --protocol, --batch-size, --seed, "
    "the network's settings, --limit-train, --points-per-shape, the --extra-* options) must stay as they were.",
)
@click.option("--overwrite", is_flag=True, help="Start a new run in an --out folder that holds one, replacing its files.")
@click.option("--max-steps", type=click.IntRange(min=1), default=None, help="Stop after this many steps (quick runs).")
@click.option(
    "--max-minutes",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Stop after this many minutes of training in this call, with a checkpoint and the model exported (--resume goes on, "
    "its minutes counted afresh; --max-steps counts the whole run's steps).",
)
@click.option("--limit-train", type=click.IntRange(min=1), default=None, help="Use only the first N training shapes.")
@click.option("--points-per-shape", type=click.IntRange(min=1), default=1024, show_default=True, help="Points per shape (first N of the HDF5 data).")
@click.option(
    "--extra-data",
    default=None,
    help="A second dataset in the same layout (e.g. python -m benchmarks.make_shapes's synthetic scans) whose pairs make --extra-share of the batches.",
)
@click.option("--extra-protocol", default="incongruent-far-view", show_default=True, help="Protocol or mixture of the --extra-data pairs.")
@click.option(
    "--extra-share",
    type=click.FloatRange(min=0, max=1, min_open=True, max_open=True),
    default=0.5,
    show_default=True,
    help="Share of the batches drawn from --extra-data.",
)
@click.option("--extra-points-per-shape", type=click.IntRange(min=1), default=1024, show_default=True, help="Points per shape of --extra-data.")
@click.option("--eval-pairs", type=click.IntRange(min=0), default=300, show_default=True, help="Test pairs evaluated after each epoch (0: none).")
@click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True, help="DataLoader worker processes.")
@click.pass_context
@_friendly_errors
def train(ctx, config_file, resume, overwrite, radius, k, separate_encoders, relative, overlap, **options):
    """Train the network on ModelNet40 and export TorchScript + a model card into OUT.

    Several processes or machines: run the same command under torchrun, e.g.
    `torchrun --nproc_per_node 4 -m o3dsoft.cli.main train --device cuda`.
    """
    from click.core import ParameterSource

    from ..train import settings_from
    from ..train import train as run_train

    given = {name: options[name] for name in _TRAIN_FIELDS if ctx.get_parameter_source(name) is ParameterSource.COMMANDLINE}
    net = {"radius": radius, "k": k, "shared_encoder": None if separate_encoders is None else not separate_encoders, "relative": relative, "overlap": overlap}
    config = settings_from(given, {name: options[name] for name in _TRAIN_FIELDS}, config_file, {n: v for n, v in net.items() if v is not None}, resume)
    if resume and overwrite:
        raise click.UsageError("--resume goes on with the run in --out, --overwrite starts a new one: give one of them")
    run_train(config, resume=resume, overwrite=overwrite, log=lambda m: click.echo(m, err=True))


@main.group()
def bench():
    """Compare o3dsoft with Open3D's ICP, FPFH + RANSAC and FGR, and KISS-Matcher + small_gicp (o3dsoft[peers]), on the same pairs."""


def _bench_options(fn):
    """Options shared by every bench command."""

    options = [
        click.option(
            "--method",
            "methods",
            multiple=True,
            help=f"Methods to run (repeat the option; default on ModelNet40 all but the KISS-Matcher peers; on scans o3dsoft, fpfh-ransac+icp and, where installed, kiss-matcher+gicp): {', '.join(METHOD_NAMES)}.",
        ),
        click.option(
            "--seed",
            type=click.IntRange(min=0),
            default=0,
            show_default=True,
            help="Seed of the pairs and of RANSAC (o3dsoft's search repeats exactly; Open3D's multi-threaded RANSAC, in the FPFH baselines, can vary between runs).",
        ),
        click.option("--out", type=click.Path(path_type=Path), default=None, help="Run folder (default runs/bench-<name>-<time>)."),
        click.option("--overwrite", is_flag=True, help="Write into an existing run folder, replacing its results (a bench run does not resume)."),
        click.option("--no-progress", is_flag=True, help="No progress bar."),
        click.option(
            "--jobs",
            type=click.IntRange(min=1),
            default=1,
            show_default=True,
            help="Pairs run at once, in as many processes sharing the CPU's threads (for many cores; every method's time is then measured on its process's share).",
        ),
    ]
    return _pipeline_options(_apply_options(options, fn))


def _run_bench(
    name, pairs, count, description, recall=None, titles=None, units=None, ready=None, *, methods, seed, out, overwrite, no_progress, jobs, **pipeline
):
    """Run the bench's methods on `pairs`; `ready`, where given, is called with the pairs once
    every setting and model is checked and the run folder made, and returns the pairs to run (what
    it writes then is not left behind by a run refused)."""
    from dataclasses import replace

    from ..bench import BenchConfig, check_methods, prepare_folder, run
    from ..coarse import cached_model, load_model, torch_device

    config = BenchConfig(methods=check_methods(methods) if methods else BenchConfig().methods, seed=seed, register=_register_config(**pipeline))
    if recall is not None:  # thresholds per protocol (folder of scans)
        config = replace(config, recall_by_protocol=recall)
    needs_model = {"o3dsoft", "o3dsoft-coarse"} & set(config.methods)
    if pipeline.get("weights") is not None and not needs_model:
        click.echo(f"Warning: --weights {pipeline['weights']} is not used: no method asked ({', '.join(config.methods)}) runs the network", err=True)
    device = config.register.device
    torch_device(device)  # an unknown or absent device, whichever methods run
    model = load_model(config.register.weights, device) if needs_model else None
    if needs_model and config.register.second_network.weights is not None:
        cached_model(config.register.second_network.weights, device)  # a file that is no model fails now, not at each flagged pair
    searches = needs_model and config.register.search.mode != "off" and config.register.search.starts.weights is not None
    search_model = load_model(config.register.search.starts.weights, device) if searches else None
    description = {"command": shlex.join(["o3dsoft", *sys.argv[1:]]), **description, "jobs": jobs}
    folder = prepare_folder(out or Path("runs") / f"bench-{name}-{time.strftime('%Y%m%d-%H%M%S')}", overwrite)
    if ready is not None:
        pairs = ready(pairs)
    result = run(
        pairs,
        count,
        config,
        model,
        folder,
        description,
        progress=not no_progress,
        log=lambda m: click.echo(m, err=True),
        search_model=search_model,
        jobs=jobs,
        titles=titles,
        units=units,
    )
    click.echo(result.table)
    names = ("pairs.csv", "summary.json", "config.json", "table.txt", "cdf_rotation_error.png", "recall_vs_angle.png")
    written = [n for n in names if (result.folder / n).is_file() and (result.folder / n).stat().st_size > 0]
    click.echo(f"\nRun folder: {result.folder} ({', '.join(written) or 'nothing written'})")
    if not result.summaries and not result.interrupted:
        raise InputError("no pair could run (each one's reason is above; summary.json lists them)")
    if result.interrupted:
        click.echo("Interrupted: the table covers the pairs finished before Ctrl-C (or SIGTERM).", err=True)
        sys.exit(130)


@bench.command("modelnet40")
@click.option("--protocol", "protocols", multiple=True, help="Protocols (repeat the option; default: the literature's seven and the four incongruent ones).")
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Only the first N test pairs of each protocol.")
@click.option("--data", help="ModelNet40 folder; default $O3DSOFT_DATA.")
@click.option(
    "--points-per-shape",
    type=click.IntRange(min=1),
    default=1024,
    show_default=True,
    help="Points of each shape (the first N of the HDF5 data); the incongruent protocols split them into two clouds of N/2.",
)
@click.option("--export-pairs", type=click.Path(path_type=Path), help="Also write the pairs to this .npz (for other tools).")
@click.option("--import-pairs", type=click.Path(path_type=Path), help="Score the pairs of this .npz instead of making them.")
@_bench_options
@_friendly_errors
def bench_modelnet40(protocols, limit, data, points_per_shape, export_pairs, import_pairs, **common):
    """Every method on the ModelNet40 test pairs of each protocol: table, CSV, JSON, plots."""
    from .. import io
    from ..bench import BENCH_PROTOCOLS, check_methods, modelnet_pairs
    from ..bench import export_pairs as write_pairs
    from ..bench import import_pairs as read_pairs
    from ..coarse import sha256_of
    from ..data import get_protocol, resolve_data_root

    check_methods(common["methods"])
    seed = common["seed"]
    if import_pairs:
        sized = click.get_current_context().get_parameter_source("points_per_shape") is not click.core.ParameterSource.DEFAULT
        made = [
            opt
            for opt, given in (("--protocol", protocols), ("--limit", limit), ("--data", data), ("--points-per-shape", sized), ("--export-pairs", export_pairs))
            if given
        ]
        if made:
            raise click.UsageError(f"--import-pairs scores the file's pairs as they are; {', '.join(made)} make(s) pairs: leave it out")
        pairs = read_pairs(import_pairs)
        count, iterator = len(pairs), iter(pairs)
        description = {"benchmark": "pairs file", "pairs_file": str(import_pairs.resolve()), "pairs_sha256": sha256_of(import_pairs)}
    else:
        protocols = tuple(dict.fromkeys(protocols)) or BENCH_PROTOCOLS  # a protocol given twice runs once
        for name in protocols:
            get_protocol(name)
        count, iterator = modelnet_pairs(data, protocols, limit, seed, points_per_shape)
        description = {
            "benchmark": "modelnet40",
            "protocols": list(protocols),
            "limit": limit,
            "data": str(resolve_data_root(data).resolve()),  # --data or $O3DSOFT_DATA, as read
            "seed": seed,
            "points_per_shape": points_per_shape,
        }
        if export_pairs:
            if export_pairs.exists() and not common["overwrite"]:
                raise click.UsageError(f"--export-pairs {export_pairs}: the file exists; choose another name or pass --overwrite")
            io.check_writable(export_pairs)

    def export(pairs):
        """The pairs, written to --export-pairs first (once the run is sure to start)."""
        if not export_pairs:
            return pairs
        pairs = list(pairs)
        write_pairs(export_pairs, pairs)
        click.echo(f"wrote {len(pairs)} pairs to {export_pairs}", err=True)
        return iter(pairs)

    _run_bench("modelnet40", iterator, count, description, ready=export, **common)


_MIN_OVERLAP = click.option(
    "--min-overlap",
    type=click.FloatRange(0, 1),
    default=0.3,
    show_default=True,
    help="Folders with a .conf: keep ordered scan pairs with at least this ground-truth overlap (a pairs.txt's pairs are all kept).",
)
_TURNS = click.option(
    "--turns",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Also run each pair N times with the source turned about its centroid by a random rotation (seeded by --seed), "
    "as 'FOLDER turned': results that do not hang on the frames the scans were saved in.",
)
_NOISE = click.option(
    "--noise",
    type=click.FloatRange(min=0, max=0.1),
    default=0.0,
    show_default=True,
    help="Also run each pair with Gaussian noise of this standard deviation, as a share of the scene's size, added to both clouds "
    "(seeded by --seed), as 'FOLDER noise P %': a noisier sensor than the folder's. 0.003 on a 4 m room: 1.2 cm per coordinate.",
)


@bench.command("scans")
@click.argument("folders", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--kind",
    type=click.Choice(["auto", "rgbd", "lidar", "object"]),
    default="auto",
    show_default=True,
    help="What the scans are, which sets the success thresholds: rgbd 2 deg / 5 cm and 15 deg / 30 cm; lidar 1 deg / 30 cm and 5 deg / 2 m; "
    "object 1 deg / 1 % and 5 deg / 5 % of the size. auto: per folder from the size of its first scan (under 1 m an object, under 30 m RGB-D).",
)
@click.option(
    "--unit",
    type=click.Choice(["m", "cm", "mm"]),
    default="m",
    show_default=True,
    help="The scans' unit: the kind's guess and the RGB-D and LiDAR tests (in metres) follow it.",
)
@_MIN_OVERLAP
@_TURNS
@_NOISE
@_bench_options
@_friendly_errors
def bench_scans(folders, kind, unit, min_overlap, turns, noise, **common):
    """Every method on the pairs of each folder of real scans: those its pairs.txt lists, or every
    overlapping pair of a Stanford .conf. Table, CSV, JSON, plots; the peers KISS-Matcher +
    small_gicp too when installed (pip install 'o3dsoft[peers]')."""
    from ..bench import scan_folder

    _run_scan_bench([scan_folder(folder, min_overlap, kind, unit) for folder in folders], min_overlap, turns, noise, common, unit)


@bench.command("bunny")
@click.option(
    "--data", type=click.Path(path_type=Path), default=None, help="Folder with scans and their .conf (default ../shared/data/stanford_bunny or $O3DSOFT_SCANS)."
)
@_MIN_OVERLAP
@click.option(
    "--recall-translation",
    type=click.FloatRange(min=0, min_open=True),
    default=0.002,
    show_default=True,
    help="Translation threshold of the 1-degree recall, in the scans' units (metres for the bunny); x5 for the 5-degree one.",
)
@_TURNS
@_NOISE
@_bench_options
@_friendly_errors
def bench_bunny(data, min_overlap, recall_translation, turns, noise, **common):
    """Every method on every overlapping pair of the Stanford bunny scans (bench scans on one folder,
    thresholds 1 deg / 2 mm and 5 deg / 1 cm)."""
    import os

    from ..bench import scan_folder
    from ..errors import UsageError

    folder = data or (Path(os.environ["O3DSOFT_SCANS"]) if "O3DSOFT_SCANS" in os.environ else Path("../shared/data/stanford_bunny"))
    if not folder.is_dir():
        raise UsageError(f"{folder}: no such folder of scans; pass --data FOLDER (scans + a Stanford .conf)")
    scans = scan_folder(folder, min_overlap, "object")._replace(recall=((1.0, recall_translation), (5.0, 5 * recall_translation)))
    _run_scan_bench([scans], min_overlap, turns, noise, common)


def _run_scan_bench(folders, min_overlap, turns, noise, common, unit="m"):
    """Run the bench on the pairs of every folder (each folder a protocol with its own thresholds),
    then on their turned copies (each folder's a protocol "FOLDER turned") and their noisy ones
    ("FOLDER noise P %"); `unit`: the scans' (--unit)."""
    from ..bench import check_methods, noise_protocol, noisy_pairs, peers_installed, turned_pairs, turned_protocol
    from ..errors import UsageError

    if common["methods"]:
        check_methods(common["methods"])
    else:  # the peers users compare with, where installed
        peers = peers_installed()
        common["methods"] = ("o3dsoft", "fpfh-ransac+icp") + (("kiss-matcher+gicp",) if peers else ())
        if not peers:
            click.echo("Note: KISS-Matcher + small_gicp left out: pip install 'o3dsoft[peers]'", err=True)
    titles, recall, units, description = {}, {}, {}, []
    for scans in folders:
        name = scans.name
        guess = "" if scans.guessed_from is None else f", from its first scan's size, {scans.guessed_from:.3g} {unit}: --unit or --kind if that is not so"
        click.echo(f"{name}: {len(scans.pairs)} of {len(scans.table)} pairs ({scans.kind}{guess})", err=True)
        for file, count in scans.left_out:
            click.echo(f"  {file}: {count} points with a non-finite coordinate left out", err=True)
        if not scans.pairs:
            raise UsageError(f"{name}: no scan pair reaches --min-overlap {min_overlap}")
        thresholds = " and ".join(f"{d:g} deg / {t:.3g} {unit}" for d, t in scans.recall)
        titles[name] = f"{name} ({scans.kind}: success within {thresholds})"
        recall[name], units[name] = scans.recall, unit
        description.append(
            {"folder": name, "path": scans.path, "kind": scans.kind, "unit": unit, "recall": [list(r) for r in scans.recall], "pairs": scans.table}
        )
    if len(recall) < len(folders):
        raise UsageError("two folders have the same name; give folders of different names")
    pairs = [p for scans in folders for p in scans.pairs]
    given = list(zip(folders, description))

    def variant(protocol, title: str, setting: dict) -> None:  # each folder's pairs again, as protocol(folder name)
        for scans, entry in given:
            name = protocol(scans.name)
            titles[name] = f"{titles[scans.name]}, {title}"
            recall[name], units[name] = scans.recall, unit
            description.append({**{k: v for k, v in entry.items() if k != "pairs"}, "folder": name, **setting})

    if turns:
        times = "once" if turns == 1 else f"{turns} times"
        variant(turned_protocol, f"the source turned {times}", {"turns": turns})
        click.echo(f"and every pair again with the source turned {times} ({turns * len(pairs)} pairs)", err=True)
    if noise:
        variant(lambda name: noise_protocol(name, noise), f"noise {noise:g} x the scene's size on both clouds", {"noise": noise})
        click.echo(f"and every pair again with noise of {noise:g} x the scene's size ({len(pairs)} pairs)", err=True)
    pairs += turned_pairs(pairs, turns, common["seed"]) + noisy_pairs(pairs, noise, common["seed"])
    _run_bench("scans", iter(pairs), len(pairs), {"benchmark": "scans", "min_overlap": min_overlap, "folders": description}, recall, titles, units, **common)


if __name__ == "__main__":  # pragma: no cover
    main()
