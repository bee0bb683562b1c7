"""The recursive fusion pass in NumPy: the same transitions as the compiled kernel, all points of a view at once.

It runs small fusions (fewer points than :data:`~.recursive.COMPILED_MIN_POINTS`, where compiling the
kernel would cost more than it saves) and is the reference the tests compare the kernel with
(``tests/unit/structure/test_point_fusion.py``); the two agree to about 1e-9 relative.
"""

from __future__ import annotations

import numpy as np

from .chunks import Chunk, concat_history
from .inverse_depth import iterated_update, pair_starts, residuals_and_cheirality
from .states import RecursiveStates

__all__ = ["recursive_states_numpy"]


def recursive_states_numpy(job: Chunk) -> RecursiveStates:
    """The reference implementation, vectorised over the points of each view.

    Each point is in one of five states when a view sees it:

    * nothing yet: the view becomes its first pending observation;
    * one pending observation a: the pair (a, v) starts the point *provisionally* if it is
      consistent (χ²(1) test); an inconsistent pair is kept as a *conflict* (a, v);
      a pair without parallax is skipped (the point waits for another view);
    * provisional (started from the pair (a, b)) or conflict (a, b): the view must agree;
      a provisional point updated by it is *verified*; otherwise the triple (a, b, v) is
      resolved (``_resolve``);
    * verified: gated iterated EKF update; a failed gate rejects the observation.
    """
    g, obs = job.geometry, job.observations
    V, n, _ = obs.shape
    seen_all = np.isfinite(obs).all(axis=2)
    theta = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    first = np.full(n, -1)  # the start pair, or the pending observation(s)
    second = np.full(n, -1)
    started = np.zeros(n, dtype=bool)
    verified = np.zeros(n, dtype=bool)
    used = np.zeros((V, n), dtype=bool)
    rejected = np.zeros((V, n), dtype=bool)
    stalled = np.zeros(n, dtype=bool)  # a pair without parallax was met
    restart = np.zeros(n, dtype=np.int64)  # history before this view belongs to an abandoned start
    hist: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    gate1_px = job.gate1 * job.sigma**2

    def resolve(idx: np.ndarray, a: np.ndarray, b: np.ndarray, c: int, provisional: np.ndarray) -> None:
        """Three observations (a, b, c) that do not agree: drop the one whose removal leaves the
        most consistent pair, if that pair is consistent; otherwise drop the oldest, keep a conflict.

        A provisional point whose own pair (a, b) wins keeps its state (c is rejected).
        """
        cv = np.full(idx.size, c)
        hyps = [(b, cv), (a, cv), (a, b)]  # drop a, drop b, drop c
        fits = [pair_starts(g, f, s_, obs, idx, job.scales) for f, s_ in hyps]
        costs = np.stack([f[2] for f in fits], axis=1)
        k = np.argmin(costs, axis=1)
        ok = costs[np.arange(idx.size), k] <= gate1_px
        keep = ok & provisional & (k == 2)
        rejected[c, idx[keep]] = True
        new = ok & ~keep
        dropped = np.where(k == 0, a, np.where(k == 1, b, cv))
        for h, (f, s_) in enumerate(hyps):
            sel = new & (k == h)
            pts = idx[sel]
            theta[pts], cov[pts] = fits[h][0][sel], fits[h][1][sel]
            first[pts], second[pts] = f[sel], s_[sel]
            used[f[sel], pts] = used[s_[sel], pts] = True
            if job.history and pts.size:
                hist.append((c, pts, fits[h][0][sel], fits[h][1][sel]))
        pts = idx[new]
        used[dropped[new], pts], rejected[dropped[new], pts] = False, True
        started[pts], verified[pts] = True, False
        restart[pts] = c
        # no consistent pair: the oldest goes, the other two remain a conflict
        pts = idx[~ok]
        used[a[~ok], pts] = used[b[~ok], pts] = False
        rejected[a[~ok], pts] = True
        theta[pts], cov[pts] = np.nan, np.nan
        started[pts], verified[pts] = False, False
        first[pts], second[pts] = b[~ok], c
        restart[pts] = c + 1

    for v in range(V):
        seen = seen_all[v]
        # states at the start of the view (a point changes state at most once per view)
        verified_now = seen & started & verified
        provisional_now = seen & started & ~verified
        single_now = seen & ~started & (first >= 0) & (second < 0)
        conflict_now = seen & ~started & (second >= 0)
        empty_now = seen & ~started & (first < 0)

        # updates: gated iterated EKF, all points at once
        idx = np.flatnonzero(verified_now | provisional_now)
        if idx.size:
            up = iterated_update(g.Q[first[idx], v], theta[idx], cov[idx], obs[v, idx], job.sigma, job.gate2,
                                 None if job.scales is None else job.scales[v, idx])
            th, P, ok = up.states, up.covariances, up.accepted
            acc = idx[ok]
            theta[acc], cov[acc] = th[ok], P[ok]
            used[v, acc] = True
            verified[acc] = True
            rejected[v, idx[~ok & verified_now[idx]]] = True
            if job.history:
                hist.append((v, acc, th[ok], P[ok]))
            fail = idx[~ok & provisional_now[idx]]
            if fail.size:
                resolve(fail, first[fail], second[fail], v, np.ones(fail.size, dtype=bool))
        # second observation: a provisional start or a conflict
        idx = np.flatnonzero(single_now)
        if idx.size:
            th, P, cost = pair_starts(g, first[idx], np.full(idx.size, v), obs, idx, job.scales)
            usable = np.isfinite(cost)
            stalled[idx[~usable]] = True  # no parallax with the pending view: wait for another view
            go_mask = usable & (cost <= gate1_px)
            go = idx[go_mask]
            theta[go], cov[go], second[go], started[go] = th[go_mask], P[go_mask], v, True
            used[first[go], go] = used[v, go] = True
            second[idx[usable & ~go_mask]] = v
            if job.history and go.size:
                hist.append((v, go, th[go_mask], P[go_mask]))
        idx = np.flatnonzero(conflict_now)
        if idx.size:
            resolve(idx, first[idx], second[idx], v, np.zeros(idx.size, dtype=bool))
        first[empty_now] = v

    anchor = np.where(started, first, -1)
    residuals, in_front = residuals_and_cheirality(g, obs, theta, anchor, started, used)
    history = None
    if job.history:
        views, pts, th, P = concat_history(hist)
        current = views >= restart[pts]  # the estimates of the point's final start only
        history = (views[current], pts[current], th[current], P[current])
    return RecursiveStates(theta, cov, anchor, started, stalled, used, rejected, residuals, in_front, history)
