"""Theory against the paper's least-squares Monte Carlo across N, on the Fig. 3 scene.

For N in {100, 200, 500, 1000, 2000, 5000} photons on the shipped `paper-fig3` scene (19x19
pixels of 79 nm, s0 = 120 nm, background sigma_b = 1 and <b> = 4 photons, the paper's camera):
Eq. sigma2dp3, the Eq. pesum pixel sum, the Cramér–Rao bound of s_x (all six parameters free,
and s_x alone), and the spread of the paper's least-squares fit over simulated images with its
Monte Carlo standard error; ratios to Eq. sigma2dp3 beside the paper's "pixel sum ~15% above the
closed form" and "simulation ~57% above".

    python validation/fig3_theory_table.py [--quick]
"""

from __future__ import annotations

import sys
import time

import numpy as np
import pandas as pd

from bayespsf import scenes, simulate, theory
from bayespsf.estimators import fit_lsq
from bayespsf.model import Model

sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from _common import parser, write

PHOTONS = (100, 200, 500, 1000, 2000, 5000)


def run(images: int, photons=PHOTONS) -> pd.DataFrame:
    base = scenes.load("paper-fig3")
    g, e, bg = base.geometry, base.emitter, base.background
    rows = []
    for k, n_photons in enumerate(photons):
        scene = base.replace(emitter={"photons": float(n_photons)})
        model = Model.from_scene(scene)
        args = (n_photons, e["s0x"], e["s0y"], g["pixel_size"], bg["sd"], bg["mean"])
        closed = float(theory.delta_s_analytic(*args))
        pixel_sum = float(theory.delta_s_numeric(*args, roi=g["roi"]))
        bound = theory.crlb(scene)["s_x"]
        alone = theory.crlb(scene, free="s_x")["s_x"]
        counts, _ = simulate(scene, images, seed=1000 + k)
        fits = fit_lsq(counts, model)
        s_x = fits.loc[fits["converged"], "s_x"].to_numpy()
        sd = s_x.std(ddof=1)
        rows.append(
            {
                "N": n_photons,
                "Eq. sigma2dp3": closed,
                "pixel sum (Eq. pesum)": pixel_sum,
                "CRLB s_x (all free)": bound,
                "CRLB s_x (alone)": alone,
                "LSQ SD of s_x": sd,
                "LSQ SD MC error": sd / np.sqrt(2 * (len(s_x) - 1)),
                "LSQ failures": int((~fits["converged"]).sum()),
                "pixel sum / closed": pixel_sum / closed,
                "CRLB / closed": bound / closed,
                "LSQ / closed": sd / closed,
            }
        )
    return pd.DataFrame(rows)


def main(argv=None):
    args = parser(__doc__).parse_args(argv)
    started = time.perf_counter()
    images = 100 if args.quick else 2000
    table = run(images, PHOTONS[:2] if args.quick else PHOTONS)
    text = (
        f"# Fig. 3 scene: width precision across N ({images} images per N)\n\n"
        + table.to_markdown(index=False, floatfmt=".3g")
        + "\n\nThe paper (DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010)): the pixel sum is "
        "~15% above Eq. sigma2dp3, simulations ~57% above. The CRLB assumes the model's Poisson "
        "background (variance 4), while the scene's background is the paper's truncated "
        "Gaussian (variance ~1), which the least-squares simulation uses."
    )
    command = "python validation/fig3_theory_table.py" + (" --quick" if args.quick else "")
    write(args.out, "fig3_theory" + ("_quick" if args.quick else ""), table, text, command, started)
    print(text)
    return table


if __name__ == "__main__":
    main()
