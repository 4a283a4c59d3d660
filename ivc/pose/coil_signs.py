"""Coil signs from the data: which recording's source coils read negated against the others' (docs/tracker.md).

A lock-in tracker's coupling signs come from a phase reference; one taken in the wrong fixture
negates some source coils in every file recorded with it. Within one recording that is
invisible (the fit takes a negative gain, or a half turn of the source frame), but a joint fit
with recordings made with the right reference cannot absorb it: the recording's residue
there is many times its residue alone. :func:`find_sign_flips` finds such recordings and the
sign pattern that makes them consistent: the one whose flip lowers the joint residue by a
large factor. It reports; applying a fix is the data set's business (the reader's
``sign_fixes``, ``--sign-fix``, a folder's options file).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ivc.errors import TrackerError
from ivc.pose.calibrate import calibrate

__all__ = ["SignFlip", "find_sign_flips"]

#: every source sign pattern but the identity
PATTERNS = tuple(np.array(p, dtype=float) for p in itertools.product((1.0, -1.0), repeat=3))[1:]


@dataclass
class SignFlip:
    """Recording ``group`` reads source coils negated against the reference recording: ``signs`` (3,) per
    source coil makes it consistent.

    RMS residues, dimensionless: ``reference`` (the reference recording fitted alone), ``joint`` (the
    recording in a joint fit with the reference, as recorded) and ``flipped`` (the same, ``signs`` applied).
    """

    group: int
    signs: np.ndarray
    reference: float
    joint: float
    flipped: float


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def find_sign_flips(S: np.ndarray, J_so: np.ndarray, J_st: np.ndarray, group: np.ndarray, *,
                    factor: float = 3.0, points: int = 60, max_iterations: int = 20) -> list[SignFlip]:
    """Recordings whose source coil signs disagree with the first recording's, from the data alone.

    ``S`` (N, 3, 3), ``J_so`` (N, 4, 4), ``J_st`` (N, 4, 4) as for
    :func:`ivc.pose.calibrate.calibrate`; ``group`` (N,) the recording of each point, the
    first point's recording the reference. The reference is fitted alone (one centre); each
    other recording is fitted jointly with it, from the reference's model. A recording whose
    joint residue exceeds ``factor`` times the reference's is suspect, and it is reported when
    one of the seven source sign patterns lowers its joint residue by ``factor`` or more. Each
    joint fit uses at most ``points`` evenly spaced points of each recording and ``max_iterations``
    (the contrast sought is tens of percent against tenths). Returns the findings, empty when
    the recordings agree.
    """
    S, group = np.asarray(S, dtype=float), np.asarray(group)
    J_st = np.asarray(J_st, dtype=float)
    J_so = np.broadcast_to(np.asarray(J_so, dtype=float), J_st.shape)
    names = list(dict.fromkeys(group.tolist()))
    if len(names) < 2:
        return []
    if min(int(np.sum(group == g)) for g in names) < 12:
        raise TrackerError("each recording needs at least 12 points to compare coil signs")
    keep = np.zeros(len(S), dtype=bool)
    for g in names:
        where = np.flatnonzero(group == g)
        keep[where[np.linspace(0, len(where) - 1, min(points, len(where))).round().astype(int)]] = True
    S, J_so, J_st, group = S[keep], J_so[keep], J_st[keep], group[keep]
    ref = group == names[0]
    first = calibrate(S[ref], J_so[ref], J_st[ref], offsets=False, output_correction=False)
    start = (first.tracker, first.fixtures)
    reference = _rms(first.residue)
    found = []
    for g in names[1:]:
        rows = ref | (group == g)
        mine = group[rows] == g

        def joint(signs, rows=rows, mine=mine):
            signal = S[rows].copy()
            signal[mine] *= signs[None, None, :]  # columns are source coils
            fit = calibrate(signal, J_so[rows], J_st[rows], offsets=False, output_correction=False, start=start,
                            max_iterations=max_iterations)
            return _rms(fit.residue[mine])

        as_is = joint(np.ones(3))
        if as_is <= factor * reference:
            continue
        value, signs = min((joint(signs), tuple(signs)) for signs in PATTERNS)
        if value * factor <= as_is:
            found.append(SignFlip(int(g), np.array(signs), reference, as_is, value))
    return found
