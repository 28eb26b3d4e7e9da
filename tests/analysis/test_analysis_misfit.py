"""Residual images and the width against the fitting window (bayespsf.analysis.misfit): noise
where the model holds, a pattern and a moving width where the spot is an Airy disk."""

import numpy as np
import pytest

from bayespsf import load_scene, simulate
from bayespsf.analysis import mean_residuals, width_by_window
from bayespsf.analysis.misfit import central
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import fit_mle
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES

GAUSSIAN = load_scene("emccd-typical").replace(emitter={"position": "fixed", "photons": 5000.0})
MODEL = Model.from_scene(GAUSSIAN)
MOLECULES = np.repeat([3, 8], 50)  # two molecules of 50 frames


def airy_scene():
    table = GAUSSIAN.to_dict()
    table["optics"] = {"psf": "airy", "wavelength": 620.0, "na": 1.0}
    for key in ("s0x", "s0y"):
        table["emitter"].pop(key)
    return type(GAUSSIAN).from_dict(table)


@pytest.fixture(scope="module", params=["gaussian", "airy"])
def case(request):
    scene = GAUSSIAN if request.param == "gaussian" else airy_scene()
    counts, _ = simulate(scene, 100, seed=1)
    fits = fit_mle(counts, MODEL, laplace=False)[list(PARAMETER_NAMES)].to_numpy(float)
    return request.param, counts, fits


def test_residual_images_are_noise_only_where_the_model_holds(case):
    # Where the model holds each pixel of sqrt(K) x the mean Pearson residual is ~N(0, 1), less
    # the fit's 6 of 225 degrees of freedom: SD ~0.99; the SD of 450 such values has SE 0.033
    # (tolerance 0.9 to 1.1). An Airy disk fitted with a Gaussian leaves a pattern: SD > 2
    # (3.5 measured at 5 000 photons).
    name, counts, fits = case
    ids, images = mean_residuals(counts, MODEL, fits, MOLECULES)
    assert list(ids) == [3, 8] and images.shape == (2, 15, 15)
    if name == "gaussian":
        assert 0.9 < images.std() < 1.1
    else:
        assert images.std() > 2.0


def test_the_width_moves_with_the_window_only_where_the_model_misfits(case):
    # Gaussian: the mean width over 50 frames is the same in 7 x 7, 11 x 11 and 15 x 15 windows
    # within 4 of the SE of a difference (taken as independent: conservative, the windows
    # share pixels). Airy: it changes by more than 6 such SEs (125 nm in 7 x 7, 120 in 15 x 15:
    # ~9.5 SEs)
    name, counts, _ = case
    table = width_by_window(counts, MODEL, MOLECULES)
    assert set(table["window"]) == {7, 11, 15} and (table["frames"] == 50).all()
    for _, rows in table.groupby("molecule"):
        small, large = rows.iloc[0], rows.iloc[-1]
        difference = abs(small["s_x"] - large["s_x"])
        se = np.hypot(small["s_x_se"], large["s_x_se"])
        assert difference < 4 * se if name == "gaussian" else difference > 6 * se


def test_bad_inputs_are_named():
    counts, _ = simulate(GAUSSIAN, 2, seed=2)
    with pytest.raises(BayespsfInputError, match="window must be odd"):
        central(counts, 8)
    with pytest.raises(BayespsfInputError, match="window must be odd"):
        central(counts, 17)
    with pytest.raises(BayespsfInputError, match="window must be odd"):
        central(counts[:, :14, :14], 7)  # an even ROI has no central pixel
    with pytest.raises(BayespsfInputError, match="none of"):
        width_by_window(counts, MODEL, [0, 0], windows=(21,))
    with pytest.raises(BayespsfInputError, match="one entry per ROI"):
        mean_residuals(counts, MODEL, np.zeros((3, 6)), [0, 0])
