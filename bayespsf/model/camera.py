"""The camera law of a scene, and the likelihood tier that inference uses by default."""

from __future__ import annotations

from bayespsf.cameras import EMCCD, SCMOS, Camera, Photon
from bayespsf.errors import BayespsfInputError
from bayespsf.scene import Scene

DEFAULT_TIER = {"emccd": "table", "scmos": "exact"}


def camera_from_scene(scene: Scene, likelihood: str | None = None) -> Camera:
    """The camera law a scene declares.

    Parameters
    ----------
    scene : Scene
    likelihood : str, optional
        The likelihood tier; default the scene's ``camera.likelihood``, else ``DEFAULT_TIER``
        (``table`` for EMCCD, ``exact`` for sCMOS).

    Returns
    -------
    Camera

    Raises
    ------
    BayespsfInputError
        If the tier does not apply to the camera.
    """
    cam = scene.camera
    kind = cam["kind"]
    tier = likelihood or cam.get("likelihood") or DEFAULT_TIER.get(kind)
    if kind == "photon":
        if tier not in (None, "exact", "poisson"):
            raise BayespsfInputError(f"likelihood {tier!r} does not apply to a photon camera")
        return Photon()
    if kind == "emccd":
        return EMCCD(cam["gain"], cam["readout_sd"], cam["offset"], cam["e_per_adu"], tier)
    return SCMOS(cam["gain"], cam["offset"], cam["variance"], likelihood=tier)


def inference_tier(camera: Camera) -> Camera:
    """``camera``, or for an EMCCD whose likelihood tier was not chosen, the same camera with
    the inference default (``DEFAULT_TIER``), as a scene gives it."""
    if isinstance(camera, EMCCD) and not camera.tier_chosen:
        return EMCCD(
            camera.gain, camera.readout_sd, camera.offset, camera.e_per_adu, DEFAULT_TIER["emccd"]
        )
    return camera
