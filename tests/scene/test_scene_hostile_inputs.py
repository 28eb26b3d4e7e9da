"""Scenes under hostile inputs: an unknown likelihood tier is refused at load, naming the key
and the tiers of the scene's camera kind (not accepted, to fail or not only when a model is
built)."""

import re

import pytest

from bayespsf import Model, Scene, load_scene, shipped_scenes
from bayespsf.cameras import emccd, photon, scmos
from bayespsf.scene import SceneError
from bayespsf.scene.schema import likelihood_tiers

CAMERAS = {
    "photon": {"kind": "photon"},
    "emccd": {"kind": "emccd", "gain": 100.0, "readout_sd": 10.0},
    "scmos": {"kind": "scmos", "gain": 2.0, "variance": 4.0},
}
ALLOWED = {
    "photon": "'exact', 'poisson'",
    "emccd": "'exact', 'table', 'high-gain', 'gaussian', 'poisson'",
    "scmos": "'exact', 'huang'",
}


@pytest.mark.parametrize("kind", list(CAMERAS))
def test_an_unknown_likelihood_tier_is_refused_at_load(tmp_path, kind):
    message = (
        f"camera.likelihood must be '' (the camera's default) or one of {ALLOWED[kind]} for "
        f"camera.kind = '{kind}', got 'bogus'"
    )
    with pytest.raises(SceneError, match=re.escape(message)):
        Scene.from_dict({"camera": {**CAMERAS[kind], "likelihood": "bogus"}})
    path = tmp_path / "bogus.toml"
    keys = "".join(f"{k} = {v!r}\n".replace("'", '"') for k, v in CAMERAS[kind].items())
    path.write_text(f'[camera]\n{keys}likelihood = "bogus"\n')
    with pytest.raises(SceneError, match=re.escape(f"{path}: {message}")):
        Scene.load(path)


def test_a_tier_of_another_camera_kind_is_refused():
    with pytest.raises(SceneError, match=r"one of 'exact', 'huang' for camera.kind = 'scmos'"):
        Scene.from_dict({"camera": {**CAMERAS["scmos"], "likelihood": "table"}})
    with pytest.raises(SceneError, match=r"for camera.kind = 'photon', got 'high-gain'"):
        Scene.from_dict({"camera": {"likelihood": "high-gain"}})


@pytest.mark.parametrize(
    ("kind", "tier"), [(k, t) for k in CAMERAS for t in ("", *likelihood_tiers(k))]
)
def test_every_tier_of_each_camera_kind_is_accepted_and_builds_its_model(kind, tier):
    scene = Scene.from_dict({"camera": {**CAMERAS[kind], "likelihood": tier}})
    model = Model.from_scene(scene)
    if kind != "photon" and tier:
        assert model.camera.likelihood == tier


def test_the_tiers_are_the_camera_laws_own():
    assert likelihood_tiers("emccd") == emccd.TIERS
    assert likelihood_tiers("scmos") == scmos.TIERS
    assert likelihood_tiers("photon") == photon.TIERS == ("exact", "poisson")


def test_changing_the_camera_kind_drops_a_tier_the_new_kind_lacks():
    scene = load_scene("emccd-typical")
    assert scene.camera["likelihood"] == "table"
    assert scene.replace(camera={"kind": "scmos"}).camera["likelihood"] == ""
    assert scene.replace(camera={"readout_sd": 5.0}).camera["likelihood"] == "table"
    given = scene.replace(camera={"kind": "scmos", "likelihood": "huang"})
    assert given.camera["likelihood"] == "huang"
    with pytest.raises(SceneError, match=r"for camera\.kind = 'scmos', got 'table'"):
        scene.replace(camera={"kind": "scmos", "likelihood": "table"})  # asked for: refused


def test_every_shipped_scene_names_a_tier_of_its_camera():
    for name in shipped_scenes():
        camera = load_scene(name).camera
        assert camera["likelihood"] in ("", *likelihood_tiers(camera["kind"])), name
