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
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

from bayespsf.scene.key import SceneError
from bayespsf.scene.schema import (
    _PRIOR_ARGS,
    _PRIOR_KINDS,
    OPTIONAL_SECTIONS,
    PRIOR_PARAMETERS,
    SCHEMA,
    Key,
    _describe_when,
    _drop_inapplicable,
    check_likelihood,
    default_prior,
)
from bayespsf.scene.sections import check_sections

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


def _freeze(d: Mapping) -> MappingProxyType:
    return MappingProxyType({k: _freeze(v) if isinstance(v, Mapping) else v for k, v in d.items()})


class Scene:
    """A validated scene. Sections are read-only mappings: ``scene.emitter["photons"]``.

    ``to_dict`` returns the normalised dict (every default filled in), and
    ``Scene.from_dict(scene.to_dict()) == scene`` exactly. Scenes are immutable and pickle as
    that dict.

    Parameters
    ----------
    data : Mapping
        A normalised scene, as ``from_dict`` makes it; not checked. Build scenes with ``load``
        (TOML file), ``loads`` (TOML text) or ``from_dict``.

    See Also
    --------
    load_scene : the scenes shipped with the package.
    bayespsf.Model.from_scene, bayespsf.simulate : a scene's model and its images.
    """

    def __init__(self, data: Mapping):
        object.__setattr__(self, "_data", _freeze(data))

    def __setattr__(self, name, value):
        raise AttributeError("a Scene is immutable: build a new one with replace() or from_dict()")

    @classmethod
    def from_dict(cls, d: Mapping) -> Scene:
        """A scene from a dict of tables, every omitted key given its default.

        Parameters
        ----------
        d : Mapping
            ``name``, ``description`` and tables (``geometry``, ``emitter``, ``optics``,
            ``background``, ``camera``, ``prior``, optional ``axial`` and ``movie``), as in a
            TOML scene; keys in the units of ``SCHEMA``.

        Returns
        -------
        Scene

        Raises
        ------
        SceneError
            If a key is unknown, unused by its kind, of the wrong type or out of range.

        Examples
        --------
        >>> from bayespsf import Scene
        >>> scene = Scene.from_dict({"geometry": {"roi": 11}, "emitter": {"photons": 2000.0}})
        >>> scene.geometry["pixel_size"], scene.camera["kind"], scene.prior["N"]["kind"]
        (100.0, 'photon', 'log-uniform')
        """
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
        """A scene from TOML text (see ``from_dict``).

        Parameters
        ----------
        text : str
            The scene in TOML.

        Returns
        -------
        Scene

        Raises
        ------
        SceneError
            If the text is not TOML, is too long or too deeply nested to be a scene, or
            ``from_dict`` refuses its tables.
        """
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
        """A scene from a TOML file.

        Parameters
        ----------
        path : str or Path
            The scene file (UTF-8 TOML).

        Returns
        -------
        Scene

        Raises
        ------
        SceneError
            If the file cannot be read or is not a valid scene (the message names the file).

        Examples
        --------
        >>> import tempfile
        >>> from bayespsf import Scene, load_scene
        >>> path = tempfile.mkdtemp() + "/fig3.toml"
        >>> load_scene("paper-fig3").save(path)
        >>> Scene.load(path) == load_scene("paper-fig3")
        True
        """
        path = Path(path)
        if path.exists() and not path.is_file():  # a directory, or a pipe: reading would wait
            kind = "a directory" if path.is_dir() else "not a regular file (a pipe or device)"
            raise SceneError(f"{path} is {kind}, not a scene file (.toml)")
        try:
            text = path.read_text(encoding="utf-8")
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
        """The normalised scene as a new, mutable dict of tables (every default filled in).

        Returns
        -------
        dict
        """

        def thaw(m):
            return {k: thaw(v) if isinstance(v, Mapping) else v for k, v in m.items()}

        return thaw(self._data)

    def __reduce__(self):
        """Pickle as the normalised dict (scenes travel to worker processes and Dask)."""
        return Scene.from_dict, (self.to_dict(),)

    def dumps(self) -> str:
        """The scene as TOML text (every default written out).

        Returns
        -------
        str
        """
        import tomli_w

        return tomli_w.dumps(self.to_dict())

    def save(self, path: str | Path) -> None:
        """Write ``dumps()`` to a file.

        Parameters
        ----------
        path : str or Path
            The TOML file to write (overwritten).
        """
        Path(path).write_text(self.dumps())

    def replace(self, **sections: Mapping) -> Scene:
        """A new scene with some keys changed: ``scene.replace(geometry={"pixel_size": 50.0})``.

        Parameters
        ----------
        **sections : Mapping
            Per table, the keys to change; ``prior={"N": {...}}`` replaces whole priors of the
            parameters it names.

        Returns
        -------
        Scene

        Raises
        ------
        SceneError
            If a table is unknown or the changed scene is invalid.

        Notes
        -----
        Keys that no longer apply after the change (e.g. ``background.sd`` when the kind becomes
        'poisson', or a ``camera.likelihood`` tier the new camera kind lacks) are dropped, and
        priors that were the defaults of the old geometry are re-derived from the new one.
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
    check_likelihood(cam)
    if cam["kind"] == "scmos" and cam["quantize"] and cam["variance"] == 0:
        gain, offset = cam["gain"], cam["offset"]
        if gain != round(gain) or offset != round(offset):  # else rounding keeps the lattice
            raise SceneError(
                "camera.quantize = true with camera.variance = 0 rounds the counts off the "
                f"readout-free sCMOS lattice offset + gain n ({offset:g} + {gain:g} n ADU), where "
                "the camera law gives them zero likelihood: declare the readout variance "
                "(camera.variance > 0), whole-ADU gain and offset, or quantize = false"
            )
    check_sections(d)
