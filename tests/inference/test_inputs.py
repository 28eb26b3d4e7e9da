"""Bad inputs through the public API: each is refused with a message naming the field
(nothing accepted without a word)."""

import numpy as np
import pytest

import bayespsf
from bayespsf.errors import BayespsfInputError


@pytest.fixture(scope="module")
def model():
    return bayespsf.Model.from_scene(bayespsf.load_scene("ideal"))


@pytest.mark.parametrize(
    "bad,words",
    [
        (np.full((15, 15), 3.0) + 1j, "complex"),
        (np.ones((15, 15), dtype=bool), "boolean"),
        (np.full((15, 15), "3"), "text"),
        ([[1.0, 2.0], [3.0]], "rectangular"),
    ],
    ids=["complex", "boolean", "text", "ragged"],
)
def test_counts_of_the_wrong_kind_are_named(model, bad, words):
    with pytest.raises(BayespsfInputError, match=f"counts.*{words}"):
        model.check_counts(bad)


def test_numbers_held_as_objects_are_read(model):
    """A row of a mixed-type DataFrame holds numbers as objects: still numbers."""
    counts = np.arange(225.0).reshape(15, 15).astype(object)
    np.testing.assert_array_equal(model.check_counts(counts), np.arange(225.0).reshape(15, 15))


# ------------------------------------------------------------------------------ scene files


@pytest.mark.parametrize(
    "text,words",
    [
        ("a = " + "[" * 100_000 + "]" * 100_000, "more than the 65536"),
        ("a" + ".a" * 100_000 + " = 1", "more than the 65536"),
        ("a = " + "[" * 3000 + "]" * 3000, "nested too deeply"),
        ("a = " + "{a=" * 3000 + "}" * 3000, "nested too deeply"),
    ],
    ids=["deep-array", "deep-dotted-key", "deep-array-short", "deep-inline-table"],
)
def test_scene_text_nested_beyond_reason_is_named(text, words):
    with pytest.raises(bayespsf.SceneError, match=words):
        bayespsf.Scene.loads(text)


def test_scene_file_that_is_not_utf8_or_not_a_file_is_named(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes(b"[geometry]\nroi = 15 # caf\xe9\n")
    with pytest.raises(bayespsf.SceneError, match=r"latin1.toml is not a scene file: .*UTF-8"):
        bayespsf.Scene.load(path)
    with pytest.raises(bayespsf.SceneError, match="is a directory, not a scene file"):
        bayespsf.Scene.load(tmp_path)
