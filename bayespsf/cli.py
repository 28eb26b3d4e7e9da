"""The ``bayespsf`` command."""

from __future__ import annotations

import argparse
import sys


class CommandError(Exception):
    """A problem the command reports as one line, ``bayespsf: ...``, with exit status 1."""


def _output_folder(path: str, option: str = "--out", stem: bool = False):
    """``path`` as a folder to write into (or, with ``stem``, a path stem whose folder is
    made): no file may stand at it or at any of its parents."""
    from pathlib import Path

    out = Path(path)
    if stem and out.is_dir():
        raise CommandError(f"{option} {out} is a folder; give a path stem such as {out}/sim")
    for place in out.parents if stem else (out, *out.parents):
        if place.exists() and not place.is_dir():
            what = "is" if place == out else f"lies under {place}, which is"
            raise CommandError(f"{option} {out} {what} a file, not a folder")
    return out


def _selfcheck(_args) -> int:
    from bayespsf import selfcheck

    print(selfcheck.run())
    return 0


def _scene_from(arg: str):
    from pathlib import Path

    from bayespsf import scenes
    from bayespsf.scene import Scene

    if arg in scenes.names():
        return scenes.load(arg)
    if not Path(arg).exists():
        raise CommandError(
            f"no scene file {arg!r} and no shipped scene of that name "
            f"(shipped: {', '.join(scenes.names())})"
        )
    return Scene.load(arg)


def _simulate(args) -> int:
    import numpy as np

    from bayespsf.simulator import describe, scene_photon_label, simulate

    out = _output_folder(args.out, stem=True)
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
    from bayespsf.movie.simulate import simulate_movie

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


def _demo(args) -> int:
    from bayespsf import demo

    _, _, text = demo.run(_output_folder(args.out), seed=args.seed)
    print(text)
    return 0


def _bench(args) -> int:
    from bayespsf import bench

    plan = bench.QUICK if args.quick else bench.FULL
    _output_folder(args.out)
    rows = bench.frontier(plan, workers=args.workers)
    command = "bayespsf bench" + (" --quick" if args.quick else "")
    print(bench.report(rows, args.out, command))
    print(f"written to {args.out}/frontier.{{md,csv,png}}")
    return 0


CAMERA_KEYS = {  # what a camera file must state for its kind: the counts' units depend on it
    "photon": (),
    "emccd": ("gain", "offset", "readout_sd", "e_per_adu"),
    "scmos": ("gain", "offset", "variance"),
}


def _camera_file(camera_file: str) -> dict:
    """The tables of a camera file (``[camera]`` with an explicit ``kind`` and, for that kind,
    every key of ``CAMERA_KEYS``; ``[geometry] pixel_size``, ``[emitter]``, ``[prior]``
    optional). A missing camera table, kind or key is an error: the counts' units depend on
    them, so they are never assumed (a default gain would scale every posterior SD)."""
    import tomllib
    from pathlib import Path

    try:
        table = tomllib.loads(Path(camera_file).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise CommandError(f"{camera_file}: cannot read it as a camera file ({exc})") from exc
    camera = table.get("camera")
    if not isinstance(camera, dict) or "kind" not in camera:
        raise CommandError(
            f"{camera_file}: no [camera] table with its kind ('emccd', 'scmos' or 'photon', "
            "and the gain, offset and readout noise of the counts); the counts' units depend "
            "on it, so it is never assumed"
        )
    missing = [k for k in CAMERA_KEYS.get(camera["kind"], ()) if k not in camera]
    if missing:
        raise CommandError(
            f"{camera_file}: [camera] of kind {camera['kind']!r} must state "
            f"{', '.join(missing)} (a `bayespsf calibrate` camera file states them all)"
        )
    for section in ("geometry", "emitter", "prior"):
        if not isinstance(table.get(section, {}), dict):
            raise CommandError(f"{camera_file}: [{section}] must be a table")
    return table


def _camera_scene(table: dict, camera_file: str, roi: int, pixel_size: float | None = None):
    """The scene of a camera file's tables (``_camera_file``) for ROIs of side ``roi``;
    ``pixel_size`` (a movie's metadata) stands in where the file gives none."""
    from bayespsf.scene import Scene

    table = {**table, "geometry": dict(table.get("geometry", {}))}
    geometry = table["geometry"]
    if "pixel_size" not in geometry and pixel_size is not None:
        geometry["pixel_size"] = pixel_size
    if "pixel_size" not in geometry:
        raise CommandError(f"{camera_file}: no [geometry] pixel_size (nm)")
    geometry["roi"] = roi
    return Scene.from_dict(table)


def _truth_table(path: str, n: int, unit: str):
    """The true parameters ``(n, 6)`` from a truth table that ``bayespsf simulate`` wrote;
    its N and b must be in ``unit`` (the model's ``photon_unit_label``) where it states one."""
    import pandas as pd

    from bayespsf.psf import PARAMETER_NAMES

    try:
        truth = pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise CommandError(f"--truth {path}: cannot read it as a CSV table ({exc})") from exc
    missing = [name for name in PARAMETER_NAMES if name not in truth]
    if missing:
        raise CommandError(f"--truth {path}: no column(s) {', '.join(missing)}")
    if len(truth) != n:
        raise CommandError(f"--truth {path}: {len(truth)} rows for {n} ROIs")
    stated = set(truth["photon_unit"]) if "photon_unit" in truth else {unit}
    if stated != {unit}:
        raise CommandError(
            f"--truth {path}: N and b in {', '.join(sorted(map(str, stated)))}, but the model's "
            f"are in {unit} (the scene's camera.photon_unit and quantum_efficiency)"
        )
    return truth[list(PARAMETER_NAMES)].to_numpy(float)


def _fit(args) -> int:
    from bayespsf.batch import sample_many
    from bayespsf.io import read_rois
    from bayespsf.model import Model

    out = _output_folder(args.out)
    rois = read_rois(args.rois)
    if args.scene:
        scene = _scene_from(args.scene)
        if scene.geometry["roi"] != rois.shape[1]:
            raise CommandError(
                f"{args.rois}: ROIs of {rois.shape[1]} pixels, but the scene declares "
                f"{scene.geometry['roi']}"
            )
    else:
        scene = _camera_scene(_camera_file(args.camera), args.camera, rois.shape[1])
    model = Model.from_scene(scene, likelihood=args.likelihood)
    truths = None
    if args.truth is not None:
        truths = _truth_table(args.truth, rois.shape[0], model.photon_unit_label)
    table = sample_many(
        rois,
        model,
        seed=args.seed,
        executor=args.scheduler,
        workers=None if args.scheduler else args.workers,
        store=out,
        truths=truths,
        scene=scene,
        ess=args.ess,
        method=args.method,
        max_seconds=args.max_seconds,
        check=args.check,
    )
    for _, row in table.iterrows():
        if row["status"] in ("refused", "failed"):
            print(f"ROI {row['molecule']}: {row['status']}: {row['message']}")
            continue
        print(
            f"ROI {row['molecule']} ({row['method']}): converged {row['converged']}, "
            f"s_x = {row['s_x_mean']:.4g} +- {row['s_x_sd']:.3g} nm"
        )
    print(f"wrote {out / 'summary.csv'} and {len(table)} result files")
    return 0


def _movie_model(args):
    """The movie, the camera file's model and the spot's SD of ``detect`` and ``analyze``."""
    from bayespsf.model import Model
    from bayespsf.movie import read_movie
    from bayespsf.movie.extract import check_sizes

    check_sizes(args.roi, args.fit)
    movie = read_movie(args.movie)
    table = _camera_file(args.camera)
    scene = _camera_scene(table, args.camera, args.fit, movie.pixel_size)
    emitter = scene.to_dict().get("emitter", {})
    s0 = args.psf_sd
    if s0 is None and {"s0x", "s0y"} <= set(table.get("emitter", {})):
        s0 = 0.5 * (emitter["s0x"] + emitter["s0y"])
    if s0 is None:
        raise CommandError(
            f"give --psf-sd (the spot's SD in nm), or [emitter] s0x and s0y in {args.camera}"
        )
    return movie, Model.from_scene(scene), s0


def _copy_camera_file(args, out):
    """The camera file used, verbatim, into the output folder."""
    from pathlib import Path

    path = out / "camera.toml"
    path.write_text(Path(args.camera).read_text(encoding="utf-8"))
    return path


def _detect(args) -> int:
    from bayespsf.movie.pipeline import find_molecules, write

    out = _output_folder(args.out)
    movie, model, s0 = _movie_model(args)
    found = find_molecules(movie, model, s0=s0, roi=args.roi, fit=args.fit,
                           false_positives=args.false_positives,
                           projection=args.projection)  # fmt: skip
    paths = write(found, out)
    paths["camera.toml"] = _copy_camera_file(args, out)
    selected = int(found.molecules["selected"].sum())
    print(f"{movie!r}: {len(found.molecules)} candidate molecules, {selected} selected")
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def _analyze(args) -> int:
    from bayespsf.analysis.pipeline import analyze
    from bayespsf.movie.select import Rules

    out = _output_folder(args.out)
    movie, model, s0 = _movie_model(args)
    settings = {} if args.min_valid_frames is None else {"min_valid_frames": args.min_valid_frames}
    rules = Rules(**settings, skip=tuple(args.skip_rule))
    command = "bayespsf analyze " + " ".join(sys.argv[2:] if args.argv is None else args.argv)
    out.mkdir(parents=True, exist_ok=True)
    camera_path = _copy_camera_file(args, out)
    z_calibration = None
    if args.z_calibration is not None:
        from bayespsf.axial.calibration_file import load_calibration

        z_calibration = load_calibration(args.z_calibration)
    result = analyze(
        movie, model, s0=s0, out=out, roi=args.roi, fit=args.fit, rules=rules,
        method=args.method, ess=args.ess, seed=args.seed,
        workers=None if args.scheduler else args.workers, executor=args.scheduler,
        provenance={"command": command, "camera file": camera_path.read_text()},
        z_calibration=z_calibration, z_range=tuple(args.z_range),
        files={"camera.toml": camera_path}, gof_discrepancy=args.gof_discrepancy,
    )  # fmt: skip
    check = result.consistency.set_index("parameter")
    print(
        f"{movie!r}: {int(result.molecules['selected'].sum())} molecules selected, "
        f"{len(result.frames)} frames analysed; z-score SD of s_x "
        f"{check.loc['s_x', 'z_sd']:.3g} +- {check.loc['s_x', 'z_sd_se']:.2g} (1 when the "
        "model holds)"
    )
    print("wrote " + ", ".join(str(p) for p in result.paths.values()))
    return 0


def _calibrate_z(args) -> int:
    from pathlib import Path

    from bayespsf.axial.calibrate import bead_rois, calibrate, step_widths, zstack_positions
    from bayespsf.axial.calibration_file import save_calibration

    out = Path(args.out)
    if out.is_dir():
        raise CommandError(f"--out {out} is a folder; give the calibration file's name")
    if args.frames_per_step < 1:
        raise CommandError(f"--frames-per-step must be >= 1, got {args.frames_per_step}")
    movie, model, s0 = _movie_model(args)
    steps, extra = divmod(len(movie), args.frames_per_step)
    if steps == 0 or extra:
        raise CommandError(
            f"the stack has {len(movie)} frames, not a whole number of steps of "
            f"--frames-per-step {args.frames_per_step}"
        )
    z = zstack_positions(args.z_start, args.z_step, steps, args.frames_per_step)
    rois, bead = bead_rois(movie, model, s0=s0, fit=args.fit, roi=args.roi)
    widths = step_widths(rois, z, model, seed=args.seed, workers=args.workers)
    command = "bayespsf calibrate-z " + " ".join(sys.argv[2:] if args.argv is None else args.argv)
    source = {"command": command, "stack": str(args.movie), "camera file": Path(args.camera)
              .read_text(encoding="utf-8"), "bead x": float(bead["x"].iloc[0]),
              "bead y": float(bead["y"].iloc[0])}  # fmt: skip
    calibration = calibrate(widths, args.curve, higher_order=not args.no_higher_order,
                            source=source)  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(calibration, out)
    fits = calibration.fits
    for axis in ("x", "y"):
        row = fits.loc[axis]
        print(f"{axis}: w0 {row['w0']:.1f} +- {row['w0_sd']:.1f} nm, focus {row['c']:.0f} +- "
              f"{row['c_sd']:.0f} nm, depth {row['d']:.0f} +- {row['d_sd']:.0f} nm; chi2 "
              f"{row['chi2']:.1f} on {int(row['dof'])} dof (p = {row['p']:.2g})")  # fmt: skip
    for problem in calibration.problems:
        print(f"warning: {problem}")
    print(f"wrote {out}")
    return 0


def _calibrate(args) -> int:
    from pathlib import Path

    from bayespsf.movie.camera_file import calibrate_camera

    out = Path(args.out)
    if out.is_dir():
        raise CommandError(f"--out {out} is a folder; give the camera file's name")
    _output_folder(str(out.parent))
    calibration = calibrate_camera(
        args.movie, args.dark, kind=args.kind, s0=args.psf_sd, pixel_size=args.pixel_size,
        e_per_adu=args.e_per_adu, roi=args.roi, fit=args.fit,
        quantum_efficiency=args.quantum_efficiency, readout_sd=args.readout_sd,
    )  # fmt: skip
    command = "bayespsf calibrate " + " ".join(sys.argv[2:] if args.argv is None else args.argv)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(calibration.toml(command))
    print(calibration.gain)
    print(f"wrote {out}")
    return 0


def _schema(_args) -> int:
    from bayespsf.scene import schema_markdown

    print(schema_markdown())
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bayespsf",
        description="Bayesian analysis of single fluorescent molecule images.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    check = commands.add_parser(
        "selfcheck",
        help="check the camera likelihoods of a typical EMCCD and time each tier",
        description="Integrate the exact EMCCD law (normalisation, mean, variance), compare "
        "every likelihood tier with it and time each tier relative to the Poisson tier.",
    )
    check.set_defaults(run=_selfcheck)
    sim = commands.add_parser(
        "simulate",
        help="simulate images of a shipped scene or a scene file",
        description="Simulate N images of a scene (a shipped scene name or a TOML file): "
        "writes OUT.npy (counts in ADU, shape (n, roi, roi)) and OUT.truth.csv. With --movie, "
        "the movie the scene's [movie] table declares: OUT.ome.tif, OUT.molecules.csv, "
        "OUT.truth.csv (one row per molecule and frame) and OUT.dark.ome.tif if it declares "
        "dark frames.",
    )
    sim.add_argument("scene", help="shipped scene name (e.g. paper-fig3) or path to a .toml")
    sim.add_argument("-n", type=int, default=None, help="number of images (default 1000)")
    sim.add_argument(
        "--movie", action="store_true", help="simulate the scene's movie (its [movie] table)"
    )
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--out", default="simulated", help="output path stem (default: simulated)")
    sim.set_defaults(run=_simulate)
    schema = commands.add_parser(
        "schema",
        help="print every scene key (the tables of docs/scenes.md)",
        description="Print the scene schema as markdown tables: key, default, unit, allowed "
        "range and meaning.",
    )
    schema.set_defaults(run=_schema)
    demo = commands.add_parser(
        "demo",
        help="one molecule of the paper's Fig. 3 scene: its posterior beside the theory",
        description="Simulate one molecule from the shipped paper-fig3 scene, sample its "
        "posterior, print each parameter's posterior SD beside the CRLB and the least-squares "
        "estimate (and Eq. sigma2dp3 and the pixel sum for s_x); write the corner plot and the "
        "result file.",
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument(
        "--out", default="bayespsf-demo", help="output folder (default bayespsf-demo)"
    )
    demo.set_defaults(run=_demo)
    bench = commands.add_parser(
        "bench",
        help="what accuracy costs in time: every likelihood tier at several ESS targets",
        description="The accuracy-time frontier: for molecules of the emccd-typical scene at "
        "low, medium and high N, every EMCCD likelihood tier at ESS targets 100-4000 and the "
        "MLE + CRLB and Laplace ends: time per molecule as a ratio to one MLE fit, error of "
        "the posterior SD of s_x against a long exact-law reference, and 68%/95% coverage. "
        "--quick: two molecules, under two minutes.",
    )
    bench.add_argument("--quick", action="store_true", help="a small run (< 2 minutes)")
    bench.add_argument("--workers", type=int, default=None, help="local processes (default: cores)")
    bench.add_argument(
        "--out", default="bayespsf-bench", help="output folder (default bayespsf-bench)"
    )
    bench.set_defaults(run=_bench)
    fit = commands.add_parser(
        "fit",
        help="posterior of every ROI of a stack (.npy or .tif)",
        description="Sample the posterior of every ROI in ROIS (a .npy or .tif stack of "
        "square, odd-sized ROIs in ADU) on local processes or a Dask cluster: one NetCDF "
        "result file per ROI and summary.csv (posterior mean, SD, quantiles of the central "
        "50/68/90/95% intervals, tau and ESS per parameter; with --truth, the truth and its "
        "SBC rank). Rerun with the same --out to resume a killed run; a progress bar is shown "
        "when stderr is a terminal.",
    )
    fit.add_argument("rois", help="ROI stack: .npy or .tif, shape (n, roi, roi)")
    source = fit.add_mutually_exclusive_group(required=True)
    source.add_argument("--scene", help="shipped scene name or scene .toml")
    source.add_argument(
        "--camera", help="TOML with [camera] and [geometry] pixel_size (and optional [prior])"
    )
    fit.add_argument(
        "--truth",
        default=None,
        help="truth table of simulated ROIs (the OUT.truth.csv of bayespsf simulate): adds "
        "truth and rank columns to summary.csv",
    )
    fit.add_argument("--likelihood", default=None, help="likelihood tier (default: the scene's)")
    fit.add_argument("--ess", type=float, default=400.0, help="ESS per parameter (default 400)")
    fit.add_argument(
        "--max-seconds",
        type=float,
        default=None,
        help="wall-clock budget of each ROI's chain (default: none); a ROI that exhausts it "
        "is reported not converged",
    )
    fit.add_argument(
        "--method",
        choices=("auto", "mcmc", "importance", "laplace"),
        default="auto",
        help="auto (default): per ROI the Laplace where a pilot shows it accurate, else "
        "importance sampling (PSIS) where its k-hat <= 0.7, else emcee; mcmc: emcee for "
        "every ROI; importance; laplace (no check)",
    )
    fit.add_argument(
        "--seed", type=int, default=0, help="run seed (ROI k uses molecule_seed(seed, k))"
    )
    fit.add_argument(
        "--check", action="store_true",
        help="also test whether the model can have made each ROI (a parametric-bootstrap "
        "goodness-of-fit p-value, gof_p, in each row and result file; about doubles the time)",
    )  # fmt: skip
    fit.add_argument("--workers", type=int, default=None, help="local processes (default: cores)")
    fit.add_argument("--scheduler", default=None, help="a Dask scheduler address (a cluster)")
    fit.add_argument("--out", default="bayespsf-fit", help="output folder (default bayespsf-fit)")
    fit.set_defaults(run=_fit)
    detect = commands.add_parser(
        "detect",
        help="molecules of a movie: detection, traces, bleaching steps, the paper's selection",
        description="Find the immobile molecules of MOVIE (TIFF, OME-TIFF, ImageJ, .npy): "
        "detection on the mean projection with a stated false-positive rate, each molecule's "
        "trace, bleaching steps and drift, a fit of each frame before bleaching, and the "
        "selection rules of DeSantis et al., Opt. Express 18 (2010). Writes candidates.csv, "
        "molecules.csv, frames.csv and selection.md into --out.",
    )
    detect.add_argument("movie", help="the movie: .tif/.tiff/.ome.tif or .npy")
    detect.add_argument(
        "--camera", required=True,
        help="TOML with [camera] (kind, gain, offset, readout) and [geometry] pixel_size "
        "(nm; optional when the movie's metadata give it), optionally [emitter] s0x, s0y",
    )  # fmt: skip
    detect.add_argument("--psf-sd", type=float, default=None, help="the spot's SD in nm")
    detect.add_argument("--roi", type=int, default=25, help="ROI cut (default 25, the paper's)")
    detect.add_argument("--fit", type=int, default=15, help="fitted centre (default 15)")
    detect.add_argument(
        "--false-positives", type=float, default=0.01,
        help="expected false detections per projected image (default 0.01)",
    )  # fmt: skip
    detect.add_argument("--projection", choices=("mean", "median"), default="mean")
    detect.add_argument("--out", default="bayespsf-detect", help="output folder")
    detect.set_defaults(run=_detect)
    analyze = commands.add_parser(
        "analyze",
        help="per-molecule posteriors of a movie, and the files SMLM tools open",
        description="The molecules `bayespsf detect` selects, then a posterior, the MLE and "
        "the paper's least squares for every valid frame (DeSantis et al., Opt. Express 18 "
        "(2010)); the calibration check without ground truth; the paper's Delta s per "
        "molecule; each molecule's joint posterior over its frames; a goodness-of-fit p-value "
        "per frame. Writes into --out: locs.hdf5 + locs.yaml (picasso), locs.csv "
        "(ThunderSTORM), locs.parquet, molecules.csv, consistency.csv, width_spread.csv, "
        "width_by_window.csv, report.md with its figures, the selection's tables and "
        "posteriors/ (a rerun continues there).",
    )
    analyze.add_argument("movie", help="the movie: .tif/.tiff/.ome.tif or .npy")
    analyze.add_argument("--camera", required=True, help="the camera file (as for detect)")
    analyze.add_argument("--psf-sd", type=float, default=None, help="the spot's SD in nm")
    analyze.add_argument("--roi", type=int, default=25, help="ROI cut (default 25)")
    analyze.add_argument("--fit", type=int, default=15, help="fitted centre (default 15)")
    analyze.add_argument(
        "--min-valid-frames", type=int, default=None,
        help="valid frames a molecule needs (default 75, the paper's)",
    )  # fmt: skip
    analyze.add_argument(
        "--skip-rule", action="append", default=[], metavar="RULE",
        help="switch off one of the paper's selection rules by its name in selection.md "
        "(repeatable); an astigmatic movie needs equal_widths and width_range off",
    )  # fmt: skip
    analyze.add_argument(
        "--method", choices=("auto", "mcmc", "importance", "laplace"), default="auto",
        help="posterior method (default auto: the batched engine, emcee where it fails)",
    )  # fmt: skip
    analyze.add_argument("--ess", type=float, default=None, help="effective draws per ROI")
    analyze.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    analyze.add_argument("--workers", type=int, default=None, help="local processes")
    analyze.add_argument("--scheduler", default=None, help="a Dask scheduler address")
    analyze.add_argument(
        "--z-calibration", default=None,
        help="a z calibration file (bayespsf.axial.calibration_file): every frame also gets "
        "the posterior of its axial position z, in the tables as picasso's z and lpz (nm)",
    )  # fmt: skip
    analyze.add_argument(
        "--z-range", type=float, nargs=2, default=(-800.0, 800.0), metavar=("LOW", "HIGH"),
        help="support of z's uniform prior in nm (default -800 800)",
    )  # fmt: skip
    analyze.add_argument(
        "--gof-discrepancy", choices=("likelihood", "pearson"), default="likelihood",
        help="the goodness-of-fit test's discrepancy (default likelihood; pearson is calibrated "
        "at a background of a few photons per pixel, where likelihood is conservative)",
    )  # fmt: skip
    analyze.add_argument("--out", default="bayespsf-analyze", help="output folder")
    analyze.set_defaults(run=_analyze)
    calibrate_z = commands.add_parser(
        "calibrate-z",
        help="defocus curves (a z calibration file) from a bead z-stack",
        description="The brightest bead of STACK (frames at stage positions --z-start, "
        "--z-start + --z-step, ..., --frames-per-step frames each): each step's widths as the "
        "joint posterior over its frames, then per axis a defocus curve (Huang et al., Science "
        "319 (2008), or its polynomial alternative) by weighted least squares, with a "
        "chi-square test that warns where the curve does not fit the stack. Writes the "
        "calibration file (TOML) that `bayespsf analyze --z-calibration` reads.",
    )
    calibrate_z.add_argument("movie", metavar="STACK", help="the z-stack: .tif/.ome.tif or .npy")
    calibrate_z.add_argument("--camera", required=True, help="the camera file (as for detect)")
    calibrate_z.add_argument(
        "--psf-sd", type=float, default=None,
        help="the bead's in-focus SD in nm (the detector's template)",
    )  # fmt: skip
    calibrate_z.add_argument("--z-start", type=float, required=True, help="first step's z, nm")
    calibrate_z.add_argument("--z-step", type=float, required=True, help="z per step, nm")
    calibrate_z.add_argument("--frames-per-step", type=int, required=True,
                             help="frames at each step")  # fmt: skip
    calibrate_z.add_argument("--curve", choices=("huang", "polynomial"), default="huang")
    calibrate_z.add_argument("--no-higher-order", action="store_true",
                             help="hold A = B = 0 (three terms per axis)")  # fmt: skip
    calibrate_z.add_argument("--roi", type=int, default=25, help="ROI cut (default 25)")
    calibrate_z.add_argument("--fit", type=int, default=15, help="fitted centre (default 15)")
    calibrate_z.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    calibrate_z.add_argument("--workers", type=int, default=None, help="local processes")
    calibrate_z.add_argument("--out", default="z-calibration.toml", help="the file to write")
    calibrate_z.set_defaults(run=_calibrate_z)
    calibrate = commands.add_parser(
        "calibrate",
        help="a camera file from a movie of immobile molecules (and dark frames, if any)",
        description="Offset and readout noise from DARK (frames without light) or, without "
        "it, from the movie's background pixels (photon transfer with their third cumulant), "
        "then the ADU "
        "per photon by Eq. photonConv of DeSantis et al., Opt. Express 18 (2010) over the "
        "movie's selected immobile molecules (as `bayespsf detect` finds them), combined with "
        "a 95% interval. Writes a camera file (TOML) for --camera, its provenance in comments.",
    )
    calibrate.add_argument("movie", help="the movie: .tif/.tiff/.ome.tif or .npy")
    calibrate.add_argument(
        "--dark",
        default=None,
        help="dark frames of the same camera (default: none; the offset and readout noise "
        "then come from the movie's background pixels, which must hold Poisson photons)",
    )
    calibrate.add_argument(
        "--kind",
        choices=("emccd", "scmos"),
        default="emccd",
        help="emccd (excess noise 2) or scmos, also a CCD (excess 1)",
    )
    calibrate.add_argument("--psf-sd", type=float, required=True, help="the spot's SD in nm")
    calibrate.add_argument(
        "--pixel-size", type=float, default=None, help="nm (default: the movie's metadata)"
    )
    calibrate.add_argument(
        "--e-per-adu",
        type=float,
        default=1.0,
        help="EMCCD electrons per ADU to state (default 1: the gain is then ADU per photon)",
    )
    calibrate.add_argument(
        "--quantum-efficiency",
        type=float,
        default=None,
        help="the camera's quantum efficiency, to state in the file (the data cannot measure "
        "it): N and b are then incident photons; default none (detected photoelectrons)",
    )
    calibrate.add_argument(
        "--readout-sd",
        type=float,
        default=None,
        help="without --dark: the camera's readout noise in electrons (its specification), "
        "where the movie's background cannot measure it (an EMCCD at high gain)",
    )
    calibrate.add_argument("--roi", type=int, default=25, help="ROI cut (default 25)")
    calibrate.add_argument("--fit", type=int, default=15, help="fitted centre (default 15)")
    calibrate.add_argument("--out", default="camera.toml", help="the camera file to write")
    calibrate.set_defaults(run=_calibrate)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command; bad input ends it with one line ``bayespsf: ...`` (exit status 1)."""
    args = build_parser().parse_args(argv)
    args.argv = None if argv is None else list(argv)[1:]
    from bayespsf.errors import BayespsfInputError

    try:
        return args.run(args)
    except (CommandError, BayespsfInputError) as exc:
        raise SystemExit(f"bayespsf: {exc}") from None
    except KeyboardInterrupt:
        print("bayespsf: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
