"""Option groups that several subcommands share: each adds its options to a subparser, with
the names, defaults, types, choices and help texts of ``bayespsf --help``.

Where two subcommands word the help of the same option differently, the wording is a
parameter (the module's ``*_HELP`` constants hold the variants), so that each command's help
stays as ``docs/cli.md`` documents it.
"""

from __future__ import annotations

import argparse

#: ``--camera`` of ``detect``, which the other movie commands refer to.
CAMERA_HELP = (
    "TOML with [camera] (kind, gain, offset, readout) and [geometry] pixel_size "
    "(nm; optional when the movie's metadata give it), optionally [emitter] s0x, s0y"
)
#: ``--camera`` of ``analyze`` and ``calibrate-z``.
CAMERA_AS_FOR_DETECT = "the camera file (as for detect)"
#: ``--camera`` of ``fit``, where it stands beside ``--scene``.
CAMERA_OR_SCENE_HELP = "TOML with [camera] and [geometry] pixel_size (and optional [prior])"

MOVIE_HELP = "the movie: .tif/.tiff/.ome.tif or .npy"
PSF_SD_HELP = (
    "the spot's SD in nm (default: the camera file's [emitter] s0x, s0y, else estimated from "
    "the data)"
)
ROI_HELP = "ROI cut (default 25)"
#: ``--roi`` of ``detect`` and ``analyze``, whose geometry follows the spot's SD.
ROI_PAPER_HELP = (
    "ROI cut (default from the spot's SD: 8 s0 each side, the paper's 25 at s0 = 120 nm on "
    "79 nm pixels)"
)
SEED_HELP = "random seed (default 0)"

METHODS = ("auto", "mcmc", "importance", "laplace")
#: ``--method`` of ``fit``: the per-ROI rule.
METHOD_PER_ROI_HELP = (
    "auto (default): per ROI the Laplace where a pilot shows it accurate, else "
    "importance sampling (PSIS) where its k-hat <= 0.7, else emcee; mcmc: emcee for "
    "every ROI; importance; laplace (no check)"
)
#: ``--method`` of ``analyze``: the batched engine.
METHOD_BATCHED_HELP = "posterior method (default auto: the batched engine, emcee where it fails)"


PIXEL_SIZE_HELP = (
    "the pixel size at the sample, nm (default: the camera file's [geometry] pixel_size, else "
    "the movie's metadata)"
)


def add_movie(
    parser: argparse.ArgumentParser, help: str = MOVIE_HELP, metavar: str | None = None
) -> None:
    """Add the positional ``movie`` argument and ``--channel``, the channel to read of a
    multi-channel file (default None).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    help : str, optional
        Its help text (default ``MOVIE_HELP``).
    metavar : str, optional
        Its name in the usage line (default ``MOVIE``).
    """
    parser.add_argument("movie", metavar=metavar, help=help)
    parser.add_argument(
        "--channel",
        type=int,
        default=None,
        help="the channel of a multi-channel OME or ImageJ file to read, from 0 (required "
        "when the file has more than one)",
    )


def add_camera(parser, help: str = CAMERA_AS_FOR_DETECT, required: bool = True) -> None:
    """Add ``--camera``, the camera file (``bayespsf.io.read_camera_file``).

    Parameters
    ----------
    parser : argparse.ArgumentParser or argparse mutually exclusive group
        Where to add it (``fit`` adds it to a group beside ``--scene``).
    help : str, optional
        Its help text: ``CAMERA_HELP``, ``CAMERA_AS_FOR_DETECT`` (default) or
        ``CAMERA_OR_SCENE_HELP``.
    required : bool, optional
        Whether the command needs it (default True; False inside a required group).
    """
    parser.add_argument("--camera", required=required, help=help)


def add_pixel_size(parser: argparse.ArgumentParser, help: str = PIXEL_SIZE_HELP) -> None:
    """Add ``--pixel-size``, the pixel size at the sample in nm (a float, default None).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    help : str, optional
        Its help text (default ``PIXEL_SIZE_HELP``).
    """
    parser.add_argument("--pixel-size", type=_pixel_size, default=None, help=help)


def _pixel_size(text: str) -> float:
    """``--pixel-size`` as a number in the scene's range for ``geometry.pixel_size``, named
    as the flag (it was named as the camera file's key, which the file did not hold)."""
    from bayespsf.scene.schema import SCHEMA

    (key,) = [key for key in SCHEMA["geometry"] if key.name == "pixel_size"]
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not key.low <= value <= key.high:  # NaN too
        raise argparse.ArgumentTypeError(f"a pixel size in nm within {key.allowed()}, got {text}")
    return value


def add_selection(parser: argparse.ArgumentParser) -> None:
    """Add the selection rules' options: ``--rules {paper,none}``, ``--min-valid-frames N`` and
    ``--skip-rule RULE`` (repeatable).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    """
    parser.add_argument(
        "--rules",
        choices=("paper", "none"),
        default="paper",
        help="the selection rules: the paper's five (default), or none (every accepted "
        "candidate is kept: blinking, moving or short movies)",
    )
    parser.add_argument(
        "--min-valid-frames",
        type=int,
        default=None,
        help="valid frames a molecule needs (default 75, the paper's)",
    )
    parser.add_argument(
        "--skip-rule",
        action="append",
        default=[],
        metavar="RULE",
        help="switch off one of the paper's selection rules by its name in selection.md "
        "(repeatable); an astigmatic movie needs equal_widths and width_range off",
    )


def add_per_frame(parser: argparse.ArgumentParser, what: str) -> None:
    """Add ``--per-frame`` (a flag): detection on every frame, each spot localised in its own
    frame (blinking or moving molecules), instead of the projection, traces and rules.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    what : str
        How each spot is localised (the end of the help text).
    """
    parser.add_argument(
        "--per-frame",
        action="store_true",
        help="blinking or moving molecules (dSTORM, PAINT, tracking): detect on every frame "
        f"and localise each spot in its own frame ({what}); no traces or selection rules",
    )


def add_psf_sd(
    parser: argparse.ArgumentParser, help: str = PSF_SD_HELP, required: bool = False
) -> None:
    """Add ``--psf-sd``, the spot's SD in nm (a float, default None).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    help : str, optional
        Its help text (default ``PSF_SD_HELP``).
    required : bool, optional
        Whether the command needs it (default False: the camera file may give it, or the data).
    """
    parser.add_argument("--psf-sd", type=float, default=None, required=required, help=help)


def add_geometry(parser: argparse.ArgumentParser, roi_help: str = ROI_HELP) -> None:
    """Add ``--roi`` (the ROI cut) and ``--fit`` (the fitted centre), default None: the
    command's default (``bayespsf.cli._shared.geometry``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    roi_help : str, optional
        The help text of ``--roi``: ``ROI_HELP`` (default) or ``ROI_PAPER_HELP``.
    """
    parser.add_argument("--roi", type=int, default=None, help=roi_help)
    fit_help = "fitted centre (default 15)"
    if roi_help == ROI_PAPER_HELP:
        fit_help = "fitted centre (default from the spot's SD: 4.5 s0 each side, the paper's 15)"
    parser.add_argument("--fit", type=int, default=None, help=fit_help)


def add_method(parser: argparse.ArgumentParser, help: str) -> None:
    """Add ``--method``, the posterior method (one of ``METHODS``, default ``auto``), and
    ``--backend`` (``numpy`` or ``jax``), where its batched pass runs.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    help : str
        Its help text: ``METHOD_PER_ROI_HELP`` or ``METHOD_BATCHED_HELP``.
    """
    parser.add_argument("--method", choices=METHODS, default="auto", help=help)
    parser.add_argument(
        "--backend",
        choices=("numpy", "jax"),
        default="numpy",
        help="where the batched posteriors run (default numpy; jax: a GPU where JAX finds "
        "one, installed by pip install 'bayespsf[gpu]')",
    )


def add_max_seconds(parser: argparse.ArgumentParser) -> None:
    """Add ``--max-seconds``, the wall-clock budget of each ROI's chain (default none).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    """
    parser.add_argument(
        "--max-seconds",
        type=float,
        default=None,
        help="wall-clock budget of each ROI's chain (default: none); a ROI that exhausts it "
        "is reported not converged",
    )


def add_seed(parser: argparse.ArgumentParser, help: str = SEED_HELP) -> None:
    """Add ``--seed``, the random seed (an int, default 0).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    help : str, optional
        Its help text (default ``SEED_HELP``).
    """
    parser.add_argument("--seed", type=int, default=0, help=help)


def add_workers(
    parser: argparse.ArgumentParser, *, scheduler: bool = False, terse: bool = False
) -> None:
    """Add ``--workers`` (local processes, default: the cores) and, optionally,
    ``--scheduler`` (a Dask scheduler address, default none).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    scheduler : bool, optional
        Whether to add ``--scheduler`` too (default False).
    terse : bool, optional
        Whether the help texts leave out their parenthesised defaults, as those of
        ``analyze`` and ``calibrate-z`` do (default False).
    """
    workers_help = "local processes" if terse else "local processes (default: cores)"
    parser.add_argument("--workers", type=int, default=None, help=workers_help)
    if scheduler:
        address = "a Dask scheduler address"
        parser.add_argument(
            "--scheduler", default=None, help=address if terse else f"{address} (a cluster)"
        )


def add_out(parser: argparse.ArgumentParser, default: str, help: str = "output folder") -> None:
    """Add ``--out``, what the command writes.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    default : str
        Its default path.
    help : str, optional
        Its help text (default ``"output folder"``).
    """
    parser.add_argument("--out", default=default, help=help)


#: ``--force`` of the commands that write a folder of one run's results.
FORCE_HELP = (
    "replace the results of another run that --out holds (its files and those this command "
    "writes; nothing else in the folder) instead of refusing"
)


def add_force(parser: argparse.ArgumentParser, help: str = FORCE_HELP) -> None:
    """Add ``--force``: replace another run's results in ``--out`` (a flag, default off).

    An output folder holds one run (its record ``run.json``, ``bayespsf.io.run_record``):
    without ``--force`` a command refuses, before writing anything, a folder that holds
    another run's results.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    help : str, optional
        Its help text (default ``FORCE_HELP``).
    """
    parser.add_argument("--force", action="store_true", help=help)
