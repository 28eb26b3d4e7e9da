"""The goodness-of-fit flag against N: how often it fires where the model holds, and where not.

``bayespsf.inference.gof.bootstrap_check`` (the MLE's negative log-likelihood against
19 refitted parametric-bootstrap replicates; a ROI is flagged at ``p <= 0.1``) on ROIs of the
``emccd-typical`` scene (15 x 15 pixels of 100 nm, s0 = 130 nm, a Poisson background of 10
photons, EMCCD gain 200), analysed with that scene's Gaussian model, at N = 300, 1 000, 3 000
and 10 000 photons:

- ``right``: the model's own scene. With 19 replicates (stopped once 10 are as discrepant)
  ``P(p <= 0.1) = 0.1`` exactly, the flag of at most one of 19 as discrepant (the
  false-alarm rate, within its binomial SE), and the mean of p is 0.527 (the sequential
  p-value's, ``bayespsf.inference.gof``);
- ``two molecules``: two spots of N photons each, 400 nm apart (the case that motivates the check:
  the posterior alone reports one converged wide spot);
- ``Airy``: the in-focus Airy disk of 620 nm light at NA 1.0 (its best-fitting Gaussian SD is
  130 nm, the scene's s0), fitted with the Gaussian;
- ``saturated``: an ADC that saturates at 1 500 ADU, undeclared to the model (a 1 000-photon
  spot peaks near 1 700 ADU);
- ``hot pixel``: 100 photoelectrons' worth of ADU added to pixel (1, 1), next to the corner;
- ``right, background 2.75``: the model's own scene with a Poisson background of 2.75
  photons per pixel (the ``paper-movie`` scene's mean), where the first discrepancy's plug-in
  p-value is conservative;
- ``paper-movie as declared``: single ROIs of the ``paper-movie`` scene (79 nm pixels, the
  paper's camera), whose background is a truncated Gaussian (mean 2.75, SD 0.92 photons:
  quieter than the Poisson background of the model made from that scene).

Each case is checked with both of ``bootstrap_check``'s discrepancies, on the same ROIs and
replicates: the MLE's negative log-likelihood (the default) and Pearson's statistic.

    python validation/model_check.py            # 200 ROIs per case and N (24 s on 2 cores)
    python validation/model_check.py --quick    # 20 ROIs per case at N = 1000 and 10 000
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import load_scene, simulate
from bayespsf.inference import bootstrap_check, fit_mle
from bayespsf.inference.gof import DISCREPANCIES
from bayespsf.model import Model

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, saved_figure, study

PHOTONS = (300.0, 1000.0, 3000.0, 10000.0)
QUICK_PHOTONS = (1000.0, 10000.0)
CASES = (
    "right",
    "two molecules",
    "Airy",
    "saturated",
    "hot pixel",
    "right, background 2.75",
    "paper-movie as declared",
)
LOW_BACKGROUND = 2.75  # photons per pixel
REPLICATES = 19
ALPHA = 0.1
SATURATION = 1500.0  # ADU
HOT = 100.0  # photoelectrons


def scene_at(photons: float, case: str):
    if case == "paper-movie as declared":
        base = load_scene("paper-movie")
        return base.replace(emitter={**base.emitter, "photons": photons, "photon_jitter": 0.0})
    scene = load_scene("emccd-typical").replace(emitter={"photons": photons})
    if case == "saturated":
        return scene.replace(camera={"saturation": SATURATION})
    if case == "right, background 2.75":
        return scene.replace(background={"kind": "poisson", "mean": LOW_BACKGROUND})
    if case == "Airy":
        table = scene.to_dict()
        table["optics"] = {"psf": "airy", "wavelength": 620.0, "na": 1.0}
        for key in ("s0x", "s0y"):
            table["emitter"].pop(key)
        return type(scene).from_dict(table)
    return scene


def rois(case: str, photons: float, n: int, seed: int, model: Model) -> np.ndarray:
    if case == "two molecules":
        rng = np.random.default_rng(seed)
        one = np.array([-200.0, 0.0, 130.0, 130.0, photons, 10.0])
        two = one.copy()
        two[0], two[5] = 200.0, 0.0
        lam = model.expected(one) + model.expected(two) - model.clock_induced_charge
        return model.camera.sample(np.broadcast_to(lam, (n, *lam.shape)), rng)
    counts, _ = simulate(scene_at(photons, case), n, seed=seed)
    if case == "hot pixel":
        per_adu, _ = model.camera.photons_per_adu()
        counts = counts.copy()
        counts[:, 1, 1] += HOT / per_adu
    return counts


def main(argv=None):
    args, started, stem = study(__doc__, argv, "model_check", posteriors=False)
    n = 20 if args.quick else 200
    emccd_typical = Model.from_scene(scene_at(1000.0, "right"))  # saturation undeclared
    rows = []
    for i, case in enumerate(CASES):
        model = emccd_typical
        if case == "paper-movie as declared":
            model = Model.from_scene(scene_at(1000.0, case))
        for j, photons in enumerate(QUICK_PHOTONS if args.quick else PHOTONS):
            counts = rois(case, photons, n, seed=100 * i + j, model=model)
            fits = fit_mle(counts, model, laplace=False, crlb=False)
            for discrepancy in DISCREPANCIES:
                check = bootstrap_check(
                    counts,
                    model,
                    replicates=REPLICATES,
                    seed=i * 10 + j,
                    fits=fits,
                    discrepancy=discrepancy,
                )
                p = check["gof_p"]
                tested = int(p.notna().sum())
                rows.append(
                    {
                        "case": case,
                        "N": photons,
                        "discrepancy": discrepancy,
                        "ROIs": n,
                        "tested": tested,
                        "flagged": float((p <= ALPHA).sum() / max(tested, 1)),
                        "binomial SE at 0.1": float(np.sqrt(ALPHA * (1 - ALPHA) / max(tested, 1))),
                        "mean p": float(p.mean()),
                    }
                )
    table = pd.DataFrame(rows)
    figure(table, args.out / f"{stem}.png")
    fmt = {"index": False, "floatfmt": ".4g"}
    text = (
        "# The goodness-of-fit flag against N (p <= 0.1, 19 replicates)\n\n"
        f"{table.to_markdown(**fmt)}\n\nFigure: [{stem}.png]({stem}.png)."
    )
    summary = f"{table.to_markdown(**fmt)}\n\n![flag rate against N](results/{stem}.png)"
    return finish(args, "model_check", table, text, started, summary)


def figure(table: pd.DataFrame, path: Path) -> None:
    """The share flagged against N per case: one panel per discrepancy."""
    with saved_figure(path, (11, 3.4), columns=len(DISCREPANCIES)) as axes:
        for ax, discrepancy in zip(axes, DISCREPANCIES, strict=True):
            part = table[table["discrepancy"] == discrepancy]
            for case, rows in part.groupby("case", sort=False):
                ax.plot(rows["N"], rows["flagged"], "o-", label=case)
            se = part["binomial SE at 0.1"].max()  # of the null rate, where the model holds
            ax.axhspan(
                ALPHA - 2 * se, ALPHA + 2 * se, color="grey", alpha=0.3, label="nominal 0.1 +- 2 SE"
            )
            ax.set_xscale("log")
            ax.set_xlabel("N (photons)")
            ax.set_ylabel("share flagged at p <= 0.1")
            ax.set_title(f"discrepancy: {discrepancy}", fontsize=9)
        axes[0].legend(fontsize=7)


if __name__ == "__main__":
    main()
