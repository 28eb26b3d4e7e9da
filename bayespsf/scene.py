"""Scenes: the single declaration of an experiment, read from TOML or a dict.

A scene declares the geometry, the emitter, the optics, the background, the camera and the
prior. The simulator applies exactly the effects it declares (no key, no effect) and the
inference model is built from the same scene, so the two cannot drift apart.

Every key, with its unit, default and allowed range, is listed in ``SCHEMA``;
``docs/scenes.md``'s tables are generated from it (``bayespsf schema``) and a test keeps the two
identical. Unknown keys, keys that the declared kind does not use, wrong types and values out of
range raise ``SceneError`` naming the key and the allowed range.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

from bayespsf import photon_units
from bayespsf.errors import BayespsfInputError


class SceneError(BayespsfInputError):
    """A scene key is unknown, unused by its kind, of the wrong type or out of range."""


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
OPTIONAL_SECTIONS = ("movie",)  # present in a scene only where declared

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
TOP_LEVEL = ("name", "description")
MAX_SCENE_CHARACTERS = 65536  # tomllib's time grows with the square of a dotted key's depth


def _check_value(section: str, key: Key, value: Any) -> Any:
    where = f"{section}.{key.name}"
    if isinstance(key.kind, tuple):
        if value not in key.kind:
            raise SceneError(f"{where} must be {key.allowed()}, got {value!r}")
        return value
    if key.kind is bool:
        if not isinstance(value, bool):
            raise SceneError(f"{where} must be true or false, got {value!r}")
        return value
    if key.kind is str:
        if not isinstance(value, str):
            raise SceneError(f"{where} must be a string, got {value!r}")
        return value
    if key.kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SceneError(f"{where} must be an integer in {key.allowed()}, got {value!r}")
    elif isinstance(value, bool) or not isinstance(value, int | float):
        raise SceneError(f"{where} must be a number in {key.allowed()}, got {value!r}")
    try:
        value = key.kind(value)
    except OverflowError:
        raise SceneError(f"{where} must be in {key.allowed()}, got {value!r}") from None
    bad_low = key.low is not None and (value <= key.low if key.low_open else value < key.low)
    bad_high = key.high is not None and (value >= key.high if key.high_open else value > key.high)
    if not math.isfinite(value) or bad_low or bad_high:
        raise SceneError(
            f"{where} must be in {key.allowed()} {key.unit}".rstrip() + f", got {value!r}"
        )
    if key.name == "roi" and value % 2 == 0:
        raise SceneError(f"{where} must be odd (the central pixel is the origin), got {value!r}")
    return value


def _normalise_section(section: str, given: Mapping) -> dict:
    if not isinstance(given, Mapping):
        raise SceneError(f"[{section}] must be a table, got {type(given).__name__}")
    keys = {k.name: k for k in SCHEMA[section]}
    unknown = sorted(set(given) - set(keys))
    if unknown:
        raise SceneError(
            f"unknown key {section}.{unknown[0]}; [{section}] takes: {', '.join(keys)}"
        )
    out: dict[str, Any] = {}
    for key in SCHEMA[section]:  # in schema order: a 'when' refers to keys decided before it
        context = {**out, **{k: v for k, v in given.items() if k not in out}}
        applies = key.when is None or key.when(context)
        if key.name in given:
            if not applies:
                raise SceneError(
                    f"{section}.{key.name} is not used by this {section} "
                    f"(it applies {_describe_when(section, key)}); remove it"
                )
            out[key.name] = _check_value(section, key, given[key.name])
        elif applies:
            out[key.name] = key.default
    return out


def _describe_when(section: str, key: Key) -> str:
    for other in SCHEMA[section]:
        if other.name == key.name or not isinstance(other.kind, tuple):
            continue
        hits = [v for v in other.kind if key.when({other.name: v})]
        if hits and len(hits) < len(other.kind):
            return f"when {other.name} is " + " or ".join(repr(h) for h in hits)
    return "only with other settings"


def _normalise_prior(given: Mapping, geometry: Mapping) -> dict:
    if not isinstance(given, Mapping):
        raise SceneError(f"[prior] must be a table, got {type(given).__name__}")
    unknown = sorted(set(given) - set(PRIOR_PARAMETERS))
    if unknown:
        raise SceneError(
            f"unknown key prior.{unknown[0]}; [prior] takes: {', '.join(PRIOR_PARAMETERS)}"
        )
    out = {}
    for name in PRIOR_PARAMETERS:
        spec = given.get(name, default_prior(name, geometry))
        out[name] = _check_prior(name, spec)
    return out


def _check_prior(name: str, spec: Any) -> dict:
    where = f"prior.{name}"
    if not isinstance(spec, Mapping) or "kind" not in spec:
        raise SceneError(f"{where} must be a table with kind = one of {_PRIOR_KINDS}")
    kind = spec["kind"]
    if not isinstance(kind, str) or kind not in _PRIOR_ARGS:
        raise SceneError(f"{where}.kind must be one of {_PRIOR_KINDS}, got {kind!r}")
    args = _PRIOR_ARGS[kind]
    extra = sorted(set(spec) - {"kind", *args})
    missing = [a for a in args if a not in spec]
    if extra or missing:
        raise SceneError(f"{where} of kind {kind!r} takes exactly {', '.join(args)}")
    out = {"kind": kind}
    for a in args:
        v = spec[a]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise SceneError(f"{where}.{a} must be a finite number, got {v!r}")
        out[a] = float(v)
    if kind in ("uniform", "log-uniform") and not out["low"] < out["high"]:
        raise SceneError(f"{where} needs low < high, got {out['low']} and {out['high']}")
    if kind == "log-uniform" and out["low"] <= 0:
        raise SceneError(f"{where}.low must be > 0 for a log-uniform prior")
    if kind == "normal" and out["sd"] <= 0:
        raise SceneError(f"{where}.sd must be > 0")
    if kind == "half-normal" and out["scale"] <= 0:
        raise SceneError(f"{where}.scale must be > 0")
    if name in ("s_x", "s_y", "N") and kind in ("uniform", "normal", "half-normal"):
        low = out.get("low", -math.inf if kind == "normal" else 0.0)
        if kind != "half-normal" and low <= 0:
            raise SceneError(
                f"{where} must give no mass to {name} <= 0 (use log-uniform, or low > 0)"
            )
    if name == "b" and kind == "uniform" and out["low"] < 0:
        raise SceneError(f"{where}.low must be >= 0 (background photons)")
    if name == "b" and kind == "normal":
        raise SceneError(
            f"{where} must give no mass to b < 0: use uniform, log-uniform or half-normal"
        )
    return out


def default_prior(name: str, geometry: Mapping) -> dict:
    """The weak, proper default prior of each parameter (uniform/log-uniform over wide ranges).

    x0, y0: uniform over the ROI; s_x, s_y: log-uniform from a/10 to the ROI side; N: log-uniform
    over [1, 1e8] photons; b: uniform over [0, 1e4] photons per pixel (including exactly 0).
    """
    half = 0.5 * geometry["roi"] * geometry["pixel_size"]
    if name in ("x0", "y0"):
        return {"kind": "uniform", "low": -half, "high": half}
    if name in ("s_x", "s_y"):
        return {"kind": "log-uniform", "low": 0.1 * geometry["pixel_size"], "high": 2 * half}
    if name == "N":
        return {"kind": "log-uniform", "low": 1.0, "high": 1e8}
    return {"kind": "uniform", "low": 0.0, "high": 1e4}


def _freeze(d: Mapping) -> MappingProxyType:
    return MappingProxyType({k: _freeze(v) if isinstance(v, Mapping) else v for k, v in d.items()})


class Scene:
    """A validated scene. Sections are read-only mappings: ``scene.emitter["photons"]``.

    Build with ``load`` (TOML file), ``loads`` (TOML text) or ``from_dict``;
    ``to_dict`` returns the normalised dict (every default filled in), and
    ``Scene.from_dict(scene.to_dict()) == scene`` exactly.
    """

    def __init__(self, data: Mapping):
        object.__setattr__(self, "_data", _freeze(data))

    def __setattr__(self, name, value):
        raise AttributeError("a Scene is immutable: build a new one with replace() or from_dict()")

    @classmethod
    def from_dict(cls, d: Mapping) -> Scene:
        if not isinstance(d, Mapping):
            raise SceneError(f"a scene must be a table (dict), got {type(d).__name__}")
        unknown = sorted(set(d) - set(SCHEMA) - {"prior", *TOP_LEVEL})
        if unknown:
            required = [s for s in SCHEMA if s not in OPTIONAL_SECTIONS]
            raise SceneError(
                f"unknown scene table or key {unknown[0]!r}; a scene has "
                + ", ".join([*TOP_LEVEL, *required, "prior", *OPTIONAL_SECTIONS])
            )
        out: dict[str, Any] = {}
        for key in TOP_LEVEL:
            if key in d:
                if not isinstance(d[key], str):
                    raise SceneError(f"{key} must be a string, got {d[key]!r}")
                out[key] = d[key]
        for section in SCHEMA:
            if section in OPTIONAL_SECTIONS and section not in d:
                continue
            out[section] = _normalise_section(section, d.get(section, {}))
        if out["optics"]["psf"] == "airy":  # the Airy pattern's width follows from wavelength, na
            for key in ("s0x", "s0y"):
                if key in d.get("emitter", {}):
                    raise SceneError(
                        f"emitter.{key} is not used with optics.psf = 'airy' (its width follows "
                        "from wavelength and na); remove it"
                    )
                del out["emitter"][key]
        out["prior"] = _normalise_prior(d.get("prior", {}), out["geometry"])
        _check_consistency(out)
        return cls(out)

    @classmethod
    def loads(cls, text: str) -> Scene:
        if len(text) > MAX_SCENE_CHARACTERS:
            raise SceneError(
                f"not a scene: {len(text)} characters, more than the {MAX_SCENE_CHARACTERS} a "
                "scene can need (a scene is a few dozen lines)"
            )
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(f"not valid TOML: {exc}") from exc
        except RecursionError:  # tomllib parses nested arrays and tables recursively
            raise SceneError(
                "not a scene: its tables or arrays are nested too deeply to parse (a scene "
                "nests two levels: [prior.N])"
            ) from None
        return cls.from_dict(data)

    @classmethod
    def load(cls, path: str | Path) -> Scene:
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except IsADirectoryError:
            raise SceneError(f"{path} is a directory, not a scene file (.toml)") from None
        except OSError as exc:
            raise SceneError(f"cannot read scene file {path}: {exc.strerror}") from exc
        except UnicodeDecodeError as exc:
            raise SceneError(
                f"{path} is not a scene file: TOML is UTF-8 text, and byte {exc.start} is not UTF-8"
            ) from None
        try:
            return cls.loads(text)
        except SceneError as exc:
            raise SceneError(f"{path}: {exc}") from exc

    def to_dict(self) -> dict:
        def thaw(m):
            return {k: thaw(v) if isinstance(v, Mapping) else v for k, v in m.items()}

        return thaw(self._data)

    def __reduce__(self):
        """Pickle as the normalised dict (scenes travel to worker processes and Dask)."""
        return Scene.from_dict, (self.to_dict(),)

    def dumps(self) -> str:
        """The scene as TOML text (every default written out)."""
        import tomli_w

        return tomli_w.dumps(self.to_dict())

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.dumps())

    def replace(self, **sections: Mapping) -> Scene:
        """A new scene with some keys changed: ``scene.replace(geometry={"pixel_size": 50.0})``;
        ``prior={"N": {...}}`` replaces whole priors of the parameters it names.

        Keys that no longer apply after the change (e.g. ``background.sd`` when the kind becomes
        'poisson') are dropped, and priors that were the defaults of the old geometry are
        re-derived from the new one.
        """
        d = self.to_dict()
        old_geometry = dict(d["geometry"])
        for section, changes in sections.items():
            if section == "prior":
                continue
            if section not in SCHEMA:
                raise SceneError(
                    f"no scene table {section!r}; tables: {', '.join([*SCHEMA, 'prior'])}"
                )
            given = {**d.get(section, {}), **changes}
            d[section] = _drop_inapplicable(section, given, set(changes))
        if d["optics"]["psf"] == "airy" and "emitter" not in sections:
            d["emitter"] = {k: v for k, v in d["emitter"].items() if k not in ("s0x", "s0y")}
        d["prior"] = {
            name: spec
            for name, spec in d["prior"].items()
            if spec != default_prior(name, old_geometry)
        }
        d["prior"].update(sections.get("prior", {}))
        return Scene.from_dict(d)

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        try:
            return self._data[name]
        except KeyError:
            raise AttributeError(f"a scene has no table {name!r}") from None

    def __eq__(self, other) -> bool:
        return isinstance(other, Scene) and self.to_dict() == other.to_dict()

    def __repr__(self) -> str:
        name = self._data.get("name", "unnamed")
        g, e, c = self.geometry, self.emitter, self.camera
        width = f"s0=({e['s0x']:g}, {e['s0y']:g}) nm" if "s0x" in e else "airy"
        return (
            f"Scene({name!r}: {g['roi']}x{g['roi']} px of {g['pixel_size']:g} nm, "
            f"N={e['photons']:g}, {width}, "
            f"background={self.background['kind']}, camera={c['kind']}"
            + (f", movie of {m['frames']} frames" if (m := self._data.get("movie")) else "")
            + ")"
        )


def _drop_inapplicable(section: str, values: dict, keep: set) -> dict:
    """Drop keys (other than ``keep``) whose 'when' fails, until none fails (they cascade:
    camera.kind decides register, which decides stages)."""
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


def _check_consistency(d: Mapping) -> None:
    bg = d["background"]
    if bg["kind"] == "gaussian":
        # rounding Normal(mean, sd) must essentially never give a negative photon count
        z = (bg["mean"] + 0.5) / bg["sd"]
        if z < 5.0:
            raise SceneError(
                "background kind 'gaussian' with mean "
                f"{bg['mean']:g} and sd {bg['sd']:g} gives negative photon counts "
                f"(P = {0.5 * math.erfc(z / math.sqrt(2)):.1e} per pixel; needs (mean + 0.5) / sd "
                ">= 5); use kind 'truncated-gaussian'"
            )
    if bg["kind"] == "binomial":
        mean, var = bg["mean"], bg["sd"] ** 2
        if not var < mean:
            raise SceneError(
                f"background.sd must satisfy sd^2 < mean for kind 'binomial' (got sd^2 = {var:g}, "
                f"mean = {mean:g})"
            )
        trials = mean * mean / (mean - var)
        if abs(trials - round(trials)) > 1e-9 * trials:
            n = max(round(trials), math.floor(mean) + 1)  # n > mean, so that 0 < sd^2 < mean
            suggestion = math.sqrt(mean - mean * mean / n)
            raise SceneError(
                f"background kind 'binomial' needs an integer number of trials mean^2/(mean - "
                f"sd^2); got {trials:.6g}. With mean {mean!r}, sd = {suggestion!r} gives {n}"
            )
    cam = d["camera"]
    if cam["kind"] == "emccd" and cam["gain"] < 1.0:
        raise SceneError(f"camera.gain must be >= 1 for an EMCCD, got {cam['gain']:g}")


_OPTIONAL_DOC = {
    "movie": "Optional: the table's presence declares a movie, simulated by "
    "`bayespsf.movie.simulate.simulate_movie` (`bayespsf simulate SCENE --movie`); "
    "`bayespsf.simulate` ignores it. Each key below declares one effect; an absent key (or 0) "
    "declares none. See [Simulated movies](#simulated-movies).",
}


def schema_markdown() -> str:
    """docs/scenes.md's key tables, generated from ``SCHEMA``."""
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
