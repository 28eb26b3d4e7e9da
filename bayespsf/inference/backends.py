"""The array backends inference runs on: NumPy (the default, every camera law) and JAX (the
stacked MLE and the chain-free posteriors on whatever device JAX finds: a CUDA GPU where one
is installed, else the CPU).

JAX is an optional dependency (``pip install "bayespsf[gpu]"`` for a CUDA 13 GPU,
``pip install "bayespsf[jax]"`` for the CPU); nothing imports it until ``backend="jax"`` is
asked for.
"""

from __future__ import annotations

from bayespsf._runtime import cache_folder
from bayespsf.errors import BayespsfInputError

BACKENDS = ("numpy", "jax")


def check_backend(backend: str, model=None) -> str:
    """The backend's name, checked; for ``"jax"`` also that JAX can be imported and, given a
    model, that the backend supports its camera law (before any work starts).

    Parameters
    ----------
    backend : str
        One of ``BACKENDS``.
    model : Model, optional
        The inference model the backend will run.

    Returns
    -------
    str
        ``backend``.

    Raises
    ------
    BayespsfInputError
        For an unknown name (naming ``backend`` and the choices), ``"jax"`` without JAX
        installed (naming the extra that installs it), or a camera law or pixel model the
        JAX backend does not support (naming the fix).
    """
    if backend not in BACKENDS:
        raise BayespsfInputError(
            f"backend must be one of {', '.join(BACKENDS)} (--backend on the command line); "
            f"got {backend!r}"
        )
    if backend == "jax":
        try:
            import jax  # noqa: F401
        except ImportError as error:
            raise BayespsfInputError(
                "backend='jax' needs JAX: pip install 'bayespsf[gpu]' (a CUDA GPU) or "
                "'bayespsf[jax]' (the CPU); or use backend='numpy' (the default)"
            ) from error
        if model is not None:
            from bayespsf.inference.jax_model import JaxModel

            JaxModel.from_model(model)  # refuses an unsupported law by name
    return backend


def jax_imported() -> bool:
    """Whether JAX itself has been imported in this process.

    A lazily registered ``jax`` entry in ``sys.modules`` does not count: arviz-base registers
    one through ``lazy_loader`` whenever it is imported, without loading JAX. JAX's import
    always loads ``jaxlib``, which the lazy entry does not.

    Returns
    -------
    bool
    """
    import sys

    return "jaxlib" in sys.modules


def jax_running() -> bool:
    """Whether JAX's runtime has started in this process (its backends, whose threads make a
    fork unsafe).

    Importing JAX starts no threads; its first computation (or ``jax.devices()``) starts its
    backends. matplotlib imports JAX when it plots after arviz-base has registered a lazy
    ``jax`` module (``matplotlib.cbook._is_jax_array`` reads ``jax.Array``), so a process that
    draws a figure has imported JAX without running it.

    Returns
    -------
    bool
        False where JAX is not imported; where this JAX does not say whether its backends
        started (``jax._src.xla_bridge.backends_are_initialized``, not public), True.
    """
    if not jax_imported():
        return False
    try:
        from jax._src.xla_bridge import backends_are_initialized
    except ImportError:
        return True
    return bool(backends_are_initialized())


def start_jax() -> None:
    """Set JAX up for the backend (idempotent): float64, and compiled programs kept on disk
    in the machine's cache folder (``bayespsf._runtime.cache_folder``, its ``jax`` folder)
    unless JAX's ``jax_compilation_cache_dir`` is set already, so that the programs a
    dataset's ROI size needs compile once per machine (tens of seconds), not once per run.

    Returns
    -------
    None
    """
    import jax

    if not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)
    folder = cache_folder()
    if folder is not None and not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir", str(folder / "jax"))


def jax_modules():
    """``jax`` and ``jax.numpy``, imported on first use (the backend's modules import JAX
    only when a JAX program runs, so that the core install never needs it).

    Returns
    -------
    jax, jax.numpy : module
    """
    import jax
    import jax.numpy as jnp

    return jax, jnp


def release_programs() -> None:
    """Release the JAX backend's compiled programs, JAX's own caches of them, and the camera
    tables it keeps on the device.

    Each compiled program holds memory and, on the CPU, hundreds of the process's memory
    maps (about 1 500 per ESS target and method of the posteriors); a process that runs
    many model configurations, each compiling its own programs, can reach the system's limit
    of memory maps (``vm.max_map_count``, commonly 65 530), where compiling fails. Call this
    between configurations; the next call of each program compiles it again (from JAX's
    compilation cache on disk where it has one). Does nothing without JAX imported.

    Returns
    -------
    None
    """
    if not jax_imported():
        return
    import gc

    import jax

    from bayespsf.inference import jax_mle, jax_model, jax_sampling

    jax_model.release_tables()
    jax_sampling._program.cache_clear()
    jax_mle._compiled.cache_clear()
    jax.clear_caches()
    gc.collect()


def device_name() -> str:
    """The device JAX computes on (e.g. ``"NVIDIA H100 80GB HBM3"`` or ``"cpu"``).

    Returns
    -------
    str
        The first device's kind, as JAX names it.
    """
    import jax

    return str(jax.devices()[0].device_kind)


__all__ = [
    "BACKENDS",
    "check_backend",
    "device_name",
    "jax_imported",
    "jax_modules",
    "jax_running",
    "release_programs",
    "start_jax",
]
