"""Per-molecule analysis against the truth: per-frame and joint posteriors, and the check
without ground truth when the model is right and when it is not.

Part 1, movies. Simulated ``paper-movie`` movies (300 frames, 40 molecules of 500-5000
photons per frame, s0 = 120 nm; with a Poisson background of 2.75 photons per pixel, the
model's own law, in place of the scene's sub-Poisson truncated Gaussian) go through the movie
path as ``bayespsf analyze`` takes them (``find_molecules`` with the scene's own camera, the
central 15 x 15 ROI of every valid frame), then:

- the joint posterior of every selected molecule over its valid frames
  (``bayespsf.inference.joint``, ``JOINT_ESS`` draws each): the 68% and 95% coverage of the
  true x0 and s_x, the SD of the z-scores, and its SD against one frame's (expected
  ~1/sqrt(K): ``sd x sqrt(K) / frame sd``, near 1, with the frame's Laplace SD);
- per-frame posteriors (``sample_many``, method ``auto``) of up to ``FRAMES_PER_MOLECULE``
  frames per selected molecule of the first movie: the 68% and 95% coverage of x0 and s_x.

A selected molecule is scored against the truth it matches (``match_truth``); a moving or
two-fluorophore molecule that passed the rules is counted and left out (its truth is not one
position and width).

Part 2, the check without ground truth (``bayespsf.analysis.consistency``) and the
bootstrap goodness-of-fit test (``bayespsf.inference.gof``, ``gof_p <= 0.1``) on stacks
of immobile molecules shaped like the movie's (79 nm pixels, 1 600 photons +-20% per frame, the
same Poisson background), each molecule at one fixed position in all its frames:

- ``right``: simulated and analysed with the same Gaussian PSF and camera;
- ``gain +20%``: simulated with EM gain 200, analysed as if it were 240;
- ``gain -20%``: analysed as if it were 160;
- ``Airy``: simulated with the in-focus Airy disk of 570 nm light at NA 1.0 (best-fitting
  Gaussian SD 120 nm), analysed with the Gaussian.

A right model gives z-score SDs of 1 within their SE and a flag rate of 0.1 within its binomial
SE; the check should fail clearly for the other three.

    python validation/movie_analysis.py            # 30 movies, 4 x 1 200 ROIs (~15 min on 2 cores)
    python validation/movie_analysis.py --quick    # 1 small movie and 4 x 30 ROIs
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import load_scene, simulate
from bayespsf.analysis import frame_consistency
from bayespsf.analysis.pipeline import valid_rois
from bayespsf.inference import bootstrap_check, fit_mle
from bayespsf.inference.gof import flag_excess_p
from bayespsf.inference.summary import quantile_column
from bayespsf.model import Model
from bayespsf.movie import Rules, find_molecules
from bayespsf.parallel import joint_posteriors, sample_many
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.simulation import match_truth, simulate_movie

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, saved_figure, study

FIT = 15
FRAMES_PER_MOLECULE = 40
JOINT_ESS = 400  # draws kept per joint posterior (analyze's default): with 200, the 68%
# interval's quantiles moved 0.04 of the coverage away from the mean +- SD band
SCORED = ("x0", "s_x")
# the model's own background law: paper-movie's truncated Gaussian is sub-Poisson, which makes
# every posterior conservative (docs/cli.md measures it), so "right" would not be right
POISSON_BACKGROUND = {"kind": "poisson", "mean": 2.75}


def _truths(found, place, made, a: float) -> pd.DataFrame:
    """Per selected molecule: the ROI-centred truth of x0, y0 (nm), s_x, s_y, and whether it is
    one immobile fluorophore."""
    chosen = found.molecules[found.molecules["selected"].astype(bool)].reset_index(drop=True)
    row = match_truth(chosen, made.molecules)
    centre = place.groupby("molecule")[["row", "col"]].first()
    out = []
    for k, molecule in enumerate(chosen["molecule"]):
        t = made.molecules.iloc[row[k]] if row[k] >= 0 else None
        r, c = centre.loc[molecule]
        out.append(
            {
                "molecule": molecule,
                "x0": np.nan if t is None else (t["x"] - c) * a,
                "y0": np.nan if t is None else (t["y"] - r) * a,
                "s_x": np.nan if t is None else t["s_x"],
                "s_y": np.nan if t is None else t["s_y"],
                "clean": t is not None and not bool(t["moving"]) and int(t["fluorophores"]) == 1,
            }
        )
    return pd.DataFrame(out).set_index("molecule")


def one_movie(scene, seed: int, per_frame: bool, workers: int, rules) -> tuple[pd.DataFrame, ...]:
    with tempfile.TemporaryDirectory() as folder:
        made = simulate_movie(scene, seed=seed, out=Path(folder) / "movie")
        model = Model.from_scene(scene)
        found = find_molecules(made.files["movie"], model, s0=120.0, rules=rules)
        if not found.molecules["selected"].any():
            return None, None
        counts, place = valid_rois(made.files["movie"], found, FIT)
    fitting = model.for_roi(FIT)
    truth = _truths(found, place, made, fitting.pixel_size)
    mle = fit_mle(counts, fitting)
    frames = place.copy()
    for p in PARAMETER_NAMES:  # the frame's MLE, and its Laplace SD as the frame's SD
        frames[f"{p}_mle"], frames[f"{p}_sd"] = mle[p].to_numpy(), mle[f"sd_{p}"].to_numpy()
    frames["mle_converged"] = mle["converged"].to_numpy(bool)
    joint = joint_posteriors(counts, frames, fitting, seed=seed, ess=JOINT_ESS, workers=workers)
    joint = joint.join(truth, on="molecule")
    joint["movie"] = seed
    if not per_frame:
        return joint, None
    first = place.groupby("molecule").cumcount() < FRAMES_PER_MOLECULE
    rows = sample_many(counts[first.to_numpy()], fitting, seed=seed, workers=workers)
    rows["molecule"] = place.loc[first, "molecule"].to_numpy()
    rows = rows.join(truth.add_suffix("_truth"), on="molecule")
    rows["movie"] = seed
    return joint, rows


def part_movies(scene, movies: int, per_frame_movies: int, workers: int, rules=None):
    joints, frames = [], []
    for seed in range(movies):
        joint, rows = one_movie(scene, seed, seed < per_frame_movies, workers, rules)
        if joint is None:  # nothing selected in this movie
            continue
        joints.append(joint)
        if rows is not None:
            frames.append(rows)
    joint = pd.concat(joints, ignore_index=True)
    sampled = joint["joint_method"].isin(["importance", "laplace"])
    scored = joint[sampled & joint["clean"].astype(bool)]
    rows = []
    for p in SCORED:
        t = scored[p]
        z = (scored[f"{p}_joint_mean"] - t) / scored[f"{p}_joint_sd"]
        in68 = ((scored[f"{p}_joint_q16"] <= t) & (t <= scored[f"{p}_joint_q84"])).mean()
        in95 = ((scored[f"{p}_joint_q2.5"] <= t) & (t <= scored[f"{p}_joint_q97.5"])).mean()
        n = len(scored)
        rows.append(
            {
                "posterior": "joint over frames",
                "parameter": p,
                "molecules or frames": n,
                "coverage 68%": in68,
                "SE 68%": np.sqrt(0.68 * 0.32 / n),
                "coverage 95%": in95,
                "SE 95%": np.sqrt(0.95 * 0.05 / n),
                "z-score SD": float(z.std(ddof=1)),
                "z-score mean": float(z.mean()),
                "joint MLE z-score mean": float(
                    ((scored[f"{p}_joint_mle"] - t) / scored[f"{p}_joint_sd"]).mean()
                ),
                "sd x sqrt(K) / frame sd": float(
                    np.median(
                        scored[f"{p}_joint_sd"]
                        * np.sqrt(scored["joint_frames"])
                        / scored[f"{p}_frame_sd"]
                    )
                ),
            }
        )
    facts = {
        "movies": movies,
        "molecules selected": len(joint),
        "left out (moving, two fluorophores or unmatched)": int((~joint["clean"]).sum()),
        "joint by importance sampling": int((joint["joint_method"] == "importance").sum()),
        "joint k-hat, largest": float(joint["joint_khat"].max()),
        "joint frames, median": float(joint["joint_frames"].median()),
    }
    if frames:
        per = pd.concat(frames, ignore_index=True)
        per = per[per["clean_truth"].astype(bool) & per["converged"].astype(bool)]
        for p in SCORED:
            t = per[f"{p}_truth"]
            n = len(per)
            in68 = (per[quantile_column(p, 0.16)] <= t) & (t <= per[quantile_column(p, 0.84)])
            in95 = (per[quantile_column(p, 0.025)] <= t) & (t <= per[quantile_column(p, 0.975)])
            z = (per[f"{p}_mean"] - t) / per[f"{p}_sd"]
            rows.append(
                {
                    "posterior": "per frame",
                    "parameter": p,
                    "molecules or frames": n,
                    "coverage 68%": float(in68.mean()),
                    "SE 68%": np.sqrt(0.68 * 0.32 / n),
                    "coverage 95%": float(in95.mean()),
                    "SE 95%": np.sqrt(0.95 * 0.05 / n),
                    "z-score SD": float(z.std(ddof=1)),
                    "z-score mean": float(z.mean()),
                }
            )
    return pd.DataFrame(rows), facts


def stack_scene(airy: bool):
    """ROIs shaped like the movie's molecules, at one fixed position per molecule."""
    scene = load_scene("paper-movie")
    table = scene.to_dict()
    table.pop("movie", None)
    table["emitter"].update(position="fixed")
    table["background"] = POISSON_BACKGROUND
    if airy:
        table["optics"] = {"psf": "airy", "wavelength": 570.0, "na": 1.0}
        for key in ("s0x", "s0y"):
            table["emitter"].pop(key, None)
    return type(scene).from_dict(table)


def one_case(name: str, molecules: int, frames: int, workers: int) -> dict:
    truth_scene = stack_scene(airy=name == "Airy")
    gain = {"gain +20%": 240.0, "gain -20%": 160.0}.get(name, 200.0)
    model = Model.from_scene(stack_scene(airy=False).replace(camera={"gain": gain}))
    rng = np.random.default_rng(7)
    stacks, labels = [], []
    for m in range(molecules):
        x0, y0 = rng.uniform(-39.5, 39.5, 2)  # within the central pixel, fixed over frames
        scene = truth_scene.replace(emitter={"x0": float(x0), "y0": float(y0)})
        counts, _ = simulate(scene, frames, seed=1000 + m)
        stacks.append(counts)
        labels += [m] * frames
    counts = np.concatenate(stacks)
    rows = sample_many(counts, model, seed=11, workers=workers)
    rows["molecule"] = labels
    _, _, overall = frame_consistency(rows)
    check = bootstrap_check(counts, model, seed=12)
    flagged = (check["gof_p"] <= 0.1).mean()
    n = check["gof_p"].notna().sum()
    out = {"case": name, "molecules": molecules, "frames": len(counts)}
    for p in ("x0", "s_x", "s_y"):
        row = overall.set_index("parameter").loc[p]
        out[f"{p} z-score SD"] = float(row["z_sd"])
        out[f"{p} SE"] = float(row["z_sd_se"])
        out[f"{p} chi2 p"] = float(row["p_value"])
        out[f"{p} two-sided p"] = float(row["p_two_sided"])
    out["GOF flagged at 0.1"] = float(flagged)
    out["GOF SE"] = float(np.sqrt(0.09 / max(n, 1)))
    out["GOF flags p"] = flag_excess_p(check["gof_p"], 0.1)
    return out


def main(argv=None):
    args, started, stem = study(__doc__, argv, "movie_analysis", posteriors=False)
    scene = load_scene("paper-movie").replace(movie={"dark_frames": 0})
    table = scene.to_dict()
    table["background"] = POISSON_BACKGROUND
    scene = type(scene).from_dict(table)
    workers = 2
    if args.quick:
        scene = scene.replace(
            movie={
                "frames": 80,
                "height": 128,
                "width": 128,
                "molecules": 9,
                "bleach_mean": 80.0,
                "two_fluorophores": 0.0,
                "moving": 0.0,
            }
        )
        movies, per_frame, molecules, frames = 1, 1, 2, 15
    else:
        movies, per_frame, molecules, frames = 30, 1, 40, 30
    rules = Rules(min_valid_frames=25) if args.quick else None  # the quick movie is short
    coverage, facts = part_movies(scene, movies, per_frame, workers, rules)
    cases = pd.DataFrame(
        [
            one_case(name, molecules, frames, workers)
            for name in ("right", "gain +20%", "gain -20%", "Airy")
        ]
    )
    fmt = {"index": False, "floatfmt": ".4g"}
    facts_table = pd.DataFrame([facts])
    text = (
        "# Per-molecule analysis against the truth\n\n## Coverage on simulated paper-movies\n\n"
        f"{facts_table.to_markdown(**fmt)}\n\n{coverage.to_markdown(**fmt)}\n\n"
        "## The check without ground truth, right and wrong models\n\n"
        f"{cases.to_markdown(**fmt)}\n\nFigure: [{stem}.png]({stem}.png)."
    )
    summary = f"{facts_table.to_markdown(**fmt)}\n\n{coverage.to_markdown(**fmt)}\n\n" + (
        f"{cases.to_markdown(**fmt)}\n\n![z-score SDs and flag rates](results/{stem}.png)"
    )
    table = pd.concat([coverage, cases], ignore_index=True)
    figure(coverage, cases, args.out / f"{stem}.png")
    return finish(args, "movie_analysis", table, text, started, summary)


def figure(coverage: pd.DataFrame, cases: pd.DataFrame, path: Path) -> None:
    """Left: coverage of the truth by the 68% and 95% intervals, per posterior and parameter.
    Right: the check's z-score SDs and the goodness-of-fit flag rate, per case."""
    with saved_figure(path, (9, 3.2), columns=2) as (left, right):
        _coverage_panel(left, coverage)
        _check_panel(right, cases)


def _coverage_panel(left, coverage: pd.DataFrame) -> None:
    labels = [f"{r.posterior}\n{r.parameter}" for r in coverage.itertuples()]
    k = np.arange(len(coverage))
    for shift, level, column, marker in (
        (-0.1, 0.68, "coverage 68%", "o"),
        (0.1, 0.95, "coverage 95%", "s"),
    ):
        se = coverage[f"SE {column.split()[-1]}"]
        left.errorbar(k + shift, coverage[column], yerr=2 * se, fmt=marker, label=column)
        left.axhline(level, lw=0.8, ls="--", color="grey")
    left.set_xticks(k, labels, fontsize=6)
    left.set_ylabel("coverage of the truth (+-2 SE)")
    left.legend(fontsize=7)


def _check_panel(right, cases: pd.DataFrame) -> None:
    k = np.arange(len(cases))
    for shift, p in zip((-0.2, 0.0, 0.2), ("x0", "s_x", "s_y"), strict=True):
        right.errorbar(
            k + shift,
            cases[f"{p} z-score SD"],
            yerr=2 * cases[f"{p} SE"],
            fmt="o",
            label=f"{p} z-score SD",
        )
    right.plot(k, cases["GOF flagged at 0.1"] * 10, "kx", label="GOF flag rate x 10")
    right.axhline(1.0, lw=0.8, ls="--", color="grey")
    right.set_xticks(k, cases["case"], fontsize=7)
    right.set_ylabel("z-score SD (+-2 SE); flag rate x 10")
    right.legend(fontsize=6)


if __name__ == "__main__":
    main()
