"""The statistics of ``benchmarks/fabric_recognition.py``, against their definitions and an independent
implementation (scipy's exact binomial test)."""

import math

import pytest

pytest.importorskip("sklearn", reason="the recognition benchmark needs the fabric extra (scikit-learn)")
scipy_stats = pytest.importorskip("scipy.stats", reason="scipy (installed with scikit-learn) is the reference")

import numpy as np  # noqa: E402

from benchmarks.fabric_recognition import against_baseline, mcnemar_exact, wilson_interval  # noqa: E402

Z95 = 1.959964


@pytest.mark.parametrize("correct,total", [(211, 220), (63, 66), (1, 20), (0, 30), (30, 30), (81, 263)])
def test_wilson_interval_inverts_the_score_test(correct, total):
    """Each bound p is where the score statistic |p_hat - p| / sqrt(p (1 - p) / n) equals z (Wilson 1927)."""
    low, high = wilson_interval(correct, total)
    share = correct / total
    assert 0 <= low <= share <= high <= 1
    for bound in (low, high):
        if 0 < bound < 1:
            assert abs(share - bound) / math.sqrt(bound * (1 - bound) / total) == pytest.approx(Z95, rel=1e-9)
        else:  # at 0 or n successes the interval closes on the observed share
            assert bound == pytest.approx(share, abs=1e-12)


@pytest.mark.parametrize("only_first,only_second", [(1, 7), (7, 1), (5, 5), (0, 9), (12, 3), (40, 22)])
def test_mcnemar_exact_is_the_two_sided_binomial_test(only_first, only_second):
    expected = scipy_stats.binomtest(only_first, only_first + only_second, 0.5).pvalue
    assert mcnemar_exact(only_first, only_second) == pytest.approx(expected, rel=1e-12)


def test_mcnemar_without_discordant_pairs_says_nothing():
    assert mcnemar_exact(0, 0) == 1.0


def test_against_baseline_counts_the_discordant_samples():
    # 10 samples: both right on 6, only the first on 1, only the baseline on 3
    right = np.array([1, 1, 1, 1, 1, 1, 1, 0, 0, 0], dtype=bool)
    baseline = np.array([1, 1, 1, 1, 1, 1, 0, 1, 1, 1], dtype=bool)
    cell = against_baseline(right, baseline, "the descriptors")
    assert cell.startswith("-20.0 (exact McNemar p = ")
    assert f"p = {mcnemar_exact(1, 3):.2g}: 1 test samples only the descriptors get right, 3 only the baseline" in cell


def test_fit_chooses_c_by_cross_validation_grouped_by_seed():
    """fit's C is the one a plain loop over the grid scores best on 5 folds that keep each seed's samples together
    (an independent computation of the same choice), and the returned pipeline is refitted on all samples."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import GroupKFold
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    from benchmarks.fabric_recognition import C_GRID, fit

    rng = np.random.default_rng(0)
    seeds = np.repeat(np.arange(20), 3)
    y = np.tile(["a", "b", "c"], 20)
    x = rng.normal(size=(60, 12)) + 0.8 * (y[:, None] == np.array(["a", "b", "c"] + [""] * 9)[None, :])
    scores = []
    for c in C_GRID:
        right = []
        for train, test in GroupKFold(5).split(x, y, seeds):
            model = make_pipeline(StandardScaler(), LogisticRegression(C=c, max_iter=20000)).fit(x[train], y[train])
            right.append((model.predict(x[test]) == y[test]).mean())
        scores.append(np.mean(right))
    search = fit(x, y, seeds)
    best = C_GRID[int(np.argmax(scores))]
    strength = search.best_estimator_.steps[1][1].C
    assert strength == best
    assert search.best_score_ == pytest.approx(max(scores))
    assert search.best_estimator_.steps[0][1].n_samples_seen_ == 60
