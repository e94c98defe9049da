"""Fabric recognition from measured structure vs. the single-image premise, on randomised synthetic fabrics.

Every class of ``data_synth.FABRICS``, each sample drawn by ``data_synth.fabric_dataset`` from its seed (yarn
spacing, width, crimp, orientation over 0-180 deg, dyed and printed albedo independent of the relief, the cloth
0-1 mm above the card, wrinkles, the simulator's noise and 8-bit quantisation), reconstructed by psmini's default
pipeline (``psmini.fabric.reconstruct_for_description``: near light for these LED captures), described
(``psmini.fabric.describe_reconstruction`` -> ``descriptor_vector``: ISO 25178-2 parameters of the depth; densities,
crossing angle, repeat, crimp and openness of the slopes' unweighted integration; waviness, and the albedo-relief
coupling; no albedo level or contrast). ``--cache DIR`` keeps
each reconstruction (keyed by a hash of the dataset, rig and pipeline code), so a second run only describes.
Beside it, the seed paper's premise: the same classifier on texture features of ONE LED image (scikit-image's
grey-level co-occurrence properties at 4 distances, averaged and ranged over 4 angles, and uniform local binary
pattern histograms at two radii). The classifier is scikit-learn's multinomial logistic regression on
standardised features, for both, its regularisation chosen by cross-validation on the training samples; the
split is by seed (train seeds 0..N-1, test seeds 10000..), so no sample is in both. Prints and appends to
``benchmarks/results.md`` the accuracies, the confusion matrices (and writes them as a PNG) and the descriptors
that carry the accuracy (permutation importance on the test set); saves the trained model as JSON
(``psmini.fabric.FabricClassifier``; ``psmini describe --model``).

Each accuracy comes with its 95% Wilson score interval, and the difference with an exact McNemar test (both
classifiers are scored on the same test samples: only the samples that one gets right and the other wrong say which
is better). A third row trains the same classifier on both feature sets: what the relief adds to the image.
The defaults, 24 training and 20 test seeds per class (264 and 220 samples), keep the interval within
about 3 points: with 6 test seeds (66 samples) it is about 5 points wide either side, wider than the differences
being compared (95.5% there came out as 92.7% on 220 samples with the same 8 training seeds).

``--protocol shift`` asks the seed paper's question where a single image is ambiguous: the structures of the
weave family (:mod:`data_synth.weaves`: plain, 2/2 basket, 2/1 and 3/1 twill, 5-end satin, 2/2 rib, jersey, at
10-40 threads/cm per system) are trained in one region of capture conditions and tested in another
(:mod:`data_synth.shift`: other dyes and prints, half of the test prints imitating another weave's shading, the
cloth turned by 90-180 deg, LEDs drifted up to 20%, the exposure off by up to a stop, the cloth 0.3-1 mm off the
card), 40 training and 145 test seeds per class (1,015 test samples) at 400 x 400 px by default. Three rows: the
relief descriptors (``describe_reconstruction`` without the albedo), one LED image's GLCM + LBP, both; each with
its Wilson interval, the differences with the exact McNemar test; ``--json`` prints one object with ``image``,
``descriptors``, ``both`` (accuracies in [0, 1]) and ``n_test``; the accuracies and confusion matrices are written
to ``benchmarks/fabric_shift.json`` (read by ``notebooks/06_fabric_structure.ipynb``).

Needs the ``fabric`` extra (scikit-learn, scikit-image). Usage::

    python benchmarks/fabric_recognition.py [--train-seeds 24] [--test-seeds 20] [--size 256] [--cache .fabric_cache]
    python benchmarks/fabric_recognition.py --protocol shift [--json] [--cache .fabric_cache]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import REPO, append_results, table  # noqa: E402
from psmini.config import ReconstructionConfig  # noqa: E402


def texture_features(image: np.ndarray) -> np.ndarray:
    """GLCM and LBP features of one 8-bit gray image (the single-image baseline)."""
    from skimage.feature import graycomatrix, graycoprops, local_binary_pattern

    codes = np.clip(np.rint(image * 255), 0, 255).astype(np.uint8)
    levels = (codes // 8).astype(np.uint8)  # 32 grey levels
    angles = [0, np.pi / 4, np.pi / 2, 3 * np.pi / 4]
    glcm = graycomatrix(levels, distances=[1, 2, 4, 8], angles=angles, levels=32, symmetric=True, normed=True)
    out = []
    for prop in ("contrast", "dissimilarity", "homogeneity", "energy", "correlation", "ASM"):
        values = graycoprops(glcm, prop)  # (distances, angles)
        out += list(values.mean(axis=1)) + list(values.max(axis=1) - values.min(axis=1))
    for points, radius in ((8, 1), (16, 2)):
        lbp = local_binary_pattern(codes, points, radius, method="uniform")
        hist, _ = np.histogram(lbp, bins=points + 2, range=(0, points + 2), density=True)
        out += list(hist)
    out += [float(codes.mean()) / 255, float(codes.std()) / 255]
    return np.asarray(out, dtype=np.float64)


# psmini's default pipeline: near light for the rig's LED captures (what `psmini describe` runs on a capture).
CONFIG = ReconstructionConfig()


def reconstruction(name: str, seed: int, options, card, cache: Path | None):
    """The default pipeline's reconstruction of one sample (depth, mask, albedo, slopes) and its first LED image,
    from the cache when there (``cache/<class>-<seed>-<size>-<tag>.npz``: :mod:`benchmarks._fabric_captures`)."""
    from benchmarks._fabric_captures import reconstruct_capture, source_tag
    from data_synth.fabric_dataset import render_sample

    def make():
        sample, _, capture = render_sample(name, seed, options, card)
        return sample, capture

    tag = source_tag(CONFIG, {"dataset": repr(options), "sources": _dataset_sources()})
    return reconstruct_capture(f"{name}-{seed}-{options.size}", make, cache, tag, CONFIG)


def _fabric_sources() -> str:
    """A hash of psmini.fabric's code (the descriptors of a cached reconstruction are kept under it)."""
    from benchmarks._fabric_captures import sources_digest

    return sources_digest(tuple(str(p.relative_to(REPO)) for p in sorted((REPO / "psmini" / "fabric").glob("*.py"))))


def _dataset_sources() -> str:
    """A hash of the dataset's generators' code (a change to them invalidates the cache)."""
    from benchmarks._fabric_captures import sources_digest

    return sources_digest(("data_synth/fabric_dataset.py", "data_synth/fabrics.py", "data_synth/shift.py",
                           "data_synth/weaves.py"))


def build(seeds: list[int], options, card, cache: Path | None = None, log_every: int = 11):
    """Descriptors, baseline features, labels and seeds (the cross-validation's groups) for every class and seed."""
    from data_synth.fabric_dataset import CLASSES
    from psmini.fabric import describe_reconstruction, descriptor_vector

    structure, texture, labels, row_seeds = [], [], [], []
    count, start = 0, time.perf_counter()
    for seed in seeds:
        for name in CLASSES:
            rec = reconstruction(name, seed, options, card, cache)
            structure.append(descriptor_vector(describe_reconstruction(rec, options.rig.pixel_pitch_mm)[0]))
            texture.append(texture_features(rec.image))
            labels.append(name)
            row_seeds.append(seed)
            count += 1
            if count % log_every == 0:
                print(f"  {count} samples, {time.perf_counter() - start:.0f} s", flush=True)
    return np.stack(structure), np.stack(texture), np.array(labels), np.array(row_seeds)


def wilson_interval(correct: int, total: int, z: float = 1.959964) -> tuple[float, float]:
    """The 95% Wilson score interval of a proportion ``correct / total`` (Wilson 1927)."""
    share = correct / total
    centre = (share + z * z / (2 * total)) / (1 + z * z / total)
    half = z * math.sqrt(share * (1 - share) / total + z * z / (4 * total * total)) / (1 + z * z / total)
    return max(0.0, centre - half), min(1.0, centre + half)  # the rounding of 0 or n successes stays in [0, 1]


def mcnemar_exact(only_first: int, only_second: int) -> float:
    """Two-sided exact McNemar p-value: the discordant pairs (samples that only the first, or only the second,
    classifier gets right) under the null hypothesis that either is as likely (McNemar 1947, the binomial form)."""
    n = only_first + only_second
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(min(only_first, only_second) + 1)) / 2**n
    return min(1.0, 2 * tail)


def accuracy_cell(right: np.ndarray) -> str:
    """``right`` (bool per test sample) as "95.9% (92.4%-97.8%)": the accuracy and its Wilson interval."""
    low, high = wilson_interval(int(right.sum()), right.size)
    return f"{right.mean():.1%} ({low:.1%}-{high:.1%})"


def against_baseline(right: np.ndarray, baseline: np.ndarray, who: str) -> str:
    """The accuracy difference of ``right`` over ``baseline`` (bool per test sample) in points, with the exact
    McNemar p-value of their discordant samples, as a table cell."""
    only, only_baseline = int((right & ~baseline).sum()), int((baseline & ~right).sum())
    p = mcnemar_exact(only, only_baseline)
    return (f"{100 * (right.mean() - baseline.mean()):+.1f} (exact McNemar p = {p:.2g}: "
            f"{only} test samples only {who} get right, {only_baseline} only the baseline)")


#: The inverse regularisation strengths :func:`fit` chooses from.
C_GRID = tuple(float(c) for c in np.logspace(-3, 2, 11))


def fit(x: np.ndarray, y: np.ndarray, groups: np.ndarray):
    """Multinomial logistic regression on standardised features, its strength C chosen from :data:`C_GRID` by
    5-fold cross-validation on the training samples alone, grouped by seed (no seed in two folds): a fixed C
    would be a choice made by looking at the test accuracy. Returns the fitted search (scikit-learn's
    ``GridSearchCV``): it predicts with the pipeline refitted on all of ``x`` at the chosen C (``best_estimator_``),
    and ``best_score_`` is that C's cross-validated accuracy, an estimate under the training conditions."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import GridSearchCV, GroupKFold
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    search = GridSearchCV(make_pipeline(StandardScaler(), LogisticRegression(max_iter=20000)),
                          {"logisticregression__C": C_GRID}, cv=GroupKFold(5))
    return search.fit(x, y, groups=groups)


def chosen(search) -> str:
    """The C a :func:`fit` chose and its cross-validated accuracy, for the ledger."""
    return f"C = {search.best_params_['logisticregression__C']:.3g}, {search.best_score_:.1%} cross-validated"


def to_classifier(model, names):
    """The fitted scikit-learn pipeline as a code-free :class:`psmini.fabric.FabricClassifier`."""
    from psmini.fabric import FabricClassifier

    scaler, logistic = model.best_estimator_.steps[0][1], model.best_estimator_.steps[1][1]
    scale = np.where(scaler.scale_ > 0, scaler.scale_, 1.0)
    return FabricClassifier(tuple(str(c) for c in logistic.classes_), tuple(names), tuple(map(float, scaler.mean_)),
                            tuple(map(float, scale)), tuple(tuple(map(float, row)) for row in logistic.coef_),
                            tuple(map(float, logistic.intercept_)))


def _shown(path: Path) -> Path:
    """``path`` relative to the repository when inside it."""
    return path.relative_to(REPO) if path.is_relative_to(REPO) else path


def confusion_png(path: Path, classes, matrices: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(matrices), figsize=(6.2 * len(matrices), 5.4))
    for ax, (title, matrix) in zip(np.atleast_1d(axes), matrices.items(), strict=True):
        ax.imshow(matrix, cmap="Blues")
        for i in range(len(classes)):
            for j in range(len(classes)):
                if matrix[i, j]:
                    ax.text(j, i, str(matrix[i, j]), ha="center", va="center", fontsize=8)
        ax.set_xticks(range(len(classes)), classes, rotation=60, fontsize=8)
        ax.set_yticks(range(len(classes)), classes, fontsize=8)
        ax.set_xlabel("predicted")
        ax.set_ylabel("true")
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def build_shift(region, seeds: list[int], size: int, card, cache: Path | None, log_every: int = 35):
    """Relief descriptors, one LED image's texture features, labels and seeds (the cross-validation's groups) of the
    weave family's structures drawn in ``region`` (:mod:`data_synth.shift`) for ``seeds``, reconstructed by the
    default pipeline (cached)."""
    from benchmarks._fabric_captures import reconstruct_capture, source_tag
    from data_synth.rig import RigConfig
    from data_synth.shift import draw_shifted, render_shifted
    from data_synth.weaves import WEAVES
    from psmini.fabric import describe_reconstruction, descriptor_vector

    rig = RigConfig(bit_depth=8, size=size)
    tag = source_tag(CONFIG, {"rig": rig.__dict__, "card": 10_007, "sources": _dataset_sources()})
    relief, texture, labels, row_seeds = [], [], [], []
    count, start = 0, time.perf_counter()
    for seed in seeds:
        for weave in WEAVES:
            draw = draw_shifted(weave, seed, region, size, rig.pixel_pitch_mm, rig.led_count)
            key = f"shift-{region.name}-{weave}-{seed}-{size}"
            features = cache / f"{key}-{tag}-features-{_fabric_sources()}.npz" if cache is not None else None
            if features is not None and features.is_file():
                data = np.load(features)
                relief.append(data["relief"])
                texture.append(data["texture"])
            else:
                rec = reconstruct_capture(key, lambda draw=draw, seed=seed: render_shifted(draw, rig, card, seed),
                                          cache, tag, CONFIG)
                # the relief alone: no albedo (a dye or a print is no structure; the premise is about the image)
                entry = describe_reconstruction(dataclasses.replace(rec, albedo=None), rig.pixel_pitch_mm)[0]
                relief.append(descriptor_vector(entry))
                texture.append(texture_features(rec.image))
                if features is not None:
                    temporary = features.with_name(f".{features.stem}.tmp.npz")
                    np.savez(temporary, relief=relief[-1], texture=texture[-1])
                    temporary.replace(features)
            labels.append(weave)
            row_seeds.append(seed)
            count += 1
            if count % log_every == 0:
                print(f"  {region.name}: {count} samples, {time.perf_counter() - start:.0f} s", file=sys.stderr,
                      flush=True)
    return np.stack(relief), np.stack(texture), np.array(labels), np.array(row_seeds)


def shift_protocol(args) -> int:
    """``--protocol shift``: train in one region of capture conditions, test in another (see the module docstring)."""
    import json

    from sklearn.metrics import confusion_matrix

    from data_synth.rig import RigConfig, render_card
    from data_synth.shift import TEST, TRAIN
    from data_synth.weaves import WEAVES

    rig = RigConfig(bit_depth=8, size=args.size)
    card = render_card(rig, seed=10_007)
    train_seeds = list(range(args.train_seeds))
    test_seeds = list(range(args.test_seed_start, args.test_seed_start + args.test_seeds))
    start = time.perf_counter()
    print(f"shift protocol: train {len(train_seeds)} x {len(WEAVES)} in the training region, test "
          f"{len(test_seeds)} x {len(WEAVES)} in the test region", file=sys.stderr, flush=True)
    train_s, train_t, train_y, groups = build_shift(TRAIN, train_seeds, args.size, card, args.cache)
    test_s, test_t, test_y, _ = build_shift(TEST, test_seeds, args.size, card, args.cache)
    elapsed = time.perf_counter() - start
    relief, image = fit(train_s, train_y, groups), fit(train_t, train_y, groups)
    both = fit(np.hstack([train_s, train_t]), train_y, groups)
    predicted = {"descriptors": relief.predict(test_s), "image": image.predict(test_t),
                 "both": both.predict(np.hstack([test_s, test_t]))}
    right = {k: v == test_y for k, v in predicted.items()}
    classes = list(WEAVES)
    matrices = {k: confusion_matrix(test_y, v, labels=classes) for k, v in predicted.items()}
    n_test = int(test_y.size)
    result = {"protocol": "shift", "image": float(right["image"].mean()),
              "descriptors": float(right["descriptors"].mean()), "both": float(right["both"].mean()),
              "n_test": n_test, "n_train": int(train_y.size), "size_px": args.size, "classes": classes,
              "cross_validated": {"descriptors": relief.best_score_, "image": image.best_score_,
                                  "both": both.best_score_},
              "intervals": {k: list(wilson_interval(int(v.sum()), v.size)) for k, v in right.items()},
              "mcnemar_p": {"descriptors vs image": mcnemar_exact(int((right["descriptors"] & ~right["image"]).sum()),
                                                                  int((right["image"] & ~right["descriptors"]).sum())),
                            "both vs image": mcnemar_exact(int((right["both"] & ~right["image"]).sum()),
                                                           int((right["image"] & ~right["both"]).sum()))},
              "confusion": {k: m.tolist() for k, m in matrices.items()}}
    if args.shift_result is not None:
        args.shift_result.write_text(json.dumps(result, indent=1) + "\n")
    if args.json:
        print(json.dumps({k: result[k] for k in ("image", "descriptors", "both", "n_test", "intervals",
                                                  "mcnemar_p")}))
        return 0
    confusion_png(args.figure, classes, {f"relief descriptors: {result['descriptors']:.1%}": matrices["descriptors"],
                                         f"one LED image (GLCM + LBP): {result['image']:.1%}": matrices["image"]})

    def by_class(key: str) -> str:
        return ", ".join(f"{c} {int(matrices[key][i, i])}/{int(matrices[key][i].sum())}"
                         for i, c in enumerate(classes))

    body = [
        f"The structures of `data_synth.weaves` ({', '.join(classes)}; densities 10-40/cm per system, any "
        "cross-section and crimp), trained in one region of capture conditions and tested in another "
        "(`data_synth.shift`): training: dye x0.75-1.0, blotch prints on 30%, orientation 0-90 deg, LEDs within "
        "+-2% of their calibration, exposure +-0.2 stop, 0-0.3 mm above the card; test: dye x0.45-0.75 or "
        "x1.0-1.3, prints on 75% (two thirds of them imitating another weave's shading), orientation 90-180 deg, LEDs "
        "drifted up to +-20%, exposure +-1 stop, 0.3-1 mm above the card. The reconstruction knows the nominal "
        f"calibration only. {len(train_y)} training samples (seeds 0..{args.train_seeds - 1}), {n_test} test "
        f"samples (seeds {test_seeds[0]}..{test_seeds[-1]}), {args.size}x{args.size} px at 0.025 mm, 8-bit "
        "captures, reconstructed by psmini's default pipeline (near light). Relief descriptors: `descriptor_vector` "
        "of `describe_reconstruction` without the albedo (the ISO parameters of the depth, the structure of the "
        "slopes' unweighted integration); image: GLCM + LBP of LED 0's image. Classifier: "
        "scikit-learn LogisticRegression on standardised features, C chosen by 5-fold cross-validation on the "
        f"training samples grouped by seed, which also estimates the accuracy under the training conditions "
        f"(descriptors: {chosen(relief)}; image: {chosen(image)}; both: {chosen(both)}). Built in {elapsed:.0f} s"
        + (" (reconstructions from the cache where present)." if args.cache else "."),
        "",
        table(["features", "test accuracy under shift (95% Wilson interval)"],
              [["relief descriptors (psmini.fabric)", accuracy_cell(right["descriptors"])],
               ["single LED image: GLCM + LBP", accuracy_cell(right["image"])],
               ["descriptors against the image (points)", against_baseline(right["descriptors"], right["image"],
                                                                           "the descriptors")],
               ["descriptors and the image's texture together", accuracy_cell(right["both"])],
               ["together against the image (points)", against_baseline(right["both"], right["image"],
                                                                        "both together")]]),
        "",
        f"Right by class, descriptors: {by_class('descriptors')}; image: {by_class('image')}; both: "
        f"{by_class('both')}.",
        "",
        "Confusion matrix, relief descriptors (rows true, columns predicted; " + ", ".join(classes) + "):",
        "",
        "```",
        "\n".join(" ".join(f"{v:3d}" for v in row) for row in matrices["descriptors"]),
        "```",
        "",
        "Confusion matrix, one LED image:",
        "",
        "```",
        "\n".join(" ".join(f"{v:3d}" for v in row) for row in matrices["image"]),
        "```",
    ]
    text = "\n".join(body)
    print(text)
    if not args.no_ledger:
        append_results("Fabric recognition under shift: relief descriptors vs one image", text)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--protocol", choices=("same", "shift"), default="same",
                        help="same: psmini's fabric classes, train and test alike (split by seed); shift: the weave "
                        "family, trained in one region of capture conditions and tested in another")
    parser.add_argument("--train-seeds", type=int, default=None,
                        help="training seeds per class (default 24; 40 with --protocol shift)")
    parser.add_argument("--test-seeds", type=int, default=None,
                        help="test seeds per class (default 20; 145 with --protocol shift: 1,015 test samples)")
    parser.add_argument("--test-seed-start", type=int, default=10_000, metavar="N",
                        help="the first test seed (default 10000; another start draws test samples no one has "
                        "looked at, for a check of a change found by reading the usual ones' errors)")
    parser.add_argument("--size", type=int, default=None,
                        help="crop side, pixels (0.025 mm each; default 256; 400 with --protocol shift)")
    parser.add_argument("--json", action="store_true", help="--protocol shift: print one JSON object (image, "
                        "descriptors, both, n_test, intervals, mcnemar_p), nothing else; no ledger, no figure")
    parser.add_argument("--shift-result", type=Path, default=REPO / "benchmarks" / "fabric_shift.json",
                        help="--protocol shift: where the accuracies and confusion matrices are written (JSON)")
    parser.add_argument("--model", type=Path, default=REPO / "benchmarks" / "fabric_model.json")
    parser.add_argument("--figure", type=Path, default=REPO / "benchmarks" / "fabric_confusion.png")
    parser.add_argument("--no-ledger", action="store_true", help="do not append to benchmarks/results.md")
    parser.add_argument("--cache", type=Path, default=None, metavar="DIR",
                        help="keep each sample's reconstruction in DIR and reuse it on the next run (keyed by a hash "
                        "of the dataset, rig and pipeline code and configuration)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    shift = args.protocol == "shift"
    args.train_seeds = args.train_seeds if args.train_seeds is not None else (40 if shift else 24)
    args.test_seeds = args.test_seeds if args.test_seeds is not None else (145 if shift else 20)
    args.size = args.size if args.size is not None else (400 if shift else 256)
    if shift:
        if args.figure == REPO / "benchmarks" / "fabric_confusion.png":
            args.figure = REPO / "benchmarks" / "fabric_shift_confusion.png"
        if args.json:
            args.no_ledger = True
        return shift_protocol(args)
    if args.json:
        parser.error("--json is for --protocol shift")

    from sklearn.inspection import permutation_importance
    from sklearn.metrics import confusion_matrix

    from data_synth.fabric_dataset import CLASSES, DatasetOptions
    from data_synth.rig import render_card
    from psmini.commands.describe import write_model
    from psmini.fabric import DESCRIPTOR_NAMES

    options = DatasetOptions(size=args.size)
    card = render_card(options.rig.replace(size=args.size), seed=10_007)
    start = time.perf_counter()
    print(f"train: seeds 0..{args.train_seeds - 1} x {len(CLASSES)} classes")
    train_s, train_t, train_y, groups = build(list(range(args.train_seeds)), options, card, args.cache)
    test_seeds = list(range(args.test_seed_start, args.test_seed_start + args.test_seeds))
    print(f"test: seeds {test_seeds[0]}..{test_seeds[-1]} x {len(CLASSES)} classes")
    test_s, test_t, test_y, _ = build(test_seeds, options, card, args.cache)
    elapsed = time.perf_counter() - start
    structure = fit(train_s, train_y, groups)
    texture = fit(train_t, train_y, groups)
    right_s, right_t = structure.predict(test_s) == test_y, texture.predict(test_t) == test_y
    acc_s, acc_t = float(right_s.mean()), float(right_t.mean())
    # what the relief adds to the image: the same classifier on both feature sets
    both = fit(np.hstack([train_s, train_t]), train_y, groups)
    right_b = both.predict(np.hstack([test_s, test_t])) == test_y
    classes = list(CLASSES)
    cm_s = confusion_matrix(test_y, structure.predict(test_s), labels=classes)
    cm_t = confusion_matrix(test_y, texture.predict(test_t), labels=classes)
    importance = permutation_importance(structure, test_s, test_y, n_repeats=20, random_state=0)
    order = np.argsort(-importance.importances_mean)[:8]
    classifier = to_classifier(structure, DESCRIPTOR_NAMES)
    assert np.allclose(classifier.predict_proba(test_s), structure.predict_proba(test_s), atol=1e-9)
    write_model(args.model, classifier)
    confusion_png(args.figure, classes, {f"structure descriptors: {acc_s:.1%}": cm_s,
                                         f"single LED image (GLCM + LBP): {acc_t:.1%}": cm_t})

    n_train, n_test = len(train_y), len(test_y)
    body = [
        f"{len(classes)} classes, {n_train} training samples (seeds 0..{args.train_seeds - 1}), {n_test} test samples "
        f"(seeds {test_seeds[0]}..{test_seeds[-1]}); {args.size}x{args.size} px at 0.025 mm "
        f"({args.size * 0.025:.1f} mm fields), 8-bit simulated rig captures (noise, shadows, vignetting), "
        "reconstructed by psmini's default pipeline (`reconstruct_for_description`, `ReconstructionConfig()`: near "
        "light for the LED captures); randomised spacing (x0.92-1.08), width, crimp (x0.7-1.3), orientation 0-180 "
        "deg, dye (x0.45-1.25) on every class and on half of every class a printed motif (blotches 0.8-3 mm, edges "
        "1.5-12 px, tone x0.25-1.6: the print class's own ink is inside that range), lift 0-1 mm, wrinkles in 30%. "
        f"Dataset built in {elapsed:.0f} s ("
        + ("reconstructions read from the cache where present" if args.cache else "every reconstruction in this run")
        + "). Classifier: scikit-learn LogisticRegression on standardised features, C chosen by 5-fold "
        f"cross-validation on the training samples grouped by seed (descriptors: {chosen(structure)}; image: "
        f"{chosen(texture)}; both: {chosen(both)}).",
        "",
        table(["features", "test accuracy (95% Wilson interval)"],
              [["structure descriptors (psmini.fabric)", accuracy_cell(right_s)],
               ["single LED image: GLCM + LBP (baseline)", accuracy_cell(right_t)],
               ["difference (points)", against_baseline(right_s, right_t, "the descriptors")],
               ["descriptors and the image's texture together", accuracy_cell(right_b)],
               ["together against the baseline (points)", against_baseline(right_b, right_t, "both together")]]),
        "",
        "Descriptors that carry it (permutation importance on the test set, mean accuracy drop):",
        "",
        table(["descriptor", "accuracy drop"],
              [[DESCRIPTOR_NAMES[k], f"{importance.importances_mean[k]:.3f}"] for k in order]),
        "",
        "Confusion matrix, structure descriptors (rows true, columns predicted; "
        + ", ".join(classes) + "):",
        "",
        "```",
        "\n".join(" ".join(f"{v:2d}" for v in row) for row in cm_s),
        "```",
        "",
        f"Confusion matrices as a figure: `{_shown(args.figure)}`; "
        f"model: `{_shown(args.model)}` (JSON, format "
        f"{classifier.to_dict()['format']} v{classifier.to_dict()['version']}).",
    ]
    text = "\n".join(body)
    print(text)
    if not args.no_ledger:
        append_results("Fabric recognition: structure descriptors vs single-image texture", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
