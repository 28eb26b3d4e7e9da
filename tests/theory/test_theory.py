"""The paper's closed forms against its own statements and their defining limits; the
Cramér–Rao bound against a Monte Carlo Fisher matrix."""

import numpy as np
import pytest

from bayespsf import simulate
from bayespsf import theory as th
from bayespsf.cameras import _emccd_law
from bayespsf.model import Model
from bayespsf.scene import Scene


def test_paper_statements():
    # DeSantis et al. 2010: width optimum a/s0 = 1.18 and centroid optimum 1.10 at N = 500,
    # sigma_b = 1, <b> = 4 (quoted to two decimals: tolerance 0.01); s-dagger 88 nm for
    # s0 = 85 nm, a = 79 nm (quoted to the nm)
    assert th.optimal_pixel_ratio(500, 1, 4) == pytest.approx(1.18, abs=0.01)
    assert th.optimal_pixel_ratio(500, 1, 4, "centroid") == pytest.approx(1.10, abs=0.01)
    assert th.s_dagger(85, 79) == pytest.approx(88, abs=0.5)


@pytest.mark.parametrize("quantity", ["width", "centroid"])
@pytest.mark.parametrize("N,sigma_b,b_mean", [(500, 1, 4), (100, 2, 10), (5000, 0.5, 1)])
def test_optimal_ratio_closed_form_matches_numerical_minimisation(quantity, N, sigma_b, b_mean):
    closed = th.optimal_pixel_ratio(N, sigma_b, b_mean, quantity)
    assert th.optimal_pixel_ratio_numeric(N, sigma_b, b_mean, quantity) == pytest.approx(
        closed, rel=1e-6
    )


def test_pixel_sum_reaches_the_high_photon_limit():
    # Eq. 1Dphotonnoise (and its 2-D form): <ds^2> -> s0^2 / N when the background vanishes;
    # tiny pixels (a/s = 0.025: the pixelation correction, O(a^2/s^2), is 5e-5) over +-10 s
    N, s0, a = 1e4, 120.0, 3.0
    assert th.delta_s_numeric(N, s0, s0, a, 0.0, 0.0, roi=801) == pytest.approx(
        s0 / np.sqrt(N), rel=2e-4
    )
    assert th.delta_s_numeric_1d(N, s0, a, 0.0, 0.0, roi=801) == pytest.approx(
        s0 / np.sqrt(N), rel=2e-4
    )


def test_pixel_sum_reaches_the_high_background_limit():
    # Eq. 1Dbgnoise: <ds^2> = 8 sqrt(pi) s0^3 (sigma_b^2 + <b>) / (3 a N^2) when 2 N_i is
    # negligible, and its 2-D form 16 pi s0x^3 s0y B / (3 a^2 N^2) (Appendix A3)
    # (a/s = 0.025 over +-10 s: the pixelation correction is 1.3e-4)
    N, s0, a, bg = 100.0, 120.0, 3.0, 1e7
    d1 = th.delta_s_numeric_1d(N, s0, a, 0.0, bg, roi=801)
    assert d1**2 == pytest.approx(8 * np.sqrt(np.pi) * s0**3 * bg / (3 * a * N**2), rel=2e-4)
    d2 = th.delta_s_numeric(N, s0, s0, a, 0.0, bg, roi=801)
    assert d2**2 == pytest.approx(16 * np.pi * s0**4 * bg / (3 * a**2 * N**2), rel=5e-4)


def test_closed_forms_are_the_sum_of_their_limits():
    N, s0, a, sb, b = 700.0, 110.0, 79.0, 1.5, 3.0
    sd = th.s_dagger(s0, a)
    assert th.delta_s_1d(N, s0, a, sb, b) == pytest.approx(
        th.delta_s_1d_no_pixel(N, sd, a, sb, b), rel=1e-14
    )
    high_n = th.delta_s_analytic(N, s0, s0, a, 0.0, 0.0) ** 2
    assert high_n == pytest.approx(sd**2 / N, rel=1e-14)
    both = th.delta_s_analytic(N, s0, s0, a, sb, b) ** 2
    assert both - high_n == pytest.approx(16 * np.pi * sd**4 * (sb**2 + b) / (3 * a**2 * N**2))
    assert th.delta_x_analytic(N, s0, s0, a, 0, 0) ** 2 == pytest.approx(2 * sd**2 / N)


def test_vectorised_over_n_a_and_s0():
    N = np.array([100.0, 500.0, 5000.0])[:, None]
    a = np.array([40.0, 79.0])[None, :]
    out = th.delta_s_analytic(N, 120.0, 120.0, a, 1.0, 4.0)
    assert out.shape == (3, 2) and np.all(np.diff(out, axis=0) < 0)
    numeric = th.delta_s_numeric(N, 120.0, 120.0, a, 1.0, 4.0, roi=19)
    assert numeric.shape == (3, 2)
    assert numeric[1, 1] == pytest.approx(th.delta_s_numeric(500, 120, 120, 79, 1, 4, roi=19)[()])


def test_axial_precision_by_error_propagation():
    s0, D, z = 120.0, 400.0, np.array([100.0, 300.0, 600.0])
    s = th.axial_width(z, s0, D)
    h = 1e-4
    slope = (th.axial_width(z + h, s0, D) - th.axial_width(z - h, s0, D)) / (2 * h)
    assert np.allclose(th.delta_z(1.0, s0, s, D), 1.0 / slope, rtol=1e-7)
    with pytest.raises(ValueError, match="s_z"):
        th.delta_z(1.0, s0, s0 - 1.0)


def _scene(camera):
    return Scene.from_dict(
        {
            "geometry": {"roi": 9, "pixel_size": 100.0},
            "emitter": {"photons": 800.0, "s0x": 120.0, "s0y": 100.0, "x0": 30.0, "y0": -20.0},
            "background": {"kind": "poisson", "mean": 3.0},
            "camera": camera,
        }
    )


def _pixel_scores(model, counts, lam):
    """d log p / d lam per pixel, in closed form (Poisson; EMCCD without readout)."""
    cam = model.camera
    if cam.to_dict()["kind"] == "photon":
        return counts / lam - 1.0
    t = cam.gain_units(counts)
    return _emccd_law.score_high_gain(t, lam)


@pytest.mark.parametrize(
    "camera",
    [{"kind": "photon"}, {"kind": "emccd", "gain": 50.0, "e_per_adu": 2.0}],
    ids=["photon", "emccd"],
)
def test_crlb_is_the_inverse_of_the_monte_carlo_fisher_matrix(camera):
    # F = E[score score^T], score = sum_i (d log p_i / d lam_i) J_i; each element of the Monte
    # Carlo estimate within 5 standard errors of the exact matrix, and the bounds within 5%
    scene = _scene(camera)
    model = Model.from_scene(scene)
    params = th.scene_params(scene)
    counts, _ = simulate(scene, 6000, seed=21)
    lam, jac = model.expected_and_jacobian(params)
    score = np.einsum("nxy,kxy->nk", _pixel_scores(model, counts, lam), jac)
    outer = score[:, :, None] * score[:, None, :]
    estimate = outer.mean(0)
    se = outer.std(0) / np.sqrt(len(score))
    exact = th.fisher_matrix(model, params)
    assert np.all(np.abs(estimate - exact) <= 5 * se + 1e-12 * np.abs(exact))
    mc_bound = np.sqrt(np.diag(np.linalg.inv(estimate)))
    assert np.allclose(mc_bound, th.crlb(scene).to_numpy(), rtol=0.05)
    assert np.all(np.abs(score.mean(0)) <= 5 * score.std(0) / np.sqrt(len(score)))  # E[score]=0


def test_crlb_variants():
    scene = _scene({"kind": "emccd", "gain": 100.0})
    full = th.crlb(scene)
    assert list(full.index) == ["x0", "y0", "s_x", "s_y", "N", "b"]
    # without readout the exact EMCCD information is at least the F^2 = 2 shortcut's
    assert np.all(full <= th.crlb(scene, method="excess-noise") * (1 + 1e-9))
    alone = th.crlb(scene, free="s_x")["s_x"]
    assert alone < full["s_x"]  # nuisance parameters cost precision
    with pytest.raises(ValueError, match="no Fisher method 'excess-noise'"):
        th.crlb(_scene({"kind": "photon"}), method="excess-noise")
    with pytest.raises(ValueError, match="free"):
        th.crlb(scene, free="z")
