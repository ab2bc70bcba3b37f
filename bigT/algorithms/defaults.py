"""What :func:`~bigT.algorithms.stratified_inverse` does when not told otherwise, and
the series methods it offers, as plain values.

The engine's signature and :mod:`.methods` take them from here, and so does ``bigT
invert --help``, which must not import the engine (numpy, scipy, the stores: ~0.5 s
of a 0.1 s help) to print them. So this module imports nothing (the prune's default is
:data:`bigT.config.DEFAULT_PRUNE`, as light), and ``bigT.algorithms`` imports its other
modules only when one of their names is first used.
"""

from __future__ import annotations

#: Series terms n of eq. 13: T_4^-1, the paper's "five-bounce" inverse (§5.1).
TERMS = 4
#: The series method (a key of :data:`METHOD_HELP`).
METHOD = "power"
#: F: T's diagonal (its 3x3 diagonal blocks for a colour T).
FIRST_BOUNCE = "diag"
#: Threads of this process that run the tasks when no scheduler is given.
WORKERS = 2

#: The series methods, in the order they are offered, each with one line that says what
#: a term computes (``bigT invert --method``'s help); :data:`.methods.METHODS` holds their
#: implementations under the same names, in the same order.
METHOD_HELP = {
    "power": "P_k = M P_{k-1}, X_k = X_{k-1} + F^-1 P_k (default)",
    "horner": "X_n = F^-1 + (I - F^-1 T) X_{n-1}",
    "newton-schulz": "X <- X (2I - T X), bounces double per step",
}
