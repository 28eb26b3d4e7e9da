"""Every camera law over its documented numerical domain (docs/cameras.md, "Numerical domain"):
``log_likelihood`` is never NaN or +inf, is -inf only outside the law's support (each place is
named below), ``score`` is finite wherever ``log_likelihood`` is (``expected >= 1e-100``), and
nothing warns (warnings are errors in this suite). Plus regressions of reported overflows and the
layering of ``bayespsf.cameras`` (no import from the simulator layer above it)."""

import ast
import pathlib

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

import bayespsf
from bayespsf.cameras import EMCCD, SCMOS, Photon, emccd
from bayespsf.cameras import _emccd_law as law
from bayespsf.cameras import _emccd_table as table
from bayespsf.cameras import draws as _draws
from bayespsf.errors import BayespsfInputError
from bayespsf.simulation import camera_effects

SCORE_MIN_EXPECTED = 1e-100  # the score's documented floor (the law's own reaches 0)


def log_uniform(lo, hi):
    return st.floats(lo, hi).map(lambda e: 10.0**e)


# expected photons per pixel: 0, the whole [1e-300, 1e10] and the typical [1e-3, 1e4]
EXPECTED = st.one_of(st.just(0.0), log_uniform(-300, 10), log_uniform(-3, 4))


# the largest count inside the documented domain: the round trip to ADU and back
# (offset + t gain / e_per_adu) may add a few ulps to MAX_GAIN_UNITS itself
INSIDE_LIMIT = emccd.MAX_GAIN_UNITS * (1 - 1e-12)


def count_in_units(lam, scale, rng_z, magnitude, kind):
    """A count (in the law's own units) near the law, far from it (either sign) or at 0."""
    if kind == "near":
        return lam + scale * rng_z
    if kind == "zero":
        return 0.0
    return magnitude if kind == "far above" else -magnitude


POINT = st.tuples(
    EXPECTED,
    st.floats(-8.0, 8.0),
    log_uniform(-14, 15),
    st.sampled_from(["near", "far above", "far below", "zero"]),
)


def emccd_support(tier, t, lam, r):
    """Where the tier's law has positive density (or mass), in gain units.

    -inf is allowed only outside: below the offset without readout (exact, table, high-gain)
    and for the poisson tier; above the offset with lam == 0 and no readout (all mass at the
    offset), and for the poisson tier at any readout; off t == 0 for the gaussian tier with
    lam == 0 and no readout (a zero-width Normal).
    """
    if tier == "poisson":
        return (t >= 0) & ((lam > 0) | (t == 0))
    if r > 0:
        return np.ones(np.shape(t), dtype=bool)
    if tier == "gaussian":
        return (lam > 0) | (t == 0)
    return (t >= 0) & ((lam > 0) | (t == 0))


def check_emccd(cam, t, lam):
    counts = cam.offset + t * cam.gain / cam.e_per_adu
    value = cam.log_likelihood(counts, lam)
    t = cam.gain_units(counts)  # the count the camera sees, after rounding to ADU
    r = cam.readout_in_gain_units
    inside = emccd_support(cam.likelihood, t, lam, r)
    if cam.likelihood == "gaussian" and r == 0:
        # Normal(lam, 2 lam) at lam < 1e-278: log p below -1.8e308 is -inf, the nearest double
        with np.errstate(over="ignore"):
            z2 = (t - lam) ** 2 / (4.0 * np.where(lam > 0, lam, 1.0))
        inside &= (lam == 0) | (z2 < 1e308)
    assert not np.any(np.isnan(value)) and not np.any(value == np.inf)
    assert np.all(np.isfinite(value[inside]))
    assert np.all(value[~inside] == -np.inf)
    score = cam.score(counts, lam)
    checked = np.isfinite(value) & (lam >= SCORE_MIN_EXPECTED)
    assert np.all(np.isfinite(score[checked]))
    return value


@settings(max_examples=60, deadline=None)
@given(
    tier=st.sampled_from(["exact", "high-gain", "gaussian", "poisson"]),
    gain=log_uniform(0, 4),
    ratio=st.one_of(st.just(0.0), log_uniform(-12, 6), log_uniform(-4, 2.5)),
    offset=st.floats(-1e3, 1e3),
    e_per_adu=log_uniform(-1, 2),
    points=st.lists(POINT, min_size=1, max_size=12),
)
# a reported +inf far above the offset, and the gaussian tier without readout at tiny lam
@example("exact", 1.0, 1e-6, 0.0, 12.0, [(1394750.35, 0.0, 329229925.285 * 12.0, "far above")])
@example(
    "gaussian",
    1.0,
    0.0,
    0.0,
    1.0,
    [(1e-290, 0.0, 1e12, "far above"), (1e-90, 0.0, 1.0, "far below")],
)
def test_emccd_tiers_over_the_documented_domain(tier, gain, ratio, offset, e_per_adu, points):
    cam = EMCCD(gain, ratio * gain, offset, e_per_adu, likelihood=tier)
    r = cam.readout_in_gain_units
    lam = np.array([p[0] for p in points])
    scale = np.sqrt(2.0 * lam + r * r)
    t = np.array(
        [count_in_units(p[0], s, p[1], p[2], p[3]) for p, s in zip(points, scale, strict=True)]
    )
    t = np.clip(t, -INSIDE_LIMIT, INSIDE_LIMIT)
    check_emccd(cam, t, lam)


# the table is built once per readout/gain ratio (seconds): one ratio inside its range (the one
# tests/cameras/test_emccd_table.py builds too), and one on either side (the exact law is used
# there)
@settings(max_examples=25, deadline=None)
@given(
    ratio=st.sampled_from([0.1, 1e-6, 5.0, 0.0]),
    points=st.lists(POINT, min_size=1, max_size=12),
)
def test_emccd_table_tier_over_the_documented_domain(ratio, points):
    cam = EMCCD(300.0, ratio * 300.0, 500.0, 12.0, likelihood="table")
    lam = np.array([p[0] for p in points])
    scale = np.sqrt(2.0 * lam + ratio * ratio)
    t = np.array(
        [count_in_units(p[0], s, p[1], p[2], p[3]) for p, s in zip(points, scale, strict=True)]
    )
    check_emccd(cam, np.clip(t, -INSIDE_LIMIT, INSIDE_LIMIT), lam)


@settings(max_examples=40, deadline=None)
@given(
    counts=st.lists(
        st.one_of(st.integers(0, 50), log_uniform(0, 15).map(np.round)), min_size=1, max_size=12
    ),
    lam=st.lists(EXPECTED, min_size=1, max_size=1),
)
def test_photon_over_the_documented_domain(counts, lam):
    k = np.array(counts, dtype=float)
    value = Photon().log_likelihood(k, lam[0])
    inside = (lam[0] > 0) | (k == 0)  # lam == 0: all mass at k == 0
    assert np.all(np.isfinite(value[inside])) and np.all(value[~inside] == -np.inf)
    if lam[0] >= SCORE_MIN_EXPECTED:
        assert np.all(np.isfinite(Photon().score(k, lam[0])))


@settings(max_examples=30, deadline=None)
@given(
    tier=st.sampled_from(["exact", "huang"]),
    gain=log_uniform(-2, 2),
    readout_e=st.one_of(st.just(0.0), log_uniform(-2, 2)),
    offset=st.floats(-1e3, 1e3),
    points=st.lists(POINT, min_size=1, max_size=8),
)
# a readout-free pixel far from the spot: differences of log p stepped onto lam = 0 (+inf)
@example("exact", 1.0, 0.0, 0.0, [(1e-20, 0.0, 3.0, "far above")])
def test_scmos_over_the_documented_domain(tier, gain, readout_e, offset, points):
    cam = SCMOS(gain, offset, (readout_e * gain) ** 2, likelihood=tier)
    lam = np.array([p[0] for p in points])
    y = np.array(
        [count_in_units(p[0], np.sqrt(p[0] + readout_e**2), p[1], p[2], p[3]) for p in points]
    )
    y = np.clip(y, -1e15, 1e15)
    if readout_e == 0:
        y = np.round(y)  # on the lattice (off it the law has no support)
    counts = offset + gain * y
    value = cam.log_likelihood(counts, lam)
    y = (counts - offset) / gain  # the count the camera sees, after rounding to ADU
    if readout_e == 0:
        inside = (y >= 0) & ((lam > 0) | (y == 0))  # the Poisson lattice
    elif tier == "huang":
        inside = y + readout_e**2 >= 0  # Huang's shifted Poisson has no support below
    else:
        inside = np.ones(y.shape, dtype=bool)
    assert not np.any(np.isnan(value)) and not np.any(value == np.inf)
    assert np.all(np.isfinite(value[inside])) and np.all(value[~inside] == -np.inf)
    score = cam.score(counts, lam)
    checked = np.isfinite(value) & (lam >= SCORE_MIN_EXPECTED)
    assert np.all(np.isfinite(score[checked]))


# ------------------------------------------------------------- regressions of reported overflows


ISSUE = [  # (camera, counts, expected) as reported: +inf and NaN in the exact and table tiers
    (dict(gain=1.0, readout_sd=1e-6, offset=0.0, e_per_adu=12.0), 329229925.285, 1394750.35),
    (dict(gain=5000.0, readout_sd=0.001, offset=0.0, e_per_adu=0.3), 188120783687.9, 9463761.1),
]


@pytest.mark.parametrize("params,counts,lam", ISSUE)
@pytest.mark.parametrize("tier", ["exact", "table", "high-gain", "gaussian", "poisson"])
def test_issue_examples_are_finite_in_every_tier(params, counts, lam, tier):
    cam = EMCCD(**params, likelihood=tier)
    assert np.isfinite(cam.log_likelihood(counts, lam))
    assert np.isfinite(cam.score(counts, lam))


@pytest.mark.parametrize("params,counts,lam", ISSUE)
def test_issue_examples_equal_the_closed_form_and_the_quadrature(params, counts, lam):
    # readout/gain 1e-6 and 2e-7 cannot change log p at double precision there: the exact tier
    # is the closed form, and the (fixed) quadrature agrees with it to its rounding: it takes
    # differences of log 0F1(;2;lam u) ~ 2 sqrt(lam t) ~ 2e7 there, ~1e-9 absolute
    cam = EMCCD(**params)
    t = np.array([cam.gain_units(counts)])
    lams = np.array([lam])
    r = cam.readout_in_gain_units
    closed = law.log_high_gain(t, lams)[0]
    assert cam.log_likelihood(counts, lam) == pytest.approx(
        closed + np.log(cam.e_per_adu / cam.gain), rel=1e-15
    )
    quadrature, score = law._log_convolved_quadrature(t, lams, r, with_score=True)
    assert quadrature[0] == pytest.approx(closed, rel=1e-13)
    assert score[0] == pytest.approx(law.score_high_gain(t, lams)[0], rel=1e-9)


@pytest.mark.parametrize(
    "t,lam,r,switched",
    [
        (3.0, 1.0, 1e-7, True),  # amplified bulk
        (40.0, 10.0, 1e-7, True),  # upper tail
        (1e4 + 300.0, 1e4, 1e-6, True),  # lam 1e4
        (3.0, 1.0, 1e-5, False),  # the readout moves log p by ~1e-11: quadrature
        (0.5, 100.0, 1e-6, False),  # lower tail, steep log f (g' ~ 13)
        (2e-3, 3.0, 4e-5, False),  # 50 readout SDs above the offset, g'' ~ -0.8
        (3e-5, 3.0, 1e-6, False),  # 30 readout SDs: never switched (boundary at 0)
    ],
)
def test_readout_negligible_only_within_its_bound(t, lam, r, switched):
    # where the switch fires the closed form equals the quadrature within the documented bound
    # B = r^2 max(g'^2, |g''|) / 2, which must then be below max(1e-13, 2^-53 |log f|)
    t, lam = np.array([t]), np.array([lam])
    negligible, log_f = law.readout_negligible(t, lam, r)
    assert negligible[0] == switched
    quadrature = law._log_convolved_quadrature(t, lam, r, with_score=False)
    closed = law.log_amplified(t, lam)
    # the quadrature's own rounding: differences of log 0F1(;2;lam u) ~ 2 sqrt(lam t)
    rounding = 1e-12 + 4e-15 * np.sqrt(lam[0] * t[0]) + 4e-16 * abs(closed[0])
    if negligible[0]:
        assert log_f[0] == closed[0]
        assert abs(quadrature[0] - closed[0]) <= 1e-13 + rounding
    g1 = -1.0 + lam * law.dlog_0f1_2(lam * t)
    _, g2 = law.dlog_0f1_2(lam * (t - 40.0 * r), second=True)
    bound = 0.5 * r * r * max(g1[0] ** 2, -(lam[0] ** 2) * g2[0])
    # the bound really bounds: |quadrature - closed| <= B (+ the quadrature's rounding)
    assert abs(quadrature[0] - closed[0]) <= bound + rounding
    if t[0] > 40.0 * r:
        assert negligible[0] == (bound <= max(1e-13, 2.0**-53 * abs(closed[0])))


# DESIGN.md's known traps, each at readout/gain 1e-6 (the regime of the reported overflows), 0.1, 3
TRAPS = {
    "lam 1e4": (1e4 + 50.0, 1e4),
    "lam 1e4, far tail": (3e4, 1e4),
    "counts far below the offset": (-5e3, 10.0),
    "counts of 1e6+ electrons/G": (2e6, 1.0),
    "lam 1e-3": (0.5, 1e-3),
    "lam 1e-3, amplified tail": (30.0, 1e-3),
}


@pytest.mark.parametrize("tier", ["exact", "table", "high-gain", "gaussian"])
# readout comparable to G = 1 (3 e-: beyond the table's R_MAX, so no table is built for it)
@pytest.mark.parametrize("gain,readout", [(1.0, 3.0), (100.0, 1e-4), (300.0, 30.0)])
@pytest.mark.parametrize("trap", TRAPS, ids=list(TRAPS))
def test_known_traps_are_finite_in_every_tier(trap, gain, readout, tier):
    t, lam = TRAPS[trap]
    cam = EMCCD(gain, readout, 100.0, 1.0, likelihood=tier)
    counts = 100.0 + t * gain
    assert np.isfinite(cam.log_likelihood(counts, lam))
    assert np.isfinite(cam.score(counts, lam))


@pytest.mark.parametrize("ratio", [0.0, 1e-12, 1e6])
def test_fisher_information_at_the_ends_of_the_readout_range(ratio):
    # expected values outside the Fisher table (1e-6..1e6) are computed directly: no table is
    # built; lam I lies in (0, 1] (at most the photon-counting information 1 / lam)
    lam = np.array([1e-100, 1e-8, 1e8, 1e10])
    info = EMCCD(1.0, ratio).fisher_information(lam)
    assert np.all(np.isfinite(info)) and np.all(info > 0)
    assert np.all(lam * info <= 1.0 + 1e-6)


def test_the_domain_is_refused_outside_with_the_limit_named():
    for readout in (1e-13, 2e6):
        with pytest.raises(BayespsfInputError, match=r"readout_sd.*1e-12.*1e\+06"):
            EMCCD(1.0, readout)
    EMCCD(1.0, 0.0), EMCCD(1.0, 1e-12), EMCCD(1.0, 1e6)  # the ends themselves are accepted
    cam = EMCCD(100.0, 10.0, 50.0, 2.0)
    edge = 50.0 + emccd.MAX_GAIN_UNITS * 100.0 / 2.0
    assert np.isfinite(cam.log_likelihood(edge, 1.0))
    for bad in (edge * 1.01, 50.0 - (edge - 50.0) * 1.01):
        with pytest.raises(BayespsfInputError, match=r"counts must be within offset"):
            cam.log_likelihood(bad, 1.0)
        with pytest.raises(BayespsfInputError, match=r"counts must be within offset"):
            cam.score(bad, 1.0)
    with pytest.raises(BayespsfInputError, match="expected"):
        cam.log_likelihood(60.0, emccd.MAX_EXPECTED * 2)


def test_table_below_its_readout_range_is_the_exact_law():
    # readout/gain below table.R_MIN: the bulk grid no longer resolves the readout peak (log p
    # was off by 1e19 at r = 1e-12); the exact law is used instead, with no table built
    table.table_for.cache_clear()
    cam = dict(gain=1.0, readout_sd=1e-6, offset=0.0, e_per_adu=1.0)
    t = np.array([5e-6, 0.02, 1.0, 60.0, -1e-5])
    lam = np.array([55.0, 50.0, 3.0, 40.0, 2.0])
    fast = EMCCD(**cam, likelihood="table").log_likelihood(t, lam)
    assert np.array_equal(fast, EMCCD(**cam).log_likelihood(t, lam))
    assert table.table_for.cache_info().currsize == 0


# ---------------------------------------------------------------------------------- layering

CAMERAS_DIR = pathlib.Path(bayespsf.__file__).parent / "cameras"
ALLOWED_OUTSIDE = {"bayespsf._validate", "bayespsf._runtime", "bayespsf.errors"}  # the foundation


def bayespsf_imports(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name.split(".")[0] == "bayespsf")
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "bayespsf":
                yield from (f"bayespsf.{a.name}" for a in node.names)
            elif node.module.startswith("bayespsf."):
                yield node.module


def test_cameras_import_nothing_from_the_layers_above():
    # effects, simulator, model, ... sit above the camera laws: a camera owns its own draws
    files = sorted(CAMERAS_DIR.glob("*.py"))
    assert CAMERAS_DIR / "emccd.py" in files
    wrong = {
        (f.name, name)
        for f in files
        for name in bayespsf_imports(f)
        if not name.startswith("bayespsf.cameras") and name not in ALLOWED_OUTSIDE
    }
    assert wrong == set()


def test_the_simulator_uses_the_cameras_draws():
    assert camera_effects.gamma_register is _draws.gamma_register
    assert camera_effects.add_normal is _draws.add_normal
