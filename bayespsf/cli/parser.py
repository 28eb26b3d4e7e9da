"""What the ``bayespsf`` command accepts: ``build_parser()``, one function per subcommand that
adds its parser, with the option groups of ``bayespsf.cli._options`` that several share.

The parser only describes; ``bayespsf.cli.commands.main`` runs the subcommand that
``args.command`` names. Nothing here imports the library, so ``bayespsf --help`` stays fast.
"""

from __future__ import annotations

import argparse

from bayespsf.cli._options import (
    CAMERA_HELP,
    CAMERA_OR_SCENE_HELP,
    METHOD_BATCHED_HELP,
    METHOD_PER_ROI_HELP,
    ROI_PAPER_HELP,
    add_camera,
    add_force,
    add_geometry,
    add_max_seconds,
    add_method,
    add_movie,
    add_out,
    add_per_frame,
    add_pixel_size,
    add_psf_sd,
    add_seed,
    add_selection,
    add_workers,
)


def build_parser() -> argparse.ArgumentParser:
    """The parser of the ``bayespsf`` command and its subcommands.

    Returns
    -------
    argparse.ArgumentParser
        The parser; its result names the subcommand in ``command``, and its
        ``subcommands`` attribute maps each subcommand's name to its parser.
    """
    parser = argparse.ArgumentParser(
        prog="bayespsf",
        description="Bayesian analysis of single fluorescent molecule images.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    for add in (
        _add_selfcheck,
        _add_simulate,
        _add_schema,
        _add_demo,
        _add_bench,
        _add_fit,
        _add_detect,
        _add_analyze,
        _add_calibrate_z,
        _add_calibrate,
    ):
        add(commands)
    parser.subcommands = dict(commands.choices)  # each subcommand's parser, by name
    return parser


def _add_selfcheck(commands) -> None:
    commands.add_parser(
        "selfcheck",
        help="check the camera likelihoods of a typical EMCCD and time each tier",
        description="Integrate the exact EMCCD law (normalisation, mean, variance), compare "
        "every likelihood tier with it and time each tier relative to the Poisson tier.",
    )


def _add_simulate(commands) -> None:
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
    add_seed(sim)
    add_out(sim, "simulated", "output path stem (default: simulated)")


def _add_schema(commands) -> None:
    commands.add_parser(
        "schema",
        help="print every scene key (the tables of docs/scenes.md)",
        description="Print the scene schema as markdown tables: key, default, unit, allowed "
        "range and meaning.",
    )


def _add_demo(commands) -> None:
    demo = commands.add_parser(
        "demo",
        help="one molecule of the paper's Fig. 3 scene: its posterior beside the theory",
        description="Simulate one molecule from the shipped paper-fig3 scene, sample its "
        "posterior, print each parameter's posterior SD beside the CRLB and the least-squares "
        "estimate (and Eq. sigma2dp3 and the pixel sum for s_x); write the corner plot and the "
        "result file.",
    )
    add_seed(demo)
    add_out(demo, "bayespsf-demo", "output folder (default bayespsf-demo)")


def _add_bench(commands) -> None:
    bench = commands.add_parser(
        "bench",
        help="what accuracy costs in time: every likelihood tier at several ESS targets",
        description="The accuracy-time frontier: for molecules of the emccd-typical scene at "
        "low, medium and high N, every EMCCD likelihood tier at ESS targets 100-4000 and the "
        "MLE + CRLB and Laplace ends: time per molecule as a ratio to one MLE fit, error of "
        "the posterior SD of s_x against a long exact-law reference, and 68%/95% coverage. "
        "Where JAX is installed, rows 'importance (JAX)' and 'auto (JAX)' run the same "
        "molecules on the JAX backend. --quick: two molecules, under two minutes.",
    )
    bench.add_argument("--quick", action="store_true", help="a small run (< 2 minutes)")
    add_workers(bench)
    add_out(bench, "bayespsf-bench", "output folder (default bayespsf-bench)")


def _add_fit(commands) -> None:
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
    add_camera(source, CAMERA_OR_SCENE_HELP, required=False)
    fit.add_argument(
        "--truth",
        default=None,
        help="truth table of simulated ROIs (the OUT.truth.csv of bayespsf simulate): adds "
        "truth and rank columns to summary.csv",
    )
    fit.add_argument("--likelihood", default=None, help="likelihood tier (default: the scene's)")
    fit.add_argument("--ess", type=float, default=400.0, help="ESS per parameter (default 400)")
    add_max_seconds(fit)
    add_method(fit, METHOD_PER_ROI_HELP)
    add_seed(fit, "run seed (ROI k uses molecule_seed(seed, k))")
    fit.add_argument(
        "--check",
        action="store_true",
        help="also test whether the model can have made each ROI (a parametric-bootstrap "
        "goodness-of-fit p-value, gof_p, in each row and result file; about four times the "
        "time on emccd-typical)",
    )
    fit.add_argument(
        "--no-draws",
        action="store_true",
        help="keep each ROI's summary in the output folder, not its draws (about 5.6 kB per "
        "ROI instead of 28-31: for stacks of millions of ROIs)",
    )
    add_workers(fit, scheduler=True)
    add_out(fit, "bayespsf-fit", "output folder (default bayespsf-fit)")


def _add_detect(commands) -> None:
    detect = commands.add_parser(
        "detect",
        help="molecules of a movie: detection, traces, bleaching steps, the paper's selection",
        description="Find the immobile molecules of MOVIE (TIFF, OME-TIFF, ImageJ, .npy): "
        "detection on the mean projection with a stated false-positive rate, each molecule's "
        "trace, bleaching steps and drift, a fit of each frame before bleaching, and the "
        "selection rules of DeSantis et al., Opt. Express 18 (2010). Writes candidates.csv, "
        "molecules.csv, frames.csv, selection.md, camera.toml and run.json into --out; a "
        "folder that holds another run's results is refused (--force replaces them).",
    )
    add_movie(detect)
    add_camera(detect, CAMERA_HELP)
    add_psf_sd(detect)
    add_pixel_size(detect)
    add_geometry(detect, ROI_PAPER_HELP)
    add_selection(detect)
    detect.add_argument(
        "--false-positives",
        type=float,
        default=0.01,
        help="expected false detections per image: the projection, or each frame with "
        "--per-frame (default 0.01)",
    )
    detect.add_argument("--projection", choices=("mean", "median"), default="mean")
    add_per_frame(detect, "the MLE and its Cramér-Rao bound; writes candidates.csv, locs.*")
    add_workers(detect, scheduler=True)
    add_out(detect, "bayespsf-detect")
    add_force(detect)


def _add_analyze(commands) -> None:
    analyze = commands.add_parser(
        "analyze",
        help="per-molecule posteriors of a movie, and the files SMLM tools open",
        description="The molecules `bayespsf detect` selects, then a posterior, the MLE and "
        "the paper's least squares for every valid frame (DeSantis et al., Opt. Express 18 "
        "(2010)); the calibration check without ground truth; the paper's Delta s per "
        "molecule; each molecule's joint posterior over its frames; a goodness-of-fit p-value "
        "per frame. Writes into --out: locs.hdf5 + locs.yaml (picasso), locs.csv "
        "(ThunderSTORM), locs.parquet, molecules.csv, consistency.csv, width_spread.csv, "
        "width_by_window.csv, report.md with its figures, the selection's tables, run.json and "
        "posteriors/ (a rerun of the same run continues there; a folder that holds another "
        "run's results is refused, --force replaces them).",
    )
    add_movie(analyze)
    add_camera(analyze)
    add_psf_sd(analyze)
    add_pixel_size(analyze)
    add_geometry(analyze, ROI_PAPER_HELP)
    add_selection(analyze)
    add_method(analyze, METHOD_BATCHED_HELP)
    analyze.add_argument("--ess", type=float, default=None, help="effective draws per ROI")
    add_max_seconds(analyze)
    add_seed(analyze)
    add_workers(analyze, scheduler=True, terse=True)
    analyze.add_argument(
        "--z-calibration",
        default=None,
        help="a z calibration file (bayespsf.io.z_calibration): every frame also gets "
        "the posterior of its axial position z, in the tables as picasso's z and lpz (nm)",
    )
    analyze.add_argument(
        "--z-range",
        type=float,
        nargs=2,
        default=None,
        metavar=("LOW", "HIGH"),
        help="with --z-calibration, the support of z's uniform prior in nm (default -800 800)",
    )
    analyze.add_argument(
        "--gof-discrepancy",
        choices=("likelihood", "pearson"),
        default="likelihood",
        help="the goodness-of-fit test's discrepancy (default likelihood; pearson is calibrated "
        "at a background of a few photons per pixel, where likelihood is conservative)",
    )
    add_per_frame(analyze, "posterior, MLE and Cramér-Rao bound; writes candidates.csv, locs.*")
    analyze.add_argument(
        "--no-draws",
        action="store_true",
        help="with --per-frame: keep each window's summary in posteriors/, not its draws "
        "(about 7 kB per window instead of 30: for datasets of millions of spots)",
    )
    add_out(analyze, "bayespsf-analyze")
    add_force(analyze)


def _add_calibrate_z(commands) -> None:
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
    add_movie(calibrate_z, "the z-stack: .tif/.ome.tif or .npy", metavar="STACK")
    add_camera(calibrate_z)
    add_psf_sd(calibrate_z, "the bead's in-focus SD in nm (the detector's template)")
    add_pixel_size(calibrate_z)
    calibrate_z.add_argument("--z-start", type=float, required=True, help="first step's z, nm")
    calibrate_z.add_argument("--z-step", type=float, required=True, help="z per step, nm")
    calibrate_z.add_argument(
        "--frames-per-step", type=int, required=True, help="frames at each step"
    )
    calibrate_z.add_argument("--curve", choices=("huang", "polynomial"), default="huang")
    calibrate_z.add_argument(
        "--no-higher-order", action="store_true", help="hold A = B = 0 (three terms per axis)"
    )
    calibrate_z.add_argument(
        "--bead",
        type=float,
        nargs=2,
        metavar=("X", "Y"),
        default=None,
        help="the bead to calibrate from, at camera pixel X Y (needed where several beads of "
        "comparable brightness are in the stack; default the only or clearly brightest one)",
    )
    add_geometry(calibrate_z)
    add_seed(calibrate_z)
    add_workers(calibrate_z, terse=True)
    add_out(calibrate_z, "z-calibration.toml", "the file to write")
    add_force(calibrate_z, "replace the calibration file that --out names instead of refusing")


def _add_calibrate(commands) -> None:
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
    add_movie(calibrate)
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
    add_psf_sd(calibrate, "the spot's SD in nm (default: estimated from the data)")
    add_pixel_size(calibrate, "nm (default: the movie's metadata)")
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
    add_geometry(calibrate)
    add_selection(calibrate)
    add_out(calibrate, "camera.toml", "the camera file to write")
    add_force(calibrate, "replace the camera file that --out names instead of refusing")
