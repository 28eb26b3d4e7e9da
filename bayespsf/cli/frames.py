"""``bayespsf detect --per-frame`` and ``bayespsf analyze --per-frame``: every spot of every
frame localised in its own frame (``bayespsf.analysis.localize_frames``)."""

from __future__ import annotations

from pathlib import Path

from bayespsf.cli._shared import CommandError, command_line, one_run

#: Options of the projection path that need a trace or a projection, by their flag.
_TRACE_OPTIONS = {
    "--rules none": lambda a: a.rules != "paper",
    "--min-valid-frames": lambda a: a.min_valid_frames is not None,
    "--skip-rule": lambda a: bool(a.skip_rule),
    "--projection": lambda a: getattr(a, "projection", "mean") != "mean",
    "--roi": lambda a: a.roi is not None,
    "--z-calibration": lambda a: getattr(a, "z_calibration", None) is not None,
}


def per_frame(args, out: Path, movie, model, s0: float | None, fit: int) -> int:
    """Run ``localize_frames`` for ``args`` (``detect``: the MLE; ``analyze``: the posterior
    too) and print what it found."""
    from bayespsf.analysis import localize_frames

    given = [flag for flag, used in _TRACE_OPTIONS.items() if used(args)]
    if given:
        raise CommandError(
            f"{', '.join(given)}: not with --per-frame, which detects on every frame and "
            "localises each spot in its own frame (no projection, traces or selection rules; "
            "--fit sets the window)"
        )
    posterior = args.command == "analyze"
    options = dict(out=out, s0=s0, fit=fit, posterior=posterior, force=args.force)
    options["provenance"] = {"command": command_line(args)}
    if posterior:
        options["provenance"]["camera file"] = Path(args.camera).read_text(encoding="utf-8")
        options.update(method=args.method, backend=args.backend, ess=args.ess, seed=args.seed)
        options.update(gof_discrepancy=args.gof_discrepancy, max_seconds=args.max_seconds)
        options["keep_draws"] = not args.no_draws
    else:
        options["false_positives"] = args.false_positives
    options.update(workers=args.workers, executor=args.scheduler)
    with one_run():  # a folder of another run is refused before anything is written
        result = localize_frames(movie, model, copies={"camera.toml": args.camera}, **options)
    print(result.psf_width.summary() + (" (--psf-sd states it)" if s0 is None else ""))
    frames = result.locs["frame"].nunique()
    described = movie.describe(model.pixel_size)
    print(f"{described}: {len(result.locs)} localisations in {frames} of {len(movie)} frames")
    print("wrote " + ", ".join(str(p) for p in result.paths.values()))
    return 0
