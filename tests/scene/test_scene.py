"""Tests of bayespsf.scene: the scene schema, its validation, round trips, replace and the docs.

Expected values are written out by hand from the documented schema (docs/scenes.md) and from
the arithmetic of the checks (Gaussian rounding, binomial trials), not re-derived from the
module; the property test draws random valid scenes from SCHEMA and checks that every value
given survives to_dict/from_dict and TOML dumps/loads exactly, with its type.
"""

from __future__ import annotations

import itertools
import math
import re
import subprocess
import sys
import tomllib
from collections.abc import Mapping
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayespsf import load_scene, shipped_scenes
from bayespsf.errors import BayespsfInputError
from bayespsf.scene import (
    OPTIONAL_SECTIONS,
    PRIOR_PARAMETERS,
    SCHEMA,
    Key,
    Scene,
    SceneError,
    default_prior,
    schema_markdown,
)
from bayespsf.scene.schema import likelihood_tiers

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs" / "scenes.md"
SCENE_DIR = ROOT / "bayespsf" / "scene" / "shipped"
PHOTON_CAMERA = {
    "kind": "photon",
    "quantum_efficiency": 1.0,
    "photon_unit": "incident",
    "likelihood": "",
}
SHIPPED = (
    "astigmatic",
    "emccd-typical",
    "ideal",
    "paper-fig2",
    "paper-fig3",
    "paper-movie",
    "scmos-typical",
)
KEYS: dict[str, dict[str, Key]] = {sec: {k.name: k for k in keys} for sec, keys in SCHEMA.items()}


def _typed(obj):
    """obj with every leaf replaced by (type, value), so that 1 and 1.0 compare unequal."""
    if isinstance(obj, Mapping):
        return {k: _typed(v) for k, v in obj.items()}
    return (type(obj).__name__, obj)


def _assert_round_trips(scene: Scene) -> None:
    d = scene.to_dict()
    again = Scene.from_dict(d)
    assert again == scene
    assert _typed(again.to_dict()) == _typed(d)
    text = scene.dumps()
    assert tomllib.loads(text) == d
    reloaded = Scene.loads(text)
    assert reloaded == scene
    assert _typed(reloaded.to_dict()) == _typed(d)


def _applicable(section: str, given: Mapping) -> dict:
    """The keys of a section that apply to ``given`` (schema order), with given or default values.

    Written independently of scene.py's normalisation: a key's ``when`` sees the keys before it.
    """
    out: dict = {}
    for key in SCHEMA[section]:
        if key.when is None or key.when(out):
            out[key.name] = given.get(key.name, key.default)
    return out


def _context(section: str, name: str, applies: bool) -> dict:
    """A section of choice keys under which key ``name`` does (or does not) apply."""
    choice_keys = [k for k in SCHEMA[section] if isinstance(k.kind, tuple) and k.name != name]
    for combo in itertools.product(*(k.kind for k in choice_keys)):
        given = {k.name: c for k, c in zip(choice_keys, combo, strict=True)}
        given = {k: v for k, v in given.items() if k in _applicable(section, given)}
        if (name in _applicable(section, given)) == applies:
            return given
    raise AssertionError(f"no context where {section}.{name} applies={applies}")


# --------------------------------------------------------------------------------------------
# Shipped scenes and round trips
# --------------------------------------------------------------------------------------------


def test_shipped_names():
    assert shipped_scenes() == list(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_scene_keeps_every_value_of_its_file(name):
    raw = tomllib.loads((SCENE_DIR / f"{name}.toml").read_text())
    scene = load_scene(name)
    d = scene.to_dict()
    assert d["name"] == name
    assert d["description"] == raw["description"]
    for section in SCHEMA:
        for key, value in raw.get(section, {}).items():
            assert d[section][key] == value, f"{section}.{key}"
            assert type(d[section][key]) is type(KEYS[section][key].default)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_scene_round_trips(name, tmp_path):
    scene = load_scene(name)
    _assert_round_trips(scene)
    path = tmp_path / f"{name}.toml"
    scene.save(path)
    loaded = Scene.load(path)
    assert loaded == scene
    assert _typed(loaded.to_dict()) == _typed(scene.to_dict())
    assert Scene.load(str(path)) == scene
    assert Scene.load(SCENE_DIR / f"{name}.toml") == scene


def test_shipped_scene_values():
    fig3 = load_scene("paper-fig3")
    assert fig3.geometry == {"roi": 19, "pixel_size": 79.0}
    assert fig3.emitter["photon_statistics"] == "fixed"
    assert "x0" not in fig3.emitter and "box" not in fig3.emitter  # position = 'pixel'
    assert fig3.background == {"kind": "truncated-gaussian", "mean": 4.0, "sd": 1.0}
    assert fig3.camera["kind"] == "emccd" and fig3.camera["gain"] == 1.0
    assert "variance" not in fig3.camera and "stages" not in fig3.camera
    scmos = load_scene("scmos-typical")
    assert "readout_sd" not in scmos.camera and "register" not in scmos.camera
    assert scmos.camera["variance"] == 12.0
    assert load_scene("ideal").camera == PHOTON_CAMERA


# Strategies: random valid scenes drawn from SCHEMA ------------------------------------------


def _number(key: Key):
    if key.kind is int:
        if key.name == "roi":  # the PSF needs odd ROIs
            return st.integers(0, (int(key.high) - 1) // 2).map(lambda k: 2 * k + 1)
        return st.integers(int(key.low), int(key.high))
    floats = st.floats(
        min_value=key.low,
        max_value=key.high,
        exclude_min=key.low_open,
        exclude_max=key.high_open,
        allow_nan=False,
        allow_infinity=False,
        allow_subnormal=False,
    )
    lo = math.ceil(key.low) + (1 if key.low_open and float(key.low).is_integer() else 0)
    hi = math.floor(min(key.high, 1e6)) - (1 if key.high_open else 0)
    ints = st.integers(lo, hi) if lo <= hi else st.nothing()
    return st.one_of(floats, floats, ints)  # an integer given for a float key becomes a float


def _value(section: str, key: Key):
    if isinstance(key.kind, tuple):
        return st.sampled_from(key.kind)
    if key.kind is bool:
        return st.booleans()
    if key.kind is str:
        return st.text(max_size=12)
    return _number(key)


@st.composite
def _prior_spec(draw, name: str):
    kinds = ["uniform", "log-uniform", "half-normal"]
    if name in ("x0", "y0"):
        kinds.append("normal")
    kind = draw(st.sampled_from(kinds))
    positive = st.floats(1e-3, 1e6)
    if kind == "half-normal":
        return {"kind": kind, "scale": draw(positive)}
    if kind == "normal":
        return {"kind": kind, "mean": draw(st.floats(-1e6, 1e6)), "sd": draw(positive)}
    if kind == "log-uniform" or name in ("s_x", "s_y", "N"):
        bound = positive
    elif name == "b":
        bound = st.floats(0.0, 1e6)
    else:
        bound = st.floats(-1e6, 1e6)
    low, high = sorted(draw(st.lists(bound, min_size=2, max_size=2, unique=True)))
    return {"kind": kind, "low": low, "high": high}


@st.composite
def scene_dicts(draw):
    """(scene dict, the applicable keys of each section with the values expected)."""
    d: dict = {}
    for top in ("name", "description"):
        if draw(st.booleans()):
            d[top] = draw(st.text(max_size=20))
    psf = draw(st.sampled_from(KEYS["optics"]["psf"].kind))
    expected: dict = {}
    for section, keys in SCHEMA.items():
        optional = section in OPTIONAL_SECTIONS
        if optional and ((section == "axial" and psf == "airy") or draw(st.booleans())):
            continue  # an optional table left out (the Airy PSF takes no [axial])
        given: dict = {}
        normal: dict = {}
        for key in keys:
            if key.when is not None and not key.when(normal):
                continue
            if section == "emitter" and key.name in ("s0x", "s0y") and psf == "airy":
                continue
            if section == "optics" and key.name == "psf":
                value = psf
            elif section == "camera" and key.name == "gain" and normal["kind"] == "emccd":
                value = draw(st.floats(1.0, 1e5))
            elif section == "camera" and key.name == "likelihood":  # a tier of the camera kind
                value = draw(st.sampled_from(("", *likelihood_tiers(normal["kind"]))))
            else:
                value = draw(_value(section, key))
            # a choice other than the default must be given; any other key may be left out
            if value != key.default or draw(st.booleans()):
                given[key.name] = value
                normal[key.name] = value
            else:
                normal[key.name] = key.default
        if section == "background" and normal["kind"] == "gaussian":
            mean = draw(st.floats(0.0, 1e6))
            sd = (mean + 0.5) / 5.0 * draw(st.floats(0.01, 0.99))
            given.update(mean=mean, sd=sd)
            normal.update(mean=mean, sd=sd)
        if section == "background" and normal["kind"] == "binomial":
            n = draw(st.integers(1, 10_000))
            p = draw(st.floats(0.05, 0.95))
            mean, sd = n * p, math.sqrt(n * p * (1 - p))
            given.update(mean=mean, sd=sd)
            normal.update(mean=mean, sd=sd)
        if (
            section == "camera"
            and normal["kind"] == "scmos"
            and normal["quantize"]
            and normal["variance"] == 0
        ):  # a readout-free sCMOS is quantized only on whole gain and offset: give it readout
            variance = draw(st.floats(0.01, 1e9))
            given.update(variance=variance)
            normal.update(variance=variance)
        if section == "axial":  # a z range inside both curves' domain: A = 0, B >= 0
            for key in ("A_x", "A_y", "B_x", "B_y"):
                if key in normal:
                    value = 0.0 if key[0] == "A" else abs(normal[key])
                    given[key] = normal[key] = value
            if "z_low" in normal:
                low, high = sorted(
                    draw(st.lists(st.floats(-1e6, 1e6), min_size=2, max_size=2, unique=True))
                )
                given.update(z_low=low, z_high=high)
                normal.update(z_low=low, z_high=high)
        if section == "movie":  # a photon range that runs forwards, both ends declared
            low, high = sorted(draw(st.lists(st.floats(1e-9, 1e9), min_size=2, max_size=2)))
            given.update(photons_low=low, photons_high=high)
            normal.update(photons_low=low, photons_high=high)
        if given or optional or draw(st.booleans()):
            d[section] = given
        expected[section] = normal
    priors = {name: draw(_prior_spec(name)) for name in PRIOR_PARAMETERS if draw(st.booleans())}
    if priors or draw(st.booleans()):
        d["prior"] = priors
    return d, expected


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scene_dicts())
def test_random_valid_scenes_round_trip_exactly(case):
    d, expected = case
    scene = Scene.from_dict(d)
    out = scene.to_dict()
    for top in ("name", "description"):
        assert out.get(top) == d.get(top)
    assert set(out) - {"name", "description", "prior"} == set(expected)
    for section in expected:
        assert list(out[section]) == list(expected[section]), section
        for key, value in expected[section].items():
            want = float(value) if KEYS[section][key].kind is float else value
            assert out[section][key] == want, f"{section}.{key}"
            assert type(out[section][key]) is type(KEYS[section][key].default), f"{section}.{key}"
    for name in PRIOR_PARAMETERS:
        spec = d.get("prior", {}).get(name) or default_prior(name, out["geometry"])
        assert out["prior"][name] == spec, name
    _assert_round_trips(scene)


# --------------------------------------------------------------------------------------------
# Defaults
# --------------------------------------------------------------------------------------------


def test_empty_scene_is_all_defaults():
    d = Scene.from_dict({}).to_dict()
    assert _typed(d) == _typed(
        {
            "geometry": {"roi": 15, "pixel_size": 100.0},
            "emitter": {
                "photons": 1000.0,
                "photon_statistics": "poisson",
                "photon_jitter": 0.0,
                "s0x": 120.0,
                "s0y": 120.0,
                "width_jitter": 0.0,
                "position": "fixed",
                "x0": 0.0,
                "y0": 0.0,
            },
            "optics": {"psf": "gaussian"},
            "background": {"kind": "none"},
            "camera": PHOTON_CAMERA,
            "prior": {
                "x0": {"kind": "uniform", "low": -750.0, "high": 750.0},
                "y0": {"kind": "uniform", "low": -750.0, "high": 750.0},
                "s_x": {"kind": "log-uniform", "low": 10.0, "high": 1500.0},
                "s_y": {"kind": "log-uniform", "low": 10.0, "high": 1500.0},
                "N": {"kind": "log-uniform", "low": 1.0, "high": 1e8},
                "b": {"kind": "uniform", "low": 0.0, "high": 1e4},
            },
        }
    )
    required = {s: {} for s in SCHEMA if s not in OPTIONAL_SECTIONS}  # [movie] declares a movie
    assert Scene.from_dict({}) == Scene.loads("") == Scene.from_dict(required)


@pytest.mark.parametrize(
    ("section", "choice", "expected_keys"),
    [
        ("emitter", {"position": "pixel"}, {"x0": None, "y0": None, "box": None}),
        ("emitter", {"position": "box"}, {"box": 50.0, "x0": None, "y0": None}),
        ("optics", {"psf": "airy"}, {"wavelength": 580.0, "na": 1.45}),
        ("background", {"kind": "poisson"}, {"mean": 0.0, "sd": None}),
        ("background", {"kind": "truncated-gaussian"}, {"mean": 0.0, "sd": 1.0}),
        (
            "camera",
            {"kind": "emccd"},
            {
                "gain": 100.0,
                "readout_sd": 0.0,
                "offset": 0.0,
                "e_per_adu": 1.0,
                "variance": None,
                "clock_induced_charge": 0.0,
                "register": "gamma",
                "stages": None,
                "quantize": False,
                "saturation": 0.0,
                "quantum_efficiency": 1.0,
                "photon_unit": "incident",
                "likelihood": "",
            },
        ),
        ("camera", {"kind": "emccd", "register": "stages"}, {"stages": 512}),
        (
            "camera",
            {"kind": "scmos"},
            {
                "gain": 100.0,
                "offset": 0.0,
                "variance": 0.0,
                "readout_sd": None,
                "e_per_adu": None,
                "register": None,
                "clock_induced_charge": None,
                "quantize": False,
                "saturation": 0.0,
            },
        ),
    ],
)
def test_defaults_of_keys_a_kind_brings_in(section, choice, expected_keys):
    got = Scene.from_dict({section: choice}).to_dict()[section]
    for key, value in expected_keys.items():
        if value is None:
            assert key not in got, key
        else:
            assert got[key] == value and type(got[key]) is type(value), key
    assert got == _applicable(section, choice)


def test_every_schema_default_is_valid_for_its_key():
    for section, keys in SCHEMA.items():
        for key in keys:
            given = {**_context(section, key.name, applies=True), key.name: key.default}
            if section == "background" and given["kind"] in ("gaussian", "binomial"):
                given["kind"] = "truncated-gaussian"
            scene = Scene.from_dict({section: given})
            assert scene.to_dict()[section][key.name] == key.default


@pytest.mark.parametrize(
    ("roi", "pixel_size", "half"),
    [(19, 79.0, 750.5), (1, 100.0, 50.0), (401, 2.5, 501.25), (15, 108.0, 810.0)],
)
def test_default_priors_follow_the_geometry(roi, pixel_size, half):
    scene = Scene.from_dict({"geometry": {"roi": roi, "pixel_size": pixel_size}})
    p = scene.prior
    for name in ("x0", "y0"):
        assert p[name] == {"kind": "uniform", "low": -half, "high": half}
    for name in ("s_x", "s_y"):
        assert p[name]["kind"] == "log-uniform"
        assert p[name]["low"] == pytest.approx(pixel_size / 10, rel=1e-15)
        assert p[name]["high"] == 2 * half
    assert p["N"] == {"kind": "log-uniform", "low": 1.0, "high": 1e8}
    assert p["b"] == {"kind": "uniform", "low": 0.0, "high": 1e4}
    for name in PRIOR_PARAMETERS:
        assert p[name] == default_prior(name, scene.geometry)


def test_smallest_allowed_pixel_size_gets_a_valid_default_prior():
    scene = Scene.from_dict({"geometry": {"pixel_size": 1.0}})
    assert scene.prior["s_x"]["low"] > 0


def test_declared_prior_replaces_only_its_own_default():
    scene = Scene.from_dict({"prior": {"x0": {"kind": "normal", "mean": 5, "sd": 20}}})
    assert _typed(scene.prior["x0"]) == _typed({"kind": "normal", "mean": 5.0, "sd": 20.0})
    assert scene.prior["y0"] == {"kind": "uniform", "low": -750.0, "high": 750.0}


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------


def _raises(d, pattern):
    with pytest.raises(ValueError, match=pattern) as info:
        Scene.from_dict(d)
    assert isinstance(info.value, SceneError)
    return str(info.value)


def test_scene_error_is_a_value_error():
    assert issubclass(SceneError, BayespsfInputError)
    assert issubclass(SceneError, ValueError)


def test_unknown_top_level_table():
    msg = _raises({"geometri": {"roi": 15}}, r"unknown scene table or key 'geometri'")
    assert "name, description, geometry, emitter, optics, background, camera, prior" in msg
    _raises({"geometry": {}, "pior": {}}, r"'pior'")


@pytest.mark.parametrize("section", [*SCHEMA, "prior"])
def test_unknown_key_in_each_section(section):
    takes = ", ".join(KEYS[section]) if section in SCHEMA else ", ".join(PRIOR_PARAMETERS)
    _raises(
        {section: {"bogus": 1}},
        re.escape(f"unknown key {section}.bogus; [{section}] takes: {takes}"),
    )


@pytest.mark.parametrize(
    ("d", "message"),
    [
        ({"geometry": {"roi": "15"}}, "geometry.roi must be an integer in [1, 401], got '15'"),
        ({"geometry": {"roi": 15.0}}, "geometry.roi must be an integer in [1, 401], got 15.0"),
        ({"geometry": {"roi": True}}, "geometry.roi must be an integer in [1, 401], got True"),
        (
            {"emitter": {"photons": "1000"}},
            "emitter.photons must be a number in (0, 1e+09], got '1000'",
        ),
        (
            {"emitter": {"photons": True}},
            "emitter.photons must be a number in (0, 1e+09], got True",
        ),
        (
            {"geometry": {"pixel_size": None}},
            "geometry.pixel_size must be a number in [1, 100000], got None",
        ),
        ({"camera": {"kind": "emccd", "quantize": 1}}, "camera.quantize must be true or false"),
        ({"camera": {"likelihood": 3}}, "camera.likelihood must be a string, got 3"),
        (
            {"emitter": {"position": "centre"}},
            "emitter.position must be one of 'fixed', 'pixel', 'box', got 'centre'",
        ),
        ({"camera": {"kind": "CCD"}}, "camera.kind must be one of 'photon', 'emccd', 'scmos'"),
        ({"geometry": 15}, "[geometry] must be a table, got int"),
        ({"prior": [1]}, "[prior] must be a table, got list"),
        ({"name": 3}, "name must be a string, got 3"),
        ({"description": ["a"]}, "description must be a string"),
    ],
)
def test_wrong_types(d, message):
    _raises(d, re.escape(message))


def test_a_scene_must_be_a_table():
    with pytest.raises(ValueError, match="a scene must be a table"):
        Scene.from_dict([("geometry", {})])


@pytest.mark.parametrize(
    ("section", "key", "value", "message"),
    [
        ("geometry", "roi", 0, "geometry.roi must be in [1, 401] pixels, got 0"),
        ("geometry", "roi", 403, "geometry.roi must be in [1, 401] pixels, got 403"),
        ("geometry", "pixel_size", 0.5, "geometry.pixel_size must be in [1, 100000] nm, got 0.5"),
        ("emitter", "photons", -1, "emitter.photons must be in (0, 1e+09] photons, got -1.0"),
        ("emitter", "photon_jitter", 1.0, "emitter.photon_jitter must be in [0, 1) relative"),
        ("emitter", "s0x", math.nan, "emitter.s0x must be in (0, 100000] nm, got nan"),
        ("emitter", "s0y", math.inf, "emitter.s0y must be in (0, 100000] nm, got inf"),
        ("optics", "na", 2.5, "optics.na must be in (0, 2], got 2.5"),
        ("background", "mean", -0.5, "background.mean must be in [0, 1e+07] photons"),
        ("camera", "stages", 0, "camera.stages must be in [1, 10000], got 0"),
        ("camera", "readout_sd", -1.0, "camera.readout_sd must be in [0, 10000] e-, got -1.0"),
    ],
)
def test_out_of_range_messages(section, key, value, message):
    given = {**_context(section, key, applies=True), key: value}
    _raises({section: given}, re.escape(message))


def _outside(key: Key):
    """Values just outside the allowed range of a numeric key."""
    if key.kind is int:
        return [int(key.low) - 1, int(key.high) + 1]
    low = key.low if key.low_open else math.nextafter(key.low, -math.inf)
    high = key.high if key.high_open else math.nextafter(key.high, math.inf)
    return [low, high, math.nan, math.inf, -math.inf]


def _inside(key: Key):
    if key.kind is int:
        return [int(key.low), int(key.high) if key.name != "roi" else 401]
    low = max(key.low + 1e-12, math.nextafter(key.low, math.inf)) if key.low_open else key.low
    high = math.nextafter(key.high, -math.inf) if key.high_open else key.high
    return [low, high]


NUMERIC = [
    (section, key)
    for section, keys in SCHEMA.items()
    for key in keys
    if key.kind in (int, float) and key.low is not None
]


def test_a_movie_photon_range_that_runs_backwards_is_refused():
    # a 0 stands for emitter.photons (1 000 here): 1 500 to 0 runs backwards as 1 500 to 500
    for movie in ({"photons_low": 6000.0, "photons_high": 5000.0}, {"photons_low": 1500.0}):
        _raises(
            {"movie": movie}, r"movie\.photons_low \(\d+\) must not be above movie\.photons_high"
        )
    for movie in ({"photons_low": 5000.0, "photons_high": 5000.0}, {"photons_high": 1500.0}):
        Scene.from_dict({"movie": movie})  # one photon count, or emitter.photons up to 1 500


@pytest.mark.parametrize(("section", "key"), NUMERIC, ids=[f"{s}.{k.name}" for s, k in NUMERIC])
def test_every_numeric_key_checks_its_range(section, key):
    base = _context(section, key.name, applies=True)
    if section == "background":
        base["kind"] = "poisson" if key.name == "mean" else "truncated-gaussian"
    if section == "camera" and base.get("kind") == "emccd" and key.name == "gain":
        base = {"kind": "scmos"}  # the EMCCD's own gain >= 1 rule is tested separately
    if section == "axial" and key.name in ("z_low", "z_high"):  # z_low < z_high is its own rule
        base.update({"z_low": -1e6, "z_high": 1e6})
    if section == "movie" and key.name in ("photons_low", "photons_high"):  # so is low <= high
        base.update({"photons_low": 1e-9, "photons_high": 1e9})
    for value in _outside(key):
        _raises({section: {**base, key.name: value}}, re.escape(f"{section}.{key.name} must be"))
        msg = _raises({section: {**base, key.name: value}}, re.escape(key.allowed()))
        assert msg.endswith(f"got {key.kind(value)!r}")
    for value in _inside(key):
        scene = Scene.from_dict({section: {**base, key.name: value}})
        assert scene.to_dict()[section][key.name] == value


def test_allowed_ranges_as_documented():
    assert KEYS["geometry"]["roi"].allowed() == "[1, 401]"
    assert KEYS["geometry"]["pixel_size"].allowed() == "[1, 100000]"
    assert KEYS["emitter"]["photon_jitter"].allowed() == "[0, 1)"
    assert KEYS["emitter"]["x0"].allowed() == "[-1e+06, 1e+06]"
    assert KEYS["camera"]["register"].allowed() == "one of 'gamma', 'stages'"
    assert KEYS["camera"]["quantize"].allowed() == "bool"


@pytest.mark.parametrize("roi", [1, 3, 15, 19, 401])
def test_odd_roi_accepted(roi):
    assert Scene.from_dict({"geometry": {"roi": roi}}).geometry["roi"] == roi


@pytest.mark.parametrize("roi", [2, 14, 400])
def test_even_roi_rejected(roi):
    _raises({"geometry": {"roi": roi}}, r"geometry\.roi.*odd")


@pytest.mark.parametrize(
    ("d", "message"),
    [
        (
            {"background": {"kind": "poisson", "mean": 1.0, "sd": 1.0}},
            "background.sd is not used by this background (it applies when kind is 'gaussian' or "
            "'truncated-gaussian' or 'binomial'); remove it",
        ),
        (
            {"background": {"mean": 1.0}},
            "background.mean is not used by this background (it applies when kind is 'poisson' "
            "or 'gaussian' or 'truncated-gaussian' or 'binomial')",
        ),
        (
            {"camera": {"kind": "photon", "gain": 10.0}},
            "camera.gain is not used by this camera (it applies when kind is 'emccd' or 'scmos')",
        ),
        (
            {"emitter": {"position": "fixed", "box": 10.0}},
            "emitter.box is not used by this emitter (it applies when position is 'box')",
        ),
        (
            {"emitter": {"position": "box", "x0": 10.0}},
            "emitter.x0 is not used by this emitter (it applies when position is 'fixed')",
        ),
        (
            {"camera": {"kind": "emccd", "register": "gamma", "stages": 100}},
            "camera.stages is not used by this camera (it applies when register is 'stages')",
        ),
        (
            {"camera": {"kind": "emccd", "stages": 100}},
            "camera.stages is not used by this camera (it applies when register is 'stages')",
        ),
        (
            {"camera": {"kind": "scmos", "readout_sd": 1.0}},
            "camera.readout_sd is not used by this camera (it applies when kind is 'emccd')",
        ),
        (
            {"camera": {"kind": "emccd", "variance": 1.0}},
            "camera.variance is not used by this camera (it applies when kind is 'scmos')",
        ),
        (
            {"optics": {"wavelength": 600.0}},
            "optics.wavelength is not used by this optics (it applies when psf is 'airy')",
        ),
    ],
)
def test_key_not_used_by_the_declared_kind(d, message):
    _raises(d, re.escape(message))


CONDITIONAL = [(s, k) for s, keys in SCHEMA.items() for k in keys if k.when is not None]


@pytest.mark.parametrize(
    ("section", "key"), CONDITIONAL, ids=[f"{s}.{k.name}" for s, k in CONDITIONAL]
)
def test_every_conditional_key_rejected_where_it_does_not_apply(section, key):
    given = {**_context(section, key.name, applies=False), key.name: key.default}
    _raises({section: given}, re.escape(f"{section}.{key.name} is not used by this {section}"))


def test_gaussian_background_that_rounds_negative_is_rejected():
    msg = _raises(
        {"background": {"kind": "gaussian", "mean": 4, "sd": 1}},
        r"background kind 'gaussian' with mean 4 and sd 1 gives negative photon counts",
    )
    assert "use kind 'truncated-gaussian'" in msg
    # P(Normal(4, 1) < -0.5) = Phi(-4.5) = 3.4e-06
    assert "P = 3.4e-06 per pixel" in msg
    ok = Scene.from_dict({"background": {"kind": "truncated-gaussian", "mean": 4, "sd": 1}})
    assert ok.background == {"kind": "truncated-gaussian", "mean": 4.0, "sd": 1.0}
    # (mean + 0.5) / sd = 5 exactly is the boundary: accepted
    Scene.from_dict({"background": {"kind": "gaussian", "mean": 4.5, "sd": 1}})
    Scene.from_dict({"background": {"kind": "gaussian", "mean": 20.0, "sd": 2.0}})
    _raises({"background": {"kind": "gaussian", "mean": 4.49, "sd": 1}}, "truncated-gaussian")


def test_binomial_background_with_integer_trials_accepted():
    # n = 20, p = 0.5: mean 10, variance 5
    scene = Scene.from_dict({"background": {"kind": "binomial", "mean": 10, "sd": math.sqrt(5)}})
    assert scene.background["mean"] == 10.0
    # n = 1, p = 0.25: mean 0.25, sd^2 = 0.1875
    Scene.from_dict({"background": {"kind": "binomial", "mean": 0.25, "sd": math.sqrt(0.1875)}})


def test_readout_free_scmos_is_not_quantized_off_its_lattice():
    # v = 0: the sCMOS law lives on offset + gain n; rounding to whole ADU leaves it (zero
    # likelihood for every simulated ROI) unless gain and offset are whole numbers of ADU
    import numpy as np

    from bayespsf import Model, simulate

    base = load_scene("scmos-typical").to_dict()
    camera = {**base["camera"], "variance": 0.0}
    _raises({**base, "camera": camera}, r"camera.quantize = true with camera.variance = 0 .*")
    continuous = Scene.from_dict({**base, "camera": {**camera, "quantize": False}})
    counts, truth = simulate(continuous, n=3, seed=2)
    model = Model.from_scene(continuous)
    assert np.isfinite(model.log_likelihood(counts, truth.to_numpy())).all()
    rounded = np.round(counts)  # what quantize would record
    law = model.camera.log_likelihood_unchecked(rounded, model.expected(truth.to_numpy()))
    assert np.isneginf(law.sum(axis=(-2, -1))).all()
    whole = Scene.from_dict({**base, "camera": {**camera, "gain": 2.0, "offset": 100.0}})
    counts, truth = simulate(whole, n=3, seed=2)
    assert np.isfinite(Model.from_scene(whole).log_likelihood(counts, truth.to_numpy())).all()


def test_binomial_background_needs_sd_squared_below_mean():
    _raises(
        {"background": {"kind": "binomial", "mean": 4, "sd": 2}},
        re.escape("background.sd must satisfy sd^2 < mean for kind 'binomial' (got sd^2 = 4,"),
    )


@pytest.mark.parametrize(
    ("mean", "sd"),
    [
        (10.0, 2.9),
        (4.0, 1.9),
        (0.5, 0.3),
        (7.0, 2.0),
        (2.4, 0.2214),
        (3.0, 0.1),
        (10.0, 3.1),
        (100.0, 9.99),
    ],
)
def test_binomial_background_non_integer_trials_and_the_suggested_sd(mean, sd):
    msg = _raises(
        {"background": {"kind": "binomial", "mean": mean, "sd": sd}},
        r"background kind 'binomial' needs an integer number of trials",
    )
    trials = mean**2 / (mean - sd**2)
    assert f"got {trials:.6g}" in msg
    m = re.search(r"sd = (\S+) gives (\d+)$", msg)
    assert m, msg
    suggested, n = float(m[1]), int(m[2])
    assert abs(n - trials) <= 1.0
    scene = Scene.from_dict({"background": {"kind": "binomial", "mean": mean, "sd": suggested}})
    assert mean**2 / (mean - scene.background["sd"] ** 2) == pytest.approx(n, rel=1e-9)


def test_emccd_gain_below_one_rejected():
    _raises(
        {"camera": {"kind": "emccd", "gain": 0.5}},
        re.escape("camera.gain must be >= 1 for an EMCCD, got 0.5"),
    )
    assert Scene.from_dict({"camera": {"kind": "emccd", "gain": 1}}).camera["gain"] == 1.0
    assert Scene.from_dict({"camera": {"kind": "scmos", "gain": 0.5}}).camera["gain"] == 0.5


@pytest.mark.parametrize(
    ("prior", "message"),
    [
        ({"z0": {"kind": "uniform", "low": 0, "high": 1}}, "unknown key prior.z0; [prior] takes"),
        ({"x0": {"kind": "cauchy", "low": 0, "high": 1}}, "prior.x0.kind must be one of ("),
        (
            {"x0": {"kind": "uniform", "low": 0}},
            "prior.x0 of kind 'uniform' takes exactly low, high",
        ),
        ({"y0": {"kind": "normal", "mean": 0}}, "prior.y0 of kind 'normal' takes exactly mean, sd"),
        (
            {"b": {"kind": "normal", "mean": 0, "sd": 1, "low": 0}},
            "prior.b of kind 'normal' takes exactly mean, sd",
        ),
        ({"b": {"kind": "half-normal", "scale": 1, "sd": 1}}, "takes exactly scale"),
        ({"x0": {"low": 0, "high": 1}}, "prior.x0 must be a table with kind = one of"),
        ({"x0": 3.0}, "prior.x0 must be a table with kind"),
        ({"x0": {"kind": "uniform", "low": 1, "high": 1}}, "prior.x0 needs low < high"),
        ({"x0": {"kind": "uniform", "low": 2, "high": 1}}, "prior.x0 needs low < high"),
        ({"N": {"kind": "log-uniform", "low": 10, "high": 5}}, "prior.N needs low < high"),
        ({"N": {"kind": "log-uniform", "low": 0, "high": 5}}, "prior.N.low must be > 0"),
        ({"s_x": {"kind": "log-uniform", "low": -1, "high": 5}}, "prior.s_x.low must be > 0"),
        (
            {"s_x": {"kind": "uniform", "low": 0, "high": 500}},
            "prior.s_x must give no mass to s_x <= 0",
        ),
        ({"s_y": {"kind": "normal", "mean": 100, "sd": 10}}, "prior.s_y must give no mass"),
        ({"N": {"kind": "uniform", "low": -1, "high": 10}}, "prior.N must give no mass to N <= 0"),
        ({"b": {"kind": "uniform", "low": -1, "high": 10}}, "prior.b.low must be >= 0"),
        ({"x0": {"kind": "normal", "mean": 0, "sd": 0}}, "prior.x0.sd must be > 0"),
        ({"b": {"kind": "half-normal", "scale": -1}}, "prior.b.scale must be > 0"),
        ({"x0": {"kind": "uniform", "low": "0", "high": 1}}, "prior.x0.low must be a finite"),
        ({"x0": {"kind": "uniform", "low": 0, "high": math.inf}}, "prior.x0.high must be a finite"),
        ({"x0": {"kind": "normal", "mean": True, "sd": 1}}, "prior.x0.mean must be a finite"),
    ],
)
def test_prior_errors(prior, message):
    _raises({"prior": prior}, re.escape(message))


def test_valid_priors_accepted():
    prior = {
        "s_x": {"kind": "uniform", "low": 1, "high": 500},
        "N": {"kind": "log-uniform", "low": 10, "high": 1e6},
        "b": {"kind": "half-normal", "scale": 3},
        "y0": {"kind": "normal", "mean": -5, "sd": 30},
    }
    scene = Scene.from_dict({"prior": prior})
    for name, spec in prior.items():
        assert _typed(scene.prior[name]) == _typed(
            {k: (v if k == "kind" else float(v)) for k, v in spec.items()}
        )
    Scene.from_dict({"prior": {"b": {"kind": "uniform", "low": 0, "high": 5}}})


def test_prior_kind_of_wrong_type():
    with pytest.raises(ValueError, match=r"prior\.x0\.kind"):
        Scene.loads('[prior.x0]\nkind = ["uniform"]\nlow = 0\nhigh = 1\n')


def test_huge_integer_for_a_float_key():
    _raises({"emitter": {"photons": 10**400}}, r"emitter\.photons")


def test_invalid_toml():
    with pytest.raises(ValueError, match=r"^not valid TOML: ") as info:
        Scene.loads("[geometry\nroi = 15\n")
    assert isinstance(info.value, SceneError)
    with pytest.raises(ValueError, match="not valid TOML"):
        Scene.loads("[geometry]\nroi = 15\nroi = 17\n")


def test_load_errors_name_the_file(tmp_path):
    missing = tmp_path / "missing.toml"
    with pytest.raises(ValueError, match=re.escape(f"cannot read scene file {missing}")):
        Scene.load(missing)
    bad = tmp_path / "bad.toml"
    bad.write_text("[geometry]\nroi = 0\n")
    with pytest.raises(ValueError, match=re.escape(f"{bad}: geometry.roi must be in [1, 401]")):
        Scene.load(bad)
    broken = tmp_path / "broken.toml"
    broken.write_text("roi = = 3\n")
    with pytest.raises(ValueError, match=re.escape(f"{broken}: not valid TOML")):
        Scene.load(broken)


def test_loads_errors_like_from_dict():
    with pytest.raises(ValueError, match=re.escape("unknown key camera.gian")):
        Scene.loads('[camera]\nkind = "emccd"\ngian = 100.0\n')
    with pytest.raises(ValueError, match=re.escape("geometry.roi must be an integer")):
        Scene.loads("[geometry]\nroi = 15.0\n")


@pytest.mark.parametrize("key", ["s0x", "s0y"])
def test_airy_with_explicit_width_rejected(key):
    _raises(
        {"optics": {"psf": "airy"}, "emitter": {key: 100.0}},
        re.escape(f"emitter.{key} is not used with optics.psf = 'airy'"),
    )


def test_airy_scene_round_trips(tmp_path):
    scene = Scene.from_dict(
        {
            "name": "airy",
            "optics": {"psf": "airy", "wavelength": 600, "na": 1.4},
            "emitter": {"photons": 2000, "position": "box", "box": 30},
        }
    )
    d = scene.to_dict()
    assert "s0x" not in d["emitter"] and "s0y" not in d["emitter"]
    assert d["optics"] == {"psf": "airy", "wavelength": 600.0, "na": 1.4}
    _assert_round_trips(scene)
    scene.save(tmp_path / "airy.toml")
    assert Scene.load(tmp_path / "airy.toml") == scene
    assert "airy" in repr(scene)


# --------------------------------------------------------------------------------------------
# replace
# --------------------------------------------------------------------------------------------


def test_replace_background_kind_drops_sd():
    fig3 = load_scene("paper-fig3")
    new = fig3.replace(background={"kind": "poisson"})
    assert new.background == {"kind": "poisson", "mean": 4.0}
    assert fig3.background == {"kind": "truncated-gaussian", "mean": 4.0, "sd": 1.0}
    assert new.to_dict() == {**fig3.to_dict(), "background": {"kind": "poisson", "mean": 4.0}}
    assert new.replace(background={"kind": "none"}).background == {"kind": "none"}


def test_replace_pixel_size_rederives_default_priors_and_keeps_declared_ones():
    declared = {
        "x0": {"kind": "uniform", "low": -100.0, "high": 100.0},
        "N": {"kind": "log-uniform", "low": 10.0, "high": 1e5},
        "b": {"kind": "half-normal", "scale": 5.0},
    }
    scene = Scene.from_dict({"geometry": {"roi": 15, "pixel_size": 100.0}, "prior": declared})
    new = scene.replace(geometry={"pixel_size": 50.0})
    assert new.geometry == {"roi": 15, "pixel_size": 50.0}
    assert new.prior["y0"] == {"kind": "uniform", "low": -375.0, "high": 375.0}
    assert new.prior["s_x"] == {"kind": "log-uniform", "low": 5.0, "high": 750.0}
    assert new.prior["s_y"] == new.prior["s_x"]
    for name, spec in declared.items():
        assert new.prior[name] == spec
    assert scene.prior["y0"] == {"kind": "uniform", "low": -750.0, "high": 750.0}
    bigger = new.replace(geometry={"roi": 21})
    assert bigger.prior["y0"] == {"kind": "uniform", "low": -525.0, "high": 525.0}
    assert bigger.prior["x0"] == declared["x0"]


def test_replace_changes_only_what_is_asked():
    scene = load_scene("emccd-typical")
    new = scene.replace(emitter={"photons": 250}, camera={"readout_sd": 10})
    expected = scene.to_dict()
    expected["emitter"]["photons"] = 250.0
    expected["camera"]["readout_sd"] = 10.0
    assert _typed(new.to_dict()) == _typed(expected)
    moved = scene.replace(emitter={"position": "box"})
    assert moved.emitter["box"] == 50.0 and "x0" not in moved.emitter
    fixed = moved.replace(emitter={"position": "fixed", "x0": 12.5})
    assert "box" not in fixed.emitter and fixed.emitter["x0"] == 12.5 and fixed.emitter["y0"] == 0
    scmos = scene.replace(camera={"kind": "scmos"})
    assert set(scmos.camera) == {
        "kind",
        "gain",
        "offset",
        "variance",
        "quantize",
        "saturation",
        "quantum_efficiency",
        "photon_unit",
        "likelihood",
    }


def test_replace_errors():
    scene = load_scene("ideal")
    with pytest.raises(ValueError, match=re.escape("no scene table 'geometri'; tables: geometry")):
        scene.replace(geometri={"roi": 15})
    with pytest.raises(ValueError, match=re.escape("unknown key geometry.rio")):
        scene.replace(geometry={"rio": 15})
    with pytest.raises(ValueError, match=re.escape("geometry.roi must be in [1, 401]")):
        scene.replace(geometry={"roi": 0})
    with pytest.raises(ValueError, match=re.escape("background.sd is not used")):
        scene.replace(background={"sd": 2.0})


def test_replace_camera_kind_drops_stages():
    scene = Scene.from_dict({"camera": {"kind": "emccd", "register": "stages", "stages": 64}})
    assert scene.replace(camera={"kind": "photon"}).camera == PHOTON_CAMERA


def test_replace_psf_to_airy_drops_widths():
    new = load_scene("ideal").replace(optics={"psf": "airy"})
    assert "s0x" not in new.emitter and "s0y" not in new.emitter


def test_replace_airy_to_gaussian_restores_default_widths():
    airy = Scene.from_dict({"optics": {"psf": "airy"}})
    new = airy.replace(optics={"psf": "gaussian"})
    assert new.optics == {"psf": "gaussian"}
    assert new.emitter["s0x"] == 120.0 and new.emitter["s0y"] == 120.0


# --------------------------------------------------------------------------------------------
# docs/scenes.md
# --------------------------------------------------------------------------------------------


def _docs_schema_block() -> str:
    text = DOCS.read_text()
    assert text.count("<!-- schema:start -->") == 1 and text.count("<!-- schema:end -->") == 1
    return text.split("<!-- schema:start -->")[1].split("<!-- schema:end -->")[0]


def test_docs_tables_equal_schema_markdown():
    assert _docs_schema_block().strip() == schema_markdown().strip()


def test_every_key_is_documented_in_its_section():
    block = _docs_schema_block()
    parts = re.split(r"^## \[(\w+)\]$", block, flags=re.M)
    sections = dict(zip(parts[1::2], parts[2::2], strict=True))
    assert list(sections) == [*SCHEMA, "prior"]
    for section, keys in SCHEMA.items():
        rows = [line for line in sections[section].splitlines() if line.startswith("| `")]
        assert [row.split("`")[1] for row in rows] == [k.name for k in keys]
        for key, row in zip(keys, rows, strict=True):
            assert f"| {key.allowed()} |" in row, key.name
    for name in PRIOR_PARAMETERS:
        assert name in sections["prior"]


@pytest.fixture(scope="module")
def schema_main():
    return subprocess.run(
        [sys.executable, "-W", "error", "-m", "bayespsf.cli", "schema"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
        timeout=60,
    )


def test_schema_command_prints_the_tables(schema_main):
    assert schema_main.stdout == schema_markdown() + "\n"


def test_schema_command_runs_cleanly(schema_main):
    assert schema_main.stderr == ""


# --------------------------------------------------------------------------------------------
# Access, immutability, repr, shipped-scene lookup
# --------------------------------------------------------------------------------------------


def test_attribute_access():
    scene = load_scene("paper-fig2")
    assert scene.geometry["roi"] == 15
    assert scene.emitter["photon_jitter"] == 0.2
    assert scene.name == "paper-fig2"
    assert scene.prior["x0"]["low"] == -0.5 * 15 * 79.0
    assert isinstance(scene.camera, Mapping)
    with pytest.raises(AttributeError, match="a scene has no table 'lens'"):
        _ = scene.lens
    with pytest.raises(AttributeError):
        _ = scene._private
    with pytest.raises(AttributeError):
        _ = Scene.from_dict({}).name


def test_sections_are_read_only():
    scene = load_scene("paper-fig3")
    with pytest.raises(TypeError):
        scene.geometry["roi"] = 21
    with pytest.raises(TypeError):
        del scene.background["sd"]
    with pytest.raises(TypeError):
        scene.prior["x0"]["low"] = 0.0
    assert scene == load_scene("paper-fig3")


def test_no_aliasing_with_dicts():
    d = {"geometry": {"roi": 15}, "prior": {"b": {"kind": "half-normal", "scale": 2.0}}}
    scene = Scene.from_dict(d)
    d["geometry"]["roi"] = 17
    d["prior"]["b"]["scale"] = 9.0
    assert scene.geometry["roi"] == 15 and scene.prior["b"]["scale"] == 2.0
    out = scene.to_dict()
    out["geometry"]["roi"] = 21
    out["prior"]["b"]["scale"] = 7.0
    assert scene.geometry["roi"] == 15 and scene.prior["b"]["scale"] == 2.0


def test_sections_cannot_be_rebound():
    scene = load_scene("ideal")
    with pytest.raises((AttributeError, TypeError)):
        scene.geometry = {"roi": 3, "pixel_size": 1.0}


def test_equality():
    a = load_scene("ideal")
    assert a == load_scene("ideal")
    assert a != a.replace(emitter={"photons": 999.0})
    assert a != a.to_dict()
    assert Scene.from_dict({"name": "a"}) != Scene.from_dict({"name": "b"})


def test_repr_mentions_the_name():
    r = repr(load_scene("paper-fig3"))
    assert r.startswith("Scene('paper-fig3': 19x19 px of 79 nm, N=500, s0=(120, 120) nm")
    assert "background=truncated-gaussian, camera=emccd" in r
    assert "'unnamed'" in repr(Scene.from_dict({}))


def test_unknown_shipped_scene():
    with pytest.raises(
        ValueError,
        match=re.escape("no shipped scene 'nope'; shipped: " + ", ".join(SHIPPED)),
    ):
        load_scene("nope")


def test_scene_pickles_to_an_equal_scene():
    import pickle

    scene = load_scene("paper-fig2")
    assert pickle.loads(pickle.dumps(scene)) == scene
