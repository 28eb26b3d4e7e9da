"""The benchmark scripts run (quick mode) and measure what they claim; no timing is asserted."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import likelihood


def test_likelihood_benchmark_quick():
    df = likelihood.run(quick=True)
    assert set(df["tier"]) == {"exact", "table", "high-gain", "gaussian", "poisson"}
    assert np.all(df["evals/s"] > 0)
    exact = df[df["tier"] == "exact"]
    assert np.all(exact["worst |Δlog p| domain"] == 0)
    table = df[df["tier"] == "table"]
    assert np.all(table["worst |Δlog p| domain"] <= 1e-4)
    assert "| camera" in likelihood.markdown(df, "python benchmarks/likelihood.py --quick")


def test_simulate_benchmark_quick():
    import simulate as simulate_benchmark

    df = simulate_benchmark.run(quick=True)
    assert set(df["roi"]) == {15, 19}
    assert np.all(df["images/s"] > 0) and np.all(df["peak MB"] > 0)
    ideal = df[df["scene"] == "ideal"]
    assert np.allclose(ideal["throughput / ideal"], 1.0)
    assert "| scene" in simulate_benchmark.markdown(df, "python benchmarks/simulate.py --quick")


def test_posterior_benchmark_quick():
    import posterior as posterior_benchmark

    costs, moves = posterior_benchmark.run(quick=True)
    assert costs["converged"].all() and np.all(costs["min ess_bulk"] >= 400)
    assert np.all(costs["time / MLE"] > 0) and set(moves["moves"]) == {
        "laplace-de",
        "de-snooker",
        "stretch",
    }
    assert "| tier" in posterior_benchmark.markdown(
        costs, moves, "python benchmarks/posterior.py --quick"
    )
