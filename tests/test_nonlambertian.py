import json

import pytest
import torch

from psmini import InputError, PhotometricStereo, ReconstructionConfig, ShapeError
from psmini.cli import main
from psmini.errors import CalibrationError
from psmini.lights import DirectionalLights, PointLights, ring_lights
from psmini.metrics import angular_error_deg, mean_angular_error
from psmini.nonlambertian import (
    BlinnPhongFit,
    NonLambertianNormals,
    NonLambertianOptions,
    blinn_phong_images,
    fit_blinn_phong,
    nonlambertian_normals,
)
from psmini.normals import albedo_normals
from psmini.render import render
from tests._analytic import analytic_sphere
from tests.conftest import BaseTester, shared_data

SHININESS, SPECULAR = 40.0, 0.8


def _lights(device, dtype):
    """24 distant lights on three rings (15°, 35°, 55° from the axis): highlights land across the sphere's cap."""
    return torch.cat([ring_lights(8, zenith, device=device, dtype=dtype) for zenith in (15.0, 35.0, 55.0)])


def _glossy_sphere(device, dtype, size=40):
    """A sphere rendered by psmini.render.render with a Blinn–Phong lobe; the cap where n_z > 0.5 is scored."""
    normals, inside, albedo = analytic_sphere(size, device=device, dtype=dtype)
    lights = _lights(device, dtype)
    images = render(torch.zeros_like(normals), normals, albedo, DirectionalLights(lights),
                    specular=SPECULAR * torch.ones_like(albedo), shininess=SHININESS)
    return normals, inside & (normals[:, 2:3] > 0.5), albedo, lights, images


class TestBlinnPhongImages(BaseTester):
    def test_matches_renderer(self, device, dtype):
        normals, inside, albedo = analytic_sphere(16, device=device, dtype=dtype)
        lights = ring_lights(8, 40.0, device=device, dtype=dtype) * torch.linspace(0.5, 1.5, 8, device=device,
                                                                                    dtype=dtype)[:, None]
        specular = 0.3 * torch.ones_like(albedo)
        expected = render(torch.zeros_like(normals), normals, albedo, DirectionalLights(lights, lights.norm(dim=1)),
                          specular=specular, shininess=25.0)
        actual = blinn_phong_images(normals, albedo, specular, torch.full_like(albedo, 25.0), lights)
        self.assert_close(actual, expected)

    def test_per_pixel_lights_match_distant(self, device, dtype):
        normals, _, albedo = analytic_sphere(8, device=device, dtype=dtype)
        lights = ring_lights(6, 50.0, device=device, dtype=dtype)
        per_pixel = lights[None, :, :, None, None].expand(1, 6, 3, 8, 8)
        maps = (albedo, 0.5 * albedo, torch.full_like(albedo, 12.0))
        self.assert_close(blinn_phong_images(normals, *maps, per_pixel), blinn_phong_images(normals, *maps, lights))

    def test_gradcheck(self):
        generator = torch.Generator().manual_seed(0)
        normals = torch.tensor([0.1, -0.2, 1.0], dtype=torch.float64).view(1, 3, 1, 1) + 0.1 * torch.rand(
            1, 3, 2, 2, generator=generator, dtype=torch.float64)
        normals = normals / normals.norm(dim=1, keepdim=True)
        maps = [torch.rand(1, 1, 2, 2, generator=generator, dtype=torch.float64) + 0.5 for _ in range(3)]
        lights = ring_lights(5, 40.0, dtype=torch.float64)  # every n·l and n·h well above 0: smooth
        self.gradcheck(blinn_phong_images, (normals.requires_grad_(), *(m.requires_grad_() for m in maps), lights))

    def test_gradcheck_per_pixel_lights(self):
        generator = torch.Generator().manual_seed(1)
        normals = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(1, 3, 1, 1).expand(1, 3, 2, 2)
        lights = ring_lights(4, 30.0, dtype=torch.float64)[None, :, :, None, None] + 0.05 * torch.rand(
            1, 4, 3, 2, 2, generator=generator, dtype=torch.float64)
        ones = torch.ones(1, 1, 2, 2, dtype=torch.float64)
        self.gradcheck(lambda n, lit: blinn_phong_images(n, ones, 0.5 * ones, 8 * ones, lit),
                       (normals.clone().requires_grad_(), lights.requires_grad_()))

    def test_errors(self):
        normals = torch.zeros(1, 3, 2, 2)
        ones = torch.ones(1, 1, 2, 2)
        with pytest.raises(ShapeError, match="albedo"):
            blinn_phong_images(normals, torch.ones(1, 1, 3, 2), ones, ones, ring_lights(4, 40.0))
        with pytest.raises(InputError, match="shininess"):
            blinn_phong_images(normals, ones, ones, 0 * ones, ring_lights(4, 40.0))
        with pytest.raises(ShapeError):
            blinn_phong_images(normals, ones, ones, ones, torch.rand(1, 4, 3, 5, 5))


class TestFit(BaseTester):
    def test_recovers_glossy_sphere_where_least_squares_fails(self, device, dtype):
        normals, scored, albedo, lights, images = _glossy_sphere(device, dtype)
        least_squares = albedo_normals(images, lights, scored)[1]
        assert float(mean_angular_error(least_squares, normals, scored)[0]) > 5.0
        fit = fit_blinn_phong(images, lights, scored)
        assert isinstance(fit, BlinnPhongFit)
        errors = angular_error_deg(fit.normals, normals)[scored]
        assert float(errors.max()) < 0.5
        # the lobe itself is recovered where a highlight was seen (near the centre of the cap)
        centre = scored & (normals[:, 2:3] > 0.9)
        torch.testing.assert_close(fit.shininess[centre].median(), torch.tensor(SHININESS).to(fit.shininess),
                                   rtol=0.05, atol=0)
        torch.testing.assert_close(fit.specular[centre].median(), torch.tensor(SPECULAR).to(fit.specular),
                                   rtol=0.05, atol=0)
        torch.testing.assert_close(fit.albedo[centre], albedo[centre], rtol=0.02, atol=0)

    def test_cast_shadows_are_rejected(self, device):
        normals, scored, albedo, lights, images = _glossy_sphere(device, torch.float32)
        generator = torch.Generator().manual_seed(0)
        shadowed = torch.rand(images.shape, generator=generator).to(device) < 0.15  # 15% of readings lost to shadow
        images = images.masked_fill(shadowed, 0.0)
        fit = fit_blinn_phong(images, lights, scored)
        errors = angular_error_deg(fit.normals, normals)[scored]
        # measured: all below 0.18°; a pixel whose highlight readings all fell in shadow may be off (allowance 1%)
        assert float(errors.mean()) < 0.05 and float((errors > 0.5).double().mean()) <= 0.01

    def test_per_pixel_lights(self, device):
        """Near point lights: the light vectors (B, K, 3, H, W) carry direction and irradiance per pixel."""
        normals, inside, albedo = analytic_sphere(32, device=device, dtype=torch.float64)
        pitch = 0.25  # mm per pixel: the 8 mm patch lies under lights 12 mm away
        grid = (torch.arange(32, device=device, dtype=torch.float64) - 15.5) * pitch
        points = torch.stack([grid.view(1, 32).expand(32, 32), -grid.view(32, 1).expand(32, 32),
                              torch.zeros(32, 32, device=device, dtype=torch.float64)])[None]
        model = PointLights(12.0 * _lights(device, torch.float64))
        images = render(points, normals, albedo, model, specular=SPECULAR * torch.ones_like(albedo),
                        shininess=SHININESS)
        directions, irradiance = model(points)
        scored = inside & (normals[:, 2:3] > 0.5)
        fit = fit_blinn_phong(images, directions * irradiance, scored)
        assert float(angular_error_deg(fit.normals, normals)[scored].max()) < 0.5

    def test_batch_mask_and_module(self, device):
        normals, scored, albedo, lights, images = _glossy_sphere(device, torch.float32, size=24)
        mask = torch.cat([scored, scored.flip(-1) & scored])
        batched = nonlambertian_normals(images.expand(2, -1, -1, -1), lights, mask)
        single = nonlambertian_normals(images, lights, scored)
        self.assert_close(batched[1][:1], single[1])
        assert (batched[0][~mask] == 0).all() and (batched[1][:, 2:3][~mask] == 1).all()
        module = NonLambertianNormals(lights, NonLambertianOptions(iterations=20))
        self.assert_close(module(images, scored)[1], single[1])

    def test_init_and_weights(self, device):
        normals, scored, albedo, lights, images = _glossy_sphere(device, torch.float64, size=24)
        start = albedo_normals(images, lights, scored)  # a worse start than the robust one still converges
        fit = fit_blinn_phong(images, lights, scored, options=NonLambertianOptions(iterations=30), init=start)
        assert float(angular_error_deg(fit.normals, normals)[scored].max()) < 0.5
        # observations dropped through the weights play no part in the fit (from a given start)
        weights = torch.ones_like(images, dtype=torch.bool)
        weights[:, 3] = False
        dropped = nonlambertian_normals(images, lights, scored, weights, init=start)[1]
        corrupted = images.clone()
        corrupted[:, 3] = 10.0
        self.assert_close(nonlambertian_normals(corrupted, lights, scored, weights, init=start)[1], dropped)

    def test_autograd_path_gives_the_no_gradient_values(self):
        """The model's no-gradient fast path (in-place product with a 0/1 mask) and its autograd path (a where)
        fit the same values."""
        _, scored, _, lights, images = _glossy_sphere("cpu", torch.float64, size=12)
        options = NonLambertianOptions(iterations=5)
        plain = nonlambertian_normals(images, lights, scored, options=options)
        tracked = nonlambertian_normals(images.clone().requires_grad_(), lights, scored, options=options)
        for expected, actual in zip(plain, tracked, strict=True):
            self.assert_close(actual.detach(), expected, rtol=1e-12, atol=1e-12)

    def test_differentiable(self):
        normals, scored, albedo, lights, images = _glossy_sphere("cpu", torch.float64, size=12)
        images = images.clone().requires_grad_()
        options = NonLambertianOptions(iterations=5)
        albedo_fit, normals_fit = nonlambertian_normals(images, lights, scored, options=options)
        (normals_fit[:, 0] * scored).sum().backward()
        assert torch.isfinite(images.grad).all() and images.grad.abs().sum() > 0

    def test_gradcheck(self):
        """Every map of the fit, at glossy pixels whose lobe passes the test (specular > 0 there)."""
        generator = torch.Generator().manual_seed(0)
        normals = torch.tensor([0.1, -0.2, 1.0], dtype=torch.float64).view(1, 3, 1, 1) + 0.1 * torch.rand(
            1, 3, 2, 2, generator=generator, dtype=torch.float64)
        normals = normals / normals.norm(dim=1, keepdim=True)
        ones = torch.ones(1, 1, 2, 2, dtype=torch.float64)
        lights = ring_lights(8, 40.0, dtype=torch.float64)
        images = blinn_phong_images(normals, 0.6 * ones, 0.8 * ones, 20 * ones, lights)
        images = images * (1 + 0.01 * torch.rand(images.shape, generator=generator, dtype=torch.float64))
        options = NonLambertianOptions(iterations=3)
        assert bool((fit_blinn_phong(images, lights, options=options).specular > 0).all())
        self.gradcheck(lambda x: tuple(fit_blinn_phong(x, lights, options=options)), (images.requires_grad_(),))
        solver = NonLambertianNormals(lights, options)
        self.gradcheck(solver, (images[..., :1, :].detach().requires_grad_(),))

    def test_errors(self):
        images, lights = torch.rand(1, 8, 4, 4) + 0.1, ring_lights(8, 55.0)
        for options, match in (({"iterations": -1}, "iterations"), ({"iterations": 2.5}, "iterations"),
                               ({"shadow": 1.0}, "shadow"), ({"scale": 0.0}, "scale"),
                               ({"saturation": 0.0}, "saturation"), ({"shininess": (0.5,)}, "shininess"),
                               ({"shininess": (3000.0,)}, "shininess"), ({"significance": 0.0}, "significance"),
                               ({"significance": 1.0}, "significance")):
            with pytest.raises(InputError, match=match):
                NonLambertianOptions(**options)
        with pytest.raises(InputError, match="NaN"):
            fit_blinn_phong(images * float("nan"), lights)
        with pytest.raises(ShapeError):
            fit_blinn_phong(images, ring_lights(6, 55.0))
        with pytest.raises(CalibrationError):
            fit_blinn_phong(images, ring_lights(8, 90.0))
        with pytest.raises(ShapeError, match="init"):
            fit_blinn_phong(images, lights, init=(torch.ones(1, 1, 4, 4), torch.ones(1, 3, 4, 5)))
        with pytest.raises(InputError, match="init"):
            fit_blinn_phong(images, lights, init=torch.ones(1, 3, 4, 4))
        with pytest.raises(ShapeError):
            fit_blinn_phong(images, torch.rand(1, 8, 3, 5, 5))
        with pytest.raises(InputError, match="NonLambertianOptions"):
            NonLambertianNormals(lights, {"iterations": 3})
        with pytest.raises(InputError, match="NonLambertianOptions"):
            fit_blinn_phong(images, lights, options={"iterations": 3})
        with pytest.raises(ShapeError):
            NonLambertianNormals(torch.rand(8, 4))


class TestPipeline(BaseTester):
    def test_photometric_stereo_method(self, device):
        normals, scored, albedo, lights, images = _glossy_sphere(device, torch.float32)
        error = {}
        for method in ("robust", "nonlambertian"):
            result = PhotometricStereo(lights, None, ReconstructionConfig(estimator=method))(images, mask=scored)
            error[method] = float(mean_angular_error(result.normals, normals, scored)[0])
        assert error["nonlambertian"] < 0.1 < error["robust"]

    def test_cli_choices(self):
        with pytest.raises(SystemExit):
            main(["evaluate", "nowhere", "--method", "blinn"])


@pytest.mark.slow
def test_cli_evaluate_ball(capsys):
    """DiLiGenT ball: 1.86° measured (robust start 1.99°, least squares 4.1°); the issue asks for at most 1.9°."""
    folder = shared_data("DiLiGenT", "ball")
    assert main(["evaluate", str(folder), "--method", "nonlambertian", "--json"]) == 0
    scores = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert scores["mean_angular_error_deg"] <= 1.9


def _noisy_sphere(count, specular, noise, dtype=torch.float64):
    """Sphere under a ring of ``count`` lights at 45°, a Blinn–Phong lobe of albedo ``specular`` (0: matte) and
    multiplicative Gaussian noise of relative size ``noise`` (shot-like), with the robust start."""
    from psmini.robust import robust_normals

    normals, inside, albedo = analytic_sphere(32, dtype=dtype)
    lights = ring_lights(count, 45.0, dtype=dtype)
    clean = render(torch.zeros_like(normals), normals, albedo, DirectionalLights(lights),
                   specular=specular * torch.ones_like(albedo) if specular else None, shininess=SHININESS)
    generator = torch.Generator().manual_seed(0)
    images = clean * (1 + noise * torch.randn(clean.shape, generator=generator, dtype=dtype))
    return normals, inside, lights, images, robust_normals(images, lights, "robust", inside)


def test_lobe_kept_only_where_the_likelihood_ratio_test_supports_it():
    """8 lights, matte sphere: a lobe could only fit noise, and the test keeps the robust start on almost every pixel
    (measured 98% with 2% relative noise; 96% with 1% absolute noise, which the relative noise model of the test
    misjudges on dark pixels). Judged on each pixel's own residual per degree of freedom (the rule before the test)
    the fit kept only ~75% and lost 6% to the start."""
    normals, inside, lights, images, start = _noisy_sphere(8, 0.0, 0.02)
    fit = fit_blinn_phong(images, lights, inside, init=start)
    kept = inside & (fit.specular == 0) & (fit.shininess == 1)
    assert int(kept.sum()) >= 0.95 * int(inside.sum())
    torch.testing.assert_close(fit.normals * kept, start[1] * kept)
    scored = inside & (normals[:, 2:] > 0.5)
    def error(n):
        return float(mean_angular_error(n, normals, scored)[0])
    assert error(fit.normals) <= error(start[1]) * 1.01
    # 1% absolute noise: dark pixels have a larger relative noise, a few more lobes pass, still within 3%
    clean = images / (1 + 0.02 * torch.randn(images.shape, generator=torch.Generator().manual_seed(0),
                                             dtype=images.dtype))
    absolute = clean + 0.01 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(1), dtype=clean.dtype)
    from psmini.robust import robust_normals

    start = robust_normals(absolute, lights, "robust", inside)
    assert error(fit_blinn_phong(absolute, lights, inside, init=start).normals) <= error(start[1]) * 1.03


def test_lobe_identifiable_beats_the_robust_start():
    """8 lights, glossy sphere (specular 0.8, exponent 40), 2% noise: where highlights are seen the lobe passes the
    test and the fit beats the robust Lambertian start (measured 0.74° against 3.78°)."""
    normals, inside, lights, images, start = _noisy_sphere(8, SPECULAR, 0.02)
    fit = fit_blinn_phong(images, lights, inside, init=start)
    scored = inside & (normals[:, 2:] > 0.5)
    def error(n):
        return float(mean_angular_error(n, normals, scored)[0])
    assert error(fit.normals) < 0.3 * error(start[1])
    assert float((fit.specular[scored] > 0).double().mean()) > 0.3


def test_lobe_not_identifiable_returns_the_robust_start():
    """5 lights: no pixel has more readings than the fit has parameters, so the image gives no noise level to test
    a lobe against; every pixel returns the robust start unchanged (albedo, normal, no lobe), glossy or not."""
    normals, inside, lights, images, start = _noisy_sphere(5, SPECULAR, 0.02)
    fit = fit_blinn_phong(images, lights, inside, init=start)
    assert bool((fit.specular == 0).all()) and bool((fit.shininess == 1).all())
    torch.testing.assert_close(fit.normals[inside.expand_as(fit.normals)], start[1][inside.expand_as(start[1])],
                               rtol=0, atol=0)
    torch.testing.assert_close(fit.albedo[inside], start[0][inside], rtol=0, atol=0)


def test_keep_lobe_test_level():
    """_keep_lobe on statistics drawn from its own null model: residual sums of squares of the fit
    tau^2 mu^2 chi^2_{K-5} and a drop tau^2 mu^2 chi^2_2 for the start; the lobe passes on a fraction close to the
    significance (the pooled noise level is estimated, not given), and always for a drop 50 times the noise."""
    from psmini.nonlambertian import _keep_lobe

    generator = torch.Generator().manual_seed(0)
    n = 200_000
    count = torch.randint(6, 97, (n,), generator=generator).double()
    median = 0.05 + torch.rand(n, generator=generator, dtype=torch.float64)
    tau = 0.03
    def chi2(d):
        return torch.randn(n, int(d.max()), generator=generator, dtype=torch.float64).square().mul(
            torch.arange(int(d.max()), dtype=torch.float64) < d[:, None]).sum(dim=1)

    fit_squares = (tau * median) ** 2 * chi2(count - 5)
    start_squares = fit_squares + (tau * median) ** 2 * chi2(torch.full_like(count, 2.0))
    for level in (0.05, 0.01):
        rate = float(_keep_lobe(torch.stack([fit_squares, start_squares, median, count], 1), level).double().mean())
        assert 0.7 * level < rate < 1.3 * level
    strong = fit_squares + 50 * (tau * median) ** 2
    assert bool(_keep_lobe(torch.stack([fit_squares, strong, median, count], 1), 0.01).all())
    # no pixel with more than 5 readings: no noise level, no lobe
    assert not bool(_keep_lobe(torch.stack([fit_squares, strong, median, torch.full_like(count, 5.0)], 1), 0.5).any())


def test_wilson_hilferty_median():
    """The chi-square median approximation against SciPy's exact quantile: within 3.5% for 1 degree, 1% from 3."""
    stats = pytest.importorskip("scipy.stats")
    from psmini.nonlambertian import _wilson_hilferty_median

    degrees = torch.arange(1, 101, dtype=torch.float64)
    exact = torch.tensor(stats.chi2.median(degrees.numpy()))
    torch.testing.assert_close(_wilson_hilferty_median(degrees), exact, rtol=0.035, atol=0)
    torch.testing.assert_close(_wilson_hilferty_median(degrees[2:]), exact[2:], rtol=0.01, atol=0)


def test_start_shadows_are_left_out():
    """The readings the start explains as shadows (|I - p| >= I: p <= 0 or I < p / 2) take no part in the fit: a
    pixel whose cast-shadowed readings are replaced by anything below half their prediction fits the same."""
    from psmini.nonlambertian import _lit_by

    normals, scored, albedo, lights, images = _glossy_sphere("cpu", torch.float64, size=16)
    start = albedo_normals(images, lights, scored)
    predicted = torch.einsum("kc,bchw->bkhw", lights, start[0] * start[1])
    values, m = images[0].flatten(1), (start[0] * start[1])[0].flatten(1)
    lit = _lit_by(values, lights, m).view_as(images)
    assert torch.equal(lit, (predicted > 0) & (images > predicted / 2))
    per_pixel = lights[:, :, None].expand(-1, -1, values.shape[1])
    assert torch.equal(_lit_by(values, per_pixel, m).view_as(images), lit)
    shadowed = torch.zeros_like(images, dtype=torch.bool)
    shadowed[:, :6] = True  # six lights cast-shadowed: half and a fifth of their prediction
    first = torch.where(shadowed, 0.45 * predicted.clamp_min(0), images)
    second = torch.where(shadowed, 0.2 * predicted.clamp_min(0), images)
    options = NonLambertianOptions(iterations=8)
    a = fit_blinn_phong(first, lights, scored, options=options, init=start)
    b = fit_blinn_phong(second, lights, scored, options=options, init=start)
    torch.testing.assert_close(a.normals, b.normals)


def test_lobe_must_be_located_by_the_half_vectors():
    """_peak_observed: inside the half vectors' cone any lobe counts; beyond it only a lobe at most half the cone wide
    (half width at half maximum acos(2^(-1/alpha)) <= radius / 2)."""
    import math

    from psmini.nonlambertian import _peak_observed, _split_lights

    lights = ring_lights(8, 40.0, dtype=torch.float64)  # half vectors on a ring 20 deg from the view
    _, half = _split_lights(lights)
    tilt = lambda deg: torch.tensor([[math.sin(math.radians(deg)), 0.0, math.cos(math.radians(deg))]],  # noqa: E731
                                    dtype=torch.float64)
    broad, narrow = torch.tensor([[4.0]], dtype=torch.float64), torch.tensor([[200.0]], dtype=torch.float64)
    assert bool(_peak_observed(tilt(10.0), broad, half)) and bool(_peak_observed(tilt(19.0), broad, half))
    assert not bool(_peak_observed(tilt(30.0), broad, half))
    assert bool(_peak_observed(tilt(30.0), narrow, half))
    # the boundary: half width 10 deg (half the 20 deg cone) at alpha = ln 2 / -ln cos 10 deg
    edge = math.log(2) / -math.log(math.cos(math.radians(10.0)))
    assert bool(_peak_observed(tilt(60.0), torch.tensor([[edge * 1.001]], dtype=torch.float64), half))
    assert not bool(_peak_observed(tilt(60.0), torch.tensor([[edge * 0.999]], dtype=torch.float64), half))
    # per-pixel half vectors (N, K, 3) give the same answers
    per_pixel = half.expand(2, -1, -1)
    normals = torch.cat([tilt(30.0), tilt(10.0)])
    assert _peak_observed(normals, torch.cat([broad, broad]), per_pixel)[:, 0].tolist() == [False, True]


def test_no_worse_than_the_robust_start_under_inter_reflection():
    """data_synth.stress V-grooves: two bounces add 10-25% to the lit readings, which a broad lobe fits by moving the
    normal. Measured (48 px, 48 lights, seed 1): robust 8.21 deg, nonlambertian 8.15; with the former rules (every
    thresholded reading, any lobe, test level 1%) 9.73. Not every draw passes at this size: folds seed 0 gives 8.56
    against 8.35, 10.37 with the former rules (the benchmark's 128 px cases under 96 lights all pass)."""
    from data_synth.stress import make_stress_case
    from psmini.robust import robust_normals

    lights = torch.cat([ring_lights(12, zenith) for zenith in (15.0, 25.0, 35.0, 45.0)])
    case = make_stress_case("grooves", lights, size=48, seed=1)
    robust = robust_normals(case.images, case.lights, "robust", case.mask)[1]
    fit = nonlambertian_normals(case.images, case.lights, case.mask)[1]
    def error(n):
        return float(mean_angular_error(n, case.normals, case.mask)[0])
    assert error(fit) <= error(robust)
