"""Every scene key: its type, default, unit, allowed range and meaning (``SCHEMA``).

``bayespsf.scene`` reads scenes against this schema; ``docs/scenes.md``'s tables are generated
from it (``schema_markdown``, ``bayespsf schema``). The default priors (``default_prior``) and
the rules for keys that apply only with others (``Key.when``) live here too.
"""

from __future__ import annotations

from collections.abc import Mapping

from bayespsf.scene import units
from bayespsf.scene.key import Key, SceneError, when_is
from bayespsf.scene.optional import AXIAL, MOVIE

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
        Key("x0", float, 0.0, "nm", "x position", -1e6, 1e6, when=when_is("position", "fixed")),
        Key("y0", float, 0.0, "nm", "y position", -1e6, 1e6, when=when_is("position", "fixed")),
        Key(
            "box",
            float,
            50.0,
            "nm",
            "half-width of the box",
            0.0,
            1e6,
            True,
            when=when_is("position", "box"),
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
            when=when_is("psf", "airy"),
        ),
        Key(
            "na", float, 1.45, "", "numerical aperture", 0.0, 2.0, True, when=when_is("psf", "airy")
        ),
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
            when=when_is("kind", "gaussian", "truncated-gaussian", "binomial"),
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
            when=when_is("kind", "emccd", "scmos"),
        ),
        Key(
            "readout_sd",
            float,
            0.0,
            "e-",
            "EMCCD readout noise SD",
            0.0,
            1e4,
            when=when_is("kind", "emccd"),
        ),
        Key(
            "offset",
            float,
            0.0,
            "ADU",
            "bias added to every pixel",
            -1e9,
            1e9,
            when=when_is("kind", "emccd", "scmos"),
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
            when=when_is("kind", "emccd"),
        ),
        Key(
            "variance",
            float,
            0.0,
            "ADU^2",
            "sCMOS readout variance",
            0.0,
            1e9,
            when=when_is("kind", "scmos"),
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
            when=when_is("kind", "emccd"),
        ),
        Key(
            "register",
            ("gamma", "stages"),
            "gamma",
            "",
            "EMCCD multiplication: 'gamma' (the Gamma(n, gain) law the likelihood uses) or "
            "'stages' (each electron multiplies stage by stage with probability "
            "gain^(1/stages) - 1)",
            when=when_is("kind", "emccd"),
        ),
        Key(
            "stages",
            int,
            512,
            "",
            "number of EM stages for register = 'stages'",
            1,
            10000,
            when=when_is("register", "stages"),
        ),
        Key(
            "quantize",
            bool,
            False,
            "",
            "round counts to whole ADU (the ADC); false declares continuous counts. An sCMOS "
            "without readout (variance 0) is quantized only with whole gain and offset",
            when=when_is("kind", "emccd", "scmos"),
        ),
        Key(
            "saturation",
            float,
            0.0,
            "ADU",
            "counts above this are recorded as this (the ADC's full scale); 0 declares none",
            0.0,
            1e12,
            when=when_is("kind", "emccd", "scmos"),
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
            units.UNITS,
            "incident",
            "",
            "unit of N and b in the prior, the model, the truth table and every result: "
            "'incident' photons (photoelectrons / quantum_efficiency) or 'detected' "
            "photoelectrons (the same when quantum_efficiency is 1)",
        ),
        Key("likelihood", str, "", "", "likelihood tier for inference ('' = the camera's default)"),
    ),
    "axial": AXIAL,  # optional (OPTIONAL_SECTIONS): bayespsf.scene.optional
    "movie": MOVIE,
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


def _describe_when(section: str, key: Key) -> str:
    for other in SCHEMA[section]:
        if other.name == key.name or not isinstance(other.kind, tuple):
            continue
        hits = [v for v in other.kind if key.when({other.name: v})]
        if hits and len(hits) < len(other.kind):
            return f"when {other.name} is " + " or ".join(repr(h) for h in hits)
    return "only with other settings"


def likelihood_tiers(kind: str) -> tuple[str, ...]:
    """The likelihood tiers a scene's ``camera.likelihood`` may name for its camera ``kind``.

    Parameters
    ----------
    kind : str
        ``camera.kind``: ``"photon"``, ``"emccd"`` or ``"scmos"``.

    Returns
    -------
    tuple of str
        The camera law's tiers (``bayespsf.cameras``: ``emccd.TIERS``, ``scmos.TIERS``;
        ``"exact"`` and ``"poisson"``, one law, for a photon counter); none for another kind.
    """
    from bayespsf.cameras import emccd, photon, scmos  # on use: the camera laws load SciPy

    return {"photon": photon.TIERS, "emccd": emccd.TIERS, "scmos": scmos.TIERS}.get(kind, ())


def check_likelihood(camera: Mapping) -> None:
    """Refuse a ``camera.likelihood`` that is not one of its camera kind's tiers.

    Parameters
    ----------
    camera : Mapping
        A scene's normalised ``[camera]`` table (``kind`` and ``likelihood``).

    Raises
    ------
    SceneError
        Naming ``camera.likelihood``, the tiers allowed for ``camera.kind`` and the value
        given (``''``, the camera's default, is always allowed).
    """
    tiers = likelihood_tiers(camera["kind"])
    if camera["likelihood"] not in ("", *tiers):
        raise SceneError(
            f"camera.likelihood must be '' (the camera's default) or one of "
            f"{', '.join(map(repr, tiers))} for camera.kind = {camera['kind']!r}, "
            f"got {camera['likelihood']!r}"
        )


def default_prior(name: str, geometry: Mapping) -> dict:
    """The weak, proper default prior of each parameter (uniform/log-uniform over wide ranges).

    x0, y0: uniform over the ROI; s_x, s_y: log-uniform from a/10 to the ROI side; N: log-uniform
    over [1, 1e8] photons; b: uniform over [0, 1e4] photons per pixel (including exactly 0).

    Parameters
    ----------
    name : str
        A parameter, one of ``PRIOR_PARAMETERS`` (``x0 y0 s_x s_y N b``).
    geometry : Mapping
        A scene's ``[geometry]`` table: ``roi`` (pixels) and ``pixel_size`` (nm).

    Returns
    -------
    dict
        The prior table: ``kind`` with ``low`` and ``high`` (nm, photons or photons per pixel).
    """
    half = 0.5 * geometry["roi"] * geometry["pixel_size"]
    if name in ("x0", "y0"):
        return {"kind": "uniform", "low": -half, "high": half}
    if name in ("s_x", "s_y"):
        return {"kind": "log-uniform", "low": 0.1 * geometry["pixel_size"], "high": 2 * half}
    if name == "N":
        return {"kind": "log-uniform", "low": 1.0, "high": 1e8}
    return {"kind": "uniform", "low": 0.0, "high": 1e4}


_OPTIONAL_DOC = {
    "axial": "Optional: the table's presence declares that the spot's widths follow the "
    "emitter's axial position z through a defocus curve (`bayespsf.psf.defocus`); "
    "emitter.s0x and s0y are then the in-focus widths, and the truth table gains a `z` column. "
    "In a movie each molecule keeps the z it draws in every frame (immobile).",
    "movie": "Optional: the table's presence declares a movie, simulated by "
    "`bayespsf.simulation.movie.simulate_movie` (`bayespsf simulate SCENE --movie`); "
    "`bayespsf.simulate` ignores it. Each key below declares one effect; an absent key (or 0) "
    "declares none. See [Simulated movies](#simulated-movies).",
}


def schema_markdown() -> str:
    """docs/scenes.md's key tables, generated from ``SCHEMA``.

    Returns
    -------
    str
        Markdown: one table per scene section (key, default, unit, allowed, meaning).
    """
    lines = []
    for section, keys in SCHEMA.items():
        lines += [f"## [{section}]", ""]
        if section in OPTIONAL_SECTIONS:
            lines += [_OPTIONAL_DOC[section], ""]
        lines += ["| key | default | unit | allowed | meaning |", "|---|---|---|---|---|"]
        for k in keys:
            cond = f" Applies {_describe_when(section, k)}." if k.when else ""
            default = repr(k.default) if not isinstance(k.default, bool) else str(k.default).lower()
            lines.append(
                f"| `{k.name}` | `{default}` | {k.unit} | {k.allowed()} | {k.doc}.{cond} |".replace(
                    "..", "."
                )
            )
        lines.append("")
    lines += [
        "## [prior]",
        "",
        f"One table per parameter ({', '.join(PRIOR_PARAMETERS)}). {_PRIOR_KEY.doc}.",
        "",
        default_prior.__doc__.split("\n\n")[1].strip().replace("\n    ", " "),
        "",
    ]
    return "\n".join(lines)


def _drop_inapplicable(section: str, values: dict, keep: set) -> dict:
    """Drop keys (other than ``keep``) whose 'when' fails, until none fails (they cascade:
    camera.kind decides register, which decides stages), and a ``camera.likelihood`` tier
    that the camera's kind lacks (it takes the new kind's default)."""
    tier = values.get("likelihood", "") if section == "camera" else ""
    if tier and "likelihood" not in keep and tier not in likelihood_tiers(values.get("kind")):
        values = {k: v for k, v in values.items() if k != "likelihood"}
    keys = {k.name: k for k in SCHEMA[section]}
    while True:
        drop = [
            k
            for k in values
            if k not in keep and k in keys and keys[k].when is not None and not keys[k].when(values)
        ]
        if not drop:
            return values
        values = {k: v for k, v in values.items() if k not in drop}
