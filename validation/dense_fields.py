"""Dense fields: what the neighbour rule keeps, and what a kept molecule's fit pays for it.

Single frames of immobile molecules at densities from 0.05 to 2 per µm²: positions uniform
over the field, N log-uniform in 500-5000 photons, the pixel-integrated Gaussian of s0 = 120 nm
on 79 nm pixels (the paper's spot), 10 photons per pixel of background, Poisson counts (an
ideal camera, counts in photons). Each frame is detected twice with ``bayespsf.movie.detect``
(noise and background estimated from the frame, 0.01 false candidates per frame, the
geometry from s0: 25 x 25 cuts, 15 x 15 fitted windows):

* old rule: ``min_distance=roi`` (25): both candidates of any pair closer than the cut in rows
  or in columns are rejected (the paper's isolated molecules);
* light rule (the default): a candidate is rejected where another candidate puts more than one
  SD of the window's summed noise into its fitted window, or where masking the neighbours'
  light out of its periphery leaves fewer pixels than the photon aperture
  (``bayespsf.movie.geometry``).

Kept share: the molecules whose cut lies inside the frame and that an accepted candidate finds
(within 1 pixel), over the molecules whose cut lies inside the frame. The price: every
molecule the light rule keeps is fitted by maximum likelihood (``bayespsf.fit_mle``, Poisson
law) on its 15 x 15 window as cut from the dense frame, and again on the same window drawn
with that molecule alone (same N, same sub-pixel position, fresh Poisson noise): the bias (mean
of fitted minus true, x0 and y0 pooled, s_x and s_y pooled) and SD of position and width
(converged fits), with the Monte Carlo SE of each bias (SD / sqrt(n)), for all kept molecules
in the field (``field``), for those of them not flagged ``elongated`` (``round``: two
molecules closer than about 2.5 SDs make one candidate, which no neighbour rule sees), and
alone (``alone``); and the share of ``outliers``, fits off by more than 25 nm on either axis
(about 5 SDs of a molecule alone). The same fits of the molecules the old rule keeps are
reported beside them.

    python validation/dense_fields.py          # 10 frames per density, 256 x 256 pixels
    python validation/dense_fields.py --quick  # 1 frame per density, 128 x 128
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, saved_figure, study

from bayespsf import psf
from bayespsf.cameras import Photon
from bayespsf.inference import fit_mle
from bayespsf.model import Model
from bayespsf.movie import detect, geometry_for_psf

A, S0, B = 79.0, 120.0, 10.0  # pixel size (nm), spot SD (nm), background (photons per pixel)
N_RANGE = (500.0, 5000.0)  # photons, log-uniform
DENSITIES = (0.05, 0.1, 0.2, 0.5, 1.0, 2.0)  # molecules per µm²
ROI, FIT = geometry_for_psf(S0, A)  # 25, 15
SPAN = 21  # pixels drawn per spot: 6.6 SDs each side (light beyond: < 1e-10)
MATCH = 1.0  # pixels: a candidate this close finds a molecule
WHERE = ("field", "round", "alone")  # all kept in the field, those not elongated, alone
OUTLIER = {"position": 25.0, "width": 25.0}  # nm: about 5 SDs of a molecule alone (4-5 nm)


def field(size: int, density: float, rng: np.random.Generator):
    """(expected photons, truth): molecules uniform over the field and 10 pixels beyond."""
    pad = SPAN // 2
    side = size + 2 * pad
    area = (side * A / 1000.0) ** 2  # µm²
    n = rng.poisson(density * area)
    truth = pd.DataFrame(
        {
            "x": rng.uniform(-pad - 0.5, size + pad - 0.5, n),
            "y": rng.uniform(-pad - 0.5, size + pad - 0.5, n),
            "N": np.exp(rng.uniform(*np.log(N_RANGE), n)),
        }
    )
    canvas = np.full((side + 2 * pad, side + 2 * pad), B)
    for x, y, photons in truth[["x", "y", "N"]].to_numpy():
        c, r = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        spot = psf.expected_counts([(x - c) * A, (y - r) * A, S0, S0, photons, 0.0], SPAN, A)
        canvas[r + pad : r + pad + SPAN, c + pad : c + pad + SPAN] += spot
    return canvas[2 * pad : 2 * pad + size, 2 * pad : 2 * pad + size], truth


def found(table: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """The accepted candidates matched to a molecule (the nearest within ``MATCH``), with the
    molecule's truth beside them; each molecule at most once."""
    accepted = table[table["status"] == "accepted"].reset_index(drop=True)
    if accepted.empty or truth.empty:
        return accepted.assign(true_x=[], true_y=[], true_N=[])
    distance = np.hypot(
        accepted["x"].to_numpy()[:, None] - truth["x"].to_numpy(),
        accepted["y"].to_numpy()[:, None] - truth["y"].to_numpy(),
    )
    nearest = distance.argmin(axis=1)
    ok = distance[np.arange(len(accepted)), nearest] < MATCH
    ok &= ~pd.Series(nearest).where(ok).duplicated(keep="first").to_numpy()
    matched = accepted[ok].reset_index(drop=True)
    picked = truth.iloc[nearest[ok]].reset_index(drop=True)
    return matched.assign(true_x=picked["x"], true_y=picked["y"], true_N=picked["N"])


def fits(windows: np.ndarray, kept: pd.DataFrame) -> pd.DataFrame:
    """MLE of each window, as errors against the truth (nm): dx, dy, ds_x, ds_y."""
    model = Model(FIT, A, Photon())
    fitted = fit_mle(windows, model, laplace=False, crlb=False)
    dx = fitted["x0"].to_numpy() - (kept["true_x"] - kept["col"]).to_numpy() * A
    dy = fitted["y0"].to_numpy() - (kept["true_y"] - kept["row"]).to_numpy() * A
    return pd.DataFrame(
        {
            "dx": dx,
            "dy": dy,
            "ds_x": fitted["s_x"].to_numpy() - S0,
            "ds_y": fitted["s_y"].to_numpy() - S0,
            "converged": fitted["converged"].to_numpy(bool),
        }
    )


def windows_of(image: np.ndarray, kept: pd.DataFrame) -> np.ndarray:
    """The ``FIT`` x ``FIT`` windows centred on each kept candidate's pixel."""
    h = FIT // 2
    out = np.empty((len(kept), FIT, FIT))
    for k, (r, c) in enumerate(kept[["row", "col"]].to_numpy(int)):
        out[k] = image[r - h : r + h + 1, c - h : c + h + 1]
    return out


def alone(kept: pd.DataFrame, rng: np.random.Generator) -> np.ndarray:
    """The same windows drawn with their molecule alone (fresh Poisson noise)."""
    offsets = np.column_stack(
        [
            (kept["true_x"] - kept["col"]).to_numpy() * A,
            (kept["true_y"] - kept["row"]).to_numpy() * A,
            np.full((len(kept), 2), S0),
            kept["true_N"].to_numpy(),
            np.full(len(kept), B),
        ]
    )
    return rng.poisson(psf.expected_counts(offsets, FIT, A)).astype(np.float64)


def one_frame(size: int, density: float, seed: int):
    """One frame at ``density``: a summary row per rule and the fitted errors."""
    rng = np.random.default_rng([seed, round(density * 1000)])
    expected, truth = field(size, density, rng)
    image = rng.poisson(expected).astype(np.float64)
    h = ROI // 2
    inside = truth[
        truth["x"].between(h - 0.5, size - h - 0.5, inclusive="left")
        & truth["y"].between(h - 0.5, size - h - 0.5, inclusive="left")
    ]
    rows, errors = [], {}
    for rule, options in (("old", {"min_distance": ROI}), ("light", {})):
        table = detect(image, psf_sd=S0, pixel_size=A, roi=ROI, fit=FIT, **options)
        kept = found(table, inside)
        rows.append(
            {
                "density": density,
                "seed": seed,
                "rule": rule,
                "molecules": len(inside),
                "kept": len(kept),
                "candidates": len(table),
                "accepted": int((table["status"] == "accepted").sum()),
            }
        )
        if len(kept):
            errors[(rule, "field")] = fits(windows_of(image, kept), kept)
            errors[(rule, "round")] = errors[(rule, "field")][~kept["elongated"].to_numpy(bool)]
            errors[(rule, "alone")] = fits(alone(kept, rng), kept)
    return rows, errors


def price(errors: list[pd.DataFrame]) -> dict:
    """Bias, its SE and SD of position (x0, y0 pooled) and width (s_x, s_y pooled), nm."""
    if not errors:
        return {}
    e = pd.concat(errors, ignore_index=True)
    e = e[e["converged"]]
    out = {"fits": len(e)}
    for name, columns in (("position", ["dx", "dy"]), ("width", ["ds_x", "ds_y"])):
        values = e[columns].to_numpy()
        sd = values.std(ddof=1) if values.size > 1 else np.nan
        out[f"{name} bias"] = values.mean()
        out[f"{name} bias SE"] = sd / np.sqrt(values.size)
        out[f"{name} SD"] = sd
        out[f"{name} outliers"] = np.mean(np.abs(values).max(axis=1) > OUTLIER[name])
    return out


def summary(frames: pd.DataFrame, errors: dict) -> pd.DataFrame:
    """Per density and rule: kept share, and the fits' price in the field and alone."""
    rows = []
    for (density, rule), group in frames.groupby(["density", "rule"], sort=False):
        row = {
            "density /µm²": density,
            "rule": rule,
            "molecules": int(group["molecules"].sum()),
            "kept share": group["kept"].sum() / max(group["molecules"].sum(), 1),
        }
        for where in WHERE:
            for key, value in price(errors.get((density, rule, where), [])).items():
                row[f"{key} ({where})"] = value
        rows.append(row)
    return pd.DataFrame(rows)


def figure(table: pd.DataFrame, path: Path) -> None:
    """Kept share against density per rule; the width's bias and SD in the field and alone."""
    with saved_figure(path, (9, 3), columns=2) as (left, right):
        for rule, group in table.groupby("rule", sort=False):
            left.plot(group["density /µm²"], group["kept share"], "o-", label=f"{rule} rule")
        light = table[table["rule"] == "light"]
        for k, (where, marker) in enumerate((("field", "o"), ("round", "s"), ("alone", "x"))):
            x = light["density /µm²"] * 1.04**k  # side by side
            right.errorbar(
                x,
                light[f"width bias ({where})"],
                yerr=2 * light[f"width bias SE ({where})"],
                fmt=marker,
                color=f"C{k}",
                label=f"{where}: bias (2 SE), SD dashed",
            )
            right.plot(x, light[f"width SD ({where})"], "--", color=f"C{k}")
        for ax in (left, right):
            ax.set_xscale("log")
            ax.set_xlabel("molecules per µm²")
            ax.legend(fontsize=7)
        left.set_ylabel("share of molecules kept")
        right.set_ylabel("fitted - true width (nm)")


def main(argv=None):
    args, started, stem = study(__doc__, argv, "dense_fields", posteriors=False)
    seeds, size = (1, 128) if args.quick else (10, 256)
    densities = (0.1, 0.5, 2.0) if args.quick else DENSITIES
    rows, errors = [], {}
    for density in densities:
        for seed in range(seeds):
            frame_rows, frame_errors = one_frame(size, density, seed)
            rows += frame_rows
            for (rule, where), e in frame_errors.items():
                errors.setdefault((density, rule, where), []).append(e)
    frames = pd.DataFrame(rows)
    table = summary(frames, errors)
    table.insert(4, "kept round", table["fits (round)"] / table["molecules"])
    figure(table, args.out / f"{stem}.png")
    fmt = {"index": False, "floatfmt": ".3g"}
    title = f"{seeds} frame(s) per density, {size} x {size} pixels"
    text = (
        f"# Dense fields ({title})\n\n{table.to_markdown(**fmt)}\n\nPer frame:\n\n"
        f"{frames.to_markdown(**fmt)}\n\nFigure: [{stem}.png]({stem}.png)."
    )
    columns = ["density /µm²", "rule", "molecules", "kept share", "kept round"]
    columns += [f"width {k} ({w})" for w in WHERE for k in ("bias", "SD", "outliers")]
    columns += [f"position {k} ({w})" for w in WHERE for k in ("bias", "SD")]
    readme = (
        f"{title}: the share of molecules each rule keeps, and the bias and SD (nm) of the "
        "kept molecules' fitted width and position in the field and alone.\n\n"
        f"{table[columns].to_markdown(**fmt)}\n\n![kept share and width](results/{stem}.png)"
    )
    return finish(args, "dense_fields", table, text, started, readme)


if __name__ == "__main__":
    main()
