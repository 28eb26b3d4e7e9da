"""The simulator: every effect's statistics against theory within stated Monte Carlo error,
pipelines that run exactly the declared effects, and reproducibility."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from bayespsf import load_scene, simulate
from bayespsf.psf import expected_counts
from bayespsf.scene import Scene
from bayespsf.simulation import build_pipeline, describe, simulate_chunks
from bayespsf.simulation import camera_effects as cx
from bayespsf.simulation import effects as fx
from bayespsf.simulation.pipeline import block_size

Z = 5.0  # Monte Carlo tolerance in standard errors: a false alarm ~1 in 3 million per check


def mc_mean_ok(x, mean, var):
    """|sample mean - mean| within Z standard errors of the mean."""
    return abs(np.mean(x) - mean) <= Z * np.sqrt(var / np.size(x))


def mc_var_ok(x, var, kurtosis_excess=0.0):
    """|sample variance - var| within Z standard errors (SE^2 = var^2 (2 + kurtosis) / n)."""
    se = var * np.sqrt((2.0 + kurtosis_excess) / np.size(x))
    return abs(np.var(x) - var) <= Z * se


def run(effect, image, rng=0, stage="photoelectrons"):
    batch = fx.Batch(n=image.shape[0], roi=image.shape[-1], image=image, stage=stage)
    effect(batch, np.random.default_rng(rng))
    return batch.image


# ------------------------------------------------------------------------------- camera effects


def test_emccd_pixel_mean_and_variance_with_cic_readout_and_adc():
    # photoelectrons Poisson(lam) plus CIC Poisson(c), Gamma register, readout, ADU:
    # mean offset + (lam + c) G / k, variance (2 (lam + c) G^2 + sd^2) / k^2
    lam, c, g, sd, off, k = 3.0, 0.05, 150.0, 40.0, 100.0, 8.0
    rng = np.random.default_rng(1)
    n = rng.poisson(lam, size=(200_000, 1, 1))
    n = run(cx.ClockInducedCharge(c), n, 2)
    e = run(cx.GammaRegister(g), n, 3)
    e = run(cx.ReadoutNoise(sd), e, 4, "electrons")
    adu = run(cx.ElectronsToADU(off, k), e, 5, "electrons").ravel()
    mean = off + (lam + c) * g / k
    var = (2 * (lam + c) * g * g + sd * sd) / k**2
    assert mc_mean_ok(adu, mean, var)
    assert mc_var_ok(adu, var, kurtosis_excess=3.0)


def test_staged_register_mean_and_excess_noise():
    # Galton-Watson register from single electrons: mean G, variance (1-p) G (G-1) / (1+p)
    g, stages = 50.0, 128
    p = g ** (1 / stages) - 1
    out = run(cx.StagedRegister(g, stages), np.ones((40_000, 1, 1), dtype=np.int64), 7).ravel()
    var = (1 - p) * g * (g - 1) / (1 + p)
    assert mc_mean_ok(out, g, var)
    assert mc_var_ok(out, var, kurtosis_excess=6.0)  # near-exponential: excess kurtosis ~6


def test_scmos_and_photon_cameras():
    lam, g, off, v = 7.0, 2.17, 100.0, 12.0
    n = np.random.default_rng(0).poisson(lam, size=(200_000, 1, 1))
    adu = run(cx.PhotoelectronsToADU(g, off), n)
    adu = run(cx.ReadoutNoise(np.sqrt(v), "adu"), adu, 9, "adu").ravel()
    assert mc_mean_ok(adu, off + g * lam, g * g * lam + v)
    assert mc_var_ok(adu, g * g * lam + v, kurtosis_excess=0.2)
    ideal = run(cx.PhotonCounting(), n)
    assert ideal.dtype == np.float64 and np.array_equal(ideal, n)


def test_quantize_and_saturate():
    x = np.array([[[0.4, 0.6, 2.5, 70000.2]]])
    q = run(cx.Quantize(), x.copy(), stage="adu")
    assert np.array_equal(q, [[[0.0, 1.0, 2.0, 70000.0]]])
    assert np.array_equal(run(cx.Saturate(65535.0), q, stage="adu"), [[[0.0, 1.0, 2.0, 65535.0]]])


# --------------------------------------------------------------------------- background effects


@pytest.mark.parametrize(
    "effect,mean,var",
    [
        (fx.PoissonBackground(4.0), 4.0, 4.0),
        # a Gaussian on whole photons with negligible truncation: continuous moments (the
        # Euler-Maclaurin error is exp(-2 pi^2 sd^2) ~ 1e-70 for sd = 9)
        (fx.DiscreteGaussianBackground(200.0, 9.0), 200.0, 81.0),
        (fx.BinomialBackground(10, 0.4), 4.0, 2.4),
    ],
)
def test_background_moments_against_closed_forms(effect, mean, var):
    assert effect.moments == pytest.approx((mean, var), rel=1e-9)
    draws = effect.draw((300_000,), np.random.default_rng(3))
    assert draws.dtype.kind == "i" and draws.min() >= 0
    assert mc_mean_ok(draws, mean, var)
    assert mc_var_ok(draws, var, kurtosis_excess=1.0)


def test_truncated_gaussian_background_matches_direct_enumeration():
    # P(k) proportional to the normal density at k = 0, 1, ... (written out independently)
    effect = fx.DiscreteGaussianBackground(1.0, 1.5)
    k = np.arange(0, 200)
    w = stats.norm.pdf(k, 1.0, 1.5)
    p = w / w.sum()
    mean = np.sum(k * p)
    var = np.sum((k - mean) ** 2 * p)
    assert effect.moments == pytest.approx((mean, var), rel=1e-12)
    draws = effect.draw((300_000,), np.random.default_rng(4))
    observed = np.bincount(draws, minlength=12)[:12]
    expected = 300_000 * p[:12]
    chi2 = np.sum((observed - expected) ** 2 / expected)
    assert stats.chi2.sf(chi2, df=11) > 1e-4  # fixed seed: a real goodness-of-fit check


# ------------------------------------------------------------------------------ photon effects


def scene(**tables):
    return Scene.from_dict(tables)


def test_poisson_pixels_mean_and_variance_equal_expected_counts():
    s = scene(
        geometry={"roi": 7, "pixel_size": 100.0},
        emitter={"photons": 300.0, "s0x": 110.0, "s0y": 90.0, "x0": 20.0, "y0": -35.0},
        background={"kind": "poisson", "mean": 2.0},
    )
    counts, truth = simulate(s, 40_000, seed=5)
    lam = expected_counts([20.0, -35.0, 110.0, 90.0, 300.0, 2.0], 7, 100.0)
    se = np.sqrt(lam / counts.shape[0])
    assert np.all(np.abs(counts.mean(0) - lam) <= Z * se)
    assert np.all(np.abs(counts.var(0) - lam) <= Z * lam * np.sqrt((2 + 1 / lam) / counts.shape[0]))
    assert np.all(truth["b"] == 2.0) and np.all(truth["N"] == 300.0)


def test_fixed_photons_are_multinomial():
    # photon camera, no background: pixel means N p, variances N p (1 - p), covariance -N p q,
    # and the total inside the ROI is Binomial(N, sum p)
    s = scene(
        geometry={"roi": 5, "pixel_size": 100.0},
        emitter={"photons": 200.0, "photon_statistics": "fixed", "s0x": 120.0, "s0y": 120.0},
    )
    counts, _ = simulate(s, 50_000, seed=6)
    p = expected_counts([0, 0, 120.0, 120.0, 1.0, 0.0], 5, 100.0)
    flat = counts.reshape(counts.shape[0], -1)
    n = flat.shape[0]
    mean, var = 200 * p.ravel(), 200 * p.ravel() * (1 - p.ravel())
    assert np.all(np.abs(flat.mean(0) - mean) <= Z * np.sqrt(var / n))
    assert np.all(np.abs(flat.var(0) - var) <= Z * var * np.sqrt(2.2 / n))
    c01 = np.cov(flat[:, 12], flat[:, 13])[0, 1]
    cov = -200 * p.ravel()[12] * p.ravel()[13]
    assert abs(c01 - cov) <= Z * np.sqrt(var[12] * var[13] / n)
    total_var = 200 * p.sum() * (1 - p.sum())
    assert abs(flat.sum(1).var() - total_var) <= Z * total_var * np.sqrt(2.2 / n)
    assert np.all(flat.sum(1) <= 200)


def _photon_spread(counts, pixel_size):
    """Mean squared x distance of detected photons (pixel centres) from 0, per photon."""
    roi = counts.shape[-1]
    x = (np.arange(roi) - (roi - 1) / 2) * pixel_size
    profile = counts.sum(axis=(0, 1))
    return np.sum(profile * x * x) / profile.sum(), profile.sum()


def test_pixelation_adds_a2_over_12_eq_tophat():
    # Eq. tophat: with the spot uniform within a pixel, photon pixel centres spread as
    # s0^2 + a^2 / 12 about the true centre. ROI of +-10 s0 loses ~nothing.
    s0, a = 60.0, 90.0
    s = scene(
        geometry={"roi": 15, "pixel_size": a},
        emitter={
            "photons": 400.0,
            "photon_statistics": "fixed",
            "s0x": s0,
            "s0y": s0,
            "position": "pixel",
        },
    )
    counts, truth = simulate(s, 20_000, seed=8)
    # distance to the true x0 of each image: subtract x0 per image
    roi = 15
    x = (np.arange(roi) - (roi - 1) / 2) * a
    prof = counts.sum(axis=1)  # (n, roi) along x
    d2 = (prof * (x[None, :] - truth["x0"].to_numpy()[:, None]) ** 2).sum() / prof.sum()
    target = s0**2 + a**2 / 12
    # per-photon value has variance ~2 target^2; photons are independent
    assert abs(d2 - target) <= Z * target * np.sqrt(2.5 / prof.sum())
    assert abs(d2 - s0**2) > 10 * target * np.sqrt(2.5 / prof.sum())  # the effect is resolved


def test_width_jitter_adds_its_variance():
    # photon by photon, widths s0 + d with d ~ N(0, w): Var(x - x0) = s0^2 + w^2 (+ a^2/12 bins);
    # the ROI spans +-7.5 SD so truncation is negligible (exp(-28))
    s0, w, a = 50.0, 20.0, 10.0
    s = scene(
        geometry={"roi": 81, "pixel_size": a},
        emitter={
            "photons": 500.0,
            "photon_statistics": "fixed",
            "s0x": s0,
            "s0y": s0,
            "width_jitter": w,
        },
    )
    assert describe(s).count("PhotonBinning") == 1
    counts, truth = simulate(s, 4_000, seed=9)
    d2, photons = _photon_spread(counts, a)
    target = s0**2 + w**2 + a**2 / 12
    assert abs(d2 - target) <= Z * target * np.sqrt(3.0 / photons)
    assert np.all(truth["photons_emitted"] == 500.0)


def test_photon_number_jitter_and_poisson_emission():
    s = scene(emitter={"photons": 1000.0, "photon_jitter": 0.2, "width_jitter": 1.0})
    _, truth = simulate(s, 20_000, seed=10)
    n = truth["N"].to_numpy()
    assert n.min() >= 800 and n.max() <= 1200
    assert mc_mean_ok(n, 1000.0, 400.0**2 / 12)
    emitted = truth["photons_emitted"].to_numpy()
    # emitted | N ~ Poisson(N): mean of (emitted - N) is 0 with variance E[N]
    assert mc_mean_ok(emitted - n, 0.0, 1000.0)


def test_airy_photons_follow_the_encircled_energy():
    # fraction of photons within radius r: 1 - J0(v)^2 - J1(v)^2, v = 2 pi NA r / lambda;
    # a ROI of +-366 nm, the first dark ring (v = 3.8317, 83.8% inside) at r = 305 nm
    from scipy import special

    s = scene(
        geometry={"roi": 61, "pixel_size": 12.0},
        emitter={"photons": 2000.0, "photon_statistics": "fixed"},
        optics={"psf": "airy", "wavelength": 600.0, "na": 1.2},
    )
    counts, truth = simulate(s, 400, seed=11)
    c = (np.arange(61) - 30) * 12.0
    r = np.hypot(c[:, None], c[None, :])
    r_ring = 3.8317 * 600.0 / (2 * np.pi * 1.2)
    inside = counts[:, r < r_ring].sum() / (400 * 2000)
    v = 2 * np.pi * 1.2 * r_ring / 600.0
    p = 1 - special.j0(v) ** 2 - special.j1(v) ** 2
    # pixels (12 nm) blur the boundary, where the density is ~0 (a dark ring): allow 0.005
    assert abs(inside - p) <= 0.005 + Z * np.sqrt(p * (1 - p) / (400 * 2000))
    assert truth["s_x"][0] == pytest.approx(0.21 * 600 / 1.2)


# ----------------------------------------------------------------------------------- pipelines

EXPECTED_PIPELINES = {
    "ideal": [
        "EmitterTruth",
        "UniformPosition",
        "ExpectedSignal",
        "PoissonBackgroundMean",
        "PoissonPhotons",
        "PhotonCounting",
    ],
    "emccd-typical": [
        "EmitterTruth",
        "UniformPosition",
        "ExpectedSignal",
        "PoissonBackgroundMean",
        "PoissonPhotons",
        "GammaRegister",
        "ReadoutNoise",
        "ElectronsToADU",
        "Quantize",
        "Saturate",
    ],
    "scmos-typical": [
        "EmitterTruth",
        "UniformPosition",
        "ExpectedSignal",
        "PoissonBackgroundMean",
        "PoissonPhotons",
        "PhotoelectronsToADU",
        "ReadoutNoise",
        "Quantize",
        "Saturate",
    ],
    "paper-fig2": [
        "EmitterTruth",
        "UniformPosition",
        "PhotonNumberJitter",
        "PhotonBinning",
        "DiscreteGaussianBackground",
        "GammaRegister",
        "ElectronsToADU",
    ],
    "paper-fig3": [
        "EmitterTruth",
        "UniformPosition",
        "WholePhotonNumber",
        "MultinomialPhotons",
        "DiscreteGaussianBackground",
        "GammaRegister",
        "ElectronsToADU",
    ],
}


@pytest.mark.parametrize("name", sorted(EXPECTED_PIPELINES))
def test_shipped_scene_runs_exactly_its_declared_effects(name):
    steps = build_pipeline(load_scene(name))
    assert [type(s).__name__ for s in steps] == EXPECTED_PIPELINES[name]


class CountingGenerator:
    """A Generator proxy that records every random-number method called through it."""

    def __init__(self, seed):
        self._rng = np.random.default_rng(seed)
        self.calls = []

    def __getattr__(self, name):
        self.calls.append(name)
        return getattr(self._rng, name)


@pytest.mark.parametrize("name", sorted(EXPECTED_PIPELINES))
def test_effects_that_do_not_draw_use_no_random_numbers(name):
    batch = fx.Batch(n=16, roi=load_scene(name).geometry["roi"])
    for step in build_pipeline(load_scene(name)):
        rng = CountingGenerator(0)
        step(batch, rng)
        assert bool(rng.calls) == step.draws, (step, rng.calls)


def test_undeclared_effects_are_absent():
    plain = scene(camera={"kind": "emccd", "gain": 100.0})
    names = [type(s).__name__ for s in build_pipeline(plain)]
    for absent in (
        "ReadoutNoise",
        "ClockInducedCharge",
        "Quantize",
        "Saturate",
        "UniformPosition",
        "PhotonNumberJitter",
        "PoissonBackgroundMean",
        "StagedRegister",
    ):
        assert absent not in names


# ---------------------------------------------------------------------------- reproducibility


def test_same_seed_same_images_for_any_chunk_size():
    s = load_scene("emccd-typical")
    a, ta = simulate(s, 2500, seed=42)
    for chunk in (1, 100, 1500, 10_000):
        parts = list(simulate_chunks(s, 2500, seed=42, chunk_size=chunk))
        assert len(parts) == -(-2500 // chunk)
        assert np.array_equal(np.concatenate([p[0] for p in parts]), a)
        truth = pd.concat([p[1] for p in parts])
        assert np.array_equal(truth.index, np.arange(2500)) and np.allclose(truth, ta)
    c, _ = simulate(s, 2500, seed=43)
    assert not np.array_equal(a, c)
    # a prefix of a longer run is the shorter run
    d, _ = simulate(s, 1000, seed=42)
    assert np.array_equal(d, a[:1000])


def test_photon_path_blocks_are_bounded_and_reproducible():
    s = load_scene("paper-fig2").replace(emitter={"photons": 1e6})
    assert block_size(s) < 1024  # photons per block bounded
    a = np.concatenate([c for c, _ in simulate_chunks(s, 5, seed=1, chunk_size=1)])
    b, _ = simulate(s, 5, seed=1)
    assert np.array_equal(a, b)


def test_truth_table_columns_and_empty_run():
    counts, truth = simulate(load_scene("paper-fig2"), 3, seed=0)
    assert list(truth.columns[:6]) == ["x0", "y0", "s_x", "s_y", "N", "b"]
    assert "photons_emitted" in truth.columns and counts.shape == (3, 15, 15)
    counts, truth = simulate(load_scene("ideal"), 0, seed=0)
    assert counts.shape == (0, 15, 15) and len(truth) == 0


@pytest.mark.parametrize(
    "kwargs,name",
    [
        ({"n": -1}, "n"),
        ({"n": 2.5}, "n"),
        ({"seed": -3}, "seed"),
        ({"chunk_size": 0}, "chunk_size"),
    ],
)
def test_bad_simulate_arguments_are_named(kwargs, name):
    args = {"n": 3, "seed": 0, **kwargs}
    with pytest.raises(ValueError, match=name):
        next(simulate_chunks(load_scene("ideal"), **args))
    with pytest.raises(ValueError, match="scene"):
        simulate({"geometry": {}}, 3, 0)
