"""The paper's experimental Delta s per molecule (bayespsf.analysis.width_spread)."""

import numpy as np
import pandas as pd
import pytest

from bayespsf.analysis import width_spread
from bayespsf.errors import BayespsfInputError

A = 79.0


def table(molecules=40, frames=80, sd=6.0, seed=0):
    rng = np.random.default_rng(seed)
    mol = np.repeat(np.arange(molecules), frames)
    n = rng.uniform(500, 5000, molecules)[mol]
    return pd.DataFrame(
        {
            "molecule": mol,
            "N_mean": n,
            "b_mean": 3.0,
            "s_x_mean": 120 + rng.normal(0, sd, mol.size),
            "s_x_mle": 120 + rng.normal(0, sd, mol.size),
            "s_y_mean": 121.0,
            "s_x_sd": sd,
            "crlb_s_x": 5.5,
            "photon_unit": "photoelectrons",
        }
    )


def test_spread_is_the_sd_over_frames_with_its_error():
    # 40 molecules x 80 frames of estimates with SD 6 nm: each delta_s within 4 of its SEs
    # of 6, and those SEs 6 / sqrt(158)
    out = width_spread(table(), A)
    for e in ("mean", "mle"):
        z = (out[f"delta_s_{e}"] - 6.0) / out[f"delta_s_{e}_se"]
        assert np.all(np.abs(z) < 4), z
    np.testing.assert_allclose(out["delta_s_mle_se"], out["delta_s_mle"] / np.sqrt(158))
    assert "delta_s_lsq" not in out and (out["frames"] == 80).all()
    assert np.allclose(out["posterior_sd"], 6.0) and np.allclose(out["crlb"], 5.5)


def test_eq_sigma2dp3_at_the_molecules_mean_values():
    # the paper's formula typed out: s'^2 / N + 16 pi s'x^3 s'y (sigma_b^2 + b) / (3 a^2 N^2)
    frames = table(molecules=3, frames=5)
    out = width_spread(frames, A, background_variance=2.0)
    g = frames.groupby("molecule")
    sx = np.sqrt(g["s_x_mean"].mean() ** 2 + A**2 / 12)
    sy = np.sqrt(121.0**2 + A**2 / 12)
    n = g["N_mean"].mean()
    expected = np.sqrt(sx**2 / n + 16 * np.pi * sx**3 * sy * (2.0 + 3.0) / (3 * A**2 * n**2))
    np.testing.assert_allclose(out["eq_sigma2dp3"], expected.to_numpy())
    poisson = width_spread(frames, A)  # sigma_b^2 = <b> = 3
    assert np.all(poisson["eq_sigma2dp3"] > out["eq_sigma2dp3"])


def test_units_and_columns_are_checked():
    frames = table(molecules=2, frames=3)
    with pytest.raises(BayespsfInputError, match="stated in detected photons"):
        width_spread(frames.assign(photon_unit="incident photons (quantum efficiency 0.9)"), A)
    with pytest.raises(BayespsfInputError, match="no column"):
        width_spread(frames.drop(columns="b_mean"), A)
    with pytest.raises(BayespsfInputError, match="no column"):
        width_spread(frames.drop(columns=["s_x_mle", "s_x_mean"]), A)
    with pytest.raises(BayespsfInputError, match="pixel_size"):
        width_spread(frames, -1.0)
    with pytest.raises(BayespsfInputError, match="width must be 's_x' or 's_y'"):
        width_spread(frames, A, width="x0")
