"""Exceptions raised by bayespsf.

Every error raised for bad input is a ``ValueError`` subclass whose message names the
offending argument (or scene key) and the allowed range, so ``except ValueError`` keeps working.
"""


class BayespsfInputError(ValueError):
    """An argument is outside its documented domain (wrong shape, NaN, out of range)."""
