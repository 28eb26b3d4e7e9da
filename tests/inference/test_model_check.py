"""The parametric-bootstrap goodness-of-fit test (bayespsf.inference.gof): its false
alarms at their nominal rate on ROIs the model describes, and flags on ROIs it cannot."""

import numpy as np
import pytest

from bayespsf import load_scene, simulate
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import bootstrap_check, fit_mle, gof
from bayespsf.inference.estimators import fit_screened
from bayespsf.inference.gof import pearson
from bayespsf.model import Model

SCENE = load_scene("emccd-typical").replace(emitter={"position": "pixel", "photons": 1000.0})
MODEL = Model.from_scene(SCENE)


def _sequential_null_moments(replicates: int, stop_after: int) -> tuple[float, float]:
    """The mean and SD of the sequential p-value where the model holds: it takes the values
    (g + 1) / (replicates + 1) for g < stop_after and stop_after / l for l from replicates down
    to stop_after, with P(p <= s) = s at each (Besag & Clifford 1991)."""
    n = replicates + 1
    values = [(g + 1) / n for g in range(stop_after)]
    values += [stop_after / length for length in range(replicates, stop_after - 1, -1)]
    s = np.array(sorted(values))
    mass = np.diff(np.r_[0.0, s])
    mean = float((s * mass).sum())
    return mean, float(np.sqrt((s**2 * mass).sum() - mean**2))


def test_false_alarms_at_their_nominal_rate():
    """300 ROIs of the model's own scene, 19 replicates stopped at 10 at least as discrepant:
    P(p <= 0.1) = 0.1 (at most one of 19 as discrepant: the full test's flag; binomial SE
    0.017), and the mean of p is that of the sequential p-value's law (0.527, SE 0.017); 4 SE
    each. Every ROI counts at least 10 replicates, and some stop before 19."""
    counts, _ = simulate(SCENE, 300, seed=11)
    check = bootstrap_check(counts, MODEL, replicates=19, seed=1)
    p = check["gof_p"].to_numpy()
    counted = check["gof_replicates"].to_numpy()
    assert np.isfinite(p).all() and (counted >= 10).all() and (counted <= 19).all()
    assert (counted < 19).mean() > 0.3
    assert abs(np.mean(p <= 0.1) - 0.1) < 4 * np.sqrt(0.1 * 0.9 / 300)
    mean, sd = _sequential_null_moments(19, 10)
    assert abs(p.mean() - mean) < 4 * sd / np.sqrt(300)


def test_the_sequential_p_value_is_the_full_tests_below_its_stop():
    """With each ROI's own seed, the replicates come in the same order whether the test stops
    or not: on 40 ROIs the model describes and 20 with a hot pixel (small p), the sequential
    p-value equals the full test's wherever fewer than 10 of 49 are as discrepant (p <= 0.2),
    and elsewhere is 10 / l with l the replicates counted, both above 0.2."""
    counts, _ = simulate(SCENE, 60, seed=14)
    per_adu, _ = MODEL.camera.photons_per_adu()
    counts[40:, 1, 1] += 100.0 / per_adu
    seeds = list(range(500, 560))
    fits = fit_mle(counts, MODEL, laplace=False, crlb=False)
    sequential = bootstrap_check(counts, MODEL, seed=seeds, fits=fits)
    full = bootstrap_check(counts, MODEL, seed=seeds, fits=fits, stop_after=None)
    low = full["gof_p"].to_numpy() <= 10 / 50
    assert low.sum() >= 20 and (~low).sum() >= 20
    assert (sequential["gof_p"][low] == full["gof_p"][low]).all()
    high = sequential[~low]
    assert np.allclose(high["gof_p"], 10 / high["gof_replicates"])
    assert (high["gof_p"] > 0.2).all() and (high["gof_replicates"] < 49).any()
    with pytest.raises(BayespsfInputError, match="stop_after"):
        bootstrap_check(counts[:2], MODEL, stop_after=0)


def test_the_sequential_rule_against_one_replicate_at_a_time():
    """``_sequential_p`` (rounds of 10, vectorised) against Besag & Clifford's rule written
    one replicate at a time, on random sequences of discrepancies with refits that fail."""
    rng = np.random.default_rng(8)
    m, replicates, stop_after = 400, 37, 7
    t = rng.normal(size=m)
    t_rep = rng.normal(size=(m, replicates)) + rng.uniform(-2.0, 2.0, size=(m, 1))
    counts = rng.random((m, replicates)) > 0.1
    served = np.zeros(m, dtype=int)

    def replicate_round(rows, k):
        first = served[rows]
        assert (first == first[0]).all()  # every ROI still running is at the same replicate
        served[rows] += k
        return t_rep[rows, first[0] : first[0] + k], counts[rows, first[0] : first[0] + k]

    p, counted = gof._sequential_p(np.arange(m), t, replicates, stop_after, replicate_round)
    for i in range(m):
        exceed = used = 0
        expected = None
        for j in range(replicates):
            if not counts[i, j]:
                continue
            used += 1
            exceed += t_rep[i, j] >= t[i]
            if exceed == stop_after:
                expected = stop_after / used
                break
        if expected is None:
            expected = (1 + exceed) / (1 + used)
        assert p[i] == pytest.approx(expected, rel=1e-12) and counted[i] == used


def test_two_molecules_in_one_roi_are_flagged():
    # two 1000-photon spots 400 nm apart (the case, which the posterior alone reports
    # as one converged wide spot): flagged at p <= 0.1 in at least 90% of 40 ROIs
    rng = np.random.default_rng(3)
    one = np.array([-200.0, 0.0, 120.0, 120.0, 1000.0, SCENE.background["mean"]])
    two = one.copy()
    two[0], two[5] = 200.0, 0.0
    lam = MODEL.expected(one) + MODEL.expected(two) - MODEL.clock_induced_charge
    counts = MODEL.camera.sample(np.broadcast_to(lam, (40, *lam.shape)), rng)
    check = bootstrap_check(counts, MODEL, replicates=19, seed=2)
    assert np.mean(check["gof_p"] <= 0.1) >= 0.9, check["gof_p"].describe()


def test_a_hot_pixel_is_flagged():
    # 100 photoelectrons' worth of ADU added to one corner pixel (background 10 photons) of 20
    # well-described ROIs. The whole-ROI discrepancy is an omnibus test: 30 photoelectrons'
    # worth went unflagged here (p 0.05-0.9, mean 0.28), inside the EM register's tail
    counts, _ = simulate(SCENE, 20, seed=12)
    per_adu, _ = MODEL.camera.photons_per_adu()
    counts[:, 1, 1] += 100.0 / per_adu
    check = bootstrap_check(counts, MODEL, replicates=19, seed=3)
    assert np.mean(check["gof_p"] <= 0.1) >= 0.9, check["gof_p"].describe()


def test_per_roi_seeds_make_a_rois_check_independent_of_its_stack():
    # with one seed per ROI, a ROI's replicates come from its own seed: the same p-value
    # whether it is checked alone, first, or among others
    counts, _ = simulate(SCENE, 6, seed=4)
    seeds = [100, 101, 102, 103, 104, 2**64 - 1]  # molecule seeds reach 2**64
    whole = bootstrap_check(counts, MODEL, replicates=9, seed=seeds)
    alone = bootstrap_check(counts[3:4], MODEL, replicates=9, seed=seeds[3:4])
    rest = bootstrap_check(counts[2:], MODEL, replicates=9, seed=seeds[2:])
    assert whole["gof_p"].iloc[3] == alone["gof_p"].iloc[0] == rest["gof_p"].iloc[1]
    with pytest.raises(BayespsfInputError, match="one per ROI"):
        bootstrap_check(counts, MODEL, seed=seeds[:5])
    with pytest.raises(BayespsfInputError, match="one per ROI"):
        bootstrap_check(counts, MODEL, seed=[-1, *seeds[1:]])
    with pytest.raises(BayespsfInputError, match="seed must be an integer"):
        bootstrap_check(counts, MODEL, seed=-1)  # numpy's own ValueError before


def test_replicates_refitted_to_a_looser_decrement_give_the_same_test(monkeypatch):
    """The check refits its replicates until the Newton decrement is below 1e-6
    (``REFIT_DECREMENT``), not fit_mle's 1e-10: each refit's log-likelihood is below the
    converged one by at most half the decrement (the quadratic model's gap; 1e-6 allowed), and
    over 60 ROIs x 19 replicates the p-values are those of refits run to 1e-10 (a flip needs
    two discrepancies, whose SD about a ROI's is ~9, within 1e-6 of each other)."""
    counts, _ = simulate(SCENE, 60, seed=13)
    fits = fit_mle(counts, MODEL, laplace=False, crlb=False)
    theta = fits[["x0", "y0", "s_x", "s_y", "N", "b"]].to_numpy()
    images = MODEL.camera.sample(
        np.repeat(MODEL.expected(theta), 4, axis=0), np.random.default_rng(5)
    )
    start = np.repeat(theta, 4, axis=0)
    tight = fit_screened(images, MODEL, None, start=start, laplace=False, crlb=False)
    loose = fit_screened(
        images, MODEL, None, start=start, laplace=False, crlb=False, decrement=gof.REFIT_DECREMENT
    )
    gap = tight["log_likelihood"] - loose["log_likelihood"]
    assert (gap >= -1e-9).all() and gap.max() < 1e-6
    assert (loose["message"] == "Newton decrement below 1e-06").mean() > 0.9
    found = bootstrap_check(counts, MODEL, replicates=19, seed=7, fits=fits)
    monkeypatch.setattr(gof, "REFIT_DECREMENT", 1e-10)
    reference = bootstrap_check(counts, MODEL, replicates=19, seed=7, fits=fits)
    assert (found["gof_p"] == reference["gof_p"]).all()
    assert (found["gof_replicates"] == reference["gof_replicates"]).all()
    for bad, words in (({"decrement": 0.0}, "decrement must be in"), ({"engine": "scipy"}, "own")):
        with pytest.raises(BayespsfInputError, match=words):
            fit_screened(images[:1], MODEL, None, **({"decrement": 1e-6} | bad))


def test_pearson_is_the_sum_of_squared_standardised_residuals():
    # the photon-counting camera: counts ~ Poisson(lam), so E y = var y = lam per pixel
    scene = SCENE.replace(camera={"kind": "photon", "likelihood": "exact"})
    model = Model.from_scene(scene)
    counts, truth = simulate(scene, 3, seed=5)
    theta = truth[["x0", "y0", "s_x", "s_y", "N", "b"]].to_numpy(float)
    lam = model.expected(theta)
    expected = np.sum((counts - lam) ** 2 / lam, axis=(1, 2))
    np.testing.assert_allclose(pearson(model, counts, theta), expected, rtol=1e-12)
    # no photons expected anywhere (N = b = 0): no variance; 0 where the counts are 0 too,
    # infinite where a count is not (that image cannot come from the model), and no warning
    empty = np.array([[0.0, 0.0, 130.0, 130.0, 0.0, 0.0]])
    quiet = np.zeros((1, model.roi, model.roi))
    assert pearson(model, quiet, empty)[0] == 0.0
    quiet[0, 1, 1] = 1.0
    assert pearson(model, quiet, empty)[0] == np.inf


def test_pearson_discrepancy_is_calibrated_at_a_low_background_and_flags_a_hot_pixel():
    # 400 ROIs with 2.75 background photons per pixel (the paper-movie's mean), 19 replicates:
    # P(p <= 0.1) = 0.1 if the p-value is uniform (binomial SE 0.015; 3.5 SE). The likelihood
    # discrepancy's plug-in p-value is conservative here (validation/model_check.py)
    low = SCENE.replace(background={"kind": "poisson", "mean": 2.75})
    counts, _ = simulate(low, 400, seed=13)
    check = bootstrap_check(counts, MODEL, replicates=19, seed=4, discrepancy="pearson")
    p = check["gof_p"].to_numpy()
    assert np.isfinite(p).all()
    assert abs(np.mean(p <= 0.1) - 0.1) < 3.5 * np.sqrt(0.1 * 0.9 / 400)
    hot, _ = simulate(SCENE, 20, seed=12)
    per_adu, _ = MODEL.camera.photons_per_adu()
    hot[:, 1, 1] += 100.0 / per_adu
    check = bootstrap_check(hot, MODEL, replicates=19, seed=3, discrepancy="pearson")
    assert np.mean(check["gof_p"] <= 0.1) >= 0.9, check["gof_p"].describe()


def test_bad_replicates_are_named():
    counts, _ = simulate(SCENE, 2, seed=1)
    with pytest.raises(BayespsfInputError, match="replicates must be"):
        bootstrap_check(counts, MODEL, replicates=0)
    with pytest.raises(BayespsfInputError, match="counts must have shape"):
        bootstrap_check(counts[0], MODEL)
    with pytest.raises(BayespsfInputError, match="fits must be fit_mle's table"):
        bootstrap_check(counts, MODEL, fits=fit_mle(counts[:1], MODEL))
    with pytest.raises(BayespsfInputError, match="discrepancy must be one of"):
        bootstrap_check(counts, MODEL, discrepancy="chi2")


def test_flag_excess_p_is_the_binomial_tail_of_the_flags():
    """At least k of n frames flagged at alpha when each is with probability alpha: the tail
    sum written out, against the function; uniform p-values are not called excessive, and
    the Airy-like excess of validation/movie_analysis.py (22% of 1 200 at 0.1) is."""
    from math import comb

    from bayespsf.inference.gof import flag_excess_p

    p = np.r_[np.full(20, 0.05), np.full(80, 0.5), np.nan]
    exact = sum(comb(100, k) * 0.1**k * 0.9 ** (100 - k) for k in range(20, 101))
    assert flag_excess_p(p, 0.1) == pytest.approx(exact, rel=1e-10)
    rng = np.random.default_rng(0)
    assert flag_excess_p(rng.random(1200), 0.1) > 0.01
    assert flag_excess_p(np.r_[np.full(264, 0.01), np.full(936, 0.6)], 0.1) < 1e-30
    assert np.isnan(flag_excess_p(np.array([np.nan]), 0.1))
