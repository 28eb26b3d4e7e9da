"""The keys of a scene's optional sections (``OPTIONAL_SECTIONS``): ``[axial]`` (the widths
follow the emitter's z through a defocus curve) and ``[movie]`` (a movie of many molecules).
``bayespsf.scene.schema`` puts them into ``SCHEMA``."""

from __future__ import annotations

from bayespsf.scene.key import Key, when_is

# Optional: the table's presence declares that the widths follow the emitter's axial
# position z through a defocus curve (bayespsf.psf.defocus); the emitter's s0x, s0y are
# then the in-focus widths.
AXIAL: tuple[Key, ...] = (
    Key(
        "curve",
        ("symmetric", "huang", "polynomial"),
        "symmetric",
        "",
        "'symmetric': s(z) = s0 sqrt(1 + (z / depth)^2) on both axes, in focus at z = 0 "
        "(DeSantis et al. 2010, Discussion); 'huang': per axis w0 sqrt(1 + u^2 + A u^3 + B "
        "u^4), u = (z - focus) / depth (Huang et al., Science 319 (2008)); 'polynomial': per "
        "axis w0 (1 + u^2 + A u^3 + B u^4); w0 is emitter.s0x or s0y",
    ),
    Key(
        "depth",
        float,
        400.0,
        "nm",
        "depth of focus D of the symmetric curve (the paper: ~400 nm)",
        1.0,
        1e6,
        when=when_is("curve", "symmetric"),
    ),
    *(
        Key(
            f"{name}_{axis}",
            float,
            default,
            unit,
            f"{meaning} of the {axis} axis's curve",
            low,
            high,
            low_open,
            when=when_is("curve", "huang", "polynomial"),
        )
        for axis in ("x", "y")
        for name, default, unit, meaning, low, high, low_open in (
            (
                "focus",
                0.0,
                "nm",
                "plane of focus (the width is smallest near it)",
                -1e6,
                1e6,
                False,
            ),
            ("depth", 400.0, "nm", "depth d", 1.0, 1e6, False),
            ("A", 0.0, "", "third-order coefficient", -1e3, 1e3, False),
            ("B", 0.0, "", "fourth-order coefficient", -1e3, 1e3, False),
        )
    ),
    Key(
        "z",
        ("fixed", "uniform", "normal"),
        "fixed",
        "",
        "the emitter's axial position: 'fixed' at z0; 'uniform' in [z_low, z_high]; "
        "'normal' of mean z0 and SD z_sd, drawn per image",
    ),
    Key(
        "z0",
        float,
        0.0,
        "nm",
        "axial position (the mean for 'normal')",
        -1e6,
        1e6,
        when=when_is("z", "fixed", "normal"),
    ),
    Key(
        "z_low",
        float,
        -600.0,
        "nm",
        "lower end of the uniform z (below z_high)",
        -1e6,
        1e6,
        high_open=True,
        when=when_is("z", "uniform"),
    ),
    Key(
        "z_high",
        float,
        600.0,
        "nm",
        "upper end of the uniform z (above z_low)",
        -1e6,
        1e6,
        low_open=True,
        when=when_is("z", "uniform"),
    ),
    Key(
        "z_sd",
        float,
        200.0,
        "nm",
        "SD of the normal z",
        0.0,
        1e6,
        True,
        when=when_is("z", "normal"),
    ),
)

# Optional (OPTIONAL_SECTIONS): the table's presence declares a movie, read only by
# bayespsf.simulation.movie; every effect in it applies only when its key is declared.
MOVIE: tuple[Key, ...] = (
    Key("frames", int, 100, "frames", "number of frames of the movie", 1, 10_000_000),
    Key("height", int, 256, "pixels", "frame height (rows)", 1, 100_000),
    Key("width", int, 256, "pixels", "frame width (columns)", 1, 100_000),
    Key(
        "exposure",
        float,
        0.0,
        "s",
        "time per frame, written as the OME TimeIncrement (the paper's illumination "
        "intervals: 1 to 500 ms); 0 declares none",
        0.0,
        1e5,
    ),
    Key(
        "molecules",
        int,
        10,
        "",
        "number of molecules, placed uniformly at random (one after another, each where it "
        "keeps min_spacing and edge)",
        0,
        10_000_000,
    ),
    Key(
        "min_spacing",
        int,
        25,
        "pixels",
        "least distance in rows or in columns (Chebyshev) between two molecules' nearest "
        "pixels at frame 0, so that ROIs of this side never overlap (the paper's 25 x 25 "
        "ROIs)",
        0,
        100_000,
    ),
    Key(
        "edge",
        int,
        12,
        "pixels",
        "least number of pixels between a molecule's nearest pixel and the frame's border "
        "at frame 0 (12: a 25 x 25 ROI fits)",
        0,
        100_000,
    ),
    Key(
        "photons_low",
        float,
        0.0,
        "photons",
        "each molecule's mean photons per frame and fluorophore is log-uniform between "
        "photons_low and photons_high; 0 stands for emitter.photons",
        0.0,
        1e9,
    ),
    Key(
        "photons_high",
        float,
        0.0,
        "photons",
        "the other end of the log-uniform range (0 stands for emitter.photons)",
        0.0,
        1e9,
    ),
    Key(
        "bleach_mean",
        float,
        0.0,
        "frames",
        "mean of the exponential time at which each fluorophore bleaches in one step; 0 "
        "declares no bleaching",
        0.0,
        1e9,
    ),
    Key(
        "two_fluorophores",
        float,
        0.0,
        "fraction",
        "fraction of molecules carrying two fluorophores that blink and bleach "
        "independently (two bleaching steps, which the paper excluded); 0 declares none",
        0.0,
        1.0,
    ),
    Key(
        "drift_x",
        float,
        0.0,
        "nm/frame",
        "stage drift of the whole field along x (columns); 0 declares none",
        -1e5,
        1e5,
    ),
    Key(
        "drift_y",
        float,
        0.0,
        "nm/frame",
        "stage drift of the whole field along y (rows); 0 declares none",
        -1e5,
        1e5,
    ),
    Key(
        "moving",
        float,
        0.0,
        "fraction",
        "fraction of molecules that also move by a random walk; 0 declares none",
        0.0,
        1.0,
    ),
    Key(
        "moving_step",
        float,
        10.0,
        "nm",
        "SD per frame and axis of the moving molecules' random-walk steps",
        0.0,
        1e5,
    ),
    Key(
        "blink_on",
        float,
        0.0,
        "frames",
        "mean on time of a two-state Markov blinking (declare it with blink_off); 0 "
        "declares no blinking",
        0.0,
        1e9,
    ),
    Key(
        "blink_off",
        float,
        0.0,
        "frames",
        "mean off time of the blinking (declare it with blink_on); 0 declares no blinking",
        0.0,
        1e9,
    ),
    Key(
        "dark_frames",
        int,
        0,
        "frames",
        "frames recorded without light before the movie (camera calibration), written to a "
        "separate file; 0 declares none",
        0,
        1_000_000,
    ),
)


__all__ = ["AXIAL", "MOVIE"]
