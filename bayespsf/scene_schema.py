"""Every scene key: its type, default, unit, allowed range and meaning (``SCHEMA``).

``bayespsf.scene`` reads scenes against this schema; ``docs/scenes.md``'s tables are generated
from it (``bayespsf schema``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from bayespsf import photon_units


@dataclass(frozen=True)
class Key:
    """One scene key: its type, default, unit, allowed values and meaning."""

    name: str
    kind: type | tuple[str, ...]  # float, int, bool, str, list, or a tuple of allowed strings
    default: Any
    unit: str
    doc: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    when: Callable[[Mapping], bool] | None = None  # the key applies only when this is true
    when_doc: str = ""

    def allowed(self) -> str:
        if isinstance(self.kind, tuple):
            return "one of " + ", ".join(repr(c) for c in self.kind)
        if self.low is None and self.high is None:
            return self.kind.__name__
        lo = "-inf" if self.low is None else f"{self.low:g}"
        hi = "inf" if self.high is None else f"{self.high:g}"
        return ("(" if self.low_open else "[") + f"{lo}, {hi}" + (")" if self.high_open else "]")


def _is(section_key: str, *values: str) -> Callable[[Mapping], bool]:
    return lambda section: section.get(section_key) in values


_PRIOR_KINDS = ("uniform", "log-uniform", "normal", "half-normal")

SCHEMA: dict[str, tuple[Key, ...]] = {
    "geometry": (
        Key("roi", int, 15, "pixels", "side of the square region of interest (odd)", 1, 401),
        Key("pixel_size", float, 100.0, "nm", "pixel side a in object space", 1.0, 1e5),
    ),
    "emitter": (
        Key("photons", float, 1000.0, "photons", "mean total photons N of the spot", 0, 1e9, True),
        Key(
            "photon_statistics",
            ("poisson", "fixed"),
            "poisson",
            "",
            "'poisson': the photon count of an image is Poisson(N); 'fixed': exactly N photons, "
            "so pixel counts are multinomial",
        ),
        Key(
            "photon_jitter",
            float,
            0.0,
            "relative",
            "N of each image drawn uniformly in N (1 +- photon_jitter) (the paper keeps frames "
            "within +-20% of the mean: 0.2); 0 declares no jitter",
            0.0,
            1.0,
            high_open=True,
        ),
        Key("s0x", float, 120.0, "nm", "spot SD along x (columns)", 0.0, 1e5, True),
        Key("s0y", float, 120.0, "nm", "spot SD along y (rows)", 0.0, 1e5, True),
        Key(
            "width_jitter",
            float,
            0.0,
            "nm",
            "SD of a per-photon change of both widths (emission bandwidth; the paper uses 2 nm); "
            "> 0 makes the simulator bin photon by photon",
            0.0,
            1e4,
        ),
        Key(
            "position",
            ("fixed", "pixel", "box"),
            "fixed",
            "",
            "'fixed': at (x0, y0); 'pixel': uniform within the central pixel; 'box': uniform in "
            "[-box, box]^2",
        ),
        Key("x0", float, 0.0, "nm", "x position", -1e6, 1e6, when=_is("position", "fixed")),
        Key("y0", float, 0.0, "nm", "y position", -1e6, 1e6, when=_is("position", "fixed")),
        Key(
            "box",
            float,
            50.0,
            "nm",
            "half-width of the box",
            0.0,
            1e6,
            True,
            when=_is("position", "box"),
        ),
    ),
    "optics": (
        Key(
            "psf",
            ("gaussian", "airy"),
            "gaussian",
            "",
            "'gaussian': the elliptical Gaussian (s0x, s0y); 'airy': the in-focus Born-Wolf Airy "
            "pattern of wavelength and na (photon by photon); inference always fits a Gaussian",
        ),
        Key(
            "wavelength",
            float,
            580.0,
            "nm",
            "emission wavelength",
            0.0,
            1e4,
            True,
            when=_is("psf", "airy"),
        ),
        Key("na", float, 1.45, "", "numerical aperture", 0.0, 2.0, True, when=_is("psf", "airy")),
    ),
    "background": (
        Key(
            "kind",
            ("none", "poisson", "gaussian", "truncated-gaussian", "binomial"),
            "none",
            "",
            "law of the background photons of each pixel (i.i.d.); they are amplified like "
            "signal photons. 'gaussian' rounds Normal(mean, sd) and must be (almost) never "
            "negative; 'truncated-gaussian' rounds Normal(mean, sd) truncated at 0; 'binomial' "
            "has the given mean and sd (needs sd^2 < mean and an integer number of trials)",
        ),
        Key(
            "mean",
            float,
            0.0,
            "photons",
            "mean (for the Gaussians: of the parent normal) background photons per pixel",
            0.0,
            1e7,
            when=lambda s: s.get("kind", "none") != "none",
        ),
        Key(
            "sd",
            float,
            1.0,
            "photons",
            "SD (for the Gaussians: of the parent normal) of the background photons",
            0.0,
            1e7,
            True,
            when=_is("kind", "gaussian", "truncated-gaussian", "binomial"),
        ),
    ),
    "camera": (
        Key(
            "kind",
            ("photon", "emccd", "scmos"),
            "photon",
            "",
            "'photon': ideal photon counting; 'emccd'; 'scmos' (scalar gain, offset, variance)",
        ),
        Key(
            "gain",
            float,
            100.0,
            "e-/e- or ADU/e-",
            "EMCCD: mean EM gain; sCMOS: ADU per photoelectron",
            0.0,
            1e5,
            True,
            when=_is("kind", "emccd", "scmos"),
        ),
        Key(
            "readout_sd",
            float,
            0.0,
            "e-",
            "EMCCD readout noise SD",
            0.0,
            1e4,
            when=_is("kind", "emccd"),
        ),
        Key(
            "offset",
            float,
            0.0,
            "ADU",
            "bias added to every pixel",
            -1e9,
            1e9,
            when=_is("kind", "emccd", "scmos"),
        ),
        Key(
            "e_per_adu",
            float,
            1.0,
            "e-/ADU",
            "EMCCD: electrons per ADU",
            0.0,
            1e6,
            True,
            when=_is("kind", "emccd"),
        ),
        Key(
            "variance",
            float,
            0.0,
            "ADU^2",
            "sCMOS readout variance",
            0.0,
            1e9,
            when=_is("kind", "scmos"),
        ),
        Key(
            "clock_induced_charge",
            float,
            0.0,
            "e-/pixel",
            "EMCCD: mean spurious electrons per pixel per frame, amplified like photoelectrons; "
            "0 declares none",
            0.0,
            100.0,
            when=_is("kind", "emccd"),
        ),
        Key(
            "register",
            ("gamma", "stages"),
            "gamma",
            "",
            "EMCCD multiplication: 'gamma' (the Gamma(n, gain) law the likelihood uses) or "
            "'stages' (each electron multiplies stage by stage with probability "
            "gain^(1/stages) - 1)",
            when=_is("kind", "emccd"),
        ),
        Key(
            "stages",
            int,
            512,
            "",
            "number of EM stages for register = 'stages'",
            1,
            10000,
            when=_is("register", "stages"),
        ),
        Key(
            "quantize",
            bool,
            False,
            "",
            "round counts to whole ADU (the ADC); false declares continuous counts",
            when=_is("kind", "emccd", "scmos"),
        ),
        Key(
            "saturation",
            float,
            0.0,
            "ADU",
            "counts above this are recorded as this (the ADC's full scale); 0 declares none",
            0.0,
            1e12,
            when=_is("kind", "emccd", "scmos"),
        ),
        Key(
            "quantum_efficiency",
            float,
            1.0,
            "e-/photon",
            "probability that an incident photon (signal or background) becomes a "
            "photoelectron; the simulator thins the photons binomially when it is below 1, and "
            "N and b can then be incident photons (see photon_unit); 1 declares none",
            0.0,
            1.0,
            low_open=True,
        ),
        Key(
            "photon_unit",
            photon_units.UNITS,
            "incident",
            "",
            "unit of N and b in the prior, the model, the truth table and every result: "
            "'incident' photons (photoelectrons / quantum_efficiency) or 'detected' "
            "photoelectrons (the same when quantum_efficiency is 1)",
        ),
        Key("likelihood", str, "", "", "likelihood tier for inference ('' = the camera's default)"),
    ),
    # Optional (OPTIONAL_SECTIONS): the table's presence declares a movie, read only by
    # bayespsf.movie.simulate; every effect in it applies only when its key is declared.
    # Optional: the table's presence declares that the widths follow the emitter's axial
    # position z through a defocus curve (bayespsf.axial.defocus); the emitter's s0x, s0y are
    # then the in-focus widths.
    "axial": (
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
            when=_is("curve", "symmetric"),
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
                when=_is("curve", "huang", "polynomial"),
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
            when=_is("z", "fixed", "normal"),
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
            when=_is("z", "uniform"),
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
            when=_is("z", "uniform"),
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
            when=_is("z", "normal"),
        ),
    ),
    "movie": (
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
    ),
}
OPTIONAL_SECTIONS = ("axial", "movie")  # present in a scene only where declared

_PRIOR_KEY = Key(
    "<parameter>",
    dict,
    None,
    "",
    "prior of one of x0, y0, s_x, s_y, N, b: a table with kind = "
    + " | ".join(repr(k) for k in _PRIOR_KINDS)
    + " and its parameters: low, high (uniform, log-uniform); mean, sd (normal); "
    "scale (half-normal, for b). Parameters left out get the documented weak default",
)
PRIOR_PARAMETERS = ("x0", "y0", "s_x", "s_y", "N", "b")
_PRIOR_ARGS = {
    "uniform": ("low", "high"),
    "log-uniform": ("low", "high"),
    "normal": ("mean", "sd"),
    "half-normal": ("scale",),
}
