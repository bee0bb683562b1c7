"""Rauch–Tung–Striebel smoothing of finished tracks, computed from the :class:`Tracks` alone.

The tracker runs its Kalman filter online and records, per frame and track, the
posterior state s_t and covariance Σ_t (the prediction while the track coasts).
Every track lives on its own interval of frames:

* frame ``s`` (its first frame, status initialising): the given or detected
  position, velocity 0 — not a filter estimate;
* frame ``s + 1`` (initialising, or predicted when the start-up search failed): the
  filter starts there with s0 = [x₁, y₁, x₁ - x₀, y₁ - y₀] and Σ0;
* frames ``s + 2 … e``: predict s⁻_t = F s_{t-1}, Σ⁻_t = F Σ_{t-1} Fᵀ + Q, then
  update (measured) or not (coasting: s_t = s⁻_t, Σ_t = Σ⁻_t);
* after ``e`` the track is lost (NaN) or the sequence ends.

The priors are therefore F s_{t-1} and F Σ_{t-1} Fᵀ + Q of the recorded
posteriors, and the filter chain ``s + 1 … e`` of every track is smoothed with
:func:`kalmansfm.estimation.smooth`, all tracks at once.  Frames ``s + 2 … e`` get
the smoothed estimates.  The filter's initial state at ``s + 1`` keeps its recorded
value: its position is a template match as accurate as any other (about 0.2 px
on the built-in scene), but its covariance is the start-up Σ0 (10 px standard
deviation by default), so its smoothed value would be mostly the motion model's
backward extrapolation from ``s + 2`` — on the built-in scene that made frame 1
worse (0.16 → 0.22 px RMS over 30 frames, 0.19 → 1.05 px over 8 faster frames).  Frames outside a track's
chain are filled so that they cannot influence it: before the chain any finite
state with a positive-definite covariance (they come earlier in time, and the
backward pass never carries information forwards); after the chain the filler's
prior equals its posterior, so the smoother's correction C (ŝ_{t+1} - s⁻_{t+1})
is exactly zero there.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError
from ..estimation.models import LinearGaussianModel, constant_velocity_2d
from ..estimation.smoothing import FilterRun, smooth
from .tracks import INITIALISING, PREDICTED, Tracks

__all__ = ["smooth_tracks"]

# (frames × tracks) per chunk of the backward pass: bounds the temporary (frames, chunk, 4, 4) arrays.
_CHUNK_ELEMENTS = 1 << 20


def _chains(tracks: Tracks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per track: first and last frame of its filter chain, and whether it has a step to smooth (>= 2 frames)."""
    alive = tracks.alive
    F = tracks.n_frames
    any_alive = alive.any(axis=0)
    first = np.where(any_alive, np.argmax(tracks.status != 0, axis=0), F)
    last = np.where(any_alive, F - 1 - np.argmax(alive[::-1], axis=0), -1)
    start = first + 1
    has_chain = any_alive & (last > start)
    # A chain must be contiguous: alive from its first frame to its last.
    frames = np.arange(F)[:, None]
    inside = (frames >= first) & (frames <= last)
    gap = inside & ~alive
    if gap.any():
        f, p = np.argwhere(gap)[0]
        raise InvalidInputError(
            f"track id {tracks.track_ids[p]} has status {tracks.status[f, p]} in frame {f}, between its first "
            f"frame {first[p]} and its last frame {last[p]} with a position; a track must be initialising, "
            f"measured or predicted (status 4, 1 or 2) on every frame of its life"
        )
    return start, last, has_chain


def _restarted_chains(tracks: Tracks) -> tuple[np.ndarray, np.ndarray] | None:
    """Tracks with more than one filter chain — lost, then found again and restarted (initialising) under their
    id — as one column per chain: (original column of each, (frames, chains) frames of each); None if none.

    A later chain that does not restart (a gap inside a track) is left to :func:`_chains`, which refuses it.
    """
    alive = tracks.alive
    begins = alive & ~np.vstack([np.zeros((1, alive.shape[1]), bool), alive[:-1]])
    count = begins.sum(axis=0)
    if not (count > 1).any():
        return None
    label = np.cumsum(begins, axis=0)  # chain number of each frame, 0 before the first
    later = begins & (label > 1)
    if (tracks.status[later] != INITIALISING).any():
        return None
    per_column = np.maximum(count, 1)
    columns = np.repeat(np.arange(alive.shape[1]), per_column)
    chain = np.arange(columns.size) - np.repeat(np.cumsum(per_column) - per_column, per_column) + 1
    inside = (label[:, columns] == chain[None, :]) | (count[columns] <= 1)[None, :]
    return columns, inside


def _check_chain_values(tracks: Tracks, in_chain: np.ndarray) -> None:
    states_ok = np.isfinite(tracks.states).all(axis=-1)
    cov_ok = np.isfinite(tracks.covariances).all(axis=(-2, -1))
    bad = in_chain & ~(states_ok & cov_ok)
    if bad.any():
        f, p = np.argwhere(bad)[0]
        what = "state" if not states_ok[f, p] else "covariance"
        raise InvalidInputError(
            f"track id {tracks.track_ids[p]} frame {f}: the {what} is not finite; smoothing needs the full "
            f"states (F, P, 4) and covariances (F, P, 4, 4) of the tracker (a tracks.npz, not a tracks.csv, "
            f"which holds only the position standard deviations)"
        )


def _check_model(tracks: Tracks, x_prior: np.ndarray, P_prior: np.ndarray,
                 coasting: np.ndarray) -> None:
    """A coasting frame's posterior is the model's prediction; if not, the model is not the tracker's."""
    if not coasting.any():
        return
    state_error = np.abs(tracks.states[coasting] - x_prior[coasting]).max(axis=-1)
    cov_scale = np.abs(P_prior[coasting]).max(axis=(-2, -1))
    cov_error = np.abs(tracks.covariances[coasting] - P_prior[coasting]).max(axis=(-2, -1))
    state_scale = 1.0 + np.abs(tracks.states[coasting]).max(axis=-1)
    wrong = (state_error > 1e-6 * state_scale) | (cov_error > 1e-6 * cov_scale)
    if wrong.any():
        k = int(np.argmax(wrong))
        f, p = np.argwhere(coasting)[k]
        raise InvalidInputError(
            f"track id {tracks.track_ids[p]} coasts in frame {f}, but its covariance is not F Σ Fᵀ + Q of the "
            f"previous frame (largest difference {cov_error[k]:.3g}, state difference {state_error[k]:.3g}); "
            f"the tracks were made with another motion model: pass the tracker's model as model="
        )


def _columns(tracks: Tracks, cols: np.ndarray) -> Tracks:
    return Tracks(positions=tracks.positions[:, cols], states=tracks.states[:, cols],  # type: ignore[index]
                  covariances=tracks.covariances[:, cols], status=tracks.status[:, cols],  # type: ignore[index]
                  track_ids=tracks.track_ids[cols])


def _smooth_part(part: Tracks, start: np.ndarray, last: np.ndarray, model: LinearGaussianModel,
                 lag: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed states and covariances of tracks that all have a chain (filler outside it)."""
    T, N = part.status.shape
    frames = np.arange(T)[:, None]
    in_chain = (frames >= start) & (frames <= last)
    # Fillers: before the chain its first posterior, after it its last one, symmetrised so
    # that the smoother's own symmetrisation leaves them bit for bit unchanged.
    anchor = np.where(in_chain, frames, np.where(frames < start, start, last))
    x = part.states[anchor, np.arange(N)]
    P = part.covariances[anchor, np.arange(N)]
    P[~in_chain] = 0.5 * (P[~in_chain] + np.swapaxes(P[~in_chain], -1, -2))

    # Inside the chain (t > start): x⁻_t = F x_{t-1},  P⁻_t = F P_{t-1} Fᵀ + Q.
    # Elsewhere the prior is the filler itself, so the smoother's correction there is exactly 0.
    linked = in_chain & (frames > start)
    x_prior = x.copy()
    P_prior = P.copy()
    x_prior[1:] = np.where(linked[1:, :, None], x[:-1] @ model.F.T, x[1:])
    P_prior[1:] = np.where(linked[1:, :, None, None], model.F @ P[:-1] @ model.F.T + model.Q, P[1:])
    _check_model(part, x_prior, P_prior, linked & (part.status == PREDICTED))

    nan = np.full((T, N), np.nan)
    run = FilterRun(x_initial=x[0], P_initial=P[0], x_prior=x_prior, P_prior=P_prior, x=x, P=P,
                    F=np.broadcast_to(model.F, (T, 4, 4)), nis=nan, log_likelihood=nan)
    result = smooth(run, lag=lag)
    # The filter's initial state keeps its recorded value (module notes).
    return (np.where(linked[..., None], result.x, part.states),
            np.where(linked[..., None, None], result.P, part.covariances))


def smooth_tracks(tracks: Tracks, *, model: LinearGaussianModel | None = None, lag: int | None = None) -> Tracks:
    """Rauch–Tung–Striebel smoothed tracks: every estimate given the whole sequence (or ``lag`` frames ahead).

    Each track is smoothed over its own filter chain (from the frame after its first
    frame, where the filter starts, to its last frame with a position), all tracks at
    once with :func:`kalmansfm.estimation.smooth`; see the module notes for how the
    priors are rebuilt from the recorded posteriors.  The first two frames of a track
    (its given or detected position, and the filter's initial state; module notes)
    and frames without a position are left as they are,
    and so are the status codes and scores: a coasting frame stays "predicted", with
    the smoothed position.

    Parameters
    ----------
    tracks : the tracker's output (:func:`kalmansfm.track`, or a ``tracks.npz``); the
        states and full covariances are needed.
    model : the tracker's motion model; default the model of ``tracks.settings`` (the
        settings the tracker ran with), or the default constant-velocity model when the
        tracks carry no settings.  Only F and Q are used.  A coasting
        frame whose covariance is not F Σ Fᵀ + Q of the frame before reveals a wrong
        model and raises.
    lag : None for fixed-interval smoothing (every frame uses all measurements of
        its track); an integer L >= 0 for fixed-lag smoothing (frame t uses the
        measurements up to frame t + L; 0 returns the filtered tracks).

    Returns
    -------
    Tracks
        A new object with smoothed ``states``, ``covariances`` and ``positions``;
        ``smoothed`` is True (fixed interval) or the lag.

    Raises
    ------
    InvalidInputError
        Tracks already smoothed, a non-finite state or covariance inside a track's
        life (e.g. tracks read from a ``tracks.csv``), a gap in a track, a model
        that does not match, or a bad ``lag``.

    Examples
    --------
    >>> import cv2
    >>> from kalmansfm.tracking import track
    >>> rng = np.random.default_rng(2)
    >>> world = cv2.GaussianBlur(rng.uniform(0, 255, (100, 160)), (0, 0), 1.5)
    >>> frames = [world[20:80, 20 + k: 100 + k] for k in range(8)]   # 1 px left per frame
    >>> filtered = track(frames, np.array([[40.0, 30.0], [50.0, 20.0]]))
    >>> smoothed = smooth_tracks(filtered)
    >>> smoothed.smoothed, smoothed.status.tolist() == filtered.status.tolist()
    (True, True)
    >>> bool(np.all(smoothed.position_std[2:] <= filtered.position_std[2:] + 1e-12))   # never less certain
    True
    """
    if not isinstance(tracks, Tracks):
        raise InvalidInputError(f"smooth_tracks expects Tracks (from kalmansfm.track); got {type(tracks).__name__}")
    if lag is not None and (isinstance(lag, bool) or int(lag) != lag or lag < 0):
        raise InvalidInputError(f"lag must be None or an integer >= 0 (frames); got {lag!r}")
    if tracks.smoothed is not False:
        raise InvalidInputError(
            f"these tracks are already smoothed (smoothed = {tracks.smoothed!r}); smoothing needs the tracker's "
            f"filtered tracks"
        )
    if tracks.states is None or tracks.covariances is None:
        raise InvalidInputError(
            "smoothing needs the tracker's states (F, P, 4) and covariances (F, P, 4, 4): a tracks.npz, not a "
            "CSV of positions"
        )
    if model is None:
        model = tracks.settings.model if tracks.settings is not None else constant_velocity_2d()
    if model.F.shape != (4, 4) or model.Q.shape != (4, 4):
        raise InvalidInputError(f"model must have a 4-state F and Q; got F {model.F.shape}, Q {model.Q.shape}")
    restarted = _restarted_chains(tracks)
    if restarted is not None:  # tracks found again after a loss: each chain smoothed on its own
        columns, inside = restarted
        f, j = np.nonzero(inside)
        virtual = Tracks(positions=np.where(inside[..., None], tracks.positions[:, columns], np.nan),
                         status=np.where(inside, tracks.status[:, columns], 0),
                         track_ids=np.arange(len(columns)),
                         states=np.where(inside[..., None], tracks.states[:, columns], np.nan),
                         covariances=np.where(inside[..., None, None], tracks.covariances[:, columns], np.nan),
                         settings=tracks.settings)
        done = smooth_tracks(virtual, model=model, lag=lag)
        positions, states, covariances = tracks.positions.copy(), tracks.states.copy(), tracks.covariances.copy()
        positions[f, columns[j]] = done.positions[f, j]
        states[f, columns[j]] = done.states[f, j]
        covariances[f, columns[j]] = done.covariances[f, j]
        return tracks.replace(positions=positions, states=states, covariances=covariances, smoothed=done.smoothed)
    start, last, has_chain = _chains(tracks)
    frames = np.arange(tracks.n_frames)[:, None]
    in_chain = (frames >= start) & (frames <= last) & has_chain
    _check_chain_values(tracks, in_chain)
    changed = in_chain & (frames > start)

    states = tracks.states.copy()
    covariances = tracks.covariances.copy()
    chained = np.flatnonzero(has_chain)
    step = max(1, _CHUNK_ELEMENTS // max(tracks.n_frames, 1))
    for begin in range(0, len(chained), step):
        cols = chained[begin:begin + step]
        states[:, cols], covariances[:, cols] = _smooth_part(
            _columns(tracks, cols), start[cols], last[cols], model, None if lag is None else int(lag)
        )
    positions = tracks.positions.copy()
    positions[changed] = states[changed][:, :2]
    return tracks.replace(positions=positions, states=states, covariances=covariances,
                          smoothed=True if lag is None else int(lag))
