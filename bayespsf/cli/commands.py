"""The ``bayespsf`` command: one thin function per subcommand (its parsed arguments in, the
library called, a summary printed), ``main`` that runs the one ``args.command`` names, and the
helpers they share.

What the command accepts is in ``bayespsf.cli.parser``; ``build_parser`` is imported here so
that ``bayespsf.cli.commands.build_parser`` keeps working. Each subcommand imports the library
only when it runs, so that ``bayespsf --help`` loads no NumPy.
"""

from __future__ import annotations

import errno
import sys
from pathlib import Path

from bayespsf.cli._shared import (
    CommandError,
    as_flag,
    command_line,
    fit_report,
    geometry,
    movie_model,
    one_run,
    output_file,
    output_folder,
    selection_rules,
)
from bayespsf.cli.frames import per_frame
from bayespsf.cli.parser import build_parser
from bayespsf.errors import BayespsfInputError


def _scene_from(arg: str):
    """The scene ``arg`` names: a shipped scene's name or the path of a scene file."""
    from bayespsf import load_scene, shipped_scenes
    from bayespsf.scene import Scene

    if arg in shipped_scenes():
        return load_scene(arg)
    if not Path(arg).exists():
        raise CommandError(
            f"no scene file {arg!r} and no shipped scene of that name "
            f"(shipped: {', '.join(shipped_scenes())})"
        )
    return Scene.load(arg)


def _truth_table(path: str, n: int, unit: str):
    """The true parameters ``(n, 6)`` from a truth table that ``bayespsf simulate`` wrote;
    its N and b must be in ``unit`` (the model's ``photon_unit_label``) where it states one."""
    import numpy as np
    import pandas as pd

    from bayespsf.psf import PARAMETER_NAMES

    try:
        truth = pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise CommandError(f"--truth {path}: cannot read it as a CSV table ({exc})") from exc
    shape = (
        f"a table of shape ({n}, 6): one row per ROI in the stack's order, columns "
        f"{', '.join(PARAMETER_NAMES)}, each a finite number (the OUT.truth.csv of "
        "bayespsf simulate)"
    )
    missing = [name for name in PARAMETER_NAMES if name not in truth]
    if missing:
        raise CommandError(f"--truth {path}: no column(s) {', '.join(missing)}; expected {shape}")
    if len(truth) != n:
        raise CommandError(f"--truth {path}: {len(truth)} rows for {n} ROIs; expected {shape}")
    values = truth[list(PARAMETER_NAMES)].apply(pd.to_numeric, errors="coerce").astype(float)
    bad = ~np.isfinite(values.to_numpy())
    if bad.any():
        row, column = (int(i[0]) for i in np.nonzero(bad))
        name, value = PARAMETER_NAMES[column], truth[PARAMETER_NAMES[column]].iloc[row]
        value = repr(value) if isinstance(value, str) else "empty" if pd.isna(value) else value
        raise CommandError(
            f"--truth {path}: {name} in row {row} is {value}, not a finite number "
            f"({int(bad.sum())} such value(s)); expected {shape}"
        )
    stated = set(truth["photon_unit"]) if "photon_unit" in truth else {unit}
    if stated != {unit}:
        raise CommandError(
            f"--truth {path}: N and b in {', '.join(sorted(map(str, stated)))}, but the model's "
            f"are in {unit} (the scene's camera.photon_unit and quantum_efficiency)"
        )
    return values.to_numpy(float)


def _selfcheck(_args) -> int:
    """``bayespsf selfcheck``: the camera likelihoods of a typical EMCCD, checked and timed."""
    from bayespsf.cli import selfcheck

    print(selfcheck.run())
    return 0


def _simulate(args) -> int:
    """``bayespsf simulate``: images of a scene and their truth table (or, with ``--movie``,
    its movie)."""
    import numpy as np

    from bayespsf.simulation.pipeline import describe, scene_photon_label, simulate

    out = output_folder(args.out, stem=True)
    scene = _scene_from(args.scene)
    if args.movie:
        return _simulate_movie(args, scene, out)
    counts, truth = simulate(scene, 1000 if args.n is None else args.n, seed=args.seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.save(out.with_suffix(".npy"), counts)
    truth.assign(photon_unit=scene_photon_label(scene)).to_csv(
        out.with_suffix(".truth.csv"), index_label="image"
    )
    print(f"{scene!r}\n{describe(scene)}")
    print(
        f"wrote {counts.shape[0]} images to {out.with_suffix('.npy')} and the truth table to "
        f"{out.with_suffix('.truth.csv')}"
    )
    return 0


def _simulate_movie(args, scene, out) -> int:
    """``bayespsf simulate --movie``: the movie the scene's ``[movie]`` table declares."""
    from bayespsf.simulation.movie import simulate_movie

    if "movie" not in scene.to_dict():
        raise CommandError(
            f"--movie: the scene {args.scene} declares no [movie] table (the shipped "
            "paper-movie does; docs/scenes.md, 'Simulated movies')"
        )
    if args.n is not None:
        raise CommandError("-n does not apply with --movie (the scene's movie.frames sets it)")
    result = simulate_movie(scene, args.seed, out=out)
    m = scene.movie
    print(
        f"{scene!r}\nwrote {m['frames']} frames of {m['height']} x {m['width']} pixels with "
        f"{len(result.molecules)} molecules: "
        + ", ".join(str(path) for path in result.files.values())
    )
    return 0


def _schema(_args) -> int:
    """``bayespsf schema``: every scene key, as markdown tables."""
    from bayespsf.scene import schema_markdown

    print(schema_markdown())
    return 0


def _demo(args) -> int:
    """``bayespsf demo``: one molecule of paper-fig3, its posterior beside the theory."""
    from bayespsf.cli import demo

    _, _, text = demo.run(output_folder(args.out), seed=args.seed)
    print(text)
    return 0


def _bench(args) -> int:
    """``bayespsf bench``: the accuracy-time frontier of the likelihood tiers."""
    from bayespsf.cli import bench

    plan = bench.QUICK if args.quick else bench.FULL
    output_folder(args.out)
    rows = bench.frontier(plan, workers=args.workers)
    command = "bayespsf bench" + (" --quick" if args.quick else "")
    print(bench.report(rows, args.out, command))
    print(f"written to {args.out}/frontier.{{md,csv,png}}")
    return 0


def _fit(args) -> int:
    """``bayespsf fit``: the posterior of every ROI of a stack, and ``summary.csv``."""
    from bayespsf.io import camera_scene, read_camera_file, read_rois
    from bayespsf.model import Model
    from bayespsf.parallel.batch import sample_many

    out = output_folder(args.out)
    rois = read_rois(args.rois)
    if args.scene:
        scene = _scene_from(args.scene)
        if scene.geometry["roi"] != rois.shape[1]:
            raise CommandError(
                f"{args.rois}: ROIs of {rois.shape[1]} pixels, but the scene declares "
                f"{scene.geometry['roi']}"
            )
    else:
        scene = camera_scene(
            read_camera_file(args.camera),
            args.camera,
            rois.shape[1],
            roi_name=f"the side of the ROIs in {args.rois}",
        )
    model = Model.from_scene(scene, likelihood=args.likelihood)
    truths = None
    if args.truth is not None:
        truths = _truth_table(args.truth, rois.shape[0], model.photon_unit_label)
    table = sample_many(
        rois,
        model,
        seed=args.seed,
        executor=args.scheduler,
        workers=args.workers,
        store=out,
        truths=truths,
        scene=scene,
        ess=args.ess,
        method=args.method,
        max_seconds=args.max_seconds,
        check=args.check,
        backend=args.backend,
        keep_draws=not args.no_draws,
    )
    print(fit_report(table, out))
    return 0


def _detect(args) -> int:
    """``bayespsf detect``: a movie's molecules, their traces and the paper's selection."""
    from bayespsf.io.run_record import check_folder, read_copies
    from bayespsf.movie.found import SELECTION_FILES, write
    from bayespsf.movie.pipeline import find_molecules, selection_run
    from bayespsf.parallel import task_runner

    out = output_folder(args.out)
    movie, model, s0 = movie_model(args)
    roi, fit = geometry(args)
    if args.per_frame:
        return per_frame(args, out, movie, model, s0, fit)
    settings = dict(s0=s0, roi=roi, fit=fit, false_positives=args.false_positives)
    settings.update(projection=args.projection, rules=selection_rules(args))
    copies = {"camera.toml": args.camera}  # the camera file used, verbatim
    with one_run():  # refused before the work, as write would refuse it after it
        run = selection_run(movie, model, **settings)  # what write records: found.run
        check_folder(out, run, SELECTION_FILES, force=args.force, copies=read_copies(copies))
    with task_runner(args.scheduler, args.workers) as runner:
        found = find_molecules(movie, model, **settings, executor=runner)
    with one_run():
        paths = write(found, out, force=args.force, copies=copies, about={"movie": args.movie})
    selected = int(found.molecules["selected"].sum())
    print(f"{found.psf_width.summary()}" + (" (--psf-sd states it)" if s0 is None else ""))
    described = movie.describe(model.pixel_size)
    print(f"{described}: {len(found.molecules)} candidate molecules, {selected} selected")
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def _analyze(args) -> int:
    """``bayespsf analyze``: per-frame and per-molecule posteriors of a movie's molecules."""
    from bayespsf.analysis.pipeline import analyze
    from bayespsf.io import read_z_calibration

    if args.z_range is not None and args.z_calibration is None:
        raise CommandError("--z-range is the prior of z: it goes with --z-calibration")
    out = output_folder(args.out)
    movie, model, s0 = movie_model(args)
    roi, fit = geometry(args)
    if args.per_frame:
        return per_frame(args, out, movie, model, s0, fit)
    if args.no_draws:
        raise CommandError("--no-draws goes with --per-frame (the molecules' draws are kept)")
    rules = selection_rules(args)
    command = command_line(args)
    camera_text = Path(args.camera).read_text(encoding="utf-8")
    z_calibration = None
    if args.z_calibration is not None:
        z_calibration = read_z_calibration(args.z_calibration)
    with one_run():  # a folder of another run is refused before anything is written
        result = analyze(
            movie,
            model,
            s0=s0,
            out=out,
            roi=roi,
            fit=fit,
            rules=rules,
            method=args.method,
            backend=args.backend,
            ess=args.ess,
            max_seconds=args.max_seconds,
            seed=args.seed,
            workers=args.workers,
            executor=args.scheduler,
            provenance={"command": command, "camera file": camera_text},
            z_calibration=z_calibration,
            copies={"camera.toml": args.camera},  # the camera file used, verbatim
            gof_discrepancy=args.gof_discrepancy,
            force=args.force,
            **({} if args.z_range is None else {"z_range": tuple(args.z_range)}),
        )
    check = result.consistency.set_index("parameter")
    z_sd, z_sd_se = check.loc["s_x", "z_sd"], check.loc["s_x", "z_sd_se"]
    spread = (
        f"z-score SD of s_x {z_sd:.3g} +- {z_sd_se:.2g} (1 when the model holds)"
        if z_sd == z_sd  # NaN where no molecule has two analysed frames to compare
        else "no z-score SD of s_x (it needs molecules with two or more analysed frames)"
    )
    print(f"{result.found.psf_width.summary()}" + (" (--psf-sd states it)" if s0 is None else ""))
    print(
        f"{movie.describe(model.pixel_size)}: {int(result.molecules['selected'].sum())} molecules "
        "selected, "
        f"{len(result.frames)} frames analysed; {spread}"
    )
    print("wrote " + ", ".join(str(p) for p in result.paths.values()))
    return 0


def _calibrate_z(args) -> int:
    """``bayespsf calibrate-z``: defocus curves from a bead z-stack, as a calibration file."""
    from bayespsf.axial.calibrate import bead_rois, calibrate, step_widths
    from bayespsf.io import write_z_calibration
    from bayespsf.simulation.zstack import zstack_positions

    out = output_file(args.out, args.force, "z-calibration.toml", "calibration file")
    if args.frames_per_step < 1:
        raise CommandError(f"--frames-per-step must be >= 1, got {args.frames_per_step}")
    movie, model, s0 = movie_model(args)
    roi, fit = geometry(args)
    steps, extra = divmod(len(movie), args.frames_per_step)
    if steps == 0 or extra:
        raise CommandError(
            f"the stack has {len(movie)} frames, not a whole number of steps of "
            f"--frames-per-step {args.frames_per_step}"
        )
    z = zstack_positions(args.z_start, args.z_step, steps, args.frames_per_step)
    pick = None if args.bead is None else tuple(args.bead)
    rois, bead = bead_rois(movie, model, s0=s0, fit=fit, roi=roi, bead=pick)
    widths = step_widths(rois, z, model, seed=args.seed, workers=args.workers)
    command = command_line(args)
    source = {
        "command": command,
        "stack": str(args.movie),
        "camera file": Path(args.camera).read_text(encoding="utf-8"),
        "bead x": float(bead["x"].iloc[0]),
        "bead y": float(bead["y"].iloc[0]),
        "beads found": int(bead["beads"].iloc[0]),
    }
    calibration = calibrate(
        widths, args.curve, higher_order=not args.no_higher_order, source=source
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    write_z_calibration(calibration, out)
    fits = calibration.fits
    for axis in ("x", "y"):
        row = fits.loc[axis]
        print(
            f"{axis}: w0 {row['w0']:.1f} +- {row['w0_sd']:.1f} nm, focus {row['c']:.0f} +- "
            f"{row['c_sd']:.0f} nm, depth {row['d']:.0f} +- {row['d_sd']:.0f} nm; chi2 "
            f"{row['chi2']:.1f} on {int(row['dof'])} dof (p = {row['p']:.2g})"
        )
    for problem in calibration.problems:
        print(f"warning: {problem}")
    beads = source["beads found"]
    print(
        f"bead at x {source['bead x']:.1f}, y {source['bead y']:.1f} (pixels)"
        + (f", the brightest of {beads} beads found" if beads > 1 and pick is None else "")
        + (f", of {beads} beads found" if beads > 1 and pick is not None else "")
    )
    print(f"wrote {out}")
    return 0


def _calibrate(args) -> int:
    """``bayespsf calibrate``: a camera file from a movie (and dark frames, if any)."""
    from bayespsf.calibration.camera import calibrate_camera
    from bayespsf.movie import read_movie
    from bayespsf.movie.psf_width import resolve_psf_sd  # the spot's SD, stated or estimated

    out = output_file(args.out, args.force, "camera.toml", "camera file")
    roi, fit = geometry(args)
    movie = read_movie(args.movie, channel=args.channel)
    dark = None if args.dark is None else _dark_frames(args.dark, args.channel)
    width = resolve_psf_sd(movie, None, args.psf_sd, pixel_size=args.pixel_size, fit=fit)
    print(width.summary() + (" (--psf-sd states it)" if args.psf_sd is None else ""))
    calibration = calibrate_camera(
        movie,
        dark,
        kind=args.kind,
        s0=width,
        pixel_size=args.pixel_size,
        e_per_adu=args.e_per_adu,
        roi=roi,
        fit=fit,
        quantum_efficiency=args.quantum_efficiency,
        readout_sd=args.readout_sd,
        rules=selection_rules(args),
    )
    command = command_line(args)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(calibration.toml(command))
    print(calibration.summary())
    print(f"wrote {out}")
    return 0


def _dark_frames(path: str, channel: int | None):
    """The dark frames: the movie's ``--channel`` where the file has several channels, the
    one channel where it has one."""
    from bayespsf.movie.read import ChannelsError, read_movie

    try:
        return read_movie(path)
    except ChannelsError:  # any other problem of the file is its own, reported as such
        if channel is None:
            raise
        return read_movie(path, channel=channel)


COMMANDS = {
    "selfcheck": _selfcheck,
    "simulate": _simulate,
    "schema": _schema,
    "demo": _demo,
    "bench": _bench,
    "fit": _fit,
    "detect": _detect,
    "analyze": _analyze,
    "calibrate-z": _calibrate_z,
    "calibrate": _calibrate,
}  # each subcommand of build_parser() and the function that runs it


def main(argv: list[str] | None = None) -> int:
    """Run the ``bayespsf`` command.

    Parameters
    ----------
    argv : list of str, optional
        The arguments, the subcommand first (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit status: 0, or 130 when interrupted. Bad input (``CommandError`` or
        ``bayespsf.errors.BayespsfInputError``), a file that cannot be read or written (an
        ``OSError``: a read-only or full disk, a path through a file) and input too large for
        the machine's memory end the command with one line ``bayespsf: ...`` (``SystemExit``,
        exit status 1).
    """
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the subcommand's usage and a close flag, not the top level's usage
        _refuse_unknown(parser.subcommands[args.command], unknown)
    args.argv = None if argv is None else list(argv)[1:]
    try:
        if getattr(args, "scheduler", None) and getattr(args, "workers", None) is not None:
            raise CommandError(
                "give --workers (local processes) or --scheduler (a Dask cluster, whose "
                "workers run the tasks), not both"
            )
        return COMMANDS[args.command](args)
    except (CommandError, BayespsfInputError) as exc:  # a function's name as the flag
        usage = parser.subcommands[args.command].format_usage()  # its flags, not its prose
        raise SystemExit(f"bayespsf: {as_flag(str(exc), usage)}") from None
    except OSError as exc:  # a file's or a disk's trouble (not a network's): no traceback
        if exc.filename is None and exc.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
            raise
        raise SystemExit(
            f"bayespsf: {exc.filename or 'a file'}: {exc.strerror or exc} (the disk, its "
            "permissions or the path; for an output, give --out a folder that can be written)"
        ) from None
    except MemoryError as exc:
        raise SystemExit(
            f"bayespsf: out of memory ({str(exc) or 'an allocation failed'}): the input or the "
            "output asked for is larger than this machine's memory"
        ) from None
    except KeyboardInterrupt:
        print("bayespsf: interrupted", file=sys.stderr)
        return 130


def _refuse_unknown(subparser, unknown: list[str]) -> None:
    """End with the subcommand's usage, naming the arguments it does not take and, for a
    flag, the nearest of its own (``--pixel_size``: ``--pixel-size``)."""
    import difflib
    import re

    flags = sorted(set(re.findall(r"--[a-z][a-z0-9-]*", subparser.format_help())))
    hints = []
    for word in unknown:
        if word.startswith("-"):
            close = difflib.get_close_matches(word.split("=")[0], flags, n=1, cutoff=0.6)
            if close:
                hints.append(f"{word}: did you mean {close[0]}?")
    subparser.error(
        f"unrecognized arguments: {' '.join(unknown)}" + ("; " + "; ".join(hints) if hints else "")
    )


__all__ = ["CommandError", "build_parser", "main"]

if __name__ == "__main__":
    sys.exit(main())
