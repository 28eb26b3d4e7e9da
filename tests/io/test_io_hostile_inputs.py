"""Input files under hostile inputs: a path that is not a regular file (a named pipe nobody
writes to) is refused by name before it is opened, where opening it would wait forever; a camera
file's misspelt table or key is named with the file.

Each call runs in a thread with a deadline: should it block in ``open`` (the old behaviour),
the test opens the pipe's other end, so the reader sees an empty file and the thread ends,
and the test fails instead of hanging the suite."""

import os
import threading

import numpy as np
import pytest

from bayespsf import Scene
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import Posterior
from bayespsf.io import read_rois

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")

DEADLINE = 20.0  # seconds; a refusal takes microseconds


def outcome_within_deadline(call, fifo):
    """What ``call()`` raised (or returned) within ``DEADLINE``; fails if it was still
    waiting on ``fifo`` then, after releasing it."""
    result = {}

    def run():
        try:
            result["value"] = call()
        except BaseException as exc:  # handed to the test
            result["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(DEADLINE)
    if thread.is_alive():
        try:  # a writer that closes at once: the blocked reader gets end-of-file
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        except OSError:
            pass
        thread.join(DEADLINE)
        pytest.fail(f"still waiting on the named pipe {fifo} after {DEADLINE:g} s")
    return result


def _refused(result, *words):
    error = result.get("error")
    assert isinstance(error, BayespsfInputError), result
    for word in words:
        assert word in str(error), str(error)
    return str(error)


@pytest.mark.parametrize("name", ["rois.npy", "rois.tif"])
def test_a_named_pipe_given_as_rois_is_refused_by_name(tmp_path, name):
    fifo = tmp_path / name
    os.mkfifo(fifo)
    message = _refused(
        outcome_within_deadline(lambda: read_rois(fifo), fifo),
        str(fifo),
        "a named pipe (FIFO)",
        "not a regular file",
    )
    assert message.startswith(f"{fifo} is a named pipe (FIFO), not a regular file: a ROI stack")


@pytest.mark.parametrize(
    "name, load, what",
    [("molecule-000000.nc", Posterior.load, "result"), ("scene.toml", Scene.load, "scene")],
    ids=["result file", "scene"],
)
def test_a_named_pipe_given_as_a_result_file_or_a_scene_is_refused_by_name(
    tmp_path, name, load, what
):
    fifo = tmp_path / name
    os.mkfifo(fifo)
    _refused(
        outcome_within_deadline(lambda: load(fifo), fifo),
        str(fifo),
        "not a regular file",
        f"not a {what} file",
    )


@pytest.mark.skipif(not os.path.exists("/dev/null"), reason="needs /dev/null")
def test_a_device_is_not_a_roi_stack(tmp_path):
    link = tmp_path / "null.npy"  # a device behind a name with the right extension
    link.symlink_to("/dev/null")
    with pytest.raises(BayespsfInputError, match="is a character device, not a regular file"):
        read_rois(link)


def test_regular_files_and_links_to_them_are_still_read(tmp_path):
    stack = np.random.default_rng(0).random((2, 15, 15))
    np.save(tmp_path / "rois.npy", stack)
    (tmp_path / "link.npy").symlink_to(tmp_path / "rois.npy")
    np.testing.assert_array_equal(read_rois(tmp_path / "link.npy"), stack)


def test_a_misspelt_camera_file_key_names_the_file(tmp_path):
    # the scene's message alone names neither the file nor that it is a camera file
    import pytest

    from bayespsf.errors import BayespsfInputError
    from bayespsf.io import camera_scene, read_camera_file

    path = tmp_path / "cam.toml"
    path.write_text(
        '[geometry]\npixel_size = 100.0\n[emiter]\ns0x = 130.0\n[camera]\nkind = "photon"\n'
    )
    with pytest.raises(BayespsfInputError, match=r"cam.toml: unknown scene table or key 'emiter'"):
        camera_scene(read_camera_file(path), path, 15)
