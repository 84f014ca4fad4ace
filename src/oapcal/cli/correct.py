"""``oapcal correct``: correct images, stacks, directories (and with ``--dask``, huge stacks)."""

from __future__ import annotations

from types import SimpleNamespace

import click

from oapcal.cli._common import (
    allow_unconverged_option,
    check_output,
    choice_option,
    console,
    count_option,
    file_option,
    flag_option,
    json_option,
    load_usable_calibration,
    parse_size,
    positive_option,
    print_json,
    progress_bar,
    with_flag_hint,
)

GEOMETRY_HELP = (
    "Output region: 'input' (default: the input's size and undistorted coordinates), 'full' "
    "(the whole corrected field, nothing cut), 'calibrated' (the box of the calibration points). "
    "Given explicitly, 'input' writes the whole frame, beyond the trust region too (with a warning)."
)
MAX_ERROR_HELP = (
    "Trust region: write only output pixels whose predicted error (the fit's covariance, the "
    "model floor and the extrapolation measured on the landmarks) is at most this many output px; "
    "the rest get --border. Default 1, unless --extent input is given (the whole frame)."
)


def trust_message(
    summary: dict,
    *,
    masked: bool,
    border: float | None = None,
    hint: str = "leave --extent input out to write only the trust region",
) -> str | None:
    """The line a command prints about where its output extrapolates (``summary`` from
    :func:`oapcal.imaging.remap.trust_summary`), or None when all of it lies within the
    landmarks' hull and is trusted."""
    w, h = summary["output_px"]
    limit = summary["max_error_px"]
    outside = summary["outside_fraction"]
    far = summary["max_distance_px"]
    worst = summary["max_predicted_px"]
    trusted = summary["trusted_fraction"]
    # inf: the map folds over there (a fold beyond the landmarks' bounds, which the fit kept)
    reach = "is unbounded (the map folds over)" if worst == float("inf") else f"reaches {worst:.3g} px"
    if outside > 0 and far is not None:
        where = (
            f"{100 * outside:.1f} % of the {w}x{h} px output lies beyond the landmarks' hull (up to "
            f"{far:.0f} px from it), where the predicted error {reach}"
        )
    elif outside > 0:  # a calibration without a hull (possible only by editing its file)
        where = (
            f"the calibration records no hull of its landmarks, so all of the {w}x{h} px output counts "
            f"as extrapolated; the predicted error reaches {worst:.3g} px"
        )
    else:
        where = (
            f"the {w}x{h} px output lies within the landmarks' hull; its predicted error reaches "
            f"{worst:.3g} px"
        )
    old = "" if summary["has_error_model"] else (
        " (this calibration has no error model, written by an older oapcal: the predicted error is the "
        "fit's covariance alone, optimistic beyond the hull; refit to measure it)"
    )  # fmt: skip
    if masked:
        if trusted is not None and trusted >= 1.0:
            return None if outside == 0 else f"oapcal: {where}, within --max-error-px {limit:g}{old}"
        return (
            f"oapcal: trust region: {100 * trusted:.1f} % of the output has a predicted error of at most "
            f"{limit:g} px and is corrected; the rest is written as the border value {border:g}: {where} "
            f"(--max-error-px sets the threshold, --extent input writes the whole frame){old}"
        )
    if outside == 0 and (trusted is None or trusted >= 1.0):
        return None
    above = "" if trusted is None else f"; {100 * (1 - trusted):.1f} % of it is predicted above {limit:g} px"
    return f"oapcal: warning: the whole output is corrected: {where}{above}; {hint}{old}"


def points_trust_message(calibration, xy_c) -> str | None:
    """The line ``correct-points`` (and any command correcting points) prints when corrected
    points ``(N, 2)`` lie beyond the landmarks' hull: how many, how far, with what predicted
    error (:func:`oapcal.uncertainty.extrapolation_report`); None when all lie within it."""
    import numpy as np

    from oapcal.uncertainty import extrapolation_report

    xy_c = np.asarray(xy_c, float).reshape(-1, 2)
    if not len(xy_c):
        return None
    with np.errstate(all="ignore"):
        rep = extrapolation_report(calibration, xy_c)
    if not rep["outside"]:
        return None
    worst = rep["max_predicted_outside_px"]
    old = "" if getattr(calibration, "error_model", None) is not None else (
        " (the calibration has no error model: the fit's covariance alone, optimistic beyond the hull; refit)"
    )  # fmt: skip
    far = (
        " (the calibration records no hull)"
        if rep["max_distance_px"] is None
        else (f" (up to {rep['max_distance_px']:.0f} px from it)")
    )
    return (
        f"oapcal: {rep['outside']} of {rep['n']} corrected points lie beyond the landmarks' hull{far}: the "
        f"model extrapolates there; predicted error {rep['median_predicted_outside_px']:.3g} px median, "
        f"{worst:.3g} px max{old}"
    )


def geometry_options(func):
    """``--extent``, ``--um-per-px``, ``--out-size`` (shared with ``export-opencv``)."""
    func = click.option(
        "--out-size",
        default=None,
        help="Fit the region into an output of WxH px (aspect kept). Excludes --um-per-px.",
    )(func)
    func = click.option(
        "--um-per-px",
        type=click.FloatRange(min=0, min_open=True),
        default=None,
        help="Output pixel size in um (needs a calibration fitted with --um-per-px).",
    )(func)
    func = click.option(
        "--extent",
        type=click.Choice(["input", "full", "calibrated"]),
        default="input",
        show_default=True,
        help=GEOMETRY_HELP,
    )(func)
    return func


@click.command("correct")
@click.argument("calib", type=click.Path(dir_okay=False))
@click.argument("inputs", nargs=-1)
@click.option(
    "--out-dir",
    type=click.Path(file_okay=False),
    default=None,
    help="Directory for the corrected images (created; must not hold the inputs).",
)
@choice_option(
    "--interp",
    choices=["linear", "cubic", "lanczos", "nearest"],
    default="linear",
    help="Interpolation of cv2.remap.",
)
@click.option(
    "--border", type=float, default=0.0, show_default=True, help="Value of pixels outside the input."
)
@count_option(
    "--workers",
    least=1,
    default=1,
    help="Files corrected at once (threads); with --dask, local-cluster workers.",
)
@geometry_options
@positive_option("--max-error-px", help=MAX_ERROR_HELP)
@file_option("--save-map", help="Write the correction map (.npz, .npy or .tif/.tiff).")
@file_option(
    "--map", "map_file", help="Use a saved map instead of building one (excludes the geometry options)."
)
@flag_option("--allow-size-mismatch", help="Correct images whose size differs from the calibration's.")
@click.option(
    "--max-pixels",
    type=click.IntRange(min=1),
    default=None,
    help="Largest frame (pixels) read; checked before decoding. Default 2**28.",
)
@flag_option("--overwrite", help="Redo outputs that already exist (default: skip them).")
@flag_option("--dask", "use_dask", help="Correct TIFF/zarr stacks with Dask, lazily.")
@click.option(
    "--scheduler",
    default=None,
    help="With --dask: a dask.distributed scheduler address (tcp://host:8786), or 'threads', "
    "'synchronous', 'processes'. Default: a new local cluster.",
)
@count_option("--chunk-frames", least=1, default=16, help="With --dask: frames per chunk (memory per task).")
@choice_option(
    "--dask-format",
    choices=["zarr", "ome-zarr", "tiff"],
    default="zarr",
    help="With --dask: write NAME.zarr, NAME.ome.zarr (OME-Zarr, NGFF 0.4) or NAME.tif.",
)
@choice_option(
    "--format",
    "output_format",
    choices=["same", "tiff", "ome-tiff", "ome-zarr"],
    default="same",
    help="Without --dask: write each input in its own format (same), or as NAME.tif, NAME.ome.tif "
    "(OME-TIFF with the pixel size and the calibration's provenance) or NAME.ome.zarr.",
)
@flag_option("--quiet", help="No progress bar.")
@json_option("Print the per-file results as one JSON object.")
@allow_unconverged_option
def correct_command(
    calib, inputs, out_dir, interp, border, workers, extent, um_per_px, out_size, max_error_px, save_map,
    map_file, allow_size_mismatch, max_pixels, overwrite, use_dask, scheduler, chunk_frames, dask_format,
    output_format, quiet, as_json, allow_unconverged,
):  # fmt: skip
    """Correct images with a calibration: files, multi-page TIFF stacks, directories, globs.

    Each INPUT is written to OUT_DIR under its own name and format, atomically; complete
    outputs are skipped on a rerun. Unreadable inputs are reported and skipped; the exit
    code is then 4.

    By default only the trust region is written: output pixels whose predicted error is at
    most --max-error-px (1 px); the others get --border, and the command says how much of
    the output that is and how far it lies beyond the landmarks. --extent input (given
    explicitly) writes the whole frame, with a warning.
    """
    from pathlib import Path

    o = SimpleNamespace(**locals())  # the command's values by name, for the steps below
    limit = _check_usage(inputs, out_dir, extent, um_per_px, out_size, max_error_px, save_map, map_file,
                         use_dask, output_format)  # fmt: skip
    o.output_format = None if output_format == "same" else output_format
    size = parse_size(out_size, "--out-size")
    plan = _plan(o)
    cal = load_usable_calibration(calib, allow_unconverged)
    name = cal.name or Path(calib).name
    geometry = {"extent": extent, "um_per_px": um_per_px, "out_size": size}
    # the sequential path builds a trust-region map per input size itself; --dask gets one map
    prebuild = limit if (use_dask or save_map) else None
    files = list(plan.files) if plan else []
    cmap = _prepare_map(cal, files, map_file, save_map, geometry, o.max_pixels, prebuild, calib)
    if inputs:
        _check_samples(cal, cmap, files, geometry, o.max_pixels, trust_region=limit is not None)
    if use_dask:  # a missing extra is one clear error, before anything else is said
        from oapcal.extras import EXTRAS, require

        for module in EXTRAS["dask"]:
            require(module, "dask")
    seeds: dict = {}  # the trust region's predicted error, computed once for the map too
    trust = _trust(cal, cmap, files, geometry, o.max_pixels, limit, border, calib, seeds)
    if not inputs:
        click.echo(f"wrote the correction map {save_map} ({cmap.shape[1]}x{cmap.shape[0]} px output)")
        return 0
    o.bar, o.update = progress_bar("correcting", enabled=not (quiet or as_json))
    o.name, o.geometry, o.limit, o.seeds, o.trust = name, geometry, limit, seeds, trust
    return (_run_dask if use_dask else _run_sequential)(o, cal, plan, cmap)


def _plan(o):
    """Check what ``correct`` (options ``o``) will write before any work: the scheduler's
    address, the outputs (:func:`oapcal.batch.stack.plan_batch`) and the output directory;
    the plan, or None with no inputs.  Sets ``o.max_pixels`` (its default filled in)."""
    from oapcal.io.images import MAX_PIXELS

    if o.use_dask and o.scheduler is not None:  # an address is checked before anything else
        from oapcal.batch.distributed import LOCAL_SCHEDULERS, parse_scheduler_address

        if o.scheduler not in LOCAL_SCHEDULERS:
            parse_scheduler_address(o.scheduler)
    o.max_pixels = o.max_pixels or MAX_PIXELS
    check_output(o.save_map, o.calib, o.map_file, *o.inputs)
    if not o.inputs:
        return None
    from oapcal.batch.stack import plan_batch
    from oapcal.io.atomic import check_directory_writable

    plan = plan_batch(
        o.inputs, o.out_dir, dask_format=o.dask_format if o.use_dask else None,
        output_format=o.output_format, protect=_protected(o),
        reserved=[(o.save_map, f"the map --save-map {o.save_map}")] if o.save_map else [],
    )  # fmt: skip
    check_directory_writable(o.out_dir)  # before any work, as every command probes its outputs
    return plan


def _protected(o) -> list:
    """The files no output may overwrite: the calibration and the ``--map`` file."""
    return [o.calib] + ([o.map_file] if o.map_file else [])


def _run_dask(o, cal, plan, cmap) -> int:
    """``correct --dask``: the planned stacks through Dask; the exit code."""
    from oapcal.batch.distributed import DaskSettings, correct_stacks_dask

    settings = DaskSettings(
        output_format=o.dask_format, chunk_frames=o.chunk_frames, interp=o.interp, border=o.border,
        allow_size_mismatch=o.allow_size_mismatch, max_pixels=o.max_pixels, scheduler=o.scheduler,
        workers=o.workers, calibration_name=o.name, overwrite=o.overwrite,
        progress=o.update, **({} if cmap is not None else o.geometry),
    )  # fmt: skip
    with o.bar:
        report = correct_stacks_dask(cal, plan, o.out_dir, cmap, settings, map_path=o.map_file)
    for note in () if o.as_json else report.notes:
        click.echo(f"oapcal: note: {note}", err=True)
    results = [_result(r, dask=True) for r in report.results]
    return _finish(results, report.summary(), report.count("failed"), o.as_json, o.trust)


def _run_sequential(o, cal, plan, cmap) -> int:
    """``correct`` without ``--dask``: every input, frame by frame; the exit code."""
    from oapcal.batch.stack import StackSettings, correct_stack

    settings = StackSettings(
        interp=o.interp, border=o.border, workers=o.workers, cmap=cmap,
        allow_size_mismatch=o.allow_size_mismatch, max_pixels=o.max_pixels, overwrite=o.overwrite,
        calibration_name=o.name, protect=_protected(o),
        reserved=[(o.save_map, f"the map --save-map {o.save_map}")] if o.save_map else (),
        progress=o.update, max_error_px=None if cmap is not None or o.map_file else o.limit,
        output_format=o.output_format, predicted_errors=o.seeds,
    )  # fmt: skip
    with o.bar:
        report = correct_stack(cal, o.inputs, o.out_dir, settings, **({} if cmap else o.geometry))
    results = [_result(r) for r in report.results]
    return _finish(results, report.summary(), report.count("failed"), o.as_json, o.trust)


# the options whose combinations it checks, as the command received them
def _check_usage(inputs, out_dir, extent, um_per_px, out_size, max_error_px, save_map, map_file, use_dask,
                 output_format):  # fmt: skip
    """Refuse combinations of ``correct``'s options that cannot work (a ``click.UsageError``
    each), and return the trust region's limit: ``--max-error-px``, or the default unless
    ``--extent input`` was given explicitly or ``--map`` holds its own."""
    from oapcal.imaging.remap import DEFAULT_MAX_ERROR_PX

    if not inputs and save_map is None:
        raise click.UsageError("give INPUT images (with --out-dir), or --save-map to only write the map")
    if inputs and out_dir is None:
        raise click.UsageError("give --out-dir DIR for the corrected images")
    if map_file and (extent != "input" or um_per_px or out_size):
        raise click.UsageError("--map fixes the output geometry: drop --extent, --um-per-px and --out-size")
    ctx = click.get_current_context()
    if map_file and max_error_px is not None:
        raise click.UsageError(
            "--map holds its own output (and trust region, if built with one): drop --max-error-px"
        )
    whole = extent == "input" and ctx.get_parameter_source("extent") != click.core.ParameterSource.DEFAULT
    if not use_dask:
        for option in ("scheduler", "chunk_frames", "dask_format"):
            if ctx.get_parameter_source(option) != click.core.ParameterSource.DEFAULT:
                flag = "--" + option.replace("_", "-")
                raise click.UsageError(f"{flag} applies to --dask only: add --dask or drop {flag}")
    if use_dask and output_format != "same":
        raise click.UsageError("with --dask the output format is --dask-format: drop --format")
    return max_error_px if max_error_px is not None else (None if whole or map_file else DEFAULT_MAX_ERROR_PX)


def _result(r, dask: bool = False) -> dict:
    """A :class:`~oapcal.batch.stack.FileResult` as the command reports it: its message
    with the flags that set the parameters it names (a zarr array: the --dask option; with
    --dask, running out of memory: the options that bound it)."""
    from oapcal.batch.stack import is_zarr_array

    out = {k: v for k, v in r.__dict__.items() if k != "param"}
    if dask and r.reason == "out_of_memory":
        out["message"] = f"{r.input}: not enough memory; lower --chunk-frames or --workers"
    elif r.status == "failed" and r.output is None and r.reason == "unsupported" and is_zarr_array(r.input):
        out["message"] = f"{r.input}: is a zarr array, which is corrected with Dask: give --dask"
    elif r.message:
        out["message"] = with_flag_hint(r.message, r.param)
    return out


def _prepare_map(
    cal, files, map_file, save_map, geometry, max_pixels, limit=None, calib_name="the calibration"
):
    """The map given by --map, or built for --save-map or a trust region (``limit``, the
    --max-error-px in effect; for the calibration's image size or the first input's), or
    None (built per input size while correcting)."""
    from oapcal.errors import DataError
    from oapcal.imaging.remap import correction_map
    from oapcal.io.maps import load_map
    from oapcal.io.maps import save_map as write_map

    if map_file:
        cmap = load_map(map_file, max_pixels=max_pixels)
    elif save_map or limit is not None:
        shape = None
        if cal.image_size:
            shape = _shape(cal.image_size)
            if shape[0] * shape[1] > max_pixels:
                raise DataError(
                    f"the calibration's image_size {shape[1]}x{shape[0]} is {shape[0] * shape[1]} px, "
                    f"more than --max-pixels {max_pixels}; its map would not fit in memory (raise "
                    "--max-pixels if the camera is really this large)"
                )
        elif files:
            from oapcal.errors import OapcalError
            from oapcal.io.images import probe

            try:
                shape = probe(files[0], max_pixels).frame_shape[:2]
            except (OapcalError, OSError):
                if save_map:
                    raise
                return None  # reported with that file; the trust region is then built per input size
        if shape is None:
            if not save_map:
                return None
            raise DataError(
                "--save-map needs the input image size: refit with 'oapcal fit --image-size WxH' "
                "or give an input image"
            )
        try:
            cmap = correction_map(cal, shape, **geometry, max_error_px=limit)
        except DataError as exc:  # e.g. no pixel trusted: the calibration's doing, name it
            if "predicted error" not in str(exc):
                raise
            raise DataError(f"{calib_name}: {exc}", param=exc.param) from None
    else:
        return None
    if save_map:
        write_map(cmap, save_map)
    return cmap


def _trust(
    cal, cmap, files, geometry, max_pixels, limit, border, calib_name="the calibration", seeds=None
) -> dict | None:
    """Say on stderr how far the output lies beyond the landmarks' hull and with what
    predicted error (:func:`trust_message`); the summary for --json, or None when the output
    size is unknown.  Refuses, naming the calibration, a trust region with no pixel in it.
    A predicted-error map it computes is put in ``seeds`` ``{(rows, cols): (geometry,
    predicted)}`` (for :func:`oapcal.batch.stack.correct_stack`'s ``predicted_errors``)."""
    from oapcal.errors import DataError
    from oapcal.imaging.remap import output_geometry, trust_summary

    hint = "leave --extent input out to write only the trust region"
    if cmap is not None:
        geo, predicted = cmap.geometry, cmap.predicted_error
        limit = cmap.max_error_px if cmap.max_error_px is not None else limit
        masked = cmap.predicted_error is not None
        if cmap.predicted_error is None:  # a --map file
            hint = "a map saved by 'oapcal correct --save-map' without --extent input holds the trust region"
    else:
        shape = _shape(cal.image_size) if cal.image_size else None
        if shape is None and files:
            from oapcal.errors import OapcalError
            from oapcal.io.images import probe

            try:
                shape = probe(files[0], max_pixels).frame_shape[:2]
            except (OapcalError, OSError):
                return None
        if shape is None:
            return None
        try:
            geo = output_geometry(cal, shape, **geometry, trust_region=limit is not None)
        except DataError:
            return None
        predicted, masked = None, limit is not None
        if masked:  # the trust region as correct_stack builds it, for the share written
            from oapcal.imaging.remap import predicted_error_map

            predicted = predicted_error_map(cal, geo)
            _refuse_empty_trust(predicted, limit, calib_name)
            if seeds is not None:
                seeds[tuple(shape)] = (geo, predicted)
    from oapcal.imaging.remap import DEFAULT_MAX_ERROR_PX

    summary = trust_summary(cal, geo, limit if limit is not None else DEFAULT_MAX_ERROR_PX, predicted)
    summary["masked"] = masked
    line = trust_message(summary, masked=masked, border=border, hint=hint)
    if line:
        click.echo(line, err=True)
    return summary


def _refuse_empty_trust(predicted, limit, calib_name) -> None:
    """One error naming the calibration, before any work, when (almost) no output pixel
    has a predicted error within ``limit``."""
    import numpy as np

    from oapcal.errors import DataError
    from oapcal.imaging.remap import MIN_SAMPLED_FRACTION

    finite = np.isfinite(predicted)
    if (finite & (predicted <= limit)).mean() >= MIN_SAMPLED_FRACTION:
        return
    if not finite.any():
        raise DataError(
            f"{calib_name}: its predicted error is not finite anywhere in the output (the covariance or "
            "the error model does not describe a fit): refit, or give --extent input to correct without "
            "a trust region"
        )
    raise DataError(
        f"{calib_name}: no output pixel (under {MIN_SAMPLED_FRACTION:.1%}) has a predicted error of "
        f"{limit:g} px or less (the smallest is {float(predicted[finite].min()):.3g} px): raise "
        "--max-error-px, or give --extent input to correct the whole output without a trust region"
    )


def _check_samples(cal, cmap, files, geometry, max_pixels, trust_region=False) -> None:
    """Refuse, before any work, a calibration (or --map) whose map samples no pixel of the
    images (:class:`~oapcal.imaging.remap.EmptyMapError`), for the calibration's image size
    or else the first input's; every other size is checked as its map is built.
    ``trust_region``: the output is written only where trusted (:func:`output_geometry`)."""
    from oapcal.imaging.remap import check_map_samples, check_model_samples, output_geometry

    shape = _shape(cal.image_size) if cal.image_size else None
    if cmap is not None:
        shape = cmap.input_shape or shape
    if shape is None and files:
        from oapcal.errors import OapcalError
        from oapcal.io.images import probe

        try:
            shape = probe(files[0], max_pixels).frame_shape[:2]
        except (OapcalError, OSError):  # reported with that file
            return
    if shape is None:
        return
    if cmap is not None:
        check_map_samples(cmap, shape)
        return
    from oapcal.errors import DataError

    try:
        geometry = output_geometry(cal, shape, **geometry, trust_region=trust_region)
    except DataError:  # a geometry refused for this size is reported with each file
        return
    check_model_samples(cal, shape, geometry)


def _finish(results, summary, n_failed, as_json, trust=None) -> int:
    """Report failures on stderr, the summary on stdout; exit 4 if any input failed.  With
    --json the object also holds ``trust`` (:func:`oapcal.imaging.remap.trust_summary`, and
    ``masked``: whether only the trust region was written)."""
    for r in results:
        if r["status"] == "failed":
            click.echo(f"oapcal: error: {r['message']}", err=True)
    if as_json:
        print_json({"results": results, "summary": summary, "failed": n_failed, "trust": trust})
    else:
        console().print(summary)
    return 4 if n_failed else 0


def _shape(image_size) -> tuple[int, int]:
    """``(rows, cols)`` of a calibration's ``(width, height)`` (:class:`oapcal.records.ImageSize`,
    imported here: loading the command imports no NumPy)."""
    from oapcal.records import ImageSize

    return ImageSize(*image_size).shape
