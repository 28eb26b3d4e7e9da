"""The camera from one frame or a few: spatial photon transfer over background blocks
(bayespsf.calibration.spatial, bayespsf.calibration.short)."""

import numpy as np
import pytest

from bayespsf.calibration import calibrate_camera
from bayespsf.calibration.spatial import (
    Known,
    block_sums,
    plane_factors,
    pooled_cumulants,
    solve,
    spatial_photon_transfer,
)
from bayespsf.cameras import EMCCD, SCMOS
from bayespsf.errors import BayespsfInputError
from bayespsf.io import read_camera_file


def emccd_frames(frames, shape, seed, slope=0.0):
    """EMCCD counts (M = 200 / 12 ADU per photon, readout 50 e-, offset 100) of a Poisson
    background of 3 photons, with an illumination slope across the columns."""
    lam = 3.0 + slope * np.linspace(-1.0, 1.0, shape[1])[None, :] * np.ones(shape)
    rng = np.random.default_rng(seed)
    return EMCCD(200.0, 50.0, 100.0, 12.0).sample(np.broadcast_to(lam, (frames, *shape)), rng)


def test_plane_fit_factors_are_those_of_a_projection():
    a, (trace, _, _, diagonal) = plane_factors(8)
    np.testing.assert_allclose(a @ a, a, atol=1e-12)
    assert trace == pytest.approx(64 - 3)
    assert diagonal == pytest.approx(np.sum(np.diag(a) ** 2))


def test_pooled_cumulants_are_unbiased_under_a_slope():
    # 30 frames of 128 x 128 with the background rising 1.5 -> 4.5 photons across the field:
    # the plane fit removes the slope, so K2 is the average of the blocks' own, 2 lam M^2 + s^2
    frames = emccd_frames(30, (128, 128), 0, slope=1.5)
    k1, k2, k3, k4 = pooled_cumulants(block_sums(frames, np.ones((128, 128), bool)))
    m, lam = 200.0 / 12.0, 3.0
    assert k1 == pytest.approx(100.0 + lam * m, rel=0.01)
    assert k2 == pytest.approx(2 * lam * m**2 + (50.0 / 12.0) ** 2, rel=0.01)
    assert k3 == pytest.approx(6 * lam * m**3, rel=0.03)
    assert k4 == pytest.approx(24 * lam * m**4, rel=0.1)


def test_emccd_frames_cover_the_gain_within_their_errors():
    # 16 single frames of 128 x 128: each M within 3.5 of its SEs, and the z-scores' SD in
    # 0.4..1.6 (the SE is the larger of two bootstraps, so about 0.9 is expected; the 99%
    # range of the SD of 16 normal z-scores is 0.62..1.4 times it)
    z = []
    for seed in range(16):
        frames = emccd_frames(1, (128, 128), seed)
        got = spatial_photon_transfer(
            block_sums(frames, np.ones((128, 128), bool)),
            2.0,
            Known(readout_e=50.0, e_per_adu=12.0),
            seed=seed,
        )
        z.append((got.adu_per_photon - 200.0 / 12.0) / got.adu_per_photon_se)
        assert got.readout_sd == pytest.approx(50.0 / 12.0) and got.readout_sd_se == 0.0
    assert np.max(np.abs(z)) < 3.5 and 0.4 < np.std(z, ddof=1) < 1.6, z


def test_the_stated_error_is_the_spread_of_the_estimate_over_frames():
    # Independent truth: the SD of M over 1200 independent 64 x 64 frames (64 blocks) from the
    # camera's own sampler (bayespsf.cameras, not the bootstrap's draws), known to 2.0%
    # (1 / sqrt(2 x 1199)). The stated SE, averaged over 32 frames (its CV ~16% at 64 blocks),
    # is known to 2.9%: the ratio to 3.5%. The SE is the larger of two estimates of the spread,
    # so somewhat above it (1.05 over 300 frames at this size); the ratio must lie in
    # 0.895..1.25, so an SE 10% below the spread fails (3 of the ratio's SDs). And at least 27
    # of the 32 within 1.96 SE (fails with probability 0.005 at a coverage of 0.95).
    known = Known(readout_e=50.0, e_per_adu=12.0)
    keep = np.ones((64, 64), bool)
    spread = []
    for chunk in range(3):
        sums = block_sums(emccd_frames(400, (64, 64), 100 + chunk), keep)
        trace, cubes, _, _ = sums.factors  # each frame's K2 and K3 (module docstring)
        for k2, k3 in zip(sums.s2.mean(axis=0) / trace, sums.s3.mean(axis=0) / cubes, strict=True):
            spread.append(solve(np.array([0.0, k2, k3, 0.0]), 2.0, known)[0])
    stated, z = [], []
    for seed in range(32):
        got = spatial_photon_transfer(
            block_sums(emccd_frames(1, (64, 64), 1000 + seed), keep), 2.0, known, seed=seed
        )
        stated.append(got.adu_per_photon_se)
        z.append((got.adu_per_photon - 200.0 / 12.0) / got.adu_per_photon_se)
    ratio = np.mean(stated) / np.std(spread, ddof=1)
    assert 0.895 < ratio < 1.25, ratio
    assert np.sum(np.abs(z) <= 1.96) >= 27, z


def test_too_little_background_and_a_readout_above_the_noise_are_refused():
    frames = emccd_frames(1, (64, 64), 0)
    with pytest.raises(BayespsfInputError, match="background blocks"):
        spatial_photon_transfer(block_sums(frames, np.zeros((64, 64), bool)), 2.0, Known())
    sums = block_sums(frames, np.ones((64, 64), bool))
    with pytest.raises(BayespsfInputError, match="--e-per-adu"):
        spatial_photon_transfer(sums, 2.0, Known(readout_e=50.0, e_per_adu=1.0))


def test_calibrate_camera_on_one_frame_says_it_is_approximate(tmp_path):
    # one sCMOS frame of 160 x 160 with two spots, and dark frames: the short path, its file
    camera = SCMOS(2.17, 100.0, 12.0)
    rng = np.random.default_rng(3)
    lam = np.full((160, 160), 3.0)
    rows, cols = np.mgrid[0:160, 0:160]
    for r, c in ((40, 50), (110, 120)):
        lam += 300.0 * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * 1.5**2))
    np.save(tmp_path / "frame.npy", camera.sample(lam[None], rng))
    np.save(tmp_path / "dark.npy", camera.sample(np.zeros((20, 160, 160)), rng))
    cal = calibrate_camera(
        tmp_path / "frame.npy", tmp_path / "dark.npy", kind="scmos", s0=120.0, pixel_size=80.0
    )
    e = cal.estimate
    assert abs(e.adu_per_photon - 2.17) < 4 * e.adu_per_photon_se < 0.3
    assert cal.spots >= 2 and e.frames == 1 and e.source == "dark"
    assert "approximate" in cal.summary() and "20 frames" in cal.summary()
    text = cal.toml("bayespsf calibrate frame.npy")
    assert "# approximate" in text
    (tmp_path / "camera.toml").write_text(text)
    read = read_camera_file(tmp_path / "camera.toml")
    assert read["camera"]["gain"] == pytest.approx(e.adu_per_photon)
    assert read["geometry"]["pixel_size"] == 80.0
