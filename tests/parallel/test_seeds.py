"""``molecule_seeds`` (SeedSequence's hash on arrays) against ``molecule_seed`` (one
``numpy.random.SeedSequence`` per molecule): the same seeds bit for bit."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bayespsf.errors import BayespsfInputError
from bayespsf.parallel import molecule_seed, molecule_seeds


@pytest.mark.parametrize(
    "seed",
    # one to five 32-bit words of entropy: the pool of four words, and the words mixed in after
    [0, 1, 7, 2**32 - 1, 2**32, 2**63 - 1, 2**63, 2**64 - 1, 2**96 + 3, 2**130 + 11],
)
def test_molecule_seeds_equal_seedsequence(seed):
    rng = np.random.default_rng(seed % 2**32)
    indices = np.concatenate([np.arange(40), rng.integers(0, 2**32, 40), [2**32 - 1]])
    got = molecule_seeds(seed, indices)
    assert got.dtype == np.uint64 and got.shape == indices.shape
    assert [int(s) for s in got] == [molecule_seed(seed, int(i)) for i in indices]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**70), st.lists(st.integers(0, 2**33), min_size=1, max_size=8))
def test_molecule_seeds_any_seed_and_index(seed, indices):
    # indices of two words (>= 2**32) take SeedSequence itself, in place
    got = molecule_seeds(seed, np.array(indices, dtype=np.uint64))
    assert [int(s) for s in got] == [molecule_seed(seed, i) for i in indices]


def test_molecule_seeds_keep_the_shape_and_refuse_negatives():
    grid = np.arange(6).reshape(2, 3)
    got = molecule_seeds(5, grid)
    assert got.shape == (2, 3) and int(got[1, 2]) == molecule_seed(5, 5)
    assert molecule_seeds(5, []).shape == (0,)
    with pytest.raises(BayespsfInputError, match="seed"):
        molecule_seeds(-1, [0])
    with pytest.raises(BayespsfInputError, match="indices"):
        molecule_seeds(1, [0, -2])
    with pytest.raises(BayespsfInputError, match="indices"):
        molecule_seeds(1, [0.5])
