"""What material recognition does to delay profiles before and around the SVM (#55): spatial pooling that never
crosses an object's boundary, folding about t_d = 0, cross-validation over spatial blocks, and a calibrated flag for
pixels unlike every trained material.

- **Pooling.** A pixel's profile is noisy (a 12-bit sensor, shot noise); its neighbours on the same object share its
  material. :func:`pool` averages the frames (counts, before normalising by area) over a window of neighbours that
  lie in the same *region*: the labelled object while training (the user drew it), superpixels of the profiles when
  classifying (:func:`superpixels`: scikit-image's SLIC on the standardised profiles, so a region follows the edges
  where the profile's shape changes). Measured on the materials dev set (docs/results.md): a plain RBF SVM goes from
  52 % per pixel to 70 % with 9 × 9 pooling inside each slab.
- **Folding.** A rectified rig lights row s + o and row s − o alike in a homogeneous medium, so the profile at
  +t_d and −t_d (about the direct light's delay) measure the same light: their sum halves the noise's variance
  (:func:`zero_of` finds the fold; ``delay_profiles`` folds).
- **Smoothing the class probabilities.** Pooling averages profiles; the SVM's class probabilities (Platt's) are
  then filtered over a neighbourhood by a guided filter (He, Sun and Tang 2013; OpenCV's ``ximgproc.guidedFilter``)
  whose guide is the log of the regular image: a soft spatial prior that follows the image's edges (an object's
  boundary is an edge in brightness), where a hard segmentation cuts a slab's edge strips into regions of their own.
  :func:`guided_smooth`; its radius is ``train_material_classifier``'s ``smooth_px`` (docs/results.md: chosen by
  cross-validation over row bands of the dev set's training placement).
- **Objects.** Pooling and smoothing act over a fixed neighbourhood; a capture of separate objects on a background
  (the dev set's slabs before a wall) is better served by finding the objects and letting each take the class most
  of its known pixels take (:func:`objects`, :func:`vote`). The objects are grown from the pixels the classifier
  knows (those within the calibrated novelty distance): their connected cores seed a watershed (scikit-image) on
  the gradient of the regular image's log, the rest of the frame seeds the background some pixels away from every
  core, and the band between goes to whichever side the brightness edge puts it on. An object's edge strip, where
  light leaks out of its sides and its profile narrows, then takes its interior's class and is not flagged
  (docs/results.md: on the dev set's test placement 90.8 % per pixel against 76.7 % smoothed alone, the slabs'
  pixels flagged 14.4 % against 24.9 %).
- **Spatial blocks.** Neighbouring pixels share light and noise, so cross-validation over random pixels leaks:
  folds are bands of rows (:func:`row_blocks`), as a new capture shares no pixel with the training one.
- **Unlike training.** A pixel's distance to its nearest training pixels (k = 5, in the SVM's standardised space) is
  compared with a threshold calibrated out of fold: each fold's pixels scored against the other folds' (split
  conformal, cross-fitted), the threshold the (1 − ``flag_rate``) quantile. On data like the training capture's, at
  most ``flag_rate`` of a trained material's pixels are flagged.
"""

from __future__ import annotations

import numpy as np

from selpath.pipeline.errors import Problem, StageError

#: spatial blocks of the cross-validation per fold (bands of rows over the labelled pixels' span)
BLOCKS_PER_FOLD = 2
#: the guided filter's regularisation ε, on the guide's [0, 1] scale (docs/results.md: 1e-2 and 1e-3 within a point)
GUIDED_EPS = 1e-2
#: neighbours whose mean distance scores a pixel's novelty
NEIGHBOURS = 5
#: an object's core: at least this many connected pixels within the novelty distance [px]
OBJECT_MIN_PX = 30


def pool(frames: np.ndarray, regions: np.ndarray, window: int) -> np.ndarray:
    """The mean of ``frames`` (delay, row, col) over a ``window`` × ``window`` neighbourhood restricted to each pixel's
    own region (``regions``: (row, col) integer codes; negative: no region, left as it is). Window 1: unchanged.

    >>> frames = np.arange(8.0).reshape(1, 2, 4)
    >>> pool(frames, np.array([[0, 0, 1, 1], [0, 0, 1, 1]]), 3)[0].round(6).tolist()
    [[2.5, 2.5, 4.5, 4.5], [2.5, 2.5, 4.5, 4.5]]
    """
    from scipy.ndimage import uniform_filter  # scipy when it computes, not when a workflow is read

    if window <= 1:
        return frames
    from scipy.ndimage import find_objects

    out = frames.copy()
    finite = np.isfinite(frames).all(axis=0)
    codes = np.where(regions >= 0, regions, -1).astype(np.int64)
    half = window // 2
    # each region filtered inside its own bounding box (padded by half a window): linear in the frame's size
    for code, box in enumerate(find_objects(codes + 1)):
        if box is None:
            continue
        rows = slice(max(box[0].start - half, 0), min(box[0].stop + half, codes.shape[0]))
        cols = slice(max(box[1].start - half, 0), min(box[1].stop + half, codes.shape[1]))
        inside = ((codes[rows, cols] == code) & finite[rows, cols]).astype(float)
        part = frames[:, rows, cols]
        total = uniform_filter(np.where(inside[None] > 0, part, 0.0), size=(1, window, window), mode="constant")
        count = uniform_filter(inside, size=window, mode="constant")
        here = inside > 0
        out[:, rows, cols][:, here] = total[:, here] / count[here]
    return out


def guided_smooth(scores: np.ndarray, area: np.ndarray, usable: np.ndarray, radius: int,
                  eps: float = GUIDED_EPS) -> np.ndarray:
    """Each class's score map of ``scores`` (row, col, class) filtered by a guided filter of ``radius`` [px] whose
    guide is log ``area`` (the regular image) scaled to [0, 1] over the ``usable`` pixels (so ``eps`` means the same
    on any intensity scale); unusable pixels take the guide's minimum and score 0 in every class.
    Radius 0: unchanged.

    >>> scores = np.zeros((8, 8, 2), np.float32); scores[..., 0] = 1.0; scores[3, 3] = (0.0, 1.0)
    >>> area = np.full((8, 8), 100.0); usable = np.ones((8, 8), bool)
    >>> [round(float(v), 2) for v in guided_smooth(scores, area, usable, 2)[3, 3]]  # an odd pixel: outvoted 24 to 1
    [0.96, 0.04]
    """
    if radius <= 0:
        return scores
    import cv2

    log = np.log(np.where(usable & (area > 0), area, np.nan))
    low, high = np.nanmin(log, initial=np.inf), np.nanmax(log, initial=-np.inf)
    if not np.isfinite(low):
        return scores
    guide = np.where(np.isfinite(log), (log - low) / max(high - low, 1e-12), 0.0).astype(np.float32)
    values = np.where(usable[..., None], scores, 0.0).astype(np.float32)
    return np.stack([cv2.ximgproc.guidedFilter(guide, np.ascontiguousarray(values[..., k]), int(radius), eps)
                     for k in range(values.shape[-1])], axis=-1)


def objects(distance: np.ndarray, threshold: float, area: np.ndarray, usable: np.ndarray, margin: int,
            min_px: int = OBJECT_MIN_PX) -> np.ndarray:
    """Objects of trained materials in a frame: (row, col) codes 1 … n, 0 for the background, −1 where a pixel is not
    ``usable``.

    Cores are the usable pixels whose novelty ``distance`` is at most ``threshold`` (the classifier's calibrated
    ``novelty_distance``), opened by one pixel and kept where at least ``min_px`` connect (8-connected); the other
    usable pixels more than ``margin`` [px] from every core (Euclidean) seed the background; a watershed on the Sobel
    gradient of log ``area`` (the regular image: any intensity scale) assigns the pixels between to a core or to the
    background, so an object ends at its edge in brightness. No core: everything is background.

    >>> area = np.full((12, 12), 10.0); area[2:10, 3:8] = 40.0          # one bright object on a wall
    >>> distance = np.where(area > 20, 0.5, 5.0); distance[2:10, 3] = 5.0  # its left column looks unlike training
    >>> found = objects(distance, 1.0, area, np.ones((12, 12), bool), margin=2, min_px=4)
    >>> bool((found[3:9, 3] == 1).all()), int((found[area < 20] == 1).sum())  # the column joins it; the wall does not
    (True, 0)
    """
    from scipy import ndimage
    from skimage.filters import sobel
    from skimage.segmentation import watershed

    usable = np.asarray(usable, bool) & np.isfinite(area) & (np.asarray(area) > 0)
    core = ndimage.binary_opening(usable & (np.nan_to_num(distance, nan=np.inf) <= threshold))
    codes, count = ndimage.label(core, structure=np.ones((3, 3)))
    sizes = np.bincount(codes.ravel(), minlength=count + 1)
    keep = sizes >= min_px
    keep[0] = False
    if not keep.any():
        return np.where(usable, 0, -1)
    renumber = np.zeros(count + 1, np.int64)
    renumber[keep] = np.arange(1, int(keep.sum()) + 1)
    markers = renumber[codes]
    background = int(keep.sum()) + 1
    markers[usable & (ndimage.distance_transform_edt(markers == 0) > margin)] = background
    log = np.log(np.where(usable, area, 1.0))
    log = np.where(usable, log, log[usable].min())
    found = watershed(sobel(log), markers, mask=usable)
    return np.where(usable, np.where(found == background, 0, found), -1)


def vote(label: np.ndarray, regions: np.ndarray, voters: np.ndarray | None = None) -> np.ndarray:
    """``label`` (row, col; class index, −1 none) with every pixel of a region of ``regions`` (codes ≥ 1) given the
    class most of that region's classified ``voters`` take (ties: the lower index; None: every pixel votes; a region
    without a voter keeps its pixels' own); pixels of code ≤ 0, and unclassified pixels (−1), keep their own.

    >>> label, regions = np.array([[0, 1, 1, 2], [1, 1, -1, 2]]), np.array([[1, 1, 1, 0], [1, 1, 1, 0]])
    >>> vote(label, regions).tolist()
    [[1, 1, 1, 2], [1, 1, -1, 2]]
    >>> vote(label, regions, voters=label == 0).tolist()  # only the pixels the classifier knows vote
    [[0, 0, 0, 2], [0, 0, -1, 2]]
    """
    label = np.asarray(label)
    regions = np.asarray(regions)
    inside = (regions > 0) & (label >= 0) & (True if voters is None else np.asarray(voters, bool))
    classes = int(label.max(initial=0)) + 1
    counts = np.zeros((int(regions.max(initial=0)) + 1, classes), np.int64)
    np.add.at(counts, (regions[inside], label[inside]), 1)
    winner = np.where(counts.sum(axis=1) > 0, counts.argmax(axis=1), -1)[np.maximum(regions, 0)]
    return np.where((regions > 0) & (winner >= 0) & (label >= 0), winner, label).astype(label.dtype)


def kept_delays(delay: np.ndarray, window_us: float | None) -> np.ndarray:
    """Which of ``delay`` [µs] a window keeps, |t_d| ≤ ``window_us`` (None: all); a window keeping fewer than 2 is
    refused."""
    delay = np.asarray(delay, float)
    keep = np.ones(delay.shape, bool) if window_us is None else np.abs(delay) <= window_us * (1 + 1e-9)
    if keep.sum() < 2:
        raise StageError(Problem(f"a window of ±{window_us:g} µs keeps {int(keep.sum())} of the profiles' delays "
                                 f"({delay[0]:g} … {delay[-1]:g} µs); a profile needs 2", fix="widen the window"))
    return keep


def zero_of(delays: np.ndarray) -> int:
    """The index of t_d = 0 in a delay grid symmetric about it (ValueError otherwise: it cannot be folded)."""
    delays = np.asarray(delays, dtype=float)
    zero = int(np.argmin(np.abs(delays)))
    if delays.size % 2 == 0 or not np.allclose(delays, -delays[::-1]) or delays[zero] != 0:
        raise ValueError(f"folding needs delays symmetric about 0 with 0 among them; these run {delays[0]:g} … "
                         f"{delays[-1]:g} µs ({delays.size})")
    return zero


def superpixels(profile: np.ndarray, pixels_per_region: int, usable: np.ndarray) -> np.ndarray:
    """Regions of about ``pixels_per_region`` pixels whose profiles are alike (SLIC on the profiles, each delay
    standardised, lightly smoothed, compactness 0.1); −1 where a pixel has no usable profile."""
    from scipy.ndimage import uniform_filter
    from skimage.segmentation import slic

    image = np.moveaxis(np.where(usable[None], profile, 0.0), 0, -1)
    image = uniform_filter(image, size=(3, 3, 1))
    spread = image[usable].std(axis=0)
    image = (image - image[usable].mean(axis=0)) / np.where(spread > 0, spread, 1.0)
    count = max(1, int(round(usable.sum() / pixels_per_region)))
    regions = slic(image, n_segments=count, compactness=0.1, channel_axis=-1, start_label=0, mask=usable)
    return np.where(usable, regions, -1)


def row_blocks(rows: np.ndarray, count: int) -> np.ndarray:
    """Each pixel's spatial block: ``count`` bands of equal height over the rows the pixels span.

    >>> row_blocks(np.array([40, 41, 60, 79]), 4).tolist()
    [0, 0, 2, 3]
    """
    rows = np.asarray(rows)
    low, span = rows.min(), rows.max() - rows.min() + 1
    return np.minimum((rows - low) * count // span, count - 1)


def block_folds(folds: int, seed: int):
    """Folds of spatial blocks, each class in every fold as far as the blocks allow (scikit-learn's
    ``StratifiedGroupKFold``, shuffled by ``seed``)."""
    from sklearn.model_selection import StratifiedGroupKFold

    return StratifiedGroupKFold(folds, shuffle=True, random_state=seed)


def widest_within_error(results: list[dict], best: list[int], folds: int) -> int:
    """Of candidates ordered narrowest to widest, each with its grid search's ``cv_results_`` and ``best_index_``, the
    widest whose best mean score lies within one standard error (std over the folds / √folds) of the best candidate's
    (Breiman's one-standard-error rule, the wider side preferred: fewer choices made on noise).

    >>> widest_within_error([{"mean_test_score": [0.90], "std_test_score": [0.02]},
    ...                      {"mean_test_score": [0.95], "std_test_score": [0.02]},
    ...                      {"mean_test_score": [0.94], "std_test_score": [0.02]}], [0, 0, 0], 4)
    2
    """
    means = [float(r["mean_test_score"][k]) for r, k in zip(results, best, strict=True)]
    top = int(np.argmax(means))
    floor = means[top] - float(results[top]["std_test_score"][best[top]]) / np.sqrt(folds)
    return max(k for k, m in enumerate(means) if m >= floor)


def novelty_threshold(standard: np.ndarray, truth: np.ndarray, blocks: np.ndarray, folds: int, seed: int,
                      flag_rate: float) -> float:
    """Cross-fitted split-conformal threshold on the mean distance to the :data:`NEIGHBOURS` nearest training pixels:
    each fold of blocks scored against the others, the (1 − ``flag_rate``) quantile (finite-sample corrected, the
    next score up). The rate holds over the training pixels of all materials together, not per material; each
    held-out score has (folds − 1)/folds of the pixels for neighbours, so on new data like the training capture's
    the flagged share is at most about ``flag_rate``."""
    from sklearn.neighbors import NearestNeighbors

    scores = np.empty(len(standard))
    for fit, held in block_folds(folds, seed).split(standard, truth, groups=blocks):
        scores[held] = NearestNeighbors(n_neighbors=NEIGHBOURS).fit(standard[fit]).kneighbors(
            standard[held])[0].mean(axis=1)
    level = min(1.0, np.ceil((1 - flag_rate) * (len(scores) + 1)) / len(scores))
    return float(np.quantile(scores, level, method="higher"))


def training_sample(codes: np.ndarray, flags: np.ndarray, names: tuple[str, ...], per_class: int, folds: int,
                    seed: int) -> np.ndarray:
    """Flat indices of up to ``per_class`` labelled pixels with usable profiles of each class (seeded)."""
    rng = np.random.default_rng(seed)
    usable = (flags == 0).ravel()
    chosen, problems = [], []
    for k, name in enumerate(names, start=1):
        labelled = codes.ravel() == k
        index = np.flatnonzero(labelled & usable)
        if labelled.any() and index.size < folds:
            problems.append(Problem(f"class {name!r} has {index.size} labelled pixels with a usable profile (of "
                                    f"{int(labelled.sum())} labelled; the rest have zero area, or are saturated "
                                    f"or missing); cross-validation over {folds} folds needs {folds}",
                                    fix="label more pixels of it, or check its frames"))
        chosen.append(rng.choice(index, min(per_class, index.size), replace=False) if index.size else index)
    present = [name for k, name in enumerate(names, start=1) if (codes == k).any()]
    if len(present) < 2:
        problems.append(Problem(f"the labels hold {len(present)} class(es) {present}: a classifier needs at least 2",
                                fix="label pixels of at least two materials"))
    if problems:
        raise StageError(problems)
    return np.concatenate(chosen)
