"""The sCMOS Fisher information for many pixels: interpolated per readout, checked by the rule.

``fisher_exact`` (the trapezoid rule, tested against scipy quadrature and Monte Carlo in
``test_scmos.py``) is the truth here; ``fisher_information`` must agree with it to 1e-10 relative
(its check's tolerance; the rule itself is good to ~1e-13) whichever path each pixel takes.
"""

from __future__ import annotations

import numpy as np
import pytest

from bayespsf.cameras import SCMOS, _scmos_fisher
from bayespsf.cameras._scmos_fisher import fisher_exact, fisher_information


def counted(monkeypatch):
    """Patch the rule to count the values it computes; returns the running count."""
    calls = []
    rule = _scmos_fisher.fisher_exact

    def counting(lam, s):
        out = rule(lam, s)
        calls.append(np.size(out))
        return out

    monkeypatch.setattr(_scmos_fisher, "fisher_exact", counting)
    return calls


@pytest.mark.parametrize("s", [0.3, 1.6, 20.0])
def test_one_readout_is_interpolated_within_the_check(monkeypatch, s):
    rng = np.random.default_rng(1)
    lam = np.exp(rng.uniform(np.log(2.0), np.log(800.0), 5000))
    want = fisher_exact(lam, s)
    calls = counted(monkeypatch)
    got = fisher_information(lam, s)
    np.testing.assert_allclose(got, want, rtol=1e-10)
    assert sum(calls) <= 2 * (48 + 47)  # nodes and checks, never the 5 000 pixels


def test_a_map_mixes_interpolated_and_single_pixels(monkeypatch):
    """Two readouts shared by many pixels, a few of their own, and pixels without light: the
    shared ones are interpolated (the rule computes far fewer values than there are pixels)."""
    want_rule = _scmos_fisher.fisher_exact
    rng = np.random.default_rng(2)
    lam = np.exp(rng.uniform(np.log(0.5), np.log(300.0), 700))
    s = np.where(np.arange(700) < 400, 1.2, 2.7)
    s[::97] = rng.uniform(0.5, 5.0, s[::97].size)  # readouts of one pixel each
    lam[::50] = 0.0
    want = want_rule(lam, s)
    calls = counted(monkeypatch)
    np.testing.assert_allclose(fisher_information(lam, s), want, rtol=1e-10)
    assert sum(calls) < lam.size / 2


def test_twelve_decades_take_an_interpolant_per_bin(monkeypatch):
    """lam over twelve decades (a stack with dark pixels): each four-decade bin has its own
    interpolant, all within the check; a bin with few pixels takes the rule."""
    lam = np.concatenate([np.geomspace(1e-7, 1e5, 3000), [3e-9, 5e-9]])
    want = fisher_exact(lam, 0.8)
    calls = counted(monkeypatch)
    np.testing.assert_allclose(fisher_information(lam, 0.8), want, rtol=1e-10)
    assert sum(calls) < lam.size / 3


def test_a_bin_no_interpolant_serves_falls_back_to_the_rule(monkeypatch):
    """Where no interpolant passes the check over a bin (forced here by a zero tolerance),
    every pixel of it takes the rule, and the answer is the rule's."""
    monkeypatch.setattr(_scmos_fisher, "_CHECK", 0.0)
    lam = np.geomspace(1.0, 1e3, 300)
    want = fisher_exact(lam, 0.8)
    calls = counted(monkeypatch)
    np.testing.assert_array_equal(fisher_information(lam, 0.8), want)
    assert sum(calls) >= lam.size


def test_camera_uses_it_per_readout():
    """``SCMOS.fisher_information`` of a stack: the rule's values, readout-free pixels 1/lam."""
    g = np.full((3, 3), 2.0)
    variance = np.full((3, 3), 9.0)
    variance[1, 1] = 0.0
    camera = SCMOS(g, 100.0, variance)
    rng = np.random.default_rng(3)
    lam = rng.uniform(1.0, 200.0, (200, 3, 3))
    got = camera.fisher_information(lam)
    readout = np.broadcast_to(variance > 0, lam.shape)
    np.testing.assert_allclose(got[readout], fisher_exact(lam[readout], 1.5), rtol=1e-10)
    np.testing.assert_array_equal(got[~readout], 1.0 / lam[~readout])
