"""Detection's false candidates per image on frames of pure EMCCD noise: does the stated rate
(``false_positives`` per image) hold on large single frames at low background?

Frames of pure background are drawn from the EMCCD law of the shipped ``emccd-typical`` camera
(readout 50 e-, 12 e- per ADU, offset 100 ADU, whole 16-bit ADU) at EM gains 100 and 300 and
backgrounds of 1, 3 and 10 photons per pixel, and each is detected as a one-frame movie, as
``bayespsf detect`` does (``detect_movie`` with the camera: the threshold from the camera law's
own tail at each pixel's background), with the default ``false_positives=0.01`` per image and
with 1 per image (where a count over 20 images can confirm the rate, not only bound it). The
table gives the candidates (any status) and the accepted ones per image, with their Poisson
standard errors.

    python validation/detection_false_positives.py          # 20 images of 1024 x 1024 a case
    python validation/detection_false_positives.py --quick  # 4 of 256 x 256, gain 100, b = 3
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, saved_figure, study

from bayespsf.cameras import EMCCD
from bayespsf.movie import detect_movie, read_movie


def rates(size: int, images: int, gain: float, b: float, false_positives: float, seed: int):
    """Candidates and accepted candidates per image on ``images`` noise frames."""
    camera = EMCCD(gain, 50.0, 100.0, 12.0)
    rng = np.random.default_rng([seed, int(gain), int(10 * b)])
    found = accepted = 0
    for _ in range(images):
        frame = np.round(camera.sample(np.full((1, size, size), b), rng))
        with tempfile.TemporaryDirectory() as folder:
            np.save(Path(folder) / "m.npy", frame.astype(np.uint16))
            table = detect_movie(
                read_movie(Path(folder) / "m.npy"),
                psf_sd=130.0,
                pixel_size=100.0,
                camera=camera,
                false_positives=false_positives,
            )
        found += len(table)
        accepted += int((table["status"] == "accepted").sum())
    return {
        "stated per image": false_positives,
        "EM gain": gain,
        "b (photons/pixel)": b,
        "images": images,
        "candidates per image": found / images,
        "SE": np.sqrt(found) / images,
        "accepted per image": accepted / images,
        "SE (accepted)": np.sqrt(accepted) / images,
    }


def figure(table: pd.DataFrame, path: Path) -> None:
    """Candidates per image over the stated rate, per case, with 2 SE bars."""
    with saved_figure(path, (6, 3)) as ax:
        labels = [
            f"{r['stated per image']:g}/image, G {r['EM gain']:g}, b {r['b (photons/pixel)']:g}"
            for _, r in table.iterrows()
        ]
        ratio = table["candidates per image"] / table["stated per image"]
        error = 2 * table["SE"] / table["stated per image"]
        ax.errorbar(range(len(table)), ratio, yerr=error, fmt="o")
        ax.axhline(1.0, color="grey", lw=1, label="stated rate")
        ax.set_xticks(range(len(table)), labels, rotation=60, ha="right", fontsize=6)
        ax.set_ylabel("false candidates / stated")
        ax.legend(fontsize=7)


def main(argv=None):
    args, started, stem = study(__doc__, argv, "detection_false_positives", posteriors=False)
    if args.quick:
        size, images, cases = 256, 4, [(0.01, 100.0, 3.0)]
    else:
        size, images = 1024, 20
        cases = [(fp, g, b) for fp in (0.01, 1.0) for g in (100.0, 300.0) for b in (1.0, 3.0, 10.0)]
    table = pd.DataFrame([rates(size, images, g, b, fp, seed=0) for fp, g, b in cases])
    figure(table, args.out / f"{stem}.png")
    text = (
        f"### False candidates per image on pure EMCCD noise ({size} x {size})\n\n"
        + table.to_markdown(index=False, floatfmt=".3g")
    )
    summary = (
        f"{images} frames of {size} x {size} pure EMCCD noise per case: candidates per image "
        "against the stated rate (the threshold from the camera law's tail).\n\n"
        + table.to_markdown(index=False, floatfmt=".3g")
        + f"\n\n![false candidates over the stated rate](results/{stem}.png)"
    )
    return finish(args, "detection_false_positives", table, text, started, summary)


if __name__ == "__main__":
    main()
