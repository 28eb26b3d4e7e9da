"""The offset and readout noise from a movie without dark frames: photon transfer with the
counts' third cumulant (bayespsf.calibration.photon_transfer)."""

import numpy as np
import pytest
from scipy import stats

from bayespsf.calibration.photon_transfer import (
    away_from,
    first_adu_per_photon,
    offset_from_cumulants,
    pixel_cumulants,
)
from bayespsf.cameras import EMCCD, SCMOS
from bayespsf.errors import BayespsfInputError

CAMERAS = {  # (camera, excess, M = ADU per photoelectron, readout SD in ADU)
    "emccd": (EMCCD(200.0, 50.0, 100.0, 12.0), 2.0, 200.0 / 12.0, 50.0 / 12.0),
    "scmos": (SCMOS(2.17, 100.0, 12.0), 1.0, 2.17, np.sqrt(12.0)),
}


def background_movie(camera, frames, shape, seed):
    """Counts of pixels whose Poisson background varies over the field (2 to 4 photons)."""
    rng = np.random.default_rng(seed)
    lam = np.linspace(2.0, 4.0, shape[0] * shape[1]).reshape(shape)
    return camera.sample(np.broadcast_to(lam, (frames, *shape)), rng), lam


def test_cumulants_are_the_k_statistics_whatever_the_blocks(tmp_path):
    # against scipy's k-statistics of each pixel's values, read 7 frames at a time
    rng = np.random.default_rng(1)
    movie = 1000.0 + rng.gamma(2.0, 30.0, size=(50, 4, 5))
    np.save(tmp_path / "m.npy", movie)
    got = pixel_cumulants(tmp_path / "m.npy", block=7)
    assert got.frames == 50
    for j, k in enumerate((got.k1, got.k2, got.k3, got.k4), 1):
        expected = np.array([[stats.kstat(movie[:, r, c], j) for c in range(5)] for r in range(4)])
        np.testing.assert_allclose(k, expected, rtol=1e-8)


@pytest.mark.parametrize("kind", sorted(CAMERAS))
def test_offset_and_readout_are_recovered_with_calibrated_errors(kind, tmp_path):
    # 12 movies of 600 pixels x 150 frames: each estimate within 4 of its SEs of the truth, and
    # the z-scores' SD within 0.55..1.6 (its 99% range for 12 normal z-scores is 0.58..1.48).
    # The EMCCD's readout (17 ADU^2 under 2 lam M^2 ~ 1700 of photon noise) is declared.
    camera, excess, m, readout = CAMERAS[kind]
    declared = readout if kind == "emccd" else None
    z_offset, z_readout = [], []
    for seed in range(12):
        movie, lam = background_movie(camera, 150, (20, 30), seed)
        np.save(tmp_path / "m.npy", movie)
        got = offset_from_cumulants(
            pixel_cumulants(tmp_path / "m.npy"), m, excess, readout_adu=declared
        )
        z_offset.append((got.offset - 100.0) / got.offset_se)
        if declared is None:
            z_readout.append((got.readout_sd - readout) / got.readout_sd_se)
        else:
            assert got.readout_sd == declared and "as declared" in got.describe()
        assert got.photons == pytest.approx(lam.mean(), rel=0.1)
    for z in (z_offset, z_readout) if declared is None else (z_offset,):
        z = np.array(z)
        assert np.all(np.abs(z) < 4) and 0.55 < z.std(ddof=1) < 1.6, z


def test_an_emccd_readout_under_its_photon_noise_is_not_measured(tmp_path):
    camera, excess, m, _ = CAMERAS["emccd"]
    movie, _ = background_movie(camera, 150, (20, 30), 0)
    np.save(tmp_path / "m.npy", movie)
    cumulants = pixel_cumulants(tmp_path / "m.npy")
    with pytest.raises(BayespsfInputError, match="readout noise cannot be measured"):
        offset_from_cumulants(cumulants, m, excess, adu_per_photon_se=0.3)


@pytest.mark.parametrize("kind", sorted(CAMERAS))
def test_the_fourth_cumulant_gives_a_first_m(kind, tmp_path):
    # 6000 pixels x 200 frames: K4 / K3 estimates M to ~2% here; 8% allowed
    camera, excess, m, _ = CAMERAS[kind]
    movie, _ = background_movie(camera, 200, (60, 100), 3)
    np.save(tmp_path / "m.npy", movie)
    assert first_adu_per_photon(pixel_cumulants(tmp_path / "m.npy"), excess) == pytest.approx(
        m, rel=0.08
    )


def test_inputs_that_cannot_work_are_named(tmp_path):
    np.save(tmp_path / "short.npy", np.zeros((10, 20, 20)))
    with pytest.raises(BayespsfInputError, match="needs at least 20"):
        pixel_cumulants(tmp_path / "short.npy")
    np.save(tmp_path / "flat.npy", np.full((30, 20, 20), 100.0))
    flat = pixel_cumulants(tmp_path / "flat.npy")
    with pytest.raises(BayespsfInputError, match="no photon noise"):
        first_adu_per_photon(flat, 2.0)
    with pytest.raises(BayespsfInputError, match="readout noise cannot be measured"):
        offset_from_cumulants(flat, 10.0, 2.0)
    with pytest.raises(BayespsfInputError, match="readout_adu must be"):
        offset_from_cumulants(flat, 10.0, 2.0, readout_adu=-1.0)
    with pytest.raises(BayespsfInputError, match="mask has shape"):
        offset_from_cumulants(flat, 10.0, 2.0, mask=np.ones((3, 3), bool))
    with pytest.raises(BayespsfInputError, match="at least 100"):
        offset_from_cumulants(flat, 10.0, 2.0, mask=np.zeros((20, 20), bool))
    with pytest.raises(BayespsfInputError, match="excess must be"):
        offset_from_cumulants(flat, 10.0, 3.0)
    with pytest.raises(BayespsfInputError, match="adu_per_photon must be"):
        offset_from_cumulants(flat, -1.0, 2.0)
    noisy = np.random.default_rng(0).gamma(3.0, 10.0, size=(30, 20, 20))
    noisy[7, 3, 3] = np.nan
    np.save(tmp_path / "nan.npy", noisy)
    with pytest.raises(
        BayespsfInputError,
        match=r"frame 7 has 1 NaN, infinite or vast pixel\(s\), the first NaN or infinite at row 3",
    ):
        pixel_cumulants(tmp_path / "nan.npy", block=4)
    noisy[7, 3, 3] = 30.0
    np.save(tmp_path / "skewed.npy", -noisy)  # negatively skewed: no amplified photons
    with pytest.raises(BayespsfInputError, match="no photon noise"):
        offset_from_cumulants(
            pixel_cumulants(tmp_path / "skewed.npy"), 10.0, 2.0, readout_adu=1.0, check=False
        )


def test_away_from_masks_each_molecule_square():
    import pandas as pd

    mask = away_from(
        pd.DataFrame({"molecule": [0, 1], "x": [2.0, 10.0], "y": [3.0, 8.0]}), (12, 14), 2
    )
    assert not mask[1:6, 0:5].any() and not mask[6:11, 8:13].any()
    assert mask.sum() == 12 * 14 - 25 - 25


def test_a_declared_readout_refuses_a_sub_poisson_background(tmp_path):
    # binomial(10, 0.3) photoelectrons (variance 2.1 for a mean of 3) through the EMCCD's own
    # register draws: the third cumulant then reads fewer photons than the mean holds, and
    # the variance left beyond their photon noise is far above the declared readout's
    from bayespsf.cameras.draws import gamma_register

    rng = np.random.default_rng(2)
    n = rng.binomial(10, 0.3, size=(150, 20, 30))
    movie = 100.0 + (gamma_register(n, 200.0, rng) + rng.normal(0, 50.0, n.shape)) / 12.0
    np.save(tmp_path / "m.npy", movie)
    cumulants = pixel_cumulants(tmp_path / "m.npy")
    with pytest.raises(BayespsfInputError, match="not Poisson photons over the declared"):
        offset_from_cumulants(cumulants, 200.0 / 12.0, 2.0, readout_adu=50.0 / 12.0)
    # the same check passes Poisson photons of the same mean (the z-score test above)
    poisson, _ = background_movie(CAMERAS["emccd"][0], 150, (20, 30), 2)
    np.save(tmp_path / "p.npy", poisson)
    offset_from_cumulants(
        pixel_cumulants(tmp_path / "p.npy"), 200.0 / 12.0, 2.0, readout_adu=50.0 / 12.0
    )
