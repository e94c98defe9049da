"""Fabric recognition from measured structure vs. the single-image premise, on randomised synthetic fabrics.

Every class of ``data_synth.FABRICS``, each sample drawn by ``data_synth.fabric_dataset`` from its seed (yarn
spacing, width, crimp, orientation over 0-180 deg, dyed and printed albedo independent of the relief, the cloth
0-1 mm above the card, wrinkles, the simulator's noise and 8-bit quantisation), reconstructed by psmini's default
pipeline (``psmini.fabric.reconstruct_for_description``: near light for these LED captures), described
(``psmini.fabric.describe`` -> ``descriptor_vector``: ISO 25178-2 parameters, densities, crossing angle, repeat,
crimp, openness, waviness, and the albedo-relief coupling; no albedo level or contrast). ``--cache DIR`` keeps
each reconstruction (keyed by a hash of the dataset, rig and pipeline code), so a second run only describes.
Beside it, the seed paper's premise: the same classifier on texture features of ONE LED image (scikit-image's
grey-level co-occurrence properties at 4 distances, averaged and ranged over 4 angles, and uniform local binary
pattern histograms at two radii). The classifier is scikit-learn's multinomial logistic regression on
standardised features, for both; the split is by seed (train seeds 0..N-1, test seeds 10000..), so no sample is
in both. Prints and appends to ``benchmarks/results.md`` the accuracies, the confusion matrices (and writes them
as a PNG) and the descriptors that carry the accuracy (permutation importance on the test set); saves the
trained model as JSON (``psmini.fabric.FabricClassifier``; ``psmini describe --model``).

Each accuracy comes with its 95% Wilson score interval, and the difference with an exact McNemar test (both
classifiers are scored on the same test samples: only the samples that one gets right and the other wrong say which
is better). A third row trains the same classifier on both feature sets: what the relief adds to the image.
The defaults, 24 training and 20 test seeds per class (264 and 220 samples), keep the interval within
about 3 points: with 6 test seeds (66 samples) it is about 5 points wide either side, wider than the differences
being compared (95.5% there came out as 92.7% on 220 samples with the same 8 training seeds).

Needs the ``fabric`` extra (scikit-learn, scikit-image). Usage::

    python benchmarks/fabric_recognition.py [--train-seeds 24] [--test-seeds 20] [--size 256] [--cache .fabric_cache]
"""

from __future__ import annotations

import argparse
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

# What a cached reconstruction depends on: the dataset's and the rig's code, the pipeline's, and the configuration.
_CACHE_SOURCES = ("data_synth/fabric_dataset.py", "data_synth/fabrics.py", "data_synth/rig.py", "psmini/pipeline.py",
                  "psmini/nearlight.py", "psmini/normals.py", "psmini/flatfield.py")


def cache_tag() -> str:
    """A hash of the sources and configuration a reconstruction depends on (a stale cache entry is never read)."""
    import hashlib
    import json

    digest = hashlib.sha1(json.dumps(CONFIG.to_dict(), sort_keys=True, default=str).encode())
    for name in _CACHE_SOURCES:
        path = REPO / name
        digest.update(path.read_bytes() if path.is_file() else name.encode())
    return digest.hexdigest()[:12]


def reconstruction(name: str, seed: int, options, card, cache: Path | None):
    """(depth, mask, albedo) of one sample by the default pipeline and its first LED image, from the cache when
    there (``cache/<class>-<seed>-<size>-<tag>.npz``, written through a temporary file)."""
    from data_synth.fabric_dataset import render_sample
    from psmini.fabric import reconstruct_for_description

    path = cache / f"{name}-{seed}-{options.size}-{cache_tag()}.npz" if cache is not None else None
    if path is not None and path.is_file():
        data = np.load(path)
        return (torch.from_numpy(data["depth"]), torch.from_numpy(data["mask"]), torch.from_numpy(data["albedo"]),
                data["image"])
    sample, _, capture = render_sample(name, seed, options, card)
    rec = reconstruct_for_description(sample, CONFIG)
    out = rec.depth[:1].cpu(), rec.mask[:1].cpu(), rec.albedo[:1].cpu(), capture.images[0].numpy()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.stem}.tmp.npz")
        np.savez(temporary, depth=out[0].numpy(), mask=out[1].numpy(), albedo=out[2].numpy(), image=out[3])
        temporary.replace(path)
    return out


def build(seeds: list[int], options, card, cache: Path | None = None, log_every: int = 11):
    """Descriptors, baseline features and labels for every class and seed."""
    from data_synth.fabric_dataset import CLASSES
    from psmini.fabric import describe, descriptor_vector

    structure, texture, labels = [], [], []
    count, start = 0, time.perf_counter()
    for seed in seeds:
        for name in CLASSES:
            depth, mask, albedo, image = reconstruction(name, seed, options, card, cache)
            entry = describe(depth, options.rig.pixel_pitch_mm, mask, albedo)[0]
            structure.append(descriptor_vector(entry))
            texture.append(texture_features(image))
            labels.append(name)
            count += 1
            if count % log_every == 0:
                print(f"  {count} samples, {time.perf_counter() - start:.0f} s", flush=True)
    return np.stack(structure), np.stack(texture), np.array(labels)


def wilson_interval(correct: int, total: int, z: float = 1.959964) -> tuple[float, float]:
    """The 95% Wilson score interval of a proportion ``correct / total`` (Wilson 1927)."""
    share = correct / total
    centre = (share + z * z / (2 * total)) / (1 + z * z / total)
    half = z * math.sqrt(share * (1 - share) / total + z * z / (4 * total * total)) / (1 + z * z / total)
    return centre - half, centre + half


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
    return (f"{100 * (right.mean() - baseline.mean()):+.1f} (exact McNemar p = "
            f"{mcnemar_exact(only, only_baseline):.2g}: "
            f"{only} test samples only {who} get right, {only_baseline} only the baseline)")


def fit(x: np.ndarray, y: np.ndarray):
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    model = make_pipeline(StandardScaler(), LogisticRegression(C=10.0, max_iter=20000))
    return model.fit(x, y)


def to_classifier(model, names):
    """The fitted scikit-learn pipeline as a code-free :class:`psmini.fabric.FabricClassifier`."""
    from psmini.fabric import FabricClassifier

    scaler, logistic = model.steps[0][1], model.steps[1][1]
    scale = np.where(scaler.scale_ > 0, scaler.scale_, 1.0)
    return FabricClassifier(tuple(str(c) for c in logistic.classes_), tuple(names), tuple(map(float, scaler.mean_)),
                            tuple(map(float, scale)), tuple(tuple(map(float, row)) for row in logistic.coef_),
                            tuple(map(float, logistic.intercept_)))


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--train-seeds", type=int, default=24)
    parser.add_argument("--test-seeds", type=int, default=20)
    parser.add_argument("--size", type=int, default=256, help="crop side, pixels (0.025 mm each)")
    parser.add_argument("--model", type=Path, default=REPO / "benchmarks" / "fabric_model.json")
    parser.add_argument("--figure", type=Path, default=REPO / "benchmarks" / "fabric_confusion.png")
    parser.add_argument("--no-ledger", action="store_true", help="do not append to benchmarks/results.md")
    parser.add_argument("--cache", type=Path, default=None, metavar="DIR",
                        help="keep each sample's reconstruction in DIR and reuse it on the next run (keyed by a hash "
                        "of the dataset, rig and pipeline code and configuration)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

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
    train_s, train_t, train_y = build(list(range(args.train_seeds)), options, card, args.cache)
    print(f"test: seeds 10000..{10000 + args.test_seeds - 1} x {len(CLASSES)} classes")
    test_s, test_t, test_y = build(list(range(10_000, 10_000 + args.test_seeds)), options, card, args.cache)
    elapsed = time.perf_counter() - start
    structure = fit(train_s, train_y)
    texture = fit(train_t, train_y)
    right_s, right_t = structure.predict(test_s) == test_y, texture.predict(test_t) == test_y
    acc_s, acc_t = float(right_s.mean()), float(right_t.mean())
    # what the relief adds to the image: the same classifier on both feature sets
    both = fit(np.hstack([train_s, train_t]), train_y)
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
        f"(seeds 10000..{10000 + args.test_seeds - 1}); {args.size}x{args.size} px at 0.025 mm "
        f"({args.size * 0.025:.1f} mm fields), 8-bit simulated rig captures (noise, shadows, vignetting), "
        "reconstructed by psmini's default pipeline (`reconstruct_for_description`, `ReconstructionConfig()`: near "
        "light for the LED captures); randomised spacing (x0.92-1.08), width, crimp (x0.7-1.3), orientation 0-180 "
        "deg, dye (x0.45-1.25) on every class and on half of every class a printed motif (blotches 0.8-3 mm, edges "
        "1.5-12 px, tone x0.25-1.6: the print class's own ink is inside that range), lift 0-1 mm, wrinkles in 30%. "
        f"Dataset built in {elapsed:.0f} s ("
        + ("reconstructions read from the cache where present" if args.cache else "every reconstruction in this run")
        + "). Classifier: scikit-learn LogisticRegression (C=10) on standardised features, both rows.",
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
        "Confusion matrices as a figure: "
        f"`{args.figure.relative_to(REPO) if args.figure.is_relative_to(REPO) else args.figure}`; "
        f"model: `{args.model.relative_to(REPO) if args.model.is_relative_to(REPO) else args.model}` (JSON, format "
        f"{classifier.to_dict()['format']} v{classifier.to_dict()['version']}).",
    ]
    text = "\n".join(body)
    print(text)
    if not args.no_ledger:
        append_results("Fabric recognition: structure descriptors vs single-image texture", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
