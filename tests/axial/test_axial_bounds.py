"""Defocus curves and the bounds on z (bayespsf.axial): the curves against their closed forms
and differences, the Fisher information of z against an independent finite-difference one,
and the identity that ties the first-order error to the bound."""

import numpy as np
import pytest

from bayespsf import load_scene
from bayespsf.axial import crlb_z, first_order_z_sd, paper_delta_z
from bayespsf.axial.bounds import fisher_z, to_widths
from bayespsf.errors import BayespsfInputError
from bayespsf.model import Model
from bayespsf.psf import Defocus, HuangCurve
from bayespsf.theory import axial_width, fisher_matrix

MODEL = Model.from_scene(load_scene("emccd-typical"))
ASTIGMATIC = Defocus.astigmatic(w0=130.0, separation=400.0, depth=400.0, A=0.1, B=0.05)


def test_curves_match_their_closed_forms_and_differences():
    z = np.linspace(-600, 600, 13)
    symmetric = Defocus.symmetric(120.0, 400.0)
    assert np.allclose(symmetric.widths(z)[0], axial_width(z, 120.0, 400.0), rtol=1e-14)
    h = 1e-3
    for curve in (symmetric.x, ASTIGMATIC.x, ASTIGMATIC.y):
        numeric = (curve.width(z + h) - curve.width(z - h)) / (2 * h)
        assert np.allclose(curve.slope(z), numeric, rtol=1e-7, atol=1e-10)
    # astigmatism: equal widths at z = 0, changing in opposite directions
    sx, sy = ASTIGMATIC.widths(0.0)
    gx, gy = ASTIGMATIC.slopes(0.0)
    assert sx == pytest.approx(sy, rel=1e-12) and gx * gy < 0


def test_fisher_of_z_against_finite_differences():
    # independent: I = sum_i F(mu_i) J_i J_i' with J = d mu / d theta by central differences
    theta = np.array([10.0, -20.0, 150.0, 2000.0, 10.0])
    steps = np.array([1e-2, 1e-2, 1e-2, 1e-3, 1e-4])
    jac = []
    for k in range(5):
        up, down = theta.copy(), theta.copy()
        up[k] += steps[k]
        down[k] -= steps[k]
        mu_up = MODEL.expected(to_widths(up, ASTIGMATIC))
        mu_down = MODEL.expected(to_widths(down, ASTIGMATIC))
        jac.append((mu_up - mu_down) / (2 * steps[k]))
    jac = np.array(jac)
    info = MODEL.camera.fisher_information(MODEL.expected(to_widths(theta, ASTIGMATIC)))
    expected = np.einsum("ixy,jxy,xy->ij", jac, jac, info)
    assert np.allclose(fisher_z(MODEL, ASTIGMATIC, theta), expected, rtol=1e-5)


@pytest.mark.parametrize("z", [-500.0, -150.0, 0.0, 80.0, 450.0])
def test_first_order_error_with_the_widths_bound_is_the_bound_on_z(z):
    # the information on z is g' S^-1 g with S the widths' CRLB covariance (x0, y0, N, b
    # unknown): an identity, so equal to rounding
    theta = np.array([0.0, 0.0, z, 3000.0, 10.0])
    covariance = np.linalg.inv(fisher_matrix(MODEL, to_widths(theta, ASTIGMATIC)))[2:4, 2:4]
    bound = crlb_z(MODEL, ASTIGMATIC, theta)["z"]
    assert first_order_z_sd(ASTIGMATIC, z, covariance) == pytest.approx(bound, rel=1e-8)


def test_symmetric_defocus_has_no_information_on_z_in_focus():
    symmetric = Defocus.symmetric(130.0, 400.0)
    focus = crlb_z(MODEL, symmetric, [0.0, 0.0, 0.0, 3000.0, 10.0])
    assert focus["z"] == np.inf and np.isfinite(focus[["x0", "y0", "N", "b"]]).all()
    # z and -z give the same image: the same bound
    plus = crlb_z(MODEL, symmetric, [0.0, 0.0, 300.0, 3000.0, 10.0])["z"]
    minus = crlb_z(MODEL, symmetric, [0.0, 0.0, -300.0, 3000.0, 10.0])["z"]
    assert np.isfinite(plus) and plus == pytest.approx(minus, rel=1e-10)


def test_bad_curves_are_named():
    with pytest.raises(BayespsfInputError, match="w0 must be in"):
        HuangCurve(0.0)
    with pytest.raises(BayespsfInputError, match="d must be in"):
        HuangCurve(120.0, d=-1.0)
    with pytest.raises(BayespsfInputError, match="outside this defocus curve's domain"):
        HuangCurve(120.0, d=100.0, A=-3.0).width(150.0)  # 1 + 2.25 - 10.1 < 0
    with pytest.raises(BayespsfInputError, match="depth must be in"):
        Defocus.astigmatic(130.0, 400.0, -400.0)
    with pytest.raises(BayespsfInputError, match="needs the paper's symmetric curve"):
        paper_delta_z(5.0, ASTIGMATIC, 100.0)  # it read 4.97 where 1/|dw/dz| is 4.47
    with pytest.raises(BayespsfInputError, match="theta must be one"):
        crlb_z(MODEL, ASTIGMATIC, [0.0, 0.0, 100.0, 3000.0])
    assert HuangCurve("130").width(0.0) == 130.0  # a number given as text, kept as a float
