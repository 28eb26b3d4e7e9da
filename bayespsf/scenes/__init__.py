"""Scenes shipped with bayespsf: ``bayespsf.scenes.load("paper-fig3")``; ``names()`` lists them."""

from __future__ import annotations

from importlib import resources

from bayespsf.errors import BayespsfInputError
from bayespsf.scene import Scene


def names() -> list[str]:
    """Names of the shipped scenes."""
    return sorted(
        p.name[:-5] for p in resources.files(__name__).iterdir() if p.name.endswith(".toml")
    )


def load(name: str) -> Scene:
    """A shipped scene by name (see ``names``)."""
    if name not in names():
        raise BayespsfInputError(f"no shipped scene {name!r}; shipped: {', '.join(names())}")
    return Scene.loads(resources.files(__name__).joinpath(f"{name}.toml").read_text())
