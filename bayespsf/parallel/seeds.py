"""The seed of each molecule: it depends on the run's seed and the molecule's index only, never
on the number of workers, the chunking or the order in which they finish.

A molecule's seed is the first 64 bits of NumPy's ``SeedSequence`` of the pair ``(seed, index)``
(``molecule_seed``). ``molecule_seeds`` gives the same seeds for a whole stack at once: it runs
``SeedSequence``'s hash (M. E. O'Neill's ``seed_seq_fe``, as NumPy implements it: a pool of
four 32-bit words mixed from the entropy, then hashed into the state) on arrays of indices,
where one ``SeedSequence`` per molecule costs microseconds each on the host, the ceiling of a
GPU run's rate. The two agree bit for bit (``tests/parallel/test_seeds.py``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from bayespsf.errors import BayespsfInputError

# numpy.random.SeedSequence's constants (numpy/random/bit_generator.pyx)
_POOL = 4
_INIT_A, _MULT_A = 0x43B0D7E5, 0x931E8875
_INIT_B, _MULT_B = 0x8B51F9DD, 0x58F38DED
_MIX_MULT_L, _MIX_MULT_R = 0xCA01F9DD, 0x4973F715
_WORD = np.uint64(0xFFFFFFFF)
_SHIFT = np.uint64(16)


def molecule_seed(seed: int, index: int) -> int:
    """The seed of molecule ``index`` in a run seeded with ``seed``.

    Parameters
    ----------
    seed : int
        The run's seed (>= 0).
    index : int
        The molecule's index in the stack (>= 0).

    Returns
    -------
    int
        A 64-bit seed, from NumPy's ``SeedSequence`` of the pair, so nearby seeds and indices
        give unrelated streams; it depends on ``seed`` and ``index`` only, never on the
        number of workers or the order in which they finish.

    See Also
    --------
    sample_many : seeds molecule ``i`` with ``molecule_seed(seed, i)``.
    molecule_seeds : the same for many indices at once.
    """
    state = np.random.SeedSequence([int(seed), int(index)]).generate_state(2, np.uint32)
    return int(state[0]) << 32 | int(state[1])


def molecule_seeds(seed: int, indices: ArrayLike) -> np.ndarray:
    """``molecule_seed(seed, i)`` for every ``i`` of ``indices``, computed as arrays.

    Parameters
    ----------
    seed : int
        The run's seed (>= 0).
    indices : array_like of int
        The molecules' indices (>= 0).

    Returns
    -------
    ndarray of uint64, shape of ``indices``
        Each molecule's seed, equal to ``molecule_seed(seed, i)``.

    Raises
    ------
    BayespsfInputError
        For a negative seed, or indices that are not whole numbers >= 0.

    Examples
    --------
    >>> from bayespsf.parallel import molecule_seed, molecule_seeds
    >>> int(molecule_seeds(7, [0, 1, 2])[2]) == molecule_seed(7, 2)
    True
    """
    if int(seed) < 0:
        raise BayespsfInputError(f"seed must be >= 0; got {seed}")
    index = np.asarray(indices)
    if index.size and (not np.issubdtype(index.dtype, np.integer) or index.min() < 0):
        raise BayespsfInputError("indices must be whole numbers >= 0")
    index = index.astype(np.uint64)
    wide = index >= 2**32  # more than one 32-bit word of entropy: SeedSequence one by one
    out = _hashed(_words(int(seed)), np.where(wide, 0, index))
    for position in np.flatnonzero(wide.ravel()):
        out.flat[position] = molecule_seed(seed, int(index.flat[position]))
    return out


def _words(n: int) -> list[int]:
    """``n``'s 32-bit words, least significant first (one word for 0), as ``SeedSequence``
    reads an int."""
    words = [0] if n == 0 else []
    while n > 0:
        words.append(n & 0xFFFFFFFF)
        n >>= 32
    return words


def _hashed(seed_words: list[int], index: np.ndarray) -> np.ndarray:
    """``SeedSequence(seed_words + [index]).generate_state(2)`` as one 64-bit word, for an
    array of one-word indices. 32-bit arithmetic in uint64 arrays, masked: the products of two
    words fit, and array arithmetic wraps without a warning."""
    hash_const = _INIT_A

    def hashmix(value):
        nonlocal hash_const
        value = value ^ np.uint64(hash_const)
        hash_const = (hash_const * _MULT_A) & 0xFFFFFFFF
        value = (value * np.uint64(hash_const)) & _WORD
        return value ^ (value >> _SHIFT)

    def mix(x, y):
        value = (np.uint64(_MIX_MULT_L) * x - np.uint64(_MIX_MULT_R) * y) & _WORD
        return value ^ (value >> _SHIFT)

    entropy = [np.full(index.shape, w, dtype=np.uint64) for w in seed_words] + [index]
    zero = np.zeros(index.shape, dtype=np.uint64)
    pool = [hashmix(entropy[i] if i < len(entropy) else zero) for i in range(_POOL)]
    for source in range(_POOL):
        for target in range(_POOL):
            if source != target:
                pool[target] = mix(pool[target], hashmix(pool[source]))
    for source in range(_POOL, len(entropy)):
        for target in range(_POOL):
            pool[target] = mix(pool[target], hashmix(entropy[source]))
    state, hash_const = [], _INIT_B
    for word in pool[:2]:
        value = word ^ np.uint64(hash_const)
        hash_const = (hash_const * _MULT_B) & 0xFFFFFFFF
        value = (value * np.uint64(hash_const)) & _WORD
        state.append(value ^ (value >> _SHIFT))
    return (state[0] << np.uint64(32)) | state[1]


__all__ = ["molecule_seed", "molecule_seeds"]
