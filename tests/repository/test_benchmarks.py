"""The benchmark scripts run (quick mode) and measure what they claim; no timing is asserted."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

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


def test_pixel_model_benchmark_quick():
    # deterministic parts: on a noiseless pixel-integrated spot the integrated model's MLE
    # recovers s0 and the sampled model's converges to the pixel-convolved width, Eq. tophat's
    # sqrt(s0^2 + a^2/12) up to its O((a/s0)^4) error (1e-4 at a/s0 = 0.5; 0.5% at 2)
    import pixel_model

    df = pixel_model.run(quick=True).set_index("a/s0")
    assert np.allclose(df["integrated: noiseless limit / s0"], 1.0, atol=1e-4)
    tophat = df["Eq. tophat sqrt(1 + (a/s0)^2/12)"]
    assert abs(df.loc[0.5, "sampled: noiseless limit / s0"] / tophat[0.5] - 1) < 1e-4
    assert abs(df.loc[2.0, "sampled: noiseless limit / s0"] / tophat[2.0] - 1) < 0.01
    assert np.all(df["log-posterior cost sampled / integrated"] > 0)
    assert "| a/s0" in pixel_model.markdown(df.reset_index(), "python benchmarks/pixel_model.py")


def test_hot_path_benchmark_quick():
    import hot_path

    parts, call, floor, psis = hot_path.main(["--quick"])
    # each second is counted in one stage only: were a nested call counted twice, "the rest"
    # (total minus the timed stages) could go negative
    stages = parts[parts["stage"] != "total"]
    assert np.all(stages["seconds"] > 0)
    # every part of the log-posterior call is timed (a part that failed would be missing)
    assert len(call) == 5 and np.all(np.isfinite(call["microseconds"]))
    assert np.all(call["microseconds"] > 0)
    assert np.all(floor["steps/s with a free log-probability"] > 0)
    assert np.all(psis["Pareto k-hat"] <= 0.7) and np.all(psis["ESS"] >= 400)


def test_localize_benchmark_quick():
    # picasso's localize and bayespsf's per-frame commands on one small movie (3 frames, 3
    # molecules at 1 000 photons: every spot far above any threshold): each finds the 9 spots
    # and nothing else, and each error bar and error is scored against the truth
    import localize

    table = localize.main(["--quick"])
    assert len(table) == 4 and table["method"].str.startswith("picasso").sum() == 2
    assert (table["missed"] == 0).all() and (table["false"] == 0).all()
    assert (table["without a position"] == 0).all()
    assert (table["localisations"] == 9).all()
    assert np.all((table["RMS error (nm)"] > 0) & (table["median error bar (nm)"] > 0))
    assert table["threshold"].iloc[:2].isin(localize.THRESHOLDS).all()
    assert table["time / picasso gausslq"].iloc[0] == 1.0


def test_throughput_benchmark_quick():
    # picasso's fitters and ours on the same ROIs; every method fits and is timed, and the
    # stack engine is unbiased in s_x within 4 standard errors (picasso's sampled-Gaussian LM
    # MLE is not asserted: its bias is what the benchmark reports)
    import throughput

    peers, scaling, cold, turns = throughput.main(["--quick"])
    assert len(peers) == 13 and np.all(peers["ROIs/s"] > 0)
    ours = peers[peers["method"] == "bayespsf fit_mle (stack, with Laplace)"]
    assert np.all(np.abs(ours["s_x - truth (nm)"]) < 4 * ours["SE (nm)"])
    batched = peers[peers["method"].str.startswith("bayespsf sample_many")]
    assert len(batched) == 4
    assert np.all(np.abs(batched["s_x - truth (nm)"]) < 4 * batched["SE (nm)"])
    assert set(scaling["varied"]) == {"roi", "N", "stack"} and np.all(scaling["peak MB"] > 0)
    assert scaling["converged"].min() > 0.9
    assert len(cold) == 1 and np.all(cold["first fit (s)"] > 0)
    # the ratios in rounds: fit_mle and auto, two rounds each, every round's ratio listed
    assert turns["method"].tolist() == [
        "bayespsf fit_mle (stack, with Laplace)",
        "bayespsf sample_many auto, ESS 400",
    ]
    assert np.all(turns["rounds"] == 2) and np.all(turns["lowest"] > 0)
    assert turns["each round"].str.split().map(len).eq(2).all()


def test_scmos_benchmark_quick():
    # every evaluation of the sCMOS law is timed on the same pixels, with its ratio to the
    # Poisson baseline; the fit and the posterior are timed against gaussmle in rounds
    import scmos

    per_pixel, turns = scmos.main(["--quick"])
    assert per_pixel["evaluation"].iloc[0] == "Poisson log-pmf (the baseline)"
    assert len(per_pixel) == 8 and np.all(per_pixel["ns per pixel"] > 0)
    assert per_pixel["time / Poisson"].iloc[0] == 1.0
    assert turns["scene"].eq("scmos-typical").all() and np.all(turns["rounds"] == 2)
    assert np.all(turns["lowest"] > 0)


def test_store_benchmark_quick():
    # sample_many without and with a store on the same ROIs, then the resume and one read back
    import store

    table = store.main(["--quick"])
    assert len(table) == 2 and np.all(table["ROIs/s, store"] > 0)
    assert np.all(table["files"] == 1)  # 48 ROIs: one task, one file
    np.testing.assert_allclose(
        table["store / no store"], table["ROIs/s, store"] / table["ROIs/s, no store"]
    )


def test_gpu_benchmark_quick():
    # both backends on the same ROIs (JAX on the CPU here): the MLE agrees to 1e-6 and the
    # posterior means within Monte Carlo error (0.071 posterior SDs for two runs at ESS 400;
    # 64 ROIs x 6 parameters know that spread to ~4%, so 0.1 is ~7 SE above it); the stream
    # makes every posterior and reports its memory
    import gpu

    result = gpu.main(["--quick"])
    fit, posterior = result["agreement"]["fit"], result["agreement"]["posterior"]
    assert fit["converged (numpy, jax)"] == (64, 64)
    assert fit["max rel. diff estimate"] < 1e-6 and fit["max rel. diff sd_"] < 1e-4
    assert posterior["mean difference / posterior SD: SD"] < 0.1
    stream = result["stream"]
    assert stream["ROIs streamed"] == 128 == stream["posteriors made on the device"]
    assert stream["peak resident memory (MiB)"] > 0
    assert all(v > 0 for k, v in result["rates (ROIs per second)"].items() if "methods" not in k)
    # at N = 1000 every emccd-typical ROI is importance-sampled (the auto section of
    # benchmarks/README.md: no Laplace in 400), and at ESS 400 each scores >= 400 draws
    made = result["work per ROI"]
    assert made["from the Laplace Gaussian"] + made["from the Laplace Student-t"] == 64
    assert made["draws scored per ROI (mean)"] >= 400
    # the device's time by program: each program the run used, within the whole call's time
    programs = {k: v for k, v in made.items() if "programs waited for" in k}
    whole = programs.pop("sample_many auto jax, the whole call (µs per ROI, programs waited for)")
    names = [k.split("device program ")[1].split(" (")[0] for k in programs]
    assert {"fit", "pilot", "gaussian", "pearson"} <= set(names)
    # the programs run inside the whole call, so their times are parts of its time
    assert all(v > 0 for v in programs.values()) and sum(programs.values()) < whole
    # the Gaussian round in parts, each compiled alone and timed (no speed is asserted here),
    # with XLA's count of its work: the draws scored do more arithmetic and move more bytes
    # than the draws alone, and the whole program at least its scoring's arithmetic (not
    # asserted of its bytes: fusing more of a program can move fewer)
    parts = {
        k.split(": ")[1].split(" (")[0]: v
        for k, v in made.items()
        if "round of" in k and "(µs per ROI" in k
    }
    assert set(parts) == {
        "draws", "draws and the spot's factors", "draws scored",
        "weights smoothed, resampled, summarised", "the whole program",
    }  # fmt: skip
    assert all(v > 0 for v in parts.values())
    counted = {
        k.split(": ")[1].split(" (")[0]: [float(x) for x in re.findall(r"([0-9.e+-]+) M", v)]
        for k, v in made.items()
        if "(XLA's cost model" in k
    }
    assert set(counted) == set(parts)
    assert all(len(v) == 2 and np.all(np.isfinite(v)) for v in counted.values())
    assert np.all(np.greater(counted["draws scored"], counted["draws"]))
    assert counted["the whole program"][0] >= counted["draws scored"][0]


def test_movie_benchmark_quick():
    # a small movie (100 frames of 128 x 128) read and projected: every step timed and its
    # memory measured (the bound on memory is tested in tests/movie/test_movie_read.py)
    import movie as movie_benchmark

    table, info = movie_benchmark.main(["--quick"])
    assert list(table["step"]) == [
        "read_movie (open, check every page)",
        "read every frame (blocks of 64)",
        "project mean",
        "project median",
        "detect_movie (mean projection, then detection)",
    ]
    assert info["accepted candidates"] == info["spots"] == 9  # bright, well-separated spots
    assert np.all(table["seconds"] > 0) and np.all(table["frames"] == 100)
    assert np.all(table["tracemalloc peak (MB)"] > 0)
    assert info["peak RSS after (MB)"] >= info["peak RSS before reading (MB)"]


def test_auto_choice_benchmark_quick():
    # dim ROIs never pass the Laplace pilot (weight SD ~0.15 at N = 1000), bright ones mostly do
    import auto

    table = auto.main(["--quick"]).set_index("N")
    assert table.loc[1000, "laplace (share)"] == 0.0
    assert table.loc[1000, "pilot weight SD (median)"] > 0.05
    assert table.loc[20_000, "laplace (share)"] >= 0.5
    assert np.allclose(table[["laplace (share)", "importance (share)", "mcmc (share)"]].sum(1), 1)


def test_parallel_benchmark_quick():
    # one process, two workers, a Dask LocalCluster (with Dask's defaults, then with the
    # configuration docs/scale.md gives) and a small dataset: all finish, and two workers and
    # both clusters give the one process's posteriors (rows do not depend on the workers); the
    # per-frame movie and the immobile one on one process and on two workers give one table
    import parallel

    table, movie, still = parallel.main(["--quick"])
    assert movie["workers"].tolist() == [1, 2] and (movie["windows"] > 0).all()
    assert movie["same table as one process"].iloc[1] == True  # noqa: E712 (a numpy bool)
    assert still["workers"].tolist() == [1, 2] and (still["analysed frames"] > 0).all()
    assert still["same tables as one process"].iloc[1] == True  # noqa: E712 (a numpy bool)
    for run in (movie, still):
        # a share, not asserted below 1: on these few frames a pool's start can outweigh the
        # work, more so from a forkserver (the suite's process runs threads: worker_start)
        share = run["calling process CPU / one process's"]
        assert share.iloc[0] == 1.0 and np.isfinite(share.iloc[1]) and share.iloc[1] > 0.0
        bound = run["16 workers at most (Amdahl)"].iloc[1]
        assert np.isclose(bound, 1 / (share.iloc[1] + (1 - share.iloc[1]) / 16))
        assert run["workers start by"].tolist()[1] in ("fork", "forkserver")
    # the local runs first, the dataset, then the clusters (which leave threads behind)
    assert len(table) == 5 and np.all(table["ROIs/s"] > 0)
    assert table["how"].tolist()[:3] == [
        "one process",
        "local worker processes",
        "local worker processes (dataset)",
    ]
    assert table["how"].iloc[3:].str.contains("Dask").all()
    assert table["how"].str.endswith(", tuned").sum() == 1
    same = table["same posteriors as one process"]
    assert same.iloc[[1, 3, 4]].tolist() == [True, True, True]
    # the calling process's CPU is measured on every row (16 ROIs: a pool's start dominates it)
    cpu = table["calling process CPU per ROI (µs)"]
    assert np.all(np.isfinite(cpu) & (cpu > 0)), cpu
    # a list of workers: one row per local run and per Dask run, the dataset on the most
    flags = ["--quick", "--workers", "3,1", "--no-dask", "--dataset", "0", "--frames", "0"]
    table, movie, still = parallel.main([*flags, "--immobile", "0"])
    assert movie is None and still is None
    assert table["workers"].tolist() == [1, 3]
    assert table["same posteriors as one process"].iloc[1:].tolist() == [True]
    # no ROIs, or a negative dataset, is refused by name before any run
    for flags in (["--rois", "0"], ["--dataset", "-5"], ["--frames", "-1"], ["--immobile", "-1"]):
        with pytest.raises(SystemExit):
            parallel.main(flags)


def test_first_use_benchmark_quick():
    # a first use with an empty cache builds the tables (the cache holds them after it, and the
    # process's peak is above its imports') and a warm run reads them; the bound on the first
    # use's memory is tested in tests/cameras/test_first_use.py
    import first_use

    table = first_use.main(["--quick"]).set_index("process")
    first, warm = table.loc["first use (empty cache)"], table.loc["warm (cache filled)"]
    assert first["cache before (MB)"] == 0 and first["cache after (MB)"] > 30
    assert warm["cache before (MB)"] == first["cache after (MB)"] == warm["cache after (MB)"]
    assert np.all(table[["imports (s)", "likelihood table (s)", "Fisher spline (s)"]] > 0)
    assert np.all(table["peak (MiB)"] > table["peak after imports (MiB)"])
