"""Accuracy figures: RMSE between two results, NEES against a ground truth.

Both results compared must be in the same frame (the benchmark's convention: pose 0); RMSE is
per coordinate with no alignment, as in the datasets README:
``sqrt(sum_k |p_k - q_k|^2 / (dim * N))``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.stats

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, to_dense

FloatArray = npt.NDArray[np.float64]


def positions(local_map: LocalMap, kind: int) -> dict[int, FloatArray]:
    """Return ``{id: position}`` of the poses (translation) or features of a map."""
    out = {}
    for i in np.flatnonzero(local_map.kinds == kind).tolist():
        off = int(local_map.offsets[i])
        out[int(local_map.ids[i])] = local_map.x[off : off + local_map.dim]
    if kind == POSE:
        out.setdefault(local_map.frame_id, np.zeros(local_map.dim))
    return out


def rmse(estimate: LocalMap, reference: LocalMap, kind: int) -> float:
    """Return the per-coordinate RMSE of pose (``POSE``) or feature (``FEATURE``) positions.

    Only ids present in both maps count; the frame pose counts as the origin.

    Raises:
        FrameError: the maps are in different frames.
        InvalidMapError: they share no variable of that kind.
    """
    if estimate.frame_id != reference.frame_id:
        raise FrameError(
            f"RMSE needs both maps in one frame: {estimate.name!r} is in pose {estimate.frame_id}, "
            f"{reference.name!r} in pose {reference.frame_id}"
        )
    a, b = positions(estimate, kind), positions(reference, kind)
    if kind == POSE:
        a.pop(estimate.frame_id, None)
        b.pop(reference.frame_id, None)
    common = sorted(set(a) & set(b))
    if not common:
        raise InvalidMapError(f"maps {estimate.name!r} and {reference.name!r} share no {'pose' if kind == POSE else 'feature'}")
    diff = np.stack([a[k] - b[k] for k in common])
    return float(np.sqrt(np.sum(diff * diff) / diff.size))


@dataclass(frozen=True)
class NeesResult:
    """Normalised estimation error squared and its chi-square bounds.

    Attributes:
        nees: ``e^T I_marginal e``.
        dof: number of scalars compared.
        lower, upper: two-sided ``confidence`` interval of a chi-square with ``dof`` degrees.
        bound: the one-sided ``confidence`` quantile of that chi-square, the paper's test (Table 3:
            1306.5 for 1224 scalars at 95%).
    """

    nees: float
    dof: int
    lower: float
    upper: float
    bound: float

    @property
    def consistent(self) -> bool:
        """Whether ``nees`` is within :attr:`bound` (the paper's one-sided test)."""
        return self.nees <= self.bound


def nees(
    estimate: LocalMap,
    truth: Mapping[tuple[int, int], FloatArray],
    kinds: Sequence[int] = (POSE, FEATURE),
    confidence: float = 0.95,
) -> NeesResult:
    """Return the NEES of the variables of the given kinds against ``truth``.

    Args:
        estimate: the map, with information, in the frame ``truth`` is given in.
        truth: ``{(kind, id): true value}`` for every variable compared.
        kinds: which variable kinds to compare; the others are marginalised out.
        confidence: the chi-square test's probability (one-sided :attr:`NeesResult.bound`; the
            two-sided interval ``lower``, ``upper`` has the same probability).
    """
    selected = [i for i in range(estimate.n_vars) if int(estimate.kinds[i]) in kinds]
    idx = estimate.scalar_index(np.array(selected, dtype=np.int64))
    err = np.empty(idx.size)
    pos = 0
    for i in selected:
        key = (int(estimate.kinds[i]), int(estimate.ids[i]))
        if key not in truth:
            raise InvalidMapError(f"no ground truth for {'pose' if key[0] == POSE else 'feature'} {key[1]}")
        sl = estimate.scalar_slice(i)
        e = estimate.x[sl] - truth[key]
        if key[0] == POSE:
            e[estimate.dim :] = wrap_angle(e[estimate.dim :])
        err[pos : pos + e.size] = e
        pos += e.size
    info = to_dense(estimate.info)
    cov = np.linalg.inv(info)
    marginal_cov = cov[np.ix_(idx, idx)]
    value = float(err @ np.linalg.solve(marginal_cov, err))
    dof = int(idx.size)
    alpha = 1.0 - confidence
    lower, upper, bound = (float(q) for q in np.atleast_1d(scipy.stats.chi2.ppf([alpha / 2, 1 - alpha / 2, confidence], dof)))
    return NeesResult(value, dof, lower, upper, bound)


__all__ = ["rmse", "nees", "NeesResult", "positions"]
