"""What the subcommands share: ``CommandError``, the output folder of one run, the command line
as typed, the movie commands' camera model, spot SD and selection rules, and the report that
``bayespsf fit`` prints."""

from __future__ import annotations

import os
import re
import sys
from contextlib import contextmanager
from pathlib import Path


class CommandError(Exception):
    """A problem the command reports as one line, ``bayespsf: ...``, with exit status 1.

    ``main`` reports ``bayespsf.errors.BayespsfInputError``, which the library raises for bad
    input, in the same way.
    """


def output_folder(path: str, option: str = "--out", stem: bool = False) -> Path:
    """``path`` as a folder (or, with ``stem``, a path stem) to write into: ``output_folder``
    of ``bayespsf.io.folders``, named by the command's flag."""
    from bayespsf.io import folders

    return folders.output_folder(path, option, stem=stem)


def as_flag(message: str, usage: str) -> str:
    """``message`` with its leading Python name (``ess must be ...``, from the functions beneath
    a command) given as the command's flag that sets it (``--ess must be ...``): ``--name``, or
    ``--z-name`` (``calibrate-z``'s ``--z-start``, ``--z-step``), where ``usage`` (the
    command's help) holds that flag and the message does not name it already; else
    ``message`` as it is."""
    name, _, rest = message.partition(" ")
    if rest and name.isidentifier():
        for flag in (f"--{name}", f"--z-{name}"):
            flag = flag.replace("_", "-")
            if re.search(rf"{re.escape(flag)}(?![\w-])", usage):
                return message if flag in rest else f"{flag} {rest}"  # named once
    return message


def output_file(path: str, force: bool, name: str, what: str) -> Path:
    """``--out`` as the file a command writes (``calibrate``'s camera file, ``calibrate-z``'s
    calibration): not a folder (the message offers ``name`` in it), not a file that exists
    unless ``--force``, in a folder that can be written (``output_folder``); before the work."""
    out = Path(path)
    if out.is_dir() or path.endswith(("/", os.sep)):
        raise CommandError(f"--out {path} is a folder; give the {what}'s name ({out / name})")
    if out.exists() and not force:
        raise CommandError(f"--out {out} exists: give another name, or --force to replace it")
    output_folder(str(out.parent))
    return out


@contextmanager
def one_run(option: str = "--out"):
    """Report a folder that holds another run's results (``RunConflict``) with the command's
    own names: ``--out`` for the folder, ``--force`` to replace them."""
    from bayespsf.io.run_record import RunConflict

    try:
        yield
    except RunConflict as exc:
        raise CommandError(exc.message(option, "--force")) from None


def geometry(args) -> tuple[int | None, int | None]:
    """``--roi`` and ``--fit``, checked: for ``detect`` and ``analyze`` a side not given is
    None (it follows the spot's SD: ``bayespsf.movie.geometry_for_psf``); ``calibrate`` and
    ``calibrate-z`` take the paper's 25 and 15 pixels."""
    from bayespsf.model import MIN_ROI
    from bayespsf.movie.extract import check_sizes

    roi, fit = args.roi, args.fit
    if args.command not in ("detect", "analyze"):
        roi, fit = (25 if roi is None else roi), (15 if fit is None else fit)
    names = ("--roi", getattr(args, "fit_from", "--fit"))
    check_sizes(roi, fit, missing_ok=True, names=names, smallest=MIN_ROI)
    return roi, fit


def movie_model(args):
    """The movie, the camera file's model and the spot's SD (None: to be estimated); a
    camera file's ``[geometry] roi`` becomes ``args.fit`` where ``--fit`` is not given."""
    from bayespsf.io import camera_scene, read_camera_file
    from bayespsf.model import Model
    from bayespsf.movie import read_movie

    movie = read_movie(args.movie, channel=args.channel)
    table = read_camera_file(args.camera)
    if args.fit is None:  # the camera file's ROI, where it states one, is the fitted window
        args.fit = table.get("geometry", {}).get("roi")
        if args.fit is not None:
            args.fit_from = f"[geometry] roi in {args.camera}"
    roi, fit = geometry(args)
    for flag, side in (("--roi", roi), (getattr(args, "fit_from", "--fit"), fit)):
        if side is not None and side > min(movie.shape[1:]):
            raise CommandError(
                f"{flag} {side} is larger than {args.movie}'s frames ({movie.shape[1]} x "
                f"{movie.shape[2]} pixels)"
            )
    stated = table.get("geometry", {}).get("pixel_size")
    if args.pixel_size is not None and stated is not None and stated != args.pixel_size:
        raise CommandError(
            f"--pixel-size {args.pixel_size:g} nm, but {args.camera} states [geometry] "
            f"pixel_size = {stated:g} nm: give one of them"
        )
    fallback = movie.pixel_size if args.pixel_size is None else args.pixel_size
    if fallback is None and stated is None:
        raise CommandError(
            f"no pixel size: {args.movie}'s metadata give none and {args.camera} has no "
            "[geometry] pixel_size; state it (nm): --pixel-size, or [geometry] pixel_size in "
            f"{args.camera}"
        )
    # without a fitted window yet (it follows the spot's SD), the model's ROI is a stand-in
    scene = camera_scene(table, args.camera, fit or 15, fallback, roi_name="--fit")
    emitter = scene.to_dict().get("emitter", {})
    s0 = args.psf_sd
    if s0 is None and {"s0x", "s0y"} <= set(table.get("emitter", {})):
        s0 = 0.5 * (emitter["s0x"] + emitter["s0y"])
    if s0 is None and args.command == "calibrate-z":  # a z-stack's spots are out of focus
        raise CommandError("give --psf-sd NM (the bead's in-focus SD), or [emitter] s0x, s0y")
    return movie, Model.from_scene(scene), s0


def selection_rules(args):
    """The selection rules of ``--rules``, ``--min-valid-frames`` and ``--skip-rule``."""
    from bayespsf.movie.select import RULES, Rules

    if args.rules == "none":
        if args.min_valid_frames is not None or args.skip_rule:
            raise CommandError(
                "--rules none keeps every accepted candidate: give --min-valid-frames or "
                "--skip-rule only with --rules paper"
            )
        return Rules(skip=RULES)
    settings = {} if args.min_valid_frames is None else {"min_valid_frames": args.min_valid_frames}
    return Rules(**settings, skip=tuple(args.skip_rule))


def command_line(args) -> str:
    """The command as typed (``bayespsf calibrate ...``), for the provenance of its files."""
    return f"bayespsf {args.command} " + " ".join(sys.argv[2:] if args.argv is None else args.argv)


SHOWN = 10  # ROIs named one by one in the fit's report, of each kind (sampled; without one)


def fit_report(table, out: Path) -> str:
    """What ``bayespsf fit`` prints: the first ``SHOWN`` posteriors' s_x and the first
    ``SHOWN`` ROIs without a posterior, one line each, then the counts of each outcome and
    method, and the files written."""
    from bayespsf.parallel import Store

    lines = []
    bad = table["status"].isin(("refused", "failed")).to_numpy()
    for _, row in table[~bad].head(SHOWN).iterrows():
        lines.append(
            f"ROI {row['molecule']} ({row['method']}): converged {row['converged']}, "
            f"s_x = {row['s_x_mean']:.4g} +- {row['s_x_sd']:.3g} nm"
        )
    for _, row in table[bad].head(SHOWN).iterrows():
        lines.append(f"ROI {row['molecule']}: {row['status']}: {row['message']}")
    named = min(SHOWN, int((~bad).sum())) + min(SHOWN, int(bad.sum()))
    if named < len(table):
        lines.append(f"... {len(table) - named} more in {out / 'summary.csv'}")
    status = ", ".join(f"{k} {v}" for k, v in table["status"].value_counts().items())
    lines.append(f"{len(table)} ROIs: {status}")
    if (~bad).any():
        methods = ", ".join(f"{k} {v}" for k, v in table.loc[~bad, "method"].value_counts().items())
        lines.append(f"posteriors by {methods}")
    store = Store(out)
    files = len(store.files())
    lines.append(
        f"wrote {out / 'summary.csv'} and the posteriors of {int((~bad).sum())} ROIs in "
        + (
            f"{files} file(s) (bayespsf.parallel.Store({str(out)!r}).posterior(i) reads ROI i's)"
            if store.keeps_draws()
            else f"{files} file(s), their summaries without draws (--no-draws)"
        )
    )
    return "\n".join(lines)
