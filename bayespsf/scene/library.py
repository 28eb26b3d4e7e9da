"""Scenes shipped with bayespsf (the TOML files of ``bayespsf/scene/shipped/``):
``load_scene("paper-fig3")``; ``shipped_scenes()`` lists them."""

from __future__ import annotations

from importlib import resources

from bayespsf.errors import BayespsfInputError
from bayespsf.scene.declaration import Scene


def _shipped():
    return resources.files("bayespsf.scene").joinpath("shipped")


def shipped_scenes() -> list[str]:
    """Names of the scenes shipped with the package.

    Returns
    -------
    list of str
        Sorted scene names, each loadable with ``load_scene``.

    See Also
    --------
    load_scene : one of them, as a ``Scene``.

    Examples
    --------
    >>> from bayespsf import shipped_scenes
    >>> "paper-fig3" in shipped_scenes()
    True
    """
    return sorted(p.name[:-5] for p in _shipped().iterdir() if p.name.endswith(".toml"))


def load_scene(name: str) -> Scene:
    """A shipped scene by name.

    Parameters
    ----------
    name : str
        One of ``shipped_scenes()``, e.g. ``"paper-fig3"``.

    Returns
    -------
    Scene
        The scene, checked against the schema.

    Raises
    ------
    BayespsfInputError
        If no shipped scene has that name (the message lists them).

    See Also
    --------
    Scene.load : a scene from a TOML file of your own.
    shipped_scenes : the names.

    Examples
    --------
    >>> from bayespsf import load_scene
    >>> scene = load_scene("paper-fig3")
    >>> scene.geometry["roi"], scene.geometry["pixel_size"], scene.camera["kind"]
    (19, 79.0, 'emccd')
    """
    if name not in shipped_scenes():
        raise BayespsfInputError(
            f"no shipped scene {name!r}; shipped: {', '.join(shipped_scenes())}"
        )
    return Scene.loads(_shipped().joinpath(f"{name}.toml").read_text())


__all__ = ["load_scene", "shipped_scenes"]
