"""The NumPyro peer of benchmarks/peer.py is the same model as bayespsf's, and its benchmark runs.

Skipped without numpyro, an optional extra (``pip install -e ".[peer]"``).
"""

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numpyro")

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import jax.numpy as jnp
import peer

from bayespsf import load_scene, simulate
from bayespsf.model import Model
from bayespsf.theory import scene_params


@pytest.mark.parametrize(
    ("name", "likelihood", "camera"),
    [
        ("ideal", "poisson", {}),
        ("emccd-typical", "gaussian", {}),
        # the EMCCD poisson tier has no support below zero photons: no readout noise here
        ("emccd-typical", "poisson", {"readout_sd": 0.0}),
    ],
)
def test_peer_log_density_is_bayespsf_log_posterior(name, likelihood, camera):
    scene = load_scene(name).replace(emitter={"position": "fixed"}, camera=camera)
    model = Model.from_scene(scene, likelihood=likelihood)
    spec = peer.PeerSpec.from_model(model)
    counts, _ = simulate(scene, 1, seed=3)
    c = model.check_counts(counts[0])
    photons = jnp.asarray(spec.to_photons(c))
    rng = np.random.default_rng(1)
    spread = np.array([60.0, 60.0, 0.4, 0.4, 0.5, 3.0])  # nm, nm, log, log, log, photons
    z = model.to_unconstrained(scene_params(scene)) + spread * rng.standard_normal((12, 6))
    z[-3, 0] = 760.0  # x0 beyond the uniform prior's 750 nm
    z[-2, 5] = -0.5  # b below its prior's 0
    z[-1, 2] = np.log(5.0)  # s_x below the log-uniform prior's 10 nm
    ours = model.log_posterior(z, c)
    theirs = -np.array([peer.potential(zz, photons, spec) for zz in z])
    inside = np.isfinite(ours)
    assert inside.sum() == 9 and np.array_equal(np.isfinite(theirs), inside)
    assert np.all(theirs[~inside] == -np.inf)
    difference = theirs[inside] - ours[inside]
    assert np.ptp(difference) < 1e-6, difference


def test_peer_benchmark_tiny_run():
    # one case and one molecule: the full quick run compiles two NumPyro models (~25 s)
    df = peer.run(quick=True, cases=[("ideal", "poisson")])
    expected = {
        "scene",
        "likelihood",
        "ROI",
        "N",
        "ours s",
        "ours ESS s_x",
        "ours ESS/s",
        "NUTS compile s",
        "NUTS warm-up s",
        "NUTS sampling s",
        "NUTS ESS s_x",
        "NUTS ESS/s sampling",
        "NUTS ESS/s incl. compile",
        "ours/NUTS sampling",
        "ours/NUTS incl. compile",
        "ours mean s_x",
        "NUTS mean s_x",
        "ours sd s_x",
        "NUTS sd s_x",
        "z mean s_x",
    }
    assert expected <= set(df.columns) and len(df) == 1
    row = df.iloc[0]
    assert row["ROI"] == "15x15" and row["N"] == 1000
    assert row["importance k-hat"] <= 0.7  # a bright photon-counting spot: near-Gaussian
    for column in [
        "ours ESS s_x",
        "NUTS ESS s_x",
        "ours ESS/s",
        "NUTS ESS/s sampling",
        "importance ESS/s",
    ]:
        assert np.isfinite(row[column]) and row[column] > 0, column
    assert row["NUTS compile s"] > 0 and row["NUTS sampling s"] > 0
    assert abs(row["z mean s_x"]) < 5  # same posterior, within Monte Carlo error
    assert 0.8 < row["NUTS sd s_x"] / row["ours sd s_x"] < 1.25
    text = peer.markdown(df, "python benchmarks/peer.py --quick")
    assert "| scene" in text and "NUTS ESS/s sampling" in text and "z mean s_x" in text
