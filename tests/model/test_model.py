"""The inference model built from a scene."""

import numpy as np
import pytest

from bayespsf import Model, Scene, load_scene, simulate
from bayespsf.cameras import EMCCD, SCMOS, Photon
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import expected_counts


def test_from_scene_picks_the_camera_and_tier():
    assert isinstance(Model.from_scene(load_scene("ideal")).camera, Photon)
    emccd = Model.from_scene(load_scene("emccd-typical")).camera
    assert isinstance(emccd, EMCCD) and emccd.likelihood == "table" and emccd.gain == 200.0
    assert (
        Model.from_scene(load_scene("emccd-typical"), likelihood="exact").camera.likelihood
        == "exact"
    )
    assert isinstance(Model.from_scene(load_scene("scmos-typical")).camera, SCMOS)
    with pytest.raises(ValueError, match="photon camera"):
        Model.from_scene(load_scene("ideal"), likelihood="table")


def test_expected_includes_clock_induced_charge_and_matches_the_psf():
    scene = Scene.from_dict(
        {"camera": {"kind": "emccd", "gain": 100.0, "clock_induced_charge": 0.05}}
    )
    model = Model.from_scene(scene)
    p = np.array([10.0, -5.0, 120.0, 110.0, 800.0, 3.0])
    assert np.allclose(model.expected(p), expected_counts(p, 15, 100.0) + 0.05, rtol=1e-15)


def test_log_likelihood_sums_pixels_and_broadcasts_walkers():
    scene = load_scene("emccd-typical")
    model = Model.from_scene(scene)
    counts, truth = simulate(scene, 1, seed=0)
    p = truth[["x0", "y0", "s_x", "s_y", "N", "b"]].to_numpy()[0]
    walkers = p + np.array([[0.0] * 6, [5.0, 0, 0, 0, 0, 0], [0, 0, 10.0, 0, 0, 0]])
    ll = model.log_likelihood(counts[0], walkers)
    direct = model.camera.log_likelihood(counts[0], model.expected(walkers)).sum(axis=(-2, -1))
    assert ll.shape == (3,) and np.allclose(ll, direct)


def test_to_photons_and_variance():
    model = Model.from_scene(load_scene("emccd-typical"))
    assert model.to_photons(100.0 + 200.0 / 12.0) == pytest.approx(1.0)
    assert model.photon_variance(4.0) == pytest.approx(2 * 4.0 + (50.0 / 200.0) ** 2)


@pytest.mark.parametrize(
    "counts,match",
    [
        (np.zeros((15, 14)), "shape"),
        (np.full((15, 15), np.nan), "finite"),
        (np.ones(3), "shape"),
        (np.zeros((15, 15)), "same value"),
    ],
)
def test_bad_rois_are_named(counts, match):
    with pytest.raises(ValueError, match=f"counts.*{match}"):
        Model.from_scene(load_scene("ideal")).check_counts(counts)


def test_negative_photon_counts_rejected():
    with pytest.raises(ValueError, match="counts"):
        Model.from_scene(load_scene("ideal")).check_counts(-np.ones((15, 15)))


def every_prior_kind():
    """A model with every prior kind, and the scipy.stats law of each parameter."""
    from scipy import stats

    prior = {
        "x0": {"kind": "uniform", "low": -50.0, "high": 50.0},
        "y0": {"kind": "normal", "mean": 3.0, "sd": 20.0},
        "s_x": {"kind": "log-uniform", "low": 90.0, "high": 180.0},
        "s_y": {"kind": "log-uniform", "low": 90.0, "high": 180.0},
        "N": {"kind": "log-uniform", "low": 200.0, "high": 5000.0},
        "b": {"kind": "half-normal", "scale": 10.0},
    }
    laws = [
        stats.uniform(-50, 100),
        stats.norm(3, 20),
        stats.loguniform(90, 180),
        stats.loguniform(90, 180),
        stats.loguniform(200, 5000),
        stats.halfnorm(scale=10),
    ]
    return Model.from_scene(load_scene("ideal").replace(prior=prior)), laws


def test_sample_prior_follows_every_prior_kind():
    # Kolmogorov-Smirnov against each kind's exact CDF (scipy.stats), 20 000 draws: a correct
    # sampler fails at the 1e-4 level once in 10^4 runs per parameter
    from scipy import stats

    model, laws = every_prior_kind()
    draws = model.sample_prior(20_000, 1)
    for k, law in enumerate(laws):
        assert stats.kstest(draws[:, k], law.cdf).pvalue > 1e-4
    assert np.all(np.isfinite(model.log_prior(draws)))
    np.testing.assert_array_equal(model.sample_prior(5, 7), model.sample_prior(5, 7))
    with pytest.raises(BayespsfInputError, match="n must"):
        model.sample_prior(-1, 0)


def test_log_prior_is_the_sum_of_the_marginal_log_densities():
    # against scipy.stats log densities: equal up to one constant inside the support (to 1e-12),
    # -inf outside any parameter's support and for NaN
    model, laws = every_prior_kind()
    draws = model.sample_prior(500, 3).reshape(50, 10, 6)  # leading batch dimensions
    reference = sum(law.logpdf(draws[..., k]) for k, law in enumerate(laws))
    difference = model.log_prior(draws) - reference
    np.testing.assert_allclose(difference, difference.flat[0], atol=1e-12)
    outside = draws[0].copy()
    outside[0, 0], outside[1, 2], outside[2, 5], outside[3, 4] = 60.0, 80.0, -1.0, np.nan
    lp = model.log_prior(outside)
    assert np.all(lp[:4] == -np.inf) and np.all(np.isfinite(lp[4:]))


def test_sampled_pixel_model_is_eq_a31_everywhere():
    # expected counts, the posterior's hot path and the MLE's Jacobian all use Eq. A3.1
    from bayespsf import psf

    scene = load_scene("emccd-typical")
    model = Model.from_scene(scene, pixel_model="sampled")
    p = np.array([[12.0, -7.0, 120.0, 140.0, 900.0, 8.0], [0.0, 30.0, 100.0, 90.0, 400.0, 3.0]])
    want = psf.sampled_gaussian(p, 15, 100.0) + model.clock_induced_charge
    np.testing.assert_allclose(model.expected(p), want, rtol=1e-14)
    np.testing.assert_allclose(model.expected_and_jacobian(p)[0], want, rtol=1e-14)
    counts, _ = simulate(scene, 1, seed=2)
    c = model.check_counts(counts[0])
    lp = model.log_posterior(model.to_unconstrained(p), c)
    direct = model.camera.log_likelihood_unchecked(c, want).sum(axis=(-2, -1))
    direct += model.log_prior(p) + np.log(p[:, 2:5]).sum(axis=1)
    np.testing.assert_allclose(lp, direct, rtol=1e-12)
    assert "sampled" in repr(model) and "sampled" not in repr(Model.from_scene(scene))
    with pytest.raises(ValueError, match="pixel_model"):
        Model.from_scene(scene, pixel_model="centre")


def test_an_emccd_built_by_hand_gets_the_inference_default_tier():
    # a hand-built EMCCD silently inferred with the exact law (18x slower) while a
    # scene's model took the table; now both take the table, unless a tier was chosen

    camera = EMCCD(200.0, 50.0, 100.0, 12.0)
    assert camera.likelihood == "exact" and not camera.tier_chosen  # its own calls: reference
    assert Model(15, 100.0, camera).camera.likelihood == "table"
    chosen = EMCCD(200.0, 50.0, 100.0, 12.0, likelihood="exact")
    assert chosen.tier_chosen and Model(15, 100.0, chosen).camera.likelihood == "exact"
    scene_model = Model.from_scene(load_scene("emccd-typical"))
    assert repr(Model(15, 100.0, camera).camera) == repr(scene_model.camera)


def _suspects_by_arrays(flat, low, floor, fraction, saturation):
    # the screen written as whole-array NumPy passes: what the one-pass kernel must equal
    top = flat.max(axis=1, initial=-np.inf)
    suspect = ~np.all(np.isfinite(flat), axis=1) | np.all(flat == flat[:, :1], axis=1)
    suspect |= np.any(flat < floor, axis=1) | (np.mean(flat < low, axis=1) > fraction)
    if saturation > 0:
        return suspect | (top >= saturation)
    return suspect | (np.count_nonzero(flat == top[:, None], axis=1) >= 2)


@pytest.mark.parametrize("saturation", [0.0, 3000.0])
@pytest.mark.parametrize("floor", [-np.inf, 30.0])
def test_the_one_pass_screen_flags_what_the_array_passes_flag(floor, saturation):
    # every kind of defect, alone and together, in ROIs of integer-valued counts (ties happen)
    from bayespsf._validate import suspect_rois

    rng = np.random.default_rng(3)
    flat = np.round(rng.normal(140.0, 30.0, (4000, 49)))
    low = np.full(49, 80.0) + rng.normal(0, 5, 49)
    kind = rng.integers(0, 8, len(flat))
    pixel = rng.integers(0, 49, len(flat))
    rows = np.arange(len(flat))
    flat[kind == 1, pixel[kind == 1]] = np.nan
    flat[kind == 2, pixel[kind == 2]] = rng.choice([np.inf, -np.inf], (kind == 2).sum())
    flat[kind == 3] = 200.0  # every pixel equal (above the floor and the camera's low counts)
    flat[kind == 4, :6] -= 90.0  # some pixels far below the camera's floor
    flat[kind == 5, pixel[kind == 5]] = 3000.0  # at the saturation
    top = flat[kind == 6].max(axis=1)
    flat[kind == 6, :3] = top[:, None] + 500.0  # a plateau of three at the maximum
    flat[rows[kind == 7], pixel[kind == 7]] = np.nan  # NaN and ...
    flat[rows[kind == 7], (pixel[kind == 7] + 1) % 49] = 3000.0  # ... saturation together
    got = suspect_rois(flat, low, floor, 0.1, saturation)
    want = _suspects_by_arrays(flat, low, floor, 0.1, saturation)
    np.testing.assert_array_equal(got, want)
    assert 0.2 < got.mean() < 1.0  # both verdicts occur
