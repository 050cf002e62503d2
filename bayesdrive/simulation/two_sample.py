"""An automated Turing test: a classifier two-sample test between real and generated trajectories.

The paper asked 21 people whether clips were real. Here a classifier (L2-regularised logistic
regression on standardised trajectory features) tries to tell real from generated segments under
stratified k-fold cross-validation; its held-out accuracy, with a Wilson 95% interval, is the
verdict: 50% means indistinguishable (Lopez-Paz & Oquab 2017). Cross-validated accuracies are not
independent Bernoulli trials (the folds share training data), so a binomial p-value is
anticonservative; the p-value for "better than chance" comes from a label-permutation test with
the same folds, and the Wilson interval is labelled approximate. Features describe one vehicle's segment: speed level and spread, gap
level and minimum, acceleration spread and jerk.

A linear boundary on six summaries makes "indistinguishable" easy to claim, so a second, stronger
discriminator sits beside it (:func:`boosted_two_sample_test`): gradient-boosted trees
(scikit-learn's ``HistGradientBoostingClassifier``) on the within-segment distributions of the
per-step series, speed, gap, acceleration, jerk, relative speed and time headway (quantiles), and on
smoothness (acceleration autocorrelation, sign changes, the acceleration's correlation with the
closing speed) (:func:`trajectory_features`). Its folds are grouped by vehicle: every segment of
one vehicle, real or generated, is in one fold, so the classifier is never tested on a vehicle it
was trained on. Its p-value is again a permutation test with the same folds, permuting labels only
where they are exchangeable under the null (:func:`permuted_labellings`), and its Wilson interval
counts the segments of one vehicle, which are not independent, as fewer trials (a design effect),
also approximate.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np
from joblib import Parallel, delayed
from scipy import special
from sklearn.ensemble import HistGradientBoostingClassifier
from sklearn.model_selection import GroupKFold
from threadpoolctl import threadpool_limits

__all__ = [
    "FEATURE_NAMES",
    "LEVEL_FEATURES",
    "TRAJECTORY_FEATURE_NAMES",
    "TwoSampleResult",
    "boosted_two_sample_test",
    "classifier_two_sample_test",
    "grouped_folds",
    "permuted_labellings",
    "segment_features",
    "trajectory_features",
]

# The log-likelihood is concave; a dozen Newton steps converge to machine precision here.
NEWTON_STEPS = 12
FEATURE_NAMES = ("speed_mean", "speed_sd", "gap_mean", "gap_min", "accel_sd", "jerk_sd")
# The features that describe where a vehicle drives, not how smoothly: a test on these alone
# separates a wrong speed or gap level from noise that is white where the data are smoothed.
LEVEL_FEATURES = slice(0, 4)

# The per-step series whose within-segment distributions the boosted classifier reads.
SERIES = ("speed", "gap", "accel", "jerk", "relative_speed", "time_headway")
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
SMOOTHNESS_NAMES = (
    "accel_sd",
    "jerk_sd",
    "accel_autocorr",
    "accel_sign_changes",
    "accel_closing_speed_corr",
)
TRAJECTORY_FEATURE_NAMES = (
    *(f"{series}_q{round(100 * q):02d}" for series in SERIES for q in QUANTILES),
    *SMOOTHNESS_NAMES,
)
# Time headway is gap / speed; below this speed it grows without bound in a queue, so the speed
# is floored here and the headway capped: a stopped car reads as "not following closely".
HEADWAY_SPEED_FLOOR = 1.0
HEADWAY_CAP_S = 10.0
# Early stopping off: every fit uses all its training rows and gives the same trees for the same
# seed; otherwise scikit-learn's defaults, fixed before any comparison was run. A leaf holds at
# least min_samples_leaf rows, so a fold that trains on fewer than twice that cannot split.
BOOSTING = {"max_iter": 100, "learning_rate": 0.1, "min_samples_leaf": 20, "early_stopping": False}


# From this many fits on, the boosted test spreads them over worker processes (the GIL keeps
# threads from running scikit-learn's small fits at once).
PARALLEL_FITS = 200


class TwoSampleResult(NamedTuple):
    accuracy: float
    # Wilson 95% interval, approximate (see the module docstring); on the effective number of
    # rows where the folds are grouped
    ci_low: float
    ci_high: float
    p_value: float
    n_real: int
    n_generated: int
    folds: int
    permutations: int
    seed: int
    # Distinct groups the folds were grouped by; None where rows were split one by one.
    groups: int | None = None

    @classmethod
    def from_scores(
        cls,
        scores: np.ndarray,
        interval: tuple[float, float],
        sizes: tuple[int, int],
        *,
        folds: int,
        permutations: int,
        seed: int,
        groups: int | None = None,
    ) -> TwoSampleResult:
        """The result of a permutation test from its correct predictions (``scores``: the
        observed labelling's first, then each permuted one's), the accuracy's ``interval`` and
        the (real, generated) row counts ``sizes``."""
        observed, null = int(scores[0]), scores[1:]
        n_real, n_generated = sizes
        return cls(
            accuracy=observed / (n_real + n_generated),
            ci_low=interval[0],
            ci_high=interval[1],
            p_value=float((1 + np.sum(null >= observed)) / (1 + permutations)),
            n_real=n_real,
            n_generated=n_generated,
            folds=folds,
            permutations=permutations,
            seed=seed,
            groups=groups,
        )


def segment_features(speed: np.ndarray, gap: np.ndarray, dt: float) -> np.ndarray:
    """Features of segments: ``speed`` and ``gap`` shaped (segments, steps); returns (segments, 6)."""
    speed = np.asarray(speed, dtype=np.float64)
    gap = np.asarray(gap, dtype=np.float64)
    accel = np.diff(speed, axis=1) / dt
    jerk = np.diff(accel, axis=1) / dt
    return np.column_stack(
        [
            speed.mean(axis=1),
            speed.std(axis=1),
            gap.mean(axis=1),
            gap.min(axis=1),
            accel.std(axis=1),
            jerk.std(axis=1),
        ]
    )


def trajectory_features(
    speed: np.ndarray, gap: np.ndarray, lead_speed: np.ndarray, dt: float
) -> np.ndarray:
    """Features of segments for the boosted classifier (:data:`TRAJECTORY_FEATURE_NAMES`):
    ``speed``, ``gap`` and the leader's ``lead_speed`` shaped (segments, steps); returns
    (segments, 35). A segment whose acceleration is constant has no autocorrelation or
    correlation: those features are NaN, which the classifier treats as missing."""
    speed = np.asarray(speed, dtype=np.float64)
    gap = np.asarray(gap, dtype=np.float64)
    accel = np.diff(speed, axis=1) / dt
    jerk = np.diff(accel, axis=1) / dt
    # Positive while the leader pulls away.
    relative = np.asarray(lead_speed, dtype=np.float64) - speed
    headway = np.minimum(gap / np.maximum(speed, HEADWAY_SPEED_FLOOR), HEADWAY_CAP_S)
    quantiles = [
        np.quantile(series, QUANTILES, axis=1).T
        for series in (speed, gap, accel, jerk, relative, headway)
    ]
    signs = np.sign(accel)
    smoothness = np.column_stack(
        [
            accel.std(axis=1),
            jerk.std(axis=1),
            _row_correlation(accel[:, 1:], accel[:, :-1]),
            np.mean(signs[:, 1:] * signs[:, :-1] < 0, axis=1),
            # The acceleration over a step against the closing speed at its start.
            _row_correlation(accel, -relative[:, :-1]),
        ]
    )
    return np.column_stack([*quantiles, smoothness])


def _row_correlation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pearson correlation of each row of ``a`` with the same row of ``b``; NaN where a row is
    constant (no correlation is defined)."""
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    scale = np.sqrt(np.sum(a**2, axis=1) * np.sum(b**2, axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(scale > 0, np.sum(a * b, axis=1) / scale, np.nan)


def _fit_logistic(features: np.ndarray, labels: np.ndarray, l2: float) -> np.ndarray:
    """L2-regularised logistic regression by Newton's method, batched over label vectors.

    ``features`` (n, d) is shared; ``labels`` (b, n) holds one labelling per row (the observed one
    and the permutations), so all fits run as one vectorised Newton iteration. Returns (b, d + 1).
    """
    design = np.column_stack([np.ones(len(features)), features])
    ridge = l2 * np.diag(np.r_[0.0, np.ones(features.shape[1])])
    weights = np.zeros((labels.shape[0], design.shape[1]))
    for _ in range(NEWTON_STEPS):
        prob = special.expit(weights @ design.T)
        grad = (prob - labels) @ design + weights @ ridge
        hessian = np.einsum("bn,ni,nj->bij", prob * (1 - prob), design, design) + ridge
        weights -= np.linalg.solve(hessian, grad[..., None])[..., 0]
    return weights


def _wilson(successes: float, trials: float, z: float = 1.96) -> tuple[float, float]:
    p = successes / trials
    centre = (p + z**2 / (2 * trials)) / (1 + z**2 / trials)
    half = z * np.sqrt(p * (1 - p) / trials + z**2 / (4 * trials**2)) / (1 + z**2 / trials)
    return float(centre - half), float(centre + half)


def classifier_two_sample_test(
    real: np.ndarray,
    generated: np.ndarray,
    *,
    seed: int,
    folds: int = 5,
    l2: float = 1.0,
    permutations: int = 199,
) -> TwoSampleResult:
    """Cross-validated accuracy of telling ``real`` rows from ``generated`` rows (features)."""
    real = np.asarray(real, dtype=np.float64)
    generated = np.asarray(generated, dtype=np.float64)
    if min(len(real), len(generated)) < folds:
        raise ValueError(
            f"need at least {folds} segments of each kind, got {len(real)} real and "
            f"{len(generated)} generated"
        )
    features = np.vstack([real, generated])
    labels = np.concatenate([np.zeros(len(real)), np.ones(len(generated))])
    rng = np.random.default_rng(seed)
    # Folds ignore the labels: stratifying by the observed labels would make the permuted
    # labellings unbalanced within folds and bias the permutation null downwards.
    fold_of = rng.permutation(len(labels)) % folds
    labellings = np.vstack([labels] + [rng.permutation(labels) for _ in range(permutations)])
    correct = np.zeros(len(labellings), dtype=int)
    for fold in range(folds):
        train, test = fold_of != fold, fold_of == fold
        mean = features[train].mean(axis=0)
        scale = features[train].std(axis=0) + 1e-12
        weights = _fit_logistic((features[train] - mean) / scale, labellings[:, train], l2)
        logits = weights[:, :1] + weights[:, 1:] @ ((features[test] - mean) / scale).T
        correct += np.sum((logits > 0) == (labellings[:, test] == 1), axis=1)
    return TwoSampleResult.from_scores(
        correct,
        _wilson(int(correct[0]), len(labels)),
        (len(real), len(generated)),
        folds=folds,
        permutations=permutations,
        seed=seed,
    )


def grouped_folds(groups: np.ndarray, folds: int) -> np.ndarray:
    """The fold of each row: ``GroupKFold``'s, so that all rows of one group share a fold. It
    ignores the labels, so every permuted labelling is tested on the same folds."""
    fold_of = np.empty(len(groups), dtype=int)
    for fold, (_, test) in enumerate(GroupKFold(n_splits=folds).split(groups, groups=groups)):
        fold_of[test] = fold
    return fold_of


def permuted_labellings(
    rng: np.random.Generator, labels: np.ndarray, groups: np.ndarray, count: int
) -> np.ndarray:
    """``count`` labellings drawn under the null, (count, rows). Within a group holding both labels
    (a vehicle's real and generated segments of the same scenes) the labels are shuffled among its
    rows; groups holding one label (vehicles on one side only) swap their labels as wholes, since
    a vehicle's segments are not exchangeable one by one with another vehicle's."""
    labels = np.asarray(labels)
    _, group_index = np.unique(groups, return_inverse=True)
    members = [np.flatnonzero(group_index == g) for g in range(group_index.max() + 1)]
    mixed = [rows for rows in members if len(np.unique(labels[rows])) > 1]
    single = [rows for rows in members if len(np.unique(labels[rows])) == 1]
    single_labels = np.array([labels[rows[0]] for rows in single])
    out = np.tile(labels, (count, 1))
    for labelling in out:
        for rows in mixed:
            labelling[rows] = rng.permutation(labels[rows])
        for rows, label in zip(single, rng.permutation(single_labels), strict=True):
            labelling[rows] = label
    return out


def _cluster_interval(correct: np.ndarray, groups: np.ndarray) -> tuple[float, float]:
    """Wilson interval of the accuracy on the effective number of rows: their number divided by
    the design effect, the cluster-robust (sandwich) variance of the accuracy over the binomial
    one, at least 1 and at most the mean group size (every group one trial). Where all rows or
    none are right neither variance says anything, so the design effect is that largest one."""
    _, group_index = np.unique(groups, return_inverse=True)
    hits = np.bincount(group_index, weights=correct)
    sizes = np.bincount(group_index)
    rows, count = sizes.sum(), len(sizes)
    accuracy = hits.sum() / rows
    binomial = accuracy * (1 - accuracy) / rows
    clustered = count / (count - 1) * np.sum((hits - accuracy * sizes) ** 2) / rows**2
    largest = rows / count
    design_effect = np.clip(clustered / binomial, 1.0, largest) if binomial > 0 else largest
    effective = rows / design_effect
    return _wilson(accuracy * effective, effective)


def _fold_hits(
    features: np.ndarray, test: np.ndarray, labellings: np.ndarray, seed: int
) -> np.ndarray:
    """For each labelling (rows of ``labellings``), whether the classifier trained on the rows
    outside ``test`` predicts each ``test`` row's label."""
    train = ~test
    hits = np.zeros((len(labellings), int(test.sum())), dtype=bool)
    # One thread: these fits are small, and OpenMP's start-up on every fit costs more than it saves.
    with threadpool_limits(limits=1):
        for labelling, row in zip(labellings, hits, strict=True):
            classifier = HistGradientBoostingClassifier(**BOOSTING, random_state=seed)
            classifier.fit(features[train], labelling[train])
            row[:] = classifier.predict(features[test]) == labelling[test]
    return hits


def boosted_two_sample_test(
    real: np.ndarray,
    generated: np.ndarray,
    *,
    real_groups: np.ndarray,
    generated_groups: np.ndarray,
    seed: int,
    folds: int = 5,
    permutations: int = 99,
) -> TwoSampleResult:
    """Cross-validated accuracy of gradient-boosted trees telling ``real`` rows from ``generated``
    rows (features, e.g. :func:`trajectory_features`), folds grouped by ``*_groups`` (one entry
    per row: the vehicle), p-value by permutation (:func:`permuted_labellings`)."""
    real = np.asarray(real, dtype=np.float64)
    generated = np.asarray(generated, dtype=np.float64)
    groups = np.concatenate([np.asarray(real_groups), np.asarray(generated_groups)])
    for name, rows, named in (
        ("real", real, real_groups),
        ("generated", generated, generated_groups),
    ):
        if len(named) != len(rows):
            raise ValueError(f"{name}: {len(rows)} rows but {len(named)} group labels")
    distinct = len(np.unique(groups))
    if distinct < folds:
        raise ValueError(
            f"need at least {folds} groups (vehicles) for {folds} folds, got {distinct}"
        )
    features = np.vstack([real, generated])
    labels = np.concatenate([np.zeros(len(real), int), np.ones(len(generated), int)])
    rng = np.random.default_rng(seed)
    labellings = np.vstack([labels[None], permuted_labellings(rng, labels, groups, permutations)])
    fold_of = grouped_folds(groups, folds)
    # Every (fold, labelling) fit is independent and seeded, so the work is split over the cores
    # in slices of labellings; the hits are the same however it is split. Worker processes take
    # seconds to start: a small test runs its fits here, in one slice.
    workers = min(os.cpu_count() or 1, len(labellings))
    if len(labellings) * folds < PARALLEL_FITS:
        workers = 1
    slices = np.array_split(np.arange(len(labellings)), workers)
    tasks = [(fold, chosen) for fold in range(folds) for chosen in slices]
    hits = Parallel(n_jobs=workers)(
        delayed(_fold_hits)(features, fold_of == fold, labellings[chosen], seed)
        for fold, chosen in tasks
    )
    correct = np.zeros(labellings.shape, dtype=bool)
    for (fold, chosen), fold_hits in zip(tasks, hits, strict=True):
        correct[np.ix_(chosen, fold_of == fold)] = fold_hits
    return TwoSampleResult.from_scores(
        correct.sum(axis=1),
        _cluster_interval(correct[0], groups),
        (len(real), len(generated)),
        groups=distinct,
        folds=folds,
        permutations=permutations,
        seed=seed,
    )
