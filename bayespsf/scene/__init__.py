"""The single declaration of an experiment: geometry, emitter, optics, background, camera and
prior, read from TOML or a dict and checked against ``SCHEMA``; the scenes shipped with the
package (``load_scene``, ``shipped_scenes``)."""

from bayespsf.scene.declaration import Scene, SceneError
from bayespsf.scene.library import load_scene, shipped_scenes
from bayespsf.scene.schema import (
    OPTIONAL_SECTIONS,
    PRIOR_PARAMETERS,
    SCHEMA,
    Key,
    default_prior,
    schema_markdown,
)

__all__ = [
    "OPTIONAL_SECTIONS",
    "PRIOR_PARAMETERS",
    "SCHEMA",
    "Key",
    "Scene",
    "SceneError",
    "default_prior",
    "load_scene",
    "schema_markdown",
    "shipped_scenes",
]
