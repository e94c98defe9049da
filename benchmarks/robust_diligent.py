"""Robust normal estimators (psmini.robust) on every DiLiGenT object under a root, next to the published rows.

For each object and method: the mean and median angular error over the mask (DiLiGenT's protocol, see
benchmarks/diligent.py), the best time of the batched torch estimator over the mask pixels, and the speed-up
over a straightforward per-pixel Python loop of the same estimator (NumPy, ``np.linalg.lstsq`` per pixel and
IRLS iteration) measured in the same run. The loop is timed on a random subset of mask pixels (``--loop-pixels``,
2,000 by default) and extrapolated linearly to the whole mask; its normals on that subset are compared with
the torch ones (last column) to show it is the same estimator. Every method runs with its defaults: nothing is
tuned per object.

Two estimators are not per-pixel IRLS. "rpca" (low-rank recovery, Wu et al. 2010) works on the whole K x N matrix
of an image: its baseline is the same inexact ALM in plain NumPy with ``np.linalg.svd`` of the matrix per iteration
(the textbook form), run on the whole mask. "nonlambertian" (Lambertian + Blinn-Phong by robust Levenberg-Marquardt,
psmini.nonlambertian) is compared with the same optimiser written per pixel in NumPy (same starts, race and
iterations, ``np.linalg.solve`` of each 5x5 system, the lobe's likelihood-ratio test with the noise level pooled
over the loop's pixels), timed on ``--nl-loop-pixels`` (200) mask pixels from the torch robust start and
extrapolated; its per-pixel time adds that of the tukey loop, which the torch time includes as the start.

Then the same methods on data_synth fabrics rendered by the simulated rig (``--fabrics``, default lurex and satin:
metallic tapes and long floats under 8 LEDs at ~58°, cast shadows, shot and read noise, 10 bits), with the LEDs as
distant lights from the field centre; the mean error is also given over the metallic pixels alone.

    python benchmarks/robust_diligent.py [ROOT] [--device cpu|cuda] [--threads N] [--loop-pixels N] [--no-record]
                                         [--fabrics lurex,satin] [--fabric-size 400]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import SHARED_DATA, append_results, best_time, table  # noqa: E402
from benchmarks.diligent import object_folders  # noqa: E402
from psmini.io import load_sample  # noqa: E402
from psmini.metrics import mean_angular_error, median_angular_error  # noqa: E402
from psmini.nonlambertian import NonLambertianOptions, nonlambertian_normals  # noqa: E402
from psmini.normals import albedo_normals  # noqa: E402
from psmini.pipeline import distant_light_matrix  # noqa: E402
from psmini.robust import RECOMMENDED_ROBUST_METHOD, ROBUST_METHODS, RobustOptions, robust_normals  # noqa: E402

# Mean angular error (degrees) on ball / cat, DiLiGenT benchmark (Shi et al., TPAMI 2019, Table 2).
PUBLISHED = {
    "least squares (Woodham 1980)": {"ball": 4.10, "cat": 8.41},
    "RPCA (Wu et al. 2010)": {"ball": 2.06, "cat": 6.73},
    "sparse regression (Ikehata et al. 2012)": {"ball": 2.54, "cat": 7.21},
    "bi-polynomial BRDF (Shi et al. 2014)": {"ball": 1.74, "cat": 6.12},
}
TUNING = {"huber": 1.345, "cauchy": 2.385, "tukey": 4.685}
# psmini.robust's cast-shadow stage: the model error, the costs of its mixture, the upper band and the support
CAST = {"tau": 0.05, "upper": 0.75, "support": 6,
        "shadow_cost": 2 * np.log(0.5 / (np.sqrt(2 * np.pi) * 0.05)),
        "outlier_cost": 2 * np.log(2 / (np.sqrt(2 * np.pi) * 0.05))}
DEFAULTS = {k: v for k, v in RobustOptions().to_dict().items() if v is not None}
# psmini.nonlambertian's defaults and constants, for the per-pixel loop
NL = {**{k: v for k, v in NonLambertianOptions().to_dict().items() if v is not None},
      "race": 6, "faint": (0.01, 30.0), "peak_ratio": 4.0}


def _loop_irls(values, lights, kept, m, method, iterations, cast):
    """IRLS iterations of psmini.robust on one pixel's thresholded readings (``kept``, bool (K,)); with ``cast``,
    only the readings the current estimate explains as lit (|I - p| < I: p > 0 and I >= p / 2) count, and the scale
    is taken over the readings lit at the first of these iterations."""
    sub_lights, sub_values = lights[kept], values[kept]
    floor = 1e-6 * np.abs(values).max() + 1e-38
    scale_set = None
    for _ in range(iterations):
        prediction = sub_lights @ m
        residuals = sub_values - prediction
        use = np.ones_like(residuals)
        if cast:
            use = (np.abs(residuals) < sub_values).astype(float)
            scale_set = use > 0 if scale_set is None else scale_set
        size = np.abs(residuals)
        if method == "l1":
            weights = 1.0 / np.maximum(size, DEFAULTS["l1_epsilon"] * np.abs(values).mean())
        else:
            # the lower median over every thresholded reading (or the stage's lit ones), as psmini.robust selects it
            chosen = size if scale_set is None else size[scale_set]
            scale = (1.4826 * np.sort(chosen)[(len(chosen) - 1) // 2] if len(chosen) else np.inf) + floor
            u = size / (TUNING[method] * scale)
            if method == "huber":
                weights = 1.0 / np.maximum(u, 1.0)
            elif method == "cauchy":
                weights = 1.0 / (1.0 + u * u)
            else:
                weights = np.clip(1.0 - u * u, 0.0, None) ** 2
        weights = weights * use
        if np.count_nonzero(weights) < 3:
            break
        root = np.sqrt(weights)
        m = np.linalg.lstsq(sub_lights * root[:, None], sub_values * root, rcond=None)[0]
    return m


def loop_pixel(values: np.ndarray, lights: np.ndarray, method: str) -> np.ndarray:
    """One pixel's m = albedo * normal by the per-pixel textbook version of ``method`` (``values`` (K,))."""
    k = values.shape[0]
    if method == "lstsq":
        return np.linalg.lstsq(lights, values, rcond=None)[0]
    if method == "trimmed":
        order = np.argsort(values, kind="stable")
        keep = order[int(np.floor(k * DEFAULTS["low"])): k - int(np.floor(k * DEFAULTS["high"]))]
        return np.linalg.lstsq(lights[keep], values[keep], rcond=None)[0]
    kept = values > DEFAULTS["shadow"] * values.max()
    n = int(kept.sum())
    if n < 3:
        return np.zeros(3)
    if method == "threshold":
        return np.linalg.lstsq(lights[kept], values[kept], rcond=None)[0]
    # start: least squares on the readings between the trimmed ranks of the thresholded ones
    ordered = np.sort(values[kept])
    band = kept & (values >= ordered[int(np.floor(n * DEFAULTS["low"]))]) \
        & (values <= ordered[max(n - 1 - int(np.floor(n * DEFAULTS["high"])), 0)])
    m = np.linalg.lstsq(lights[kept], values[kept], rcond=None)[0]
    if band.sum() >= 3:  # the more consistent of the two starts
        m = _more_consistent(values, lights, m, np.linalg.lstsq(lights[band], values[band], rcond=None)[0])
    shadow = min(DEFAULTS["shadow_iterations"], DEFAULTS["iterations"])
    m = _loop_irls(values, lights, kept, m, method, DEFAULTS["iterations"] - shadow, cast=False)
    if shadow == 0:
        return m
    # the cast-shadow stage: from the brightest quarter of the thresholded readings when the estimate so far
    # explains fewer than half of them as lit; the more likely of its result and that estimate
    plain_cost, plain_lit = _likelihood(values, lights, kept, m)
    upper = kept & (values >= ordered[int(np.floor(n * CAST["upper"]))])
    start = m
    if 2 * plain_lit < n and upper.sum() >= 3:
        start = np.linalg.lstsq(lights[upper], values[upper], rcond=None)[0]
    m_cast = _loop_irls(values, lights, kept, start, method, shadow, cast=True)
    cast_cost, cast_lit = _likelihood(values, lights, kept, m_cast)
    return m_cast if cast_cost < plain_cost and cast_lit >= CAST["support"] else m


def _likelihood(values, lights, kept, m):
    """psmini.robust's mixture cost of m over the kept readings (lit: Gaussian of sd tau (p+ + t); cast shadow,
    I < p / 2: its own cost; other: the outlier cost) and the count of readings better explained as lit."""
    tau, level = CAST["tau"], DEFAULTS["shadow"] * values[kept].max() + 1e-38
    prediction = lights @ m
    positive = np.maximum(prediction, 0)
    lit_cost = ((values - positive) / (tau * (positive + level))) ** 2
    cost = np.where(2 * values < prediction, CAST["shadow_cost"], np.minimum(lit_cost, CAST["outlier_cost"]))
    return float(cost[kept].sum()), int((kept & (lit_cost < CAST["shadow_cost"])).sum())


def _more_consistent(values, lights, first, second):
    """The estimate whose clamped model has the lower (lower-)median absolute residual over all readings."""
    k = values.shape[0]
    spread = [np.sort(np.abs(values - np.maximum(lights @ x, 0)))[(k - 1) // 2] for x in (first, second)]
    return second if spread[1] < spread[0] else first


def loop_rpca(values: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """m (3, N) by the textbook inexact ALM (np.linalg.svd per iteration) on the whole (K, N) matrix, then lstsq."""
    observed = values > DEFAULTS["shadow"] * values.max(axis=0, keepdims=True)
    weight = 1.0 / np.sqrt(max(values.shape))
    spectral = np.linalg.norm(values, 2)
    multiplier = values / max(spectral, np.abs(values).max() / weight)
    penalty, low_rank = 1.25 / spectral, np.zeros_like(values)
    for _ in range(DEFAULTS["rpca_iterations"]):
        target = values - low_rank + multiplier / penalty
        sparse = np.where(observed, np.sign(target) * np.maximum(np.abs(target) - weight / penalty, 0), target)
        u, sigma, vt = np.linalg.svd(values - sparse + multiplier / penalty, full_matrices=False)
        low_rank = (u * np.maximum(sigma - 1.0 / penalty, 0)) @ vt
        multiplier = multiplier + penalty * (values - low_rank - sparse)
        penalty *= 1.5
    return np.linalg.lstsq(lights, low_rank, rcond=None)[0]


def _nl_shade(n, rho, s, alpha, lights, energy, half):
    cosine = lights @ n
    g = np.maximum(half @ n, 1e-300)
    lobe = np.where(cosine > 0, energy * g ** alpha, 0.0)
    return cosine, lobe, g, rho * np.maximum(cosine, 0) + s * lobe


def _nl_cost(residuals, usable, sigma):
    return float((usable * np.log1p((residuals / sigma) ** 2)).sum())


def _nl_iterate(values, usable, sigma, most, lights, energy, half, state, damping, iterations):
    """Per-pixel Levenberg-Marquardt of psmini.nonlambertian on one pixel (state: n, rho, s, log alpha)."""
    n, rho, s, log_alpha = state
    cost = _nl_cost(values - _nl_shade(n, rho, s, np.exp(log_alpha), lights, energy, half)[3], usable, sigma)
    top = np.log(NL["max_shininess"])
    for _ in range(iterations):
        alpha = np.exp(log_alpha)
        cosine, lobe, g, model = _nl_shade(n, rho, s, alpha, lights, energy, half)
        residuals = values - model
        weights = usable / (1 + (residuals / sigma) ** 2)
        axis = np.array([1.0, 0, 0]) if abs(n[2]) > 0.9 else np.array([0, 0, 1.0])
        first = np.cross(n, axis)
        first /= np.linalg.norm(first)
        second = np.cross(n, first)
        diffuse, glossy = rho * (cosine > 0), s * alpha * lobe / g
        jacobian = np.stack([diffuse * (lights @ first) + glossy * (half @ first),
                             diffuse * (lights @ second) + glossy * (half @ second),
                             np.maximum(cosine, 0), lobe, s * alpha * lobe * np.log(g)], axis=1)  # (K, 5)
        gram = jacobian.T @ (weights[:, None] * jacobian)
        diagonal = np.diag(gram)
        try:
            step = np.linalg.solve(gram + np.diag(damping * diagonal + 1e-9 * diagonal.sum() + 1e-300),
                                   jacobian.T @ (weights * residuals))
        except np.linalg.LinAlgError:
            step = np.zeros(5)
        trial_n = n + step[0] * first + step[1] * second
        trial = (trial_n / np.linalg.norm(trial_n), max(rho + step[2], 0.0), min(max(s + step[3], 0.0), most),
                 float(np.clip(log_alpha + step[4], 0.0, top)))
        trial_cost = _nl_cost(values - _nl_shade(trial[0], trial[1], trial[2], np.exp(trial[3]), lights, energy,
                                                 half)[3], usable, sigma)
        if trial_cost < cost:
            (n, rho, s, log_alpha), cost, damping = trial, trial_cost, max(damping / 3, 1e-7)
        else:
            damping = min(damping * 4, 1e7)
    return (n, rho, s, log_alpha), cost, damping


def loop_nonlambertian(values: np.ndarray, lights: np.ndarray, rho0: float,
                       n0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """One pixel's fitted and starting normals, its lobe-test statistics and whether the readings locate the lobe,
    by the per-pixel version of psmini.nonlambertian (``values`` (K,), robust start)."""
    # the thresholded readings that the start explains as lit (|I - p| < I), as psmini.nonlambertian keeps them
    usable = ((values > NL["shadow"] * values.max()) & (np.abs(values - lights @ (rho0 * n0)) < values)).astype(float)
    energy = np.linalg.norm(lights, axis=1)
    half = lights / energy[:, None] + np.array([0, 0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    kept = np.sort(values[usable > 0])
    sigma = max(NL["scale"] * kept[(len(kept) - 1) // 2], 1e-6 * kept[-1] + 1e-300)
    most = NL["peak_ratio"] * (usable * values / energy).max()
    faint = (n0, rho0, NL["faint"][0] * rho0, np.log(NL["faint"][1]))
    peak = half[np.argmax(np.where(usable > 0, values, -np.inf))]
    bisector = (n0 + peak) / max(np.linalg.norm(n0 + peak), 1e-300)
    best, best_cost = None, np.inf
    for normal in (n0, peak, bisector):
        for exponent in NL["shininess"]:
            cosine, lobe, _, _ = _nl_shade(normal, rho0, rho0, exponent, lights, energy, half)
            design = np.stack([np.maximum(cosine, 0), lobe], axis=1) * usable[:, None]
            a, b, d = design[:, 0] @ design[:, 0], design[:, 0] @ design[:, 1], design[:, 1] @ design[:, 1]
            r1, r2 = design[:, 0] @ values, design[:, 1] @ values
            s = min(max((a * r2 - b * r1) / max(a * d - b * b, 1e-300), 0.0), most)
            rho = max((r1 - b * s) / max(a, 1e-300), 0.0)
            cost = _nl_cost(values - _nl_shade(normal, rho, s, exponent, lights, energy, half)[3], usable, sigma)
            if cost < best_cost:
                best, best_cost = (normal, rho, s, np.log(exponent)), cost
    raced = [_nl_iterate(values, usable, sigma, most, lights, energy, half, start, 1e-2, NL["race"])
             for start in (faint, best)]
    state, _, damping = raced[0] if raced[0][1] <= raced[1][1] else raced[1]
    state, _, _ = _nl_iterate(values, usable, sigma, most, lights, energy, half, state, damping,
                              NL["iterations"] - NL["race"])
    # the statistics of the likelihood-ratio test (psmini.nonlambertian._keep_lobe): both models' residual sums of
    # squares on the usable readings, the median usable reading and the count; the test pools over pixels
    squares = [float((usable * (values - _nl_shade(n, rho, s, alpha, lights, energy, half)[3]) ** 2).sum())
               for n, rho, s, alpha in ((state[0], state[1], state[2], np.exp(state[3])), (n0, rho0, 0.0, 1.0))]
    # the lobe's peak among the half vectors, or the lobe at most half their cone wide (psmini's _peak_observed)
    axis = half.mean(axis=0) / np.linalg.norm(half.mean(axis=0))
    widest = (half @ axis).min()
    observed = state[0] @ axis >= widest or np.arccos(2 ** (-1 / np.exp(state[3]))) <= np.arccos(widest) / 2
    return state[0], n0, np.array(squares + [kept[(len(kept) - 1) // 2], usable.sum()]), bool(observed)


def lobe_test(statistics: np.ndarray) -> np.ndarray:
    """Per pixel, whether the lobe passes the likelihood-ratio test at NL["significance"]: (n, 4) statistics of
    loop_nonlambertian, the noise level pooled over these pixels (psmini pools over the whole image)."""
    fit, start, median, count = statistics.T
    free = count > 5
    if not free.any():
        return np.zeros(len(count), bool)
    degrees = np.maximum(count - 5, 1)
    chi2_median = degrees * (1 - 2 / (9 * degrees)) ** 3  # Wilson & Hilferty 1931
    noise = np.sort((fit / (median**2 * chi2_median))[free])[(free.sum() - 1) // 2]  # lower median
    return (start - fit) / (noise * median**2) > -2 * np.log(NL["significance"])


def torch_normals(images, lights, mask, method):
    if method == "lstsq":
        return albedo_normals(images, lights, mask)[1]
    if method == "nonlambertian":
        return nonlambertian_normals(images, lights, mask)[1]
    return robust_normals(images, lights, method, mask)[1]


def loop_time(method, values_np, lights_np, start, ours):
    """Per-pixel seconds of the loop version of ``method`` and its mean angle (°) to the torch normals ``ours``."""
    begin = time.perf_counter()
    if method == "rpca":  # a matrix method: the baseline runs on the whole mask
        loop_m = loop_rpca(values_np, lights_np)
    elif method == "nonlambertian":
        rho0, n0 = start
        fits = [loop_nonlambertian(values_np[:, i], lights_np, rho0[i], n0[:, i]) for i in range(values_np.shape[1])]
        lobe = lobe_test(np.stack([f[2] for f in fits])) & np.array([f[3] for f in fits])
        loop_m = np.stack([f[0] if keep else f[1] for f, keep in zip(fits, lobe, strict=True)], 1)
    else:
        loop_m = np.stack([loop_pixel(values_np[:, i], lights_np, method) for i in range(values_np.shape[1])], 1)
    per_pixel = (time.perf_counter() - begin) / values_np.shape[1]
    loop_n = loop_m / np.maximum(np.linalg.norm(loop_m, axis=0, keepdims=True), 1e-30)
    return per_pixel, np.degrees(np.arccos(np.clip((loop_n * ours).sum(0), -1.0, 1.0))).mean()


def fabric_rows(names: list[str], size: int, methods: tuple[str, ...], device: torch.device) -> list[list]:
    """Rows (fabric, method, mean °, metallic mean °, pixels, seconds) on data_synth renders with distant LEDs."""
    from data_synth import make_fabric
    from data_synth.rig import RigConfig, distant_lights, render_capture

    rows = []
    for name in names:
        config = RigConfig(size=size)
        fabric = make_fabric(name, size=size)
        lights = distant_lights(config)
        capture = render_capture(fabric, config, lights=lights)
        images = (capture.images - capture.dark).unsqueeze(0).to(device)
        matrix = (lights.directions * lights.intensities[:, None]).to(device)
        mask = fabric.mask.to(device)
        truth = capture.normals.unsqueeze(0).to(device)
        metallic = mask & (fabric.specular.to(device) > 0)
        for method in methods:
            begin = time.perf_counter()
            normals = torch_normals(images, matrix, mask, method)
            seconds = time.perf_counter() - begin
            on_metal = float(mean_angular_error(normals, truth, metallic)[0]) if bool(metallic.any()) else "—"
            rows.append([name, method, float(mean_angular_error(normals, truth, mask)[0]), on_metal,
                         int(mask.sum()), seconds])
            print(f"{name:8s} {method:13s} {rows[-1][2]:6.3f} deg  {seconds:7.3f} s", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", nargs="?", type=Path, default=SHARED_DATA / "DiLiGenT")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--loop-pixels", type=int, default=2000, help="mask pixels the per-pixel loop is timed on")
    parser.add_argument("--nl-loop-pixels", type=int, default=200,
                        help="mask pixels the per-pixel loop of the non-Lambertian fit is timed on")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs of each torch estimator (best is kept)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (default 1: the loop is single-threaded, and on a shared machine "
                        "more threads than free cores stall every parallel op)")
    parser.add_argument("--fabrics", default="lurex,satin",
                        help="comma-separated data_synth fabrics to add (empty: none)")
    parser.add_argument("--fabric-size", type=int, default=400, help="side of the fabric renders, pixels")
    parser.add_argument("--no-record", action="store_true", help="do not append to benchmarks/results.md")
    args = parser.parse_args(argv)
    folders = object_folders(args.root)
    if not folders:
        print(f"no DiLiGenT object folder under {args.root}", file=sys.stderr)
        return 1
    device = torch.device(args.device)
    torch.set_num_threads(args.threads)
    methods = ("lstsq",) + ROBUST_METHODS + ("nonlambertian",)
    rows, errors = [], {}
    for folder in folders:
        sample = load_sample(folder)
        assert sample.mask is not None and sample.normals_gt is not None, f"{folder} lacks a mask or normals"
        images = sample.images.to(device).unsqueeze(0)
        mask = sample.mask.to(device).unsqueeze(0).bool()
        normals_gt = torch.nan_to_num(sample.normals_gt.to(device).unsqueeze(0))
        lights = distant_light_matrix(sample.lights.to(device), False, images)
        pixels = int(mask.sum())
        rng = np.random.default_rng(0)
        subset = rng.choice(pixels, size=min(args.loop_pixels, pixels), replace=False)
        all_values = images[0][:, mask[0, 0]].double().cpu().numpy()
        values_np = all_values[:, subset]  # (K, n)
        lights_np = lights.double().cpu().numpy()
        start_albedo, start_normals = robust_normals(images, lights, RECOMMENDED_ROBUST_METHOD, mask)
        nl_subset = subset[:args.nl_loop_pixels]
        nl_start = (start_albedo[0, 0][mask[0, 0]].double().cpu().numpy()[nl_subset],
                    start_normals[0][:, mask[0, 0]].double().cpu().numpy()[:, nl_subset])
        tukey_loop = None
        for method in methods:
            # the non-Lambertian fit takes seconds: time it once (its first run is the timed one)
            repeat, warmup = (1, 0) if method == "nonlambertian" else (args.repeat, 1)
            def solve(images=images, lights=lights, mask=mask, method=method):
                return torch_normals(images, lights, mask, method)

            seconds = best_time(solve, repeat, warmup, args.device)
            normals = torch_normals(images, lights, mask, method)
            ours = normals[0][:, mask[0, 0]].double().cpu().numpy()
            if method == "rpca":
                loop_per_pixel, agreement = loop_time(method, all_values, lights_np, None, ours)
            elif method == "nonlambertian":
                loop_per_pixel, agreement = loop_time(method, values_np[:, :len(nl_subset)], lights_np, nl_start,
                                                      ours[:, nl_subset])
                loop_per_pixel += tukey_loop
            else:
                loop_per_pixel, agreement = loop_time(method, values_np, lights_np, None, ours[:, subset])
            if method == RECOMMENDED_ROBUST_METHOD:
                tukey_loop = loop_per_pixel
            mean = float(mean_angular_error(normals, normals_gt, mask)[0])
            errors[(folder.name, method)] = mean
            rows.append([
                folder.name, method, mean, float(median_angular_error(normals, normals_gt, mask)[0]), pixels, seconds,
                seconds / pixels * 1e6, loop_per_pixel * 1e6, loop_per_pixel * pixels / seconds, f"{agreement:.2g}",
            ])
            print(f"{folder.name:8s} {method:9s} {mean:6.3f} deg  {seconds:7.3f} s  "
                  f"loop {loop_per_pixel * 1e6:7.1f} us/px", flush=True)
    header = ["object", "method", "mean (°)", "median (°)", "mask pixels", "torch (s)", "torch (µs/px)",
              "loop (µs/px)", "speed-up", "loop vs torch (°)"]
    report = table(header, rows)
    names = [f.name for f in folders]
    published_rows: list[list[object]] = [[m, *(by.get(n, "—") for n in names)] for m, by in PUBLISHED.items()]
    published_rows += [[f"psmini {m}" + (" (= robust)" if m == RECOMMENDED_ROBUST_METHOD else ""),
                        *(errors[(n, m)] for n in names)] for m in methods]
    published = table(["method (published)"] + names, published_rows)
    note = (f"Loop: per-pixel NumPy (np.linalg.lstsq per pixel and IRLS iteration), timed on {args.loop_pixels} "
            "random mask pixels and extrapolated linearly to the whole mask (speed-up = loop time for the mask / "
            "torch time for the mask). rpca: the same inexact ALM in NumPy with np.linalg.svd of the whole matrix "
            "per iteration, on the whole mask. nonlambertian: the same Levenberg-Marquardt per pixel in NumPy on "
            f"{args.nl_loop_pixels} of those pixels from the torch robust start, extrapolated, plus the tukey loop's "
            "time per pixel (the torch time includes the robust start), with the lobe's likelihood-ratio test "
            "pooling its noise level over those pixels (psmini over the whole image); torch timed once. "
            f"Torch: best of {args.repeat}, device {args.device}, "
            f"{torch.get_num_threads()} threads. Defaults for every method: {DEFAULTS}; no per-object tuning.")
    fabrics = [name for name in args.fabrics.split(",") if name]
    fabric_report = ""
    if fabrics:
        fabric_report = table(["fabric", "method", "mean (°)", "metallic pixels mean (°)", "pixels", "torch (s)"],
                              fabric_rows(fabrics, args.fabric_size, methods, device))
        fabric_report = ("data_synth fabrics, simulated rig (8 LEDs, cast shadows, noise, 10 bits), LEDs as distant "
                         f"lights, {args.fabric_size}x{args.fabric_size} px, torch timed once:\n\n" + fabric_report)
    print(report)
    print()
    print(published)
    print(note)
    print(fabric_report)
    if not args.no_record:
        append_results("Robust normals on DiLiGenT (benchmarks/robust_diligent.py)",
                       report + "\n\n" + published + "\n\n" + note + ("\n\n" + fabric_report if fabrics else ""),
                       args.device)
    return 0


if __name__ == "__main__":
    sys.exit(main())
