"""The simulator: a pipeline of exactly the effects a scene declares, run in reproducible blocks.

``simulate(scene, n, seed)`` returns ``(counts, truth)``: counts ``(n, roi, roi)`` in ADU and a
DataFrame with one row per image and the columns ``x0 y0 s_x s_y N b`` (plus
``photons_emitted`` when photons are binned one by one, and ``z`` where the scene declares
``[axial]``). ``build_pipeline(scene)`` shows the
effects and their order.

Photon paths, chosen from what the scene declares: Poisson pixel counts from the expected image
(fast); a multinomial over the pixels when each image emits exactly N photons; photon-by-photon
binning (the paper's method) when photons carry their own width (``width_jitter``).

Reproducibility: images are simulated in blocks of ``block_size`` images (a function of the
scene only); block ``k`` draws from ``Generator(PCG64(SeedSequence(seed, spawn_key=(k,))))``.
Whole blocks are always simulated, so image ``i`` depends on ``seed`` and ``i`` only: the same
seed gives the same images for any ``n`` (a shorter run is a prefix of a longer one), in chunks
of any size (``simulate_chunks``, for runs larger than memory) and on any machine. The
working memory is one block: at most 1024 images and ``2**22`` pixels (32 MB per array), so a
ROI of 401 x 401 pixels is simulated 26 images at a time, not 1024 (1.3 GB per array, and the
work of 1024 images for one). A run whose counts cannot fit in the machine's memory is refused
by name before anything is allocated (``bayespsf._runtime.refuse_beyond_memory``).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

import numpy as np
import pandas as pd

from bayespsf._runtime import refuse_beyond_memory
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.psf.defocus import Defocus
from bayespsf.scene import Scene, units
from bayespsf.simulation import camera_effects as cx
from bayespsf.simulation import effects as fx

_PHOTONS_PER_BLOCK = 2**22  # bounds the photon-by-photon path's memory (~200 MB of arrays)
_PIXELS_PER_BLOCK = 2**22  # bounds a block's arrays (32 MB each); ROIs up to 63 x 63 get 1024
_MAX_BLOCK = 1024
_PIXELS_PER_CHUNK = 2**24  # simulate_chunks' default chunk: 16 384 images of up to 31 x 31
_MAX_CHUNK = 16_384


def background_effect(scene: Scene) -> fx.BackgroundPhotons | None:
    """The background law of the scene as an effect (None for kind 'none')."""
    bg = scene.background
    kind = bg["kind"]
    if kind == "none":
        return None
    if kind == "poisson":
        return fx.PoissonBackground(bg["mean"])
    if kind in ("gaussian", "truncated-gaussian"):
        return fx.DiscreteGaussianBackground(bg["mean"], bg["sd"])
    var = bg["sd"] ** 2
    probability = 1.0 - var / bg["mean"]
    return fx.BinomialBackground(round(bg["mean"] / probability), probability)


def photon_path(scene: Scene) -> str:
    """'expected', 'multinomial' or 'photons': how the scene's signal photons are drawn."""
    e = scene.emitter
    if e["width_jitter"] > 0 or scene.optics["psf"] == "airy":
        return "photons"
    return "multinomial" if e["photon_statistics"] == "fixed" else "expected"


def build_pipeline(scene: Scene) -> list[fx.Effect]:
    """The ordered effects that exactly the scene's declarations call for.

    Parameters
    ----------
    scene : Scene
        The scene to simulate.

    Returns
    -------
    list of Effect
        The effects (``bayespsf.simulation.effects``) in the order they act on a block of
        images: the emitter's truth first, the camera law's last. No key, no effect.

    See Also
    --------
    describe : the same list in words.

    Examples
    --------
    >>> from bayespsf import load_scene
    >>> from bayespsf.simulation import build_pipeline
    >>> [type(step).__name__ for step in build_pipeline(load_scene("paper-fig3"))][:4]
    ['EmitterTruth', 'UniformPosition', 'WholePhotonNumber', 'MultinomialPhotons']
    """
    e, g = scene.emitter, scene.geometry
    a = g["pixel_size"]
    background = background_effect(scene)
    b_mean = background.moments[0] if background is not None else 0.0
    x0, y0 = (e["x0"], e["y0"]) if e["position"] == "fixed" else (0.0, 0.0)
    airy = scene.optics["psf"] == "airy"
    if airy:
        s_x = s_y = fx.airy_gaussian_sd(scene.optics["wavelength"], scene.optics["na"])
    else:
        s_x, s_y = e["s0x"], e["s0y"]
    steps: list[fx.Effect] = [fx.EmitterTruth(x0, y0, s_x, s_y, e["photons"], b_mean)]
    if "axial" in scene.to_dict():
        steps += axial_effects(scene)
    if e["position"] == "pixel":
        steps.append(fx.UniformPosition(0.5 * a))
    elif e["position"] == "box":
        steps.append(fx.UniformPosition(e["box"]))
    if e["photon_jitter"] > 0:
        steps.append(fx.PhotonNumberJitter(e["photon_jitter"]))
    path = photon_path(scene)
    fixed = e["photon_statistics"] == "fixed"
    if fixed:
        steps.append(fx.WholePhotonNumber())
    if path == "expected":
        steps += [fx.ExpectedSignal(a), *detection_effects(scene, "expected")]
    else:
        if path == "multinomial":
            steps.append(fx.MultinomialPhotons(a))
        elif airy:
            o = scene.optics
            steps.append(fx.AiryPhotons(a, o["wavelength"], o["na"], e["width_jitter"], fixed))
        else:
            steps.append(fx.PhotonBinning(a, e["width_jitter"], fixed))
        steps += detection_effects(scene, "photoelectrons")
    if (factor := truth_photon_factor(scene)) != 1.0:
        steps.append(fx.DetectedTruth(factor))
    return steps


def axial_effects(scene: Scene) -> list[fx.Effect]:
    """The emitter's z and the widths it gives, where the scene declares ``[axial]``."""
    ax = scene.axial
    law = ax["z"]
    position = fx.AxialPosition(
        law,
        z0=ax.get("z0", 0.0),
        low=ax.get("z_low", 0.0),
        high=ax.get("z_high", 0.0),
        sd=ax.get("z_sd", 0.0),
    )
    return [position, fx.DefocusWidths(Defocus.from_scene(scene))]


def scene_photon_label(scene: Scene) -> str:
    """The unit of the scene's N and b in words (``bayespsf.scene.units.label``)."""
    cam = scene.camera
    return units.label(cam["quantum_efficiency"], cam["photon_unit"])


def truth_photon_factor(scene: Scene) -> float:
    """The factor from the scene's declared photons (incident on the camera) to its
    ``photon_unit``: the quantum efficiency for 'detected', 1 for 'incident'."""
    cam = scene.camera
    if cam["photon_unit"] == "detected":
        return cam["quantum_efficiency"]
    return 1.0


def detection_effects(scene: Scene, stage: str) -> list[fx.Effect]:
    """The effects that turn a signal image into camera counts: the photon draws (from an
    ``"expected"`` image; none for whole ``"photoelectrons"``), the scene's background law (a
    Poisson background folded into the expected image), the quantum efficiency's thinning
    (where declared) and its camera law.

    They read only the image's shape, so whole frames ``(k, height, width)`` pass through them
    as ROIs do (``bayespsf.simulation.movie``).
    """
    if stage not in ("expected", "photoelectrons"):
        raise BayespsfInputError(f"stage must be 'expected' or 'photoelectrons', got {stage!r}")
    background = background_effect(scene)
    steps: list[fx.Effect] = []
    if stage == "expected":
        if isinstance(background, fx.PoissonBackground):
            steps.append(fx.PoissonBackgroundMean(background.mean))
            background = None
        steps.append(fx.PoissonPhotons())
    if background is not None:
        steps.append(background)
    if scene.camera["quantum_efficiency"] < 1.0:
        steps.append(fx.QuantumEfficiency(scene.camera["quantum_efficiency"]))
    return steps + camera_effects(scene.camera)


def camera_effects(cam: Mapping) -> list[fx.Effect]:
    """The camera law's effects, from photoelectrons to ADU (``cam``: a scene's camera table)."""
    kind = cam["kind"]
    if kind == "photon":
        return [cx.PhotonCounting()]
    steps: list[fx.Effect] = []
    if kind == "emccd":
        if cam["clock_induced_charge"] > 0:
            steps.append(cx.ClockInducedCharge(cam["clock_induced_charge"]))
        if cam["register"] == "stages":
            steps.append(cx.StagedRegister(cam["gain"], cam["stages"]))
        else:
            steps.append(cx.GammaRegister(cam["gain"]))
        if cam["readout_sd"] > 0:
            steps.append(cx.ReadoutNoise(cam["readout_sd"], "electrons"))
        steps.append(cx.ElectronsToADU(cam["offset"], cam["e_per_adu"]))
    else:
        steps.append(cx.PhotoelectronsToADU(cam["gain"], cam["offset"]))
        if cam["variance"] > 0:
            steps.append(cx.ReadoutNoise(float(np.sqrt(cam["variance"])), "adu"))
    if cam["quantize"]:
        steps.append(cx.Quantize())
    if cam["saturation"] > 0:
        steps.append(cx.Saturate(cam["saturation"]))
    return steps


def describe(scene: Scene) -> str:
    """The pipeline, one effect per line, marking those that draw random numbers.

    Parameters
    ----------
    scene : Scene
        The scene to simulate.

    Returns
    -------
    str
        ``"1. EmitterTruth(...)"`` and so on, with ``"  [random]"`` after each effect that
        draws random numbers.

    See Also
    --------
    build_pipeline : the effects themselves.
    """
    return "\n".join(
        f"{i}. {step!r}" + ("  [random]" if step.draws else "")
        for i, step in enumerate(build_pipeline(scene), 1)
    )


def block_size(scene: Scene) -> int:
    """Images per random-number block: 1024, fewer when photons are binned one by one or a
    block of 1024 ROIs would exceed ``2**22`` pixels (ROIs larger than 63 x 63)."""
    largest = int(np.clip(_PIXELS_PER_BLOCK // scene.geometry["roi"] ** 2, 1, _MAX_BLOCK))
    if photon_path(scene) != "photons":
        return largest
    mean = scene.emitter["photons"] * (1.0 + scene.emitter["photon_jitter"])
    return int(np.clip(_PHOTONS_PER_BLOCK // max(mean, 1.0), 1, largest))


def simulate(scene: Scene, n: int, seed: int) -> tuple[np.ndarray, pd.DataFrame]:
    """Simulate ``n`` images of ``scene``.

    Parameters
    ----------
    scene : Scene
        The scene: its geometry, emitter, optics, background and camera decide the images.
    n : int
        Number of images (>= 0).
    seed : int
        Non-negative integer; image ``i`` depends on ``seed`` and ``i`` only.

    Returns
    -------
    counts : ndarray, shape (n, roi, roi)
        Camera counts in ADU.
    truth : pandas.DataFrame
        One row per image: ``x0 y0 s_x s_y N b`` (nm; N and b in the scene's
        ``camera.photon_unit``, b per pixel), plus ``photons_emitted`` on the
        photon-by-photon paths and ``z`` (nm) where the scene declares ``[axial]``.

    Raises
    ------
    BayespsfInputError
        If ``scene`` is not a ``Scene``, ``n`` or ``seed`` is not an integer >= 0, or the
        ``n`` images cannot fit in the machine's memory (refused before anything is
        allocated, naming ``n``).

    See Also
    --------
    simulate_chunks : the same images in chunks, for runs too large to hold in memory.
    simulate_movie : a movie of many molecules.
    bayespsf.Model.from_scene : the inference model of the same scene.

    Notes
    -----
    A scene's ``[movie]`` table does not apply here: the ROIs are those its other tables
    declare (``bayespsf.simulation.movie.simulate_movie`` simulates the movie). Images are
    drawn in blocks whose random streams depend on ``seed`` and the block's number only, so
    a shorter run is a prefix of a longer one (module docstring).

    Examples
    --------
    >>> from bayespsf import load_scene, simulate
    >>> counts, truth = simulate(load_scene("paper-fig3"), n=4, seed=1)
    >>> counts.shape
    (4, 19, 19)
    >>> list(truth.columns)
    ['x0', 'y0', 's_x', 's_y', 'N', 'b']
    """
    roi = _check_run(scene, n, seed, 1)
    refuse_beyond_memory(
        8.0 * n * (roi * roi + 8),  # the counts and the truth table
        f"n = {n} images of {roi} x {roi} pixels",
        "simulate fewer images (n; -n on the command line), or stream them in chunks with "
        "bayespsf.simulation.simulate_chunks",
    )
    counts = np.empty((n, roi, roi))
    truths = []
    start = 0
    for chunk, truth in simulate_chunks(scene, n, seed):
        counts[start : start + chunk.shape[0]] = chunk
        start += chunk.shape[0]
        truths.append(truth)
    if not truths:
        return counts, pd.DataFrame(columns=list(PARAMETER_NAMES), dtype=float)
    return counts, pd.concat(truths, ignore_index=True)


def simulate_chunks(
    scene: Scene, n: int, seed: int, chunk_size: int | None = None
) -> Iterator[tuple[np.ndarray, pd.DataFrame]]:
    """Yield ``(counts, truth)`` for consecutive chunks of at most ``chunk_size`` images.

    Memory is bounded by the chunk; the images (and the truth rows, indexed by image number)
    are those of ``simulate`` whatever the chunk size.

    Parameters
    ----------
    scene : Scene
        The scene to simulate.
    n : int
        Number of images in all (>= 0).
    seed : int
        Non-negative integer; image ``i`` depends on ``seed`` and ``i`` only.
    chunk_size : int, optional
        Most images per chunk (>= 1). Default: 16 384, fewer where a chunk would exceed
        ``2**24`` pixels (128 MB of counts; ROIs larger than 31 x 31).

    Yields
    ------
    counts : ndarray, shape (k, roi, roi)
        The chunk's counts in ADU, ``k <= chunk_size``.
    truth : pandas.DataFrame
        The chunk's rows of ``simulate``'s truth table, indexed by image number.

    Raises
    ------
    BayespsfInputError
        If ``scene`` is not a ``Scene``, an integer argument is out of range, or a chunk
        cannot fit in the machine's memory (naming ``chunk_size``).

    See Also
    --------
    simulate : all images at once.
    """
    roi = scene.geometry["roi"] if isinstance(scene, Scene) else 1
    if chunk_size is None:
        chunk_size = int(np.clip(_PIXELS_PER_CHUNK // roi**2, 1, _MAX_CHUNK))
    roi = _check_run(scene, n, seed, chunk_size)
    refuse_beyond_memory(
        8.0 * min(n, chunk_size) * (roi * roi + 8),
        f"chunk_size = {chunk_size} images of {roi} x {roi} pixels",
        "use a smaller chunk_size",
    )
    steps = build_pipeline(scene)
    block = block_size(scene)
    columns = list(PARAMETER_NAMES)
    cached: tuple[int, fx.Batch] | None = None  # a block shared by consecutive small chunks
    start = 0
    while start < n:
        stop = min(n, start + chunk_size)
        counts = np.empty((stop - start, roi, roi))
        truths = []
        for k in range(start // block, -(-stop // block)):
            if cached is None or cached[0] != k:
                cached = (k, _run_block(steps, block, roi, seed, k))
            batch = cached[1]
            lo, hi = max(start, k * block), min(stop, (k + 1) * block)
            counts[lo - start : hi - start] = batch.image[lo - k * block : hi - k * block]
            truth = pd.DataFrame(batch.truth, index=np.arange(k * block, (k + 1) * block))
            truths.append(truth.loc[lo : hi - 1])
        truth = pd.concat(truths)
        yield counts, truth[columns + [c for c in truth.columns if c not in columns]]
        start = stop


def _run_block(steps, block: int, roi: int, seed: int, k: int) -> fx.Batch:
    """Block ``k``: always whole, so that image i never depends on n or the chunking."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(k,))))
    batch = fx.Batch(block, roi)
    for step in steps:
        step(batch, rng)
    return batch


def _check_run(scene, n, seed, chunk_size) -> int:
    if not isinstance(scene, Scene):
        raise BayespsfInputError(f"scene must be a bayespsf.Scene, got {type(scene).__name__}")
    for name, value, low in (("n", n, 0), ("seed", seed, 0), ("chunk_size", chunk_size, 1)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
            raise BayespsfInputError(f"{name} must be an integer >= {low}, got {value!r}")
    return scene.geometry["roi"]
