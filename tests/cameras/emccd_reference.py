"""Independent, slow, high-precision EMCCD laws (mpmath) used as truth by the tests.

Two routes that share no code with bayespsf:

* ``series``: the Poisson-Gamma series ``sum_n Pois(n; lam) (Gamma(n, 1) * Normal(0, r))(t)``,
  each term in closed form through the parabolic cylinder function D_{-n}(z):
  ``int_0^inf u^(n-1) e^(-u/G) e^(-(x-u)^2 / 2s^2) du``
  ``= s^n Gamma(n) e^(-x^2/2s^2 + z^2/4) D_{-n}(z)`` with ``z = s/G - x/s``
  (Gradshteyn & Ryzhik 3.462.1). Good for small lam.
* ``quadrature``: mpmath tanh-sinh quadrature of the Bessel closed form times the readout
  Gaussian, on many sub-intervals placed around both factors so that no narrow peak is missed.

Both are in gain units: ``t = electrons / gain``, ``r = readout_sd / gain``.
"""

import mpmath as mp

mp.mp.dps = 25  # far beyond the tests' 1e-9 (40 digits gave the same 20 digits, 1.5x slower)


def amplified(u, lam):
    """Density of the n >= 1 part without readout at u > 0 (Bessel closed form)."""
    u, lam = mp.mpf(u), mp.mpf(lam)
    return mp.exp(-lam - u) * mp.sqrt(lam / u) * mp.besseli(1, 2 * mp.sqrt(lam * u))


def high_gain_series(t, lam, nmax=None):
    """Readout-free density at t > 0 as the explicit Poisson-weighted Gamma sum."""
    t, lam = mp.mpf(t), mp.mpf(lam)
    nmax = nmax or int(lam + 40 * mp.sqrt(lam + 1) + t + 40 * mp.sqrt(t + 1) + 60)
    total = mp.mpf(0)
    for n in range(1, nmax):
        total += mp.exp(
            n * mp.log(lam) - lam - mp.loggamma(n + 1) + (n - 1) * mp.log(t) - t - mp.loggamma(n)
        )
    return total


def readout_series(t, lam, r, nmax=None):
    """Law with readout r > 0: atom convolved plus the parabolic-cylinder series."""
    t, lam, r = mp.mpf(t), mp.mpf(lam), mp.mpf(r)
    nmax = nmax or int(lam + 30 * mp.sqrt(lam + 1) + 40)
    base = -(t**2) / (2 * r**2) - mp.log(r * mp.sqrt(2 * mp.pi))
    total = mp.exp(-lam + base)
    z = r - t / r
    for n in range(1, nmax):
        log_term = (
            n * mp.log(lam)
            - lam
            - mp.loggamma(n + 1)  # Poisson weight
            + n * mp.log(r)
            + base
            + z**2 / 4
        )  # Gamma(n,1) * Normal(0, r)
        total += mp.exp(log_term) * mp.pcfd(-n, z)
    return total


def readout_quadrature(t, lam, r):
    """Law with readout r > 0 by tanh-sinh quadrature on many sub-intervals."""
    t, lam, r = mp.mpf(t), mp.mpf(lam), mp.mpf(r)
    sd_f = mp.sqrt(2 * lam) + 1
    pts = {mp.mpf(0)} | {mp.mpf(10) ** k for k in range(-10, 1)}
    for j in range(-40, 41):
        for c, s in ((t, r), (lam, sd_f)):
            p = c + j * s / 2
            if p > 0:
                pts.add(p)
    top = max(pts)
    for k in range(1, 200):
        pts.add(top + k * (1 + r + sd_f))
    pts = sorted(pts)

    def integrand(u):
        if u <= 0:
            return mp.mpf(0)
        return amplified(u, lam) * mp.exp(-((t - u) ** 2) / (2 * r**2))

    j = mp.quad(integrand, pts) / (r * mp.sqrt(2 * mp.pi))
    atom = mp.exp(-lam - t**2 / (2 * r**2)) / (r * mp.sqrt(2 * mp.pi))
    return atom + j


REFERENCE_FILE = "data/emccd_quadrature_references.json"


def write_quadrature_references(traps) -> None:
    """Store the quadrature route's log p of each ``(name, t, lam, r, "quad")`` trap (25
    digits), which takes ~30 s: ``python tests/cameras/emccd_reference.py`` rewrites the file."""
    import json
    from pathlib import Path

    values = {
        name: {
            "t": t,
            "lam": lam,
            "r": r,
            "log_p": mp.nstr(mp.log(readout_quadrature(t, lam, r)), 22),
        }
        for name, t, lam, r, route in traps
        if route == "quad"
    }
    header = {
        "command": "python tests/cameras/emccd_reference.py",
        "mpmath": mp.__version__,
        "dps": mp.mp.dps,
    }
    path = Path(__file__).parents[1] / REFERENCE_FILE
    path.write_text(json.dumps({"made by": header, "traps": values}, indent=1) + "\n")


if __name__ == "__main__":
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_emccd import TRAPS

    write_quadrature_references(TRAPS)
