"""The inference model built from a scene."""

import numpy as np
import pytest

from bayespsf import Model, Scene, scenes, simulate
from bayespsf.cameras import EMCCD, SCMOS, Photon
from bayespsf.psf import expected_counts


def test_from_scene_picks_the_camera_and_tier():
    assert isinstance(Model.from_scene(scenes.load("ideal")).camera, Photon)
    emccd = Model.from_scene(scenes.load("emccd-typical")).camera
    assert isinstance(emccd, EMCCD) and emccd.likelihood == "table" and emccd.gain == 200.0
    assert (
        Model.from_scene(scenes.load("emccd-typical"), likelihood="exact").camera.likelihood
        == "exact"
    )
    assert isinstance(Model.from_scene(scenes.load("scmos-typical")).camera, SCMOS)
    with pytest.raises(ValueError, match="photon camera"):
        Model.from_scene(scenes.load("ideal"), likelihood="table")


def test_expected_includes_clock_induced_charge_and_matches_the_psf():
    scene = Scene.from_dict(
        {"camera": {"kind": "emccd", "gain": 100.0, "clock_induced_charge": 0.05}}
    )
    model = Model.from_scene(scene)
    p = np.array([10.0, -5.0, 120.0, 110.0, 800.0, 3.0])
    assert np.allclose(model.expected(p), expected_counts(p, 15, 100.0) + 0.05, rtol=1e-15)


def test_log_likelihood_sums_pixels_and_broadcasts_walkers():
    scene = scenes.load("emccd-typical")
    model = Model.from_scene(scene)
    counts, truth = simulate(scene, 1, seed=0)
    p = truth[["x0", "y0", "s_x", "s_y", "N", "b"]].to_numpy()[0]
    walkers = p + np.array([[0.0] * 6, [5.0, 0, 0, 0, 0, 0], [0, 0, 10.0, 0, 0, 0]])
    ll = model.log_likelihood(counts[0], walkers)
    direct = model.camera.log_likelihood(counts[0], model.expected(walkers)).sum(axis=(-2, -1))
    assert ll.shape == (3,) and np.allclose(ll, direct)


def test_to_photons_and_variance():
    model = Model.from_scene(scenes.load("emccd-typical"))
    assert model.to_photons(100.0 + 200.0 / 12.0) == pytest.approx(1.0)
    assert model.photon_variance(4.0) == pytest.approx(2 * 4.0 + (50.0 / 200.0) ** 2)


@pytest.mark.parametrize(
    "counts,match",
    [
        (np.zeros((15, 14)), "shape"),
        (np.full((15, 15), np.nan), "finite"),
        (np.ones(3), "shape"),
        (np.zeros((15, 15)), "same value"),
    ],
)
def test_bad_rois_are_named(counts, match):
    with pytest.raises(ValueError, match=f"counts.*{match}"):
        Model.from_scene(scenes.load("ideal")).check_counts(counts)


def test_negative_photon_counts_rejected():
    with pytest.raises(ValueError, match="counts"):
        Model.from_scene(scenes.load("ideal")).check_counts(-np.ones((15, 15)))
