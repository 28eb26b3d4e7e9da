"""Quantum efficiency: declared in scenes, camera files and Model; N and b in incident photons
or detected photoelectrons, stated in every table."""

import numpy as np
import pandas as pd
import pytest

from bayespsf import Scene, load_scene, simulate
from bayespsf.cameras import EMCCD
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import fit_mle
from bayespsf.model import Model
from bayespsf.movie.extract import photon_model
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.scene import SceneError
from bayespsf.simulation import build_pipeline
from bayespsf.theory import crlb, scene_params

Q = 0.6


def with_qe(name, unit="incident", q=Q, **emitter):
    scene = load_scene(name).replace(emitter={"position": "fixed", **emitter})
    return scene.replace(camera={"quantum_efficiency": q, "photon_unit": unit})


def test_undeclared_quantum_efficiency_adds_no_effect():
    for name in ("ideal", "emccd-typical", "paper-fig3"):
        steps = [type(s).__name__ for s in build_pipeline(load_scene(name))]
        assert "QuantumEfficiency" not in steps and "DetectedTruth" not in steps
    steps = [type(s).__name__ for s in build_pipeline(with_qe("emccd-typical"))]
    assert steps.index("QuantumEfficiency") < steps.index("GammaRegister")


def test_thinning_of_exactly_n_photons_is_binomial():
    # 'fixed' statistics, no background, photon camera: each image's photoelectrons (the ROI
    # of 15 px holds 1 - 1e-9 of the spot) ~ Binomial(N, Q): mean N Q, variance N Q (1 - Q).
    # 4000 images: the mean's SE is sd / sqrt(n); the variance's SE is ~ var sqrt(2 / n).
    scene = with_qe("ideal", photons=500.0, photon_statistics="fixed").replace(
        background={"kind": "none"}
    )
    counts, truth = simulate(scene, 4000, seed=5)
    totals = counts.sum(axis=(1, 2))
    n, var = 500.0, 500.0 * Q * (1 - Q)
    assert abs(totals.mean() - n * Q) < 5 * np.sqrt(var / len(totals))
    assert abs(totals.var(ddof=1) / var - 1) < 5 * np.sqrt(2 / len(totals))
    assert np.all(truth["N"] == 500.0)  # incident photons, as declared


def test_thinned_poisson_background_is_poisson_of_the_detected_mean():
    # Poisson(b) thinned by Q is Poisson(Q b): corner pixels (no spot) have mean = var = Q b
    scene = with_qe("ideal", photons=1.0).replace(background={"kind": "poisson", "mean": 20.0})
    counts, _ = simulate(scene, 2000, seed=6)
    corner = counts[:, :3, :3].ravel()
    expected = Q * 20.0
    assert abs(corner.mean() - expected) < 5 * np.sqrt(expected / corner.size)
    assert abs(corner.var(ddof=1) / expected - 1) < 5 * np.sqrt(2 / corner.size)


def test_truth_follows_the_photon_unit():
    incident = with_qe("emccd-typical")
    detected = with_qe("emccd-typical", unit="detected")
    _, t_in = simulate(incident, 3, seed=1)
    counts_de, t_de = simulate(detected, 3, seed=1)
    assert np.array_equal(counts_de, simulate(incident, 3, seed=1)[0])  # the same images
    np.testing.assert_allclose(t_de[["N", "b"]], Q * t_in[["N", "b"]].to_numpy())
    np.testing.assert_allclose(scene_params(detected)[4:], Q * scene_params(incident)[4:])


def test_model_scales_the_spot_and_background_by_the_quantum_efficiency():
    cam = EMCCD(100.0, 40.0, 100.0, 10.0)
    plain = Model(15, 100.0, cam, clock_induced_charge=0.02)
    model = Model(15, 100.0, cam, clock_induced_charge=0.02, quantum_efficiency=Q)
    params = np.array([10.0, -20.0, 120.0, 130.0, 2000.0, 5.0])
    detected = params * [1, 1, 1, 1, Q, Q]
    np.testing.assert_allclose(model.expected(params), plain.expected(detected))
    _, jac = model.expected_and_jacobian(params)
    step = 1e-6 * np.abs(params)
    for k in range(6):
        e = np.zeros(6)
        e[k] = step[k]
        numeric = (model.expected(params + e) - model.expected(params - e)) / (2 * step[k])
        np.testing.assert_allclose(jac[k], numeric, rtol=1e-6, atol=1e-9)
    counts = simulate(with_qe("emccd-typical", photons=2000.0), 1, seed=2)[0][0]
    np.testing.assert_allclose(
        model.log_likelihood(counts, params), plain.log_likelihood(counts, detected)
    )
    np.testing.assert_allclose(model.to_photons(counts), plain.to_photons(counts) / Q)
    assert model.photon_unit_label == "incident photons (quantum efficiency 0.6)"
    assert plain.photon_unit_label == "photoelectrons"
    other = Model(15, 100.0, cam, quantum_efficiency=Q, photon_unit="detected")
    assert other.photon_unit_label == "photoelectrons"
    np.testing.assert_allclose(other.expected(params), plain.expected(params) - 0.02)


def test_fisher_bound_of_incident_photons_is_the_detected_bound_over_the_efficiency():
    # N_incident = N_detected / Q exactly, so its bound is the detected one over Q; the other
    # parameters' bounds are those of a scene of Q N photons without quantum efficiency
    scene = with_qe("emccd-typical", photons=3000.0)
    plain = load_scene("emccd-typical").replace(
        emitter={"position": "fixed", "photons": Q * 3000.0},
        background={"mean": Q * scene.background["mean"]},
    )
    ours, theirs = crlb(scene).to_numpy(), crlb(plain).to_numpy()
    np.testing.assert_allclose(ours[:4], theirs[:4], rtol=1e-9)
    np.testing.assert_allclose(ours[4:], theirs[4:] / Q, rtol=1e-9)


@pytest.mark.parametrize("unit", ["incident", "detected"])
def test_mle_recovers_n_in_its_unit_at_the_bound(unit):
    # N = 1e4 incident (6000 detected): MLE bias and excess variance are O(1/N); 5 SE
    # tolerances on the mean, 5 SE + 1% on the SD (as the QE-free test in test_estimators)
    scene = with_qe("emccd-typical", unit=unit, photons=1e4)
    model = Model.from_scene(scene)
    counts, truth = simulate(scene, 400, seed=32)
    fits = fit_mle(counts, model)
    assert fits["converged"].all() and set(fits["photon_unit"]) == {model.photon_unit_label}
    bound = crlb(scene).to_numpy()
    est = fits[list(PARAMETER_NAMES)].to_numpy()
    n = len(est)
    assert np.all(np.abs(est.mean(0) - scene_params(scene)) <= 5 * bound / np.sqrt(n))
    se = bound / np.sqrt(2 * (n - 1))
    assert np.all(np.abs(est.std(0, ddof=1) - bound) <= 5 * se + 0.01 * bound)
    np.testing.assert_allclose(truth["N"], scene_params(scene)[4])


@pytest.mark.parametrize(
    ("camera", "message"),
    [
        ({"quantum_efficiency": 0.0}, "camera.quantum_efficiency must be in (0, 1]"),
        ({"quantum_efficiency": 1.2}, "camera.quantum_efficiency must be in (0, 1]"),
        ({"photon_unit": "electrons"}, "camera.photon_unit must be one of 'incident', 'detected'"),
    ],
)
def test_bad_declarations_are_named(camera, message):
    with pytest.raises(SceneError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Scene.from_dict({"camera": camera})


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"quantum_efficiency": 0}, "quantum_efficiency must be a number in"),
        ({"quantum_efficiency": float("nan")}, "quantum_efficiency must be a number in"),
        ({"quantum_efficiency": True}, "quantum_efficiency must be a number in"),
        ({"photon_unit": "photons"}, "photon_unit must be one of 'incident', 'detected'"),
    ],
)
def test_bad_model_arguments_are_named(options, message):
    with pytest.raises(BayespsfInputError, match=message):
        Model(15, 100.0, EMCCD(100.0, 40.0, 100.0, 10.0), **options)


def test_the_movie_path_converts_to_detected_photoelectrons():
    cam = EMCCD(100.0, 40.0, 100.0, 10.0)
    counts = np.full((2, 5, 5), 600.0)
    with_q = photon_model(Model(15, 100.0, cam, quantum_efficiency=Q))
    np.testing.assert_allclose(with_q.to_photons(counts), photon_model(cam).to_photons(counts))
    assert with_q.photon_unit_label == "photoelectrons"


def test_store_refuses_a_model_of_another_quantum_efficiency(tmp_path):
    from bayespsf.parallel import sample_many

    scene = with_qe("emccd-typical", photons=3000.0)
    counts, _ = simulate(scene, 2, seed=4)
    model = Model.from_scene(scene)
    table = sample_many(
        counts, model, seed=1, workers=1, store=tmp_path / "s", ess=50, method="laplace"
    )
    assert set(table["photon_unit"]) == {"incident photons (quantum efficiency 0.6)"}
    other = Model.from_scene(scene.replace(camera={"quantum_efficiency": 0.9}))
    with pytest.raises(BayespsfInputError, match="model differ"):
        sample_many(
            counts, other, seed=1, workers=1, store=tmp_path / "s", ess=50, method="laplace"
        )


def test_simulated_tables_state_the_unit(tmp_path):
    from bayespsf import cli

    scene = with_qe("emccd-typical", unit="detected")
    path = tmp_path / "s.toml"
    scene.save(path)
    assert cli.main(["simulate", str(path), "-n", "2", "--out", str(tmp_path / "a")]) == 0
    truth = pd.read_csv(tmp_path / "a.truth.csv")
    assert set(truth["photon_unit"]) == {"photoelectrons"}
    incident = tmp_path / "i.toml"
    scene.replace(camera={"photon_unit": "incident"}).save(incident)
    with pytest.raises(
        SystemExit, match="N and b in photoelectrons, but the model's are in incident photons"
    ):
        cli.main(
            [
                "fit",
                str(tmp_path / "a.npy"),
                "--scene",
                str(incident),
                "--truth",
                str(tmp_path / "a.truth.csv"),
                "--out",
                str(tmp_path / "f"),
            ]
        )
