"""psmini.fabric: ISO 25178-2 parameters against closed forms and dense numerical references, yarn structure
against data_synth's generator parameters, the no-structure result and the error paths."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from psmini.errors import DataFormatError, InputError, ShapeError
from psmini.fabric import (
    FabricClassifier,
    StructureOptions,
    SurfaceOptions,
    autocorrelation,
    describe,
    describe_reconstruction,
    descriptor_vector,
    fabric_structure,
    gaussian_filter,
    height_parameters,
    iso25178,
    remove_form,
    scale_limited_surface,
    spatial_parameters,
    structure_row,
    structure_spectrum,
    structure_surface,
    valid_pixels,
)
from tests.conftest import BaseTester

PITCH = 0.025
S = 0.2  # the standard's ACF threshold
FLAT = SurfaceOptions(form_degree=0)  # analytic surfaces with whole periods: no form to remove


def grid(n: int, dtype=torch.float64, device="cpu"):
    """x right, y up, in mm, on an n x n grid of PITCH."""
    idx = torch.arange(n, dtype=dtype, device=device) * PITCH
    y, x = torch.meshgrid(-idx, idx, indexing="ij")
    return x, y


def rel(a, b):
    return abs(float(a) / float(b) - 1)


def first_crossing_reference(acf, directions=3600, reach=5.0):
    """Dense numerical reference for Sal and Str: the first lag (mm) at which an analytic ACF falls to s, along
    3600 directions, by a 1e-4 mm march refined by bisection (independent of the library's bilinear rays)."""
    lengths = []
    for theta in np.arange(directions) * np.pi / directions:
        d = np.array([math.cos(theta), math.sin(theta)])
        r = np.arange(0, reach, 1e-3)
        values = acf(r[:, None] * d)
        below = np.nonzero(values <= S)[0]
        if not below.size:
            lengths.append(math.inf)
            continue
        lo, hi = r[below[0] - 1], r[below[0]]
        for _ in range(40):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if acf(np.array([mid * d]))[0] > S else (lo, mid)
        lengths.append((lo + hi) / 2)
    lengths = np.array(lengths)
    return lengths.min(), (lengths.min() / lengths.max() if np.isfinite(lengths.max()) else 0.0)


class TestIsoAnalytic(BaseTester):
    def test_sinusoid(self, device, dtype):
        amplitude, wavelength = 0.04, 0.5  # mm; 400 px = 10 mm = 20 periods
        x, _ = grid(400, dtype, device)
        z = (amplitude * torch.sin(2 * math.pi * x / wavelength))[None, None]
        p = iso25178(z, PITCH, options=FLAT)
        a_um, k = amplitude * 1000, 2 * math.pi / wavelength
        expected = {"Sq": a_um / math.sqrt(2), "Sa": 2 * a_um / math.pi, "Sku": 1.5, "Sp": a_um, "Sv": a_um,
                    "Sz": 2 * a_um, "Sdq": k * amplitude / math.sqrt(2),
                    "Sal": wavelength * math.acos(S) / (2 * math.pi)}
        phase = np.linspace(0, 2 * np.pi, 2_000_001)[:-1]
        expected["Sdr"] = 100 * np.mean(np.sqrt(1 + (k * amplitude * np.cos(phase)) ** 2) - 1)  # dense quadrature
        for name, value in expected.items():
            assert rel(p[name][0], value) < 0.01, (name, float(p[name][0]), value)
        assert abs(float(p["Ssk"][0])) < 0.01
        assert float(p["Str"][0]) == 0.0  # along the lay the ACF never decays
        assert abs(float(p["Std"][0]) - 90.0) < 0.5  # the lay runs along y

    def test_crossed_sinusoids(self, device):
        a, b, la, lb = 0.03, 0.02, 0.4, 0.3  # whole pixels to the crests: Sp is sampled
        x, y = grid(400, torch.float64, device)
        z = (a * torch.sin(2 * math.pi * x / la) + b * torch.sin(2 * math.pi * y / lb))[None, None]
        p = iso25178(z, PITCH, options=FLAT)
        ka, kb = 2 * math.pi / la, 2 * math.pi / lb
        sq = math.sqrt(a * a / 2 + b * b / 2)
        m4 = 3 * a**4 / 8 + 6 * (a * a / 2) * (b * b / 2) + 3 * b**4 / 8
        assert rel(p["Sq"][0], sq * 1000) < 0.01
        assert rel(p["Sku"][0], m4 / sq**4) < 0.01
        assert rel(p["Sp"][0], (a + b) * 1000) < 0.01 and rel(p["Sz"][0], 2 * (a + b) * 1000) < 0.01
        assert rel(p["Sdq"][0], math.sqrt((ka * a) ** 2 / 2 + (kb * b) ** 2 / 2)) < 0.01
        u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 2001)[:-1], np.linspace(0, 2 * np.pi, 2001)[:-1])
        gx, gy = ka * a * np.cos(u), kb * b * np.cos(v)
        assert rel(p["Sdr"][0], 100 * np.mean(np.sqrt(1 + gx**2 + gy**2) - 1)) < 0.01
        # Sa by dense quadrature over both phases
        assert rel(p["Sa"][0], 1000 * np.mean(np.abs(a * np.sin(u) + b * np.sin(v)))) < 0.01

        def acf(t):
            return (a * a * np.cos(ka * t[:, 0]) + b * b * np.cos(kb * t[:, 1])) / (a * a + b * b)

        sal, str_ = first_crossing_reference(acf)
        assert rel(p["Sal"][0], sal) < 0.01
        assert str_ == 0.0 and float(p["Str"][0]) == 0.0  # along y the ACF stays above (a² - b²)/(a² + b²) > s
        # equal amplitudes: the ACF decays in every direction, Str is a ratio of two finite lengths
        z = (b * torch.sin(2 * math.pi * x / la) + b * torch.sin(2 * math.pi * y / lb))[None, None]
        p = iso25178(z, PITCH, options=FLAT)

        def acf_equal(t):
            return (np.cos(ka * t[:, 0]) + np.cos(kb * t[:, 1])) / 2

        sal, str_ = first_crossing_reference(acf_equal)
        assert 0 < str_ < 1
        assert rel(p["Sal"][0], sal) < 0.01
        assert rel(p["Str"][0], str_) < 0.01

    def test_gaussian_random_surface(self):
        # white noise filtered by a Gaussian of sigma px (periodic, by FFT): ACF exp(-tau^2 / (4 sigma^2))
        n, sigma = 512, 3.0
        gen = torch.Generator().manual_seed(7)
        noise = torch.randn(n, n, generator=gen, dtype=torch.float64)
        f = torch.fft.fftfreq(n, dtype=torch.float64)
        transfer = torch.exp(-2 * math.pi**2 * sigma**2 * (f.view(-1, 1) ** 2 + f.view(1, -1) ** 2))
        z = torch.fft.ifft2(torch.fft.fft2(noise) * transfer).real
        z = (0.01 * z / z.std())[None, None]
        p = iso25178(z, PITCH, options=FLAT)
        values = z.flatten().numpy() * 1000
        values = values - values.mean()
        sq = np.sqrt(np.mean(values**2))  # sample moments, by numpy
        assert rel(p["Sq"][0], sq) < 1e-6
        assert rel(p["Sa"][0], np.mean(np.abs(values))) < 1e-6
        assert abs(float(p["Ssk"][0]) - np.mean(values**3) / sq**3) < 1e-6
        assert rel(p["Sku"][0], np.mean(values**4) / sq**4) < 1e-6
        assert rel(p["Sku"][0], 3.0) < 0.02 and rel(p["Sa"][0], sq * math.sqrt(2 / math.pi)) < 0.01  # Gaussian
        sal = 2 * sigma * PITCH * math.sqrt(math.log(1 / S))
        assert rel(p["Sal"][0], sal) < 0.03  # one realisation: a few per cent of sampling spread
        assert float(p["Str"][0]) > 0.85  # isotropic

    @pytest.mark.parametrize("angle", [0.0, 30.0, 75.0, 120.0, 160.0])
    def test_rotated_anisotropic(self, angle):
        # a lay running at `angle`: heights vary across it only
        x, y = grid(400)
        lay = math.radians(angle)
        across = -x * math.sin(lay) + y * math.cos(lay)
        z = (0.02 * torch.sin(2 * math.pi * across / 0.3) + 0.005 * torch.sin(2 * math.pi * (x * math.cos(lay)
             + y * math.sin(lay)) / 2.0))[None, None]
        p = iso25178(z, PITCH, options=SurfaceOptions(form_degree=1))
        assert abs((float(p["Std"][0]) - angle + 90) % 180 - 90) < 0.5
        a2, b2 = 0.02**2, 0.005**2
        k1, k2 = 2 * math.pi / 0.3, 2 * math.pi / 2.0

        def acf(t):
            return (a2 * np.cos(k1 * t[:, 1]) + b2 * np.cos(k2 * t[:, 0])) / (a2 + b2)

        sal, _ = first_crossing_reference(acf, directions=720)
        assert rel(p["Sal"][0], sal) < 0.02  # the slow wave is cut by form removal and the finite field
        assert float(p["Str"][0]) < 0.2

    def test_gradcheck(self):
        # seeded: Sa = mean |z| has a kink where a levelled height is 0, and an unseeded draw put one within the
        # finite difference's step of it about once in 40 runs (a failure of the check, not of the gradient)
        gen = torch.Generator().manual_seed(0)
        z = (torch.rand(1, 1, 12, 12, dtype=torch.float64, generator=gen) * 0.01).requires_grad_()

        def heights(h):
            p = iso25178(h, PITCH, options=SurfaceOptions(form_degree=1, s_cutoff_mm=0.06))
            return torch.stack([p["Sq"], p["Sa"], p["Ssk"], p["Sku"], p["Sdq"], p["Sdr"]])

        self.gradcheck(heights, (z,))

    def test_batch_matches_single(self, dtype):
        x, y = grid(64, dtype)
        z = torch.stack([0.01 * torch.sin(2 * math.pi * x / 0.4), 0.02 * torch.cos(2 * math.pi * y / 0.2)])[:, None]
        both = iso25178(z, PITCH)
        for i in range(2):
            one = iso25178(z[i:i + 1], PITCH)
            for k in both:
                torch.testing.assert_close(both[k][i:i + 1], one[k], rtol=1e-5, atol=1e-6)


class TestPreparation(BaseTester):
    def test_gaussian_transmission(self, device, dtype):
        # ISO 16610-61: a sine of wavelength L passes with exp(-pi (alpha lc / L)^2); 50% at the cut-off
        alpha = math.sqrt(math.log(2) / math.pi)
        x, _ = grid(400, dtype, device)
        for wavelength in (0.5, 1.0, 2.0):
            z = torch.sin(2 * math.pi * x / wavelength)[None, None]
            low = gaussian_filter(z, 1.0, PITCH)[0, 0, 200, 150:250]
            expected = math.exp(-math.pi * (alpha * 1.0 / wavelength) ** 2)
            amp = float(low.abs().max())
            assert abs(amp - expected) < 0.01, (wavelength, amp, expected)

    def test_remove_form_quadratic(self, device, dtype):
        x, y = grid(40, dtype, device)
        form = 0.3 + 0.1 * x - 0.2 * y + 0.05 * x * x - 0.02 * x * y + 0.03 * y * y
        out = remove_form(form[None, None], degree=2)
        assert float(out.abs().max()) < (1e-5 if dtype == torch.float32 else 1e-10)

    def test_unsolved_pixels_are_not_spikes(self):
        # the same surface with 5% of its pixels unsolved (huge or NaN depth, mask False): nothing changes
        x, y = grid(400)
        z = (0.03 * torch.sin(2 * math.pi * x / 0.4) * torch.cos(2 * math.pi * y / 0.3))[None, None]
        gen = torch.Generator().manual_seed(0)
        holes = torch.rand(z.shape, generator=gen, dtype=torch.float64) < 0.05
        spiky = torch.where(holes, torch.full_like(z, 5.0), z)
        nan = torch.where(holes, torch.full_like(z, math.nan), z)
        clean = iso25178(z, PITCH, options=FLAT)
        masked = iso25178(spiky, PITCH, ~holes, options=FLAT)
        unmasked_nan = iso25178(nan, PITCH, options=FLAT)
        for k in ("Sq", "Sa", "Sku", "Sdq", "Sdr", "Sal"):
            assert rel(masked[k][0], clean[k][0]) < 0.01, k
            assert rel(unmasked_nan[k][0], clean[k][0]) < 0.01, k
        assert rel(masked["Sp"][0], clean["Sp"][0]) < 0.01  # the 5 mm spikes are not peaks
        spiked = iso25178(spiky, PITCH, options=FLAT)
        assert float(spiked["Sdq"][0]) > 10 * float(clean["Sdq"][0])  # what they do when not excluded

    def test_autocorrelation_is_one_at_zero_lag(self, device):
        acf, count = autocorrelation(torch.randn(2, 1, 9, 7, device=device), torch.ones(2, 1, 9, 7, dtype=torch.bool,
                                                                                      device=device))
        assert acf.shape == (2, 1, 17, 13)
        torch.testing.assert_close(acf[:, 0, 8, 6], torch.ones(2, device=device))
        assert float(count[0, 0, 8, 6]) == 63

    def test_gradcheck_filters(self):
        gen = torch.Generator().manual_seed(0)
        z = (torch.rand(1, 1, 10, 10, generator=gen, dtype=torch.float64) * 0.01).requires_grad_()
        mask = torch.ones(1, 1, 10, 10, dtype=torch.bool)
        mask[..., :2, :3] = False
        self.gradcheck(lambda h: remove_form(h, mask, degree=2), (z,))
        self.gradcheck(lambda h: gaussian_filter(h, 0.1, 0.02, mask), (z,))
        options = SurfaceOptions(form_degree=1, s_cutoff_mm=0.05, l_cutoff_mm=0.15)  # F, S and L operators
        self.gradcheck(lambda h: scale_limited_surface(h, 0.02, mask, options)[0], (z,))

    def test_gradcheck_parameters(self):
        # seeded: Sp and Sv are a max and a min, Sal the first crossing along rays: one draw keeps every kink away
        gen = torch.Generator().manual_seed(0)
        z = (torch.rand(1, 1, 10, 10, generator=gen, dtype=torch.float64) * 0.01).requires_grad_()
        valid = torch.ones(1, 1, 10, 10, dtype=torch.bool)
        self.gradcheck(lambda h: torch.stack([height_parameters(h, valid)[k] for k in ("Sp", "Sv", "Sz")]), (z,))
        self.gradcheck(lambda h: autocorrelation(h - h.mean(), valid)[0], (z,))
        # Sal: documented differentiable in iso25178 (Str and Std are a ratio of first crossings and an argmax)
        self.gradcheck(lambda h: spatial_parameters(h - h.mean(), valid, 0.02, directions=16)["Sal"], (z,))
        self.gradcheck(lambda h: iso25178(h, 0.02, options=SurfaceOptions(directions=16))["Sal"], (z,))

    def test_gradcheck_structure_spectrum(self):
        z = (torch.rand(1, 1, 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.01)
        self.gradcheck(lambda h: structure_spectrum(h, 0.02)[0], (z.requires_grad_(),))

    def test_cuda_matches_cpu(self, cuda_device):
        x, y = grid(128)
        z = (0.02 * torch.sin(2 * math.pi * x / 0.3) + 0.01 * torch.cos(2 * math.pi * y / 0.2))[None, None]
        cpu = iso25178(z, PITCH)
        gpu = iso25178(z.to(cuda_device), PITCH)
        for k in cpu:
            torch.testing.assert_close(gpu[k].cpu(), cpu[k], rtol=1e-6, atol=1e-6)


class TestErrors:
    def test_empty_mask(self):
        with pytest.raises(InputError, match="no valid pixel"):
            iso25178(torch.zeros(1, 1, 16, 16), PITCH, torch.zeros(1, 1, 16, 16, dtype=torch.bool))

    def test_all_nan(self):
        with pytest.raises(InputError, match="no valid pixel"):
            fabric_structure(torch.full((1, 1, 16, 16), math.nan), PITCH)

    def test_shapes_and_pitch(self):
        with pytest.raises(ShapeError):
            iso25178(torch.zeros(16, 16), PITCH)
        with pytest.raises(ShapeError, match="mask"):
            iso25178(torch.zeros(1, 1, 16, 16), PITCH, torch.ones(1, 1, 8, 8, dtype=torch.bool))
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            iso25178(torch.zeros(1, 1, 16, 16), 0.0)
        with pytest.raises(InputError, match="cutoff"):
            gaussian_filter(torch.zeros(1, 1, 16, 16), -1.0, PITCH)
        with pytest.raises(InputError, match="degree"):
            remove_form(torch.zeros(1, 1, 8, 8), degree=3)

    def test_mask_of_another_size_raise(self):
        from psmini.fabric import albedo_periodicity

        # remove_form, valid_pixels and albedo_periodicity failed with a bare RuntimeError of broadcasting
        height = torch.zeros(1, 1, 16, 16)
        with pytest.raises(ShapeError, match="height's shape \\(1, 1, 16, 16\\) .* got \\(1, 1, 16, 15\\)"):
            remove_form(height, torch.ones(1, 1, 16, 15, dtype=torch.bool))
        with pytest.raises(ShapeError, match="got \\(2, 1, 16, 16\\)"):  # was two results for one height
            valid_pixels(height, torch.ones(2, 1, 16, 16, dtype=torch.bool))
        with pytest.raises(ShapeError, match="mask must have the height's shape"):
            albedo_periodicity(torch.ones(1, 1, 16, 16), PITCH, torch.ones(1, 1, 15, 16, dtype=torch.bool))
        assert valid_pixels(height.expand(2, 1, 16, 16), torch.ones(1, 1, 16, 16)).shape == (2, 1, 16, 16)  # batch 1

    def test_valid_map_misuse_raise(self):
        from psmini.fabric import height_parameters, hybrid_parameters, spatial_parameters

        surface = torch.randn(1, 1, 16, 16, dtype=torch.float64)
        calls = {"height_parameters": lambda valid: height_parameters(surface, valid),
                 "hybrid_parameters": lambda valid: hybrid_parameters(surface, valid, PITCH),
                 "spatial_parameters": lambda valid: spatial_parameters(surface, valid, PITCH),
                 "autocorrelation": lambda valid: autocorrelation(surface, valid)}
        for call in calls.values():
            # another W: a bare RuntimeError of broadcasting
            with pytest.raises(ShapeError, match="valid must have the surface's shape \\(1, 1, 16, 16\\) .* got "
                                                 "\\(1, 1, 16, 15\\)"):
                call(torch.ones(1, 1, 16, 15, dtype=torch.bool))
            # a batch of 2 maps for one surface: two results, silently
            with pytest.raises(ShapeError, match="got \\(2, 1, 16, 16\\)"):
                call(torch.ones(2, 1, 16, 16, dtype=torch.bool))
            with pytest.raises(ShapeError, match="got \\(16, 16\\)"):  # broadcasts, but not a (B, 1, H, W) map
                call(torch.ones(16, 16, dtype=torch.bool))
            with pytest.raises(ShapeError, match="got list"):
                call([[True]])
            # a float map: a bare RuntimeError in height_parameters, weights elsewhere
            with pytest.raises(InputError, match="valid must be a bool map .* got torch.float64"):
                call(torch.ones(1, 1, 16, 16, dtype=torch.float64))
        with pytest.raises(ShapeError, match="surface must have shape"):
            height_parameters(surface[0], torch.ones(1, 16, 16, dtype=torch.bool))
        # a batch-1 map serves every surface of a batch, as before
        two = surface.expand(2, 1, 16, 16)
        out = height_parameters(two, torch.ones(1, 1, 16, 16, dtype=torch.bool))
        assert out["Sq"].shape == (2,) and torch.equal(out["Sq"][0], out["Sq"][1])
        assert autocorrelation(two, torch.ones(1, 1, 16, 16, dtype=torch.bool))[0].shape == (2, 1, 31, 31)

    def test_wrong_argument_types_raise(self):
        # a height tensor failed as a bare AttributeError ('Tensor' object has no attribute 'mask')
        with pytest.raises(InputError, match="reconstruction must have depth and mask .* got Tensor without depth "
                                             "or mask; .*describe\\(height"):
            describe_reconstruction(torch.zeros(1, 1, 16, 16), PITCH)
        with pytest.raises(InputError, match="got SimpleNamespace without mask"):
            describe_reconstruction(SimpleNamespace(depth=torch.zeros(1, 1, 16, 16)), PITCH)
        # an empty dict failed as a bare KeyError 'iso25178'; a list of entries likewise with a TypeError
        with pytest.raises(InputError, match="one describe\\(\\) entry, a dict with an iso25178 dict, got a dict "
                                             "without an iso25178 dict"):
            descriptor_vector({})
        with pytest.raises(InputError, match="got list; pass the list's entries one by one"):
            descriptor_vector([{"iso25178": {}}])

    def test_structure_spectrum_misuse_raise(self):
        z = torch.zeros(1, 1, 16, 16)
        with pytest.raises(ShapeError, match="height must have shape \\(B, 1, H, W\\), got \\(16, 16\\)"):
            structure_spectrum(z[0, 0], PITCH)
        with pytest.raises(InputError, match="pixel_pitch_mm must be a positive number .* got 0.0"):
            structure_spectrum(z, 0.0)
        with pytest.raises(InputError, match="no valid pixel"):
            structure_spectrum(torch.full_like(z, math.nan), PITCH)
        # options=None failed as a bare AttributeError ('NoneType' object has no attribute 'form_degree')
        for function in (structure_spectrum, fabric_structure):
            with pytest.raises(InputError, match="options must be a StructureOptions, got NoneType"):
                function(z, PITCH, options=None)

    def test_structure_row_of_a_tensor_raise(self):
        # a height tensor failed as "height must be a torch.Tensor, got NoneType" (its depth read as None)
        with pytest.raises(InputError, match="reconstruction must have depth and mask .* got Tensor without depth "
                                             "or mask"):
            structure_row(torch.zeros(1, 1, 16, 16), PITCH)
        assert structure_row(None, None)["structure_found"] is False  # no pitch: the empty columns, as before

    def test_reconstruct_for_description_misuse_raise(self):
        from psmini.fabric import reconstruct_for_description
        from psmini.io.sample import Sample
        from psmini.lights import DirectionalLights, ring_lights

        with pytest.raises(InputError, match="needs a loaded sample .* got Tensor"):
            reconstruct_for_description(torch.rand(8, 16, 16))
        sample = Sample(name="s", images=torch.rand(8, 16, 16) + 0.1, lights=DirectionalLights(ring_lights(8, 55.0)))
        # a solver name for the config failed as a bare AttributeError ('str' object has no attribute 'device')
        with pytest.raises(InputError, match="config must be a ReconstructionConfig, got str"):
            reconstruct_for_description(sample, "near")

    def test_options(self):
        with pytest.raises(InputError, match="shorter"):
            SurfaceOptions(s_cutoff_mm=1.0, l_cutoff_mm=0.5)
        with pytest.raises(InputError, match="acf_threshold"):
            SurfaceOptions(acf_threshold=1.5)
        with pytest.raises(InputError, match="strong_db"):
            StructureOptions(strong_db=5.0, weak_db=10.0)
        with pytest.raises(InputError, match="max_repeat"):
            StructureOptions(max_repeat=0)

    def test_scale_limited_needs_valid_pixels(self):
        with pytest.raises(InputError):
            scale_limited_surface(torch.full((1, 1, 8, 8), math.inf), PITCH)


def truth_systems(fabric):
    """(threads per cm, direction the yarns run) of the generator's two systems."""
    p, o = fabric.params, fabric.params["orientation_deg"]
    a = p.get("spacing_mm", p.get("wale_spacing_mm"))
    b = p.get("weft_spacing_mm", p.get("course_spacing_mm", a))
    return [(10 / a, (o + 90) % 180), (10 / b, o % 180)]  # warp/wales across u run along v; weft along u


def structure_errors(result, truth):
    """Worst relative density error and angle error (degrees), matching found systems to true ones."""
    assert result.found, result.reason
    assert len(result.threads_per_cm) == 2
    assert result.threads_per_cm[0] >= result.threads_per_cm[1]  # the denser first
    worst_d = worst_a = 0.0
    for density, angle in zip(result.threads_per_cm, result.thread_angles_deg, strict=True):
        best = min(truth, key=lambda t: abs((angle - t[1] + 90) % 180 - 90) / 10 + abs(density / t[0] - 1))
        worst_d = max(worst_d, abs(density / best[0] - 1))
        worst_a = max(worst_a, abs((angle - best[1] + 90) % 180 - 90))
    return worst_d, worst_a


STRUCTURED = ["jute", "cotton", "silk", "twill", "satin", "knit", "purl", "net", "lurex", "taffeta", "print"]


class TestStructure:
    def test_crossed_cosines(self, device, dtype):
        x, y = grid(200, dtype, device)
        z = 0.05 * torch.cos(2 * math.pi * x / 0.25) + 0.03 * torch.cos(2 * math.pi * y / 0.5)
        found = fabric_structure(z[None, None], PITCH)[0]
        assert found.found
        assert found.threads_per_cm == pytest.approx([40.0, 20.0], rel=1e-3)
        assert found.thread_angles_deg == pytest.approx([90.0, 0.0], abs=0.05)
        assert found.weave_repeat == 1

    @pytest.mark.parametrize("name", STRUCTURED)
    def test_ground_truth_heights(self, name):
        # randomness 0.25: the realised mean spacing of a field of 10 mm stays within 0.2% of the nominal one
        from data_synth import make_fabric

        fabric = make_fabric(name, size=400, seed=5, orientation_deg=61.0, randomness=0.25)
        result = fabric_structure(fabric.height_mm, PITCH)[0]
        density, angle = structure_errors(result, truth_systems(fabric))
        assert density < 0.01 and angle < 0.5, (density, angle)

    @pytest.mark.slow
    @pytest.mark.parametrize("name", STRUCTURED)
    def test_ground_truth_five_orientations(self, name):
        from data_synth import make_fabric

        for orientation in (0.0, 17.0, 95.0, 140.0, 178.0):
            fabric = make_fabric(name, size=400, seed=5, orientation_deg=orientation, randomness=0.25)
            density, angle = structure_errors(fabric_structure(fabric.height_mm, PITCH)[0], truth_systems(fabric))
            assert density < 0.01 and angle < 0.5, (orientation, density, angle)

    @pytest.mark.parametrize(("name", "repeat"), [("cotton", 2), ("twill", 3), ("satin", 5), ("knit", 1)])
    def test_weave_repeat(self, name, repeat):
        from data_synth import make_fabric

        fabric = make_fabric(name, size=400, seed=5, orientation_deg=0.0, randomness=0.25)
        assert fabric_structure(fabric.height_mm, PITCH)[0].weave_repeat == repeat

    @pytest.mark.parametrize("orientation", [0.0, 17.0, 61.0, 95.0, 140.0, 178.0])
    def test_purl_wales_and_courses(self, orientation):
        """The purl side shifts alternate courses by half a wale: the strongest peaks are the two diagonals of a
        centred-rectangular lattice, not the wales and courses; these come out of its axes, not 2x or diagonal."""
        from data_synth import make_fabric

        fabric = make_fabric("purl", size=400, seed=5, orientation_deg=orientation, randomness=0.25)
        found = fabric_structure(fabric.height_mm, PITCH)[0]
        wales, courses = 10 / fabric.params["wale_spacing_mm"], 10 / fabric.params["course_spacing_mm"]
        assert found.wales_per_cm == pytest.approx(wales, rel=0.01)
        assert found.courses_per_cm == pytest.approx(courses, rel=0.01)
        assert found.weave_repeat == 1
        assert found.threads_per_cm == pytest.approx([courses, wales], rel=0.01)  # the denser first
        expected = [orientation % 180, (orientation + 90) % 180]  # courses run along u, wales along v
        for got, want in zip(found.thread_angles_deg, expected, strict=True):
            assert abs((got - want + 90) % 180 - 90) < 0.5

    def test_repeat_ignores_incommensurate_peaks(self, device, dtype):
        """A plain weave's interlacing peak (1/2, 1/2) plus two weaker modulations near (1/2, 3/4) and (2/3, 1/2)
        of the thread lattice (fibre twist, stripes): the grid (i/4, j/4) or (i/6, j/6) would hold them, no
        regular weave of repeat 4 or 6 does; the repeat is 2."""
        x, y = grid(320, dtype, device)
        a = math.radians(25.0)
        u, v = x * math.cos(a) + y * math.sin(a), -x * math.sin(a) + y * math.cos(a)
        f = 1 / 0.2

        def wave(i, j, amplitude):
            return amplitude * torch.cos(2 * math.pi * f * (i * u + j * v))

        z = wave(1, 0, 0.03) + wave(0, 1, 0.03) + wave(0.5, 0.5, 0.004) + wave(0.5, 0.74, 0.003) \
            + wave(0.66, -0.5, 0.003)
        found = fabric_structure(z[None, None], PITCH)[0]
        assert found.threads_per_cm == pytest.approx([50.0, 50.0], rel=1e-3)
        assert found.weave_repeat == 2
        assert found.crimp_um == pytest.approx(8.0, rel=0.02)  # twice the interlacing amplitude, 4 um

    def test_net_openness(self):
        from data_synth import make_fabric

        net = make_fabric("net", size=400, seed=1)
        cotton = make_fabric("cotton", size=400, seed=1)
        holes = float((~net.mask).float().mean())
        found = fabric_structure(torch.cat([net.height_mm, cotton.height_mm]), PITCH)
        assert abs(found[0].openness - holes) < 0.05
        assert found[1].openness < 0.1

    def test_structureless_surface(self):
        gen = torch.Generator().manual_seed(3)
        z = torch.randn(1, 1, 256, 256, generator=gen, dtype=torch.float64)
        z = gaussian_filter(z, 0.1, PITCH) * 0.01
        found = fabric_structure(z, PITCH)[0]
        assert not found.found and "no" in found.reason and found.threads_per_cm is None

    def test_crop_shorter_than_two_periods(self):
        x, y = grid(64)  # 1.6 mm field, 1.2 mm yarn repeat
        z = 0.05 * torch.cos(2 * math.pi * x / 1.2) + 0.05 * torch.cos(2 * math.pi * y / 1.2)
        found = fabric_structure(z[None, None], PITCH, options=StructureOptions(l_cutoff_mm=None))[0]
        assert not found.found and "two periods" in found.reason

    @pytest.mark.slow
    @pytest.mark.parametrize("solver", ["distant", "near"])
    @pytest.mark.parametrize("name", STRUCTURED)
    def test_reconstructed_captures(self, name, solver):
        """From the simulator's noisy 8-bit captures, reconstructed by the default pipeline (near light, for LED
        captures) and by the classical one (distant lights with the card): within 2% and 1°, at 0, 0.5 and 1 mm
        above the card and five orientations (every pair for the classical pipeline; for near light, at about a
        second per capture on a CPU, each orientation at one of the lifts in turn). Near light finds the net's mesh
        but reads its densities 1.2-3.7% off (the step from its yarns down to the card in its holes is flattened:
        docs/guides/fabric.md): a known failure kept visible as an xfail, under a bound it must still hold (5%: a
        strict xfail on the whole test hid a third harmonic read as the yarns, 198% off, on two captures)."""
        from data_synth import make_fabric
        from data_synth.rig import RigConfig, render_capture, render_card
        from psmini.config import ReconstructionConfig
        from psmini.fabric import reconstruct_for_description
        from psmini.io.sample import Sample

        known_limit = name == "net" and solver == "near"
        config = RigConfig(bit_depth=8)
        card = render_card(config, seed=99)
        orientations, lifts = (0.0, 37.0, 90.0, 121.0, 163.0), (0.0, 0.5, 1.0)
        cases = [(lift, orientation) for lift in lifts for orientation in orientations] if solver == "distant" \
            else [(lifts[i % 3], orientation) for i, orientation in enumerate(orientations)]
        worst = 0.0
        for lift, orientation in cases:
            fabric = make_fabric(name, size=400, seed=11, orientation_deg=orientation, randomness=0.25)
            capture = render_capture(fabric, config, seed=11, height_offset_mm=lift)
            sample = Sample(name=name, images=capture.images, lights=capture.lights, dark=capture.dark,
                            reference=card.images, reference_dark=card.dark, card_albedo=0.8,
                            pixel_pitch_mm=PITCH, saturation_level=1.0)
            rec = reconstruct_for_description(sample, ReconstructionConfig(solver=solver))
            surface = structure_surface(rec.p, rec.q, PITCH, rec.mask)  # where describe_reconstruction reads it
            density, angle = structure_errors(fabric_structure(surface, PITCH, rec.mask)[0], truth_systems(fabric))
            assert density < (0.05 if known_limit else 0.02) and angle < 1.0, (lift, orientation, density, angle)
            worst = max(worst, density)
        if known_limit:
            assert worst >= 0.02, "near light now reads the net within 2%: drop its known limit here and in the guide"
            pytest.xfail(f"near light reads the net's densities up to {100 * worst:.1f}% off (the 2% not met)")


class TestStructureSurface:
    """The surface describe_reconstruction reads the structure from: the slopes integrated without weights."""

    def test_analytic_relief_and_masked_slopes(self):
        x, y = grid(128)
        z = 0.02 * torch.cos(2 * math.pi * x / 0.4) * torch.cos(2 * math.pi * y / 0.32)
        p = -0.02 * 2 * math.pi / 0.4 * torch.sin(2 * math.pi * x / 0.4) * torch.cos(2 * math.pi * y / 0.32)
        q = -0.02 * 2 * math.pi / 0.32 * torch.cos(2 * math.pi * x / 0.4) * torch.sin(2 * math.pi * y / 0.32)
        got = structure_surface(p[None, None], q[None, None], PITCH)[0, 0]
        # the DCT solve of central differences: the relief within 3% of its amplitude
        assert float((got - (z - z.mean())).abs().max()) < 0.03 * 0.02
        mask = torch.ones(1, 1, 128, 128, dtype=torch.bool)
        mask[..., 60:68, 60:68] = False
        nonsense = torch.full_like(p[None, None], 1e3)
        masked = structure_surface(torch.where(mask, p[None, None], nonsense), q[None, None], PITCH, mask)
        unmasked_zero = structure_surface(p[None, None] * mask, q[None, None] * mask, PITCH)
        torch.testing.assert_close(masked, unmasked_zero)

    def test_gradcheck(self):
        gen = torch.Generator().manual_seed(0)
        p = (torch.randn(1, 1, 8, 8, generator=gen, dtype=torch.float64) * 4).requires_grad_()  # some beyond 80 deg
        q = torch.randn(1, 1, 8, 8, generator=gen, dtype=torch.float64)
        q[..., :2, :] = 0  # a flat patch: no NaN from the limit's norm at zero slope
        q.requires_grad_()
        assert torch.autograd.gradcheck(lambda a, b: structure_surface(a, b, PITCH), (p, q))

    def test_grazing_slopes_limited(self):
        """One grazing normal (a slope of 100, the gradients' clamp) beside a flat field: limited to 80 deg, its step
        is tan(80 deg) pixels' pitch, not a hundred."""
        p = torch.zeros(1, 1, 32, 32, dtype=torch.float64)
        p[..., 16, 16] = 100.0
        z = structure_surface(p, torch.zeros_like(p), PITCH)
        step = math.tan(math.radians(80.0)) * PITCH
        assert float(z.max() - z.min()) < 1.01 * step
        assert float(z.max() - z.min()) > 0.3 * step
        with pytest.raises(InputError, match=r"max_slope_deg must be in \(0, 90\)"):
            structure_surface(p, p, PITCH, max_slope_deg=90.0)

    def test_errors(self):
        p = torch.zeros(1, 1, 16, 16)
        with pytest.raises(ShapeError, match="mask must have the slopes' shape"):
            structure_surface(p, p, PITCH, torch.ones(1, 1, 8, 8, dtype=torch.bool))
        with pytest.raises(ShapeError, match="p and q must have one shape"):
            structure_surface(p, torch.zeros(1, 1, 8, 8), PITCH)
        with pytest.raises(ShapeError, match="structure_height must have the height's shape"):
            describe(p, PITCH, structure_height=torch.zeros(1, 1, 8, 8))

    def test_describe_reconstruction_reads_structure_from_the_slopes(self):
        """A depth that lost every other groove (paired threads read as one) beside slopes that keep it: the density
        comes from the slopes, the ISO amplitudes from the depth."""
        from psmini.result import Reconstruction

        x, y = grid(256)
        depth = (0.03 * torch.cos(2 * math.pi * x / 0.5))[None, None].float()  # 20 /cm, what the depth kept
        p = (-0.03 * 2 * math.pi / 0.25 * torch.sin(2 * math.pi * x / 0.25))[None, None].float()  # 40 /cm, the cloth's
        rec = Reconstruction(torch.ones_like(depth), torch.zeros(1, 3, 256, 256), p, torch.zeros_like(p), depth,
                             depth > -1)
        entry = describe_reconstruction(rec, PITCH)[0]
        assert entry["threads_per_cm"][0] == pytest.approx(40.0, rel=1e-3)
        assert entry["iso25178"]["Sq"] == pytest.approx(describe(depth, PITCH)[0]["iso25178"]["Sq"], rel=1e-6)
        assert describe(depth, PITCH)[0]["threads_per_cm"][0] == pytest.approx(20.0, rel=1e-3)
        no_slopes = describe_reconstruction(SimpleNamespace(depth=depth, mask=depth > -1, p=None, q=None), PITCH)[0]
        assert no_slopes["threads_per_cm"][0] == pytest.approx(20.0, rel=1e-3)


class TestDescribe:
    def test_structure_row_and_vector(self):
        from psmini.result import Reconstruction

        x, y = grid(200)
        z = (0.05 * torch.cos(2 * math.pi * x / 0.25) + 0.03 * torch.cos(2 * math.pi * y / 0.5))[None, None].float()
        p = (-0.05 * 2 * math.pi / 0.25 * torch.sin(2 * math.pi * x / 0.25))[None, None].float()
        q = (-0.03 * 2 * math.pi / 0.5 * torch.sin(2 * math.pi * y / 0.5))[None, None].float()
        rec = Reconstruction(torch.ones_like(z), torch.zeros(1, 3, 200, 200), p, q, z, z > -1)
        row = structure_row(rec, PITCH)
        assert row["structure_found"] and row["threads_per_cm_1"] == pytest.approx(40.0, rel=1e-3)
        alpha = math.sqrt(math.log(2) / math.pi)

        def passed(wavelength, s_cutoff=0.5):  # ISO 16610-61 Gaussian S-filter, and the L-filter of 2.5 mm
            return math.exp(-math.pi * (alpha * s_cutoff / wavelength) ** 2) * (
                1 - math.exp(-math.pi * (alpha * 2.5 / wavelength) ** 2))

        # describe's ISO parameters: the S-filter of 25 um pixels (80 um) and the L-filter of 2.5 mm
        sq = 1000 * math.sqrt((0.05 * passed(0.25, 0.08)) ** 2 / 2 + (0.03 * passed(0.5, 0.08)) ** 2 / 2)
        assert row["Sq_um"] == pytest.approx(sq, rel=0.01)
        assert structure_row(rec, None)["structure_found"] is False
        entry = describe(z, PITCH)[0]
        vector = descriptor_vector(entry)
        assert vector.shape == (47,) and np.isfinite(vector).all()

        expected = 1000 * math.sqrt((0.05 * passed(0.25)) ** 2 / 2 + (0.03 * passed(0.5)) ** 2 / 2)
        assert entry["waviness_um"] == pytest.approx(expected, rel=0.02)
        assert vector[13] == pytest.approx(90.0, abs=0.1)  # the systems cross at right angles

    def test_classifier_round_trip_and_version(self):
        model = FabricClassifier(("a", "b", "c"), ("x", "y"), (0.0, 1.0), (1.0, 2.0),
                                 ((1.0, 0.0), (0.0, 1.0), (-1.0, -1.0)), (0.0, 0.5, 0.0))
        again = FabricClassifier.from_dict(model.to_dict())
        x = np.array([[1.0, 3.0], [-2.0, 0.0]])
        np.testing.assert_allclose(again.predict_proba(x), model.predict_proba(x))
        z = (x - [0.0, 1.0]) / [1.0, 2.0]
        logits = z @ np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]]).T + [0.0, 0.5, 0.0]
        expected = np.exp(logits) / np.exp(logits).sum(1, keepdims=True)
        np.testing.assert_allclose(model.predict_proba(x), expected)
        assert model.predict(x) == ["b", "c"]
        data = model.to_dict() | {"version": 1}
        with pytest.raises(DataFormatError, match="version 1"):
            FabricClassifier.from_dict(data)
        with pytest.raises(DataFormatError, match="not a fabric model"):
            FabricClassifier.from_dict({"format": "pickle"})
        with pytest.raises(DataFormatError, match="malformed"):
            FabricClassifier.from_dict(model.to_dict() | {"coef": [[1.0]]})
        with pytest.raises(InputError, match="features"):
            model.predict_proba(np.zeros(3))


def test_yarn_angle_of_a_vertical_peak_wraps_to_zero_not_180():
    """A peak a hair off the y axis (sub-bin noise) gives yarns at 0°, never a value that prints as 180°."""
    from psmini.fabric.structure import SpectralPeak

    for fx in (1e-12, -1e-12, 0.0, 1e-6, -1e-6):  # 1e-6 cycles/mm: 3e-5° off the axis, float32 refinement noise
        angle = SpectralPeak(fx, 2.0, 30.0, 10.0).yarn_angle_deg
        assert 0.0 <= angle < 180.0 and round(angle, 2) in (0.0,), (fx, angle)
    assert SpectralPeak(2.0, 0.0, 30.0, 10.0).yarn_angle_deg == 90.0
    assert abs(SpectralPeak(1.0, 1.0, 30.0, 10.0).yarn_angle_deg - 135.0) < 1e-9


class TestAlbedoReliefCoupling:
    @staticmethod
    def blotches(n, seed, dtype=torch.float64):
        """A printed motif in [0, 1]: soft-edged blotches of about 1 mm at PITCH."""
        gen = torch.Generator().manual_seed(seed)
        coarse = torch.randn(1, 1, 9, 9, generator=gen, dtype=torch.float64)
        field = torch.nn.functional.interpolate(coarse, size=(n, n), mode="bicubic", align_corners=True)
        return torch.sigmoid(field * 6).to(dtype)

    def test_ink_layer_and_independent_print(self, device, dtype):
        from psmini.fabric import albedo_relief_coupling

        x, y = grid(192, dtype, device)
        yarns = (0.03 * torch.cos(2 * math.pi * x / 0.2) * torch.cos(2 * math.pi * y / 0.2))[None, None]
        ink = self.blotches(192, 1, dtype).to(device)
        other = self.blotches(192, 2, dtype).to(device)
        raised_dark = albedo_relief_coupling(0.004 * ink, 0.8 - 0.6 * ink, PITCH)
        assert float(raised_dark[0]) == pytest.approx(-1.0, abs=1e-6)
        raised_bright = albedo_relief_coupling(0.004 * ink, 0.3 + 0.6 * ink, PITCH)
        assert float(raised_bright[0]) == pytest.approx(1.0, abs=1e-6)
        # scale-free: the same under any albedo and height scale
        scaled = albedo_relief_coupling(0.04 * ink, 3 * (0.8 - 0.6 * ink), PITCH)
        assert float(scaled[0]) == pytest.approx(-1.0, abs=1e-6)
        # a print with no relief of its own on cloth with relief of its own: near 0
        independent = albedo_relief_coupling(0.004 * other + yarns, 0.8 - 0.6 * ink, PITCH)
        assert abs(float(independent[0])) < 0.2
        # the yarns (0.2 mm) lie below the band: adding them to an inked surface changes little
        with_yarns = albedo_relief_coupling(0.004 * ink + yarns, 0.8 - 0.6 * ink, PITCH)
        assert float(with_yarns[0]) < -0.9
        # batched: the same numbers as one by one
        both = albedo_relief_coupling(torch.cat([0.004 * ink, 0.004 * other + yarns]),
                                      torch.cat([0.8 - 0.6 * ink, 0.8 - 0.6 * ink]), PITCH)
        tol = 1e-9 if dtype == torch.float64 else 1e-5
        assert both.tolist() == pytest.approx([float(raised_dark[0]), float(independent[0])], abs=tol)

    def test_data_synth_print_against_printed_cotton(self):
        """Ground truth of the recognition dataset, every sample with a random print on top: the print class's ink
        is raised where dark (c < 0); the same kind of motif on a cotton (no relief of its own) scatters around 0
        (measured: print -0.31..-0.08, cotton -0.16..+0.11 over seeds 0-7)."""
        from data_synth.fabric_dataset import DatasetOptions, draw_fabric
        from psmini.fabric import albedo_relief_coupling

        options = DatasetOptions(size=192, print_probability=1.0, wrinkle_probability=0.0)
        inked = [draw_fabric("print", seed, options).fabric for seed in range(6)]
        printed = [draw_fabric("cotton", seed, options).fabric for seed in range(6)]
        c_print = albedo_relief_coupling(torch.cat([f.height_mm for f in inked]),
                                         torch.cat([f.albedo for f in inked]), PITCH)
        c_cotton = albedo_relief_coupling(torch.cat([f.height_mm for f in printed]),
                                          torch.cat([f.albedo for f in printed]), PITCH)
        assert (c_print < -0.05).all(), c_print
        assert (c_cotton.abs() < 0.2).all(), c_cotton
        assert float(c_cotton.mean() - c_print.mean()) > 0.12, (c_print, c_cotton)

    def test_flat_albedo_and_errors(self):
        from psmini.fabric import albedo_relief_coupling

        z = self.blotches(64, 3) * 0.01
        assert math.isnan(float(albedo_relief_coupling(z, torch.ones_like(z), PITCH)[0]))
        assert describe(z, PITCH, albedo=torch.ones_like(z))[0]["albedo_relief_coupling"] is None
        assert describe(z, PITCH)[0]["albedo_relief_coupling"] is None
        with pytest.raises(ShapeError, match="albedo"):
            albedo_relief_coupling(z, torch.ones(1, 1, 32, 32, dtype=z.dtype), PITCH)
        with pytest.raises(InputError):
            albedo_relief_coupling(z, torch.ones_like(z), -1.0)

    @pytest.mark.slow
    def test_gradcheck(self):
        from psmini.fabric import albedo_relief_coupling

        z = (self.blotches(20, 4) * 0.01).requires_grad_(True)
        a = 0.8 - 0.5 * self.blotches(20, 5)
        torch.autograd.gradcheck(lambda h: albedo_relief_coupling(h, a, 0.1), (z,), eps=1e-7, atol=1e-6)


class TestAlbedoPeriodicity:
    def test_stripes_dye_and_print(self, device, dtype):
        from psmini.fabric import albedo_periodicity

        x, y = grid(200, dtype, device)
        stripes = 1 + 0.2 * torch.cos(2 * math.pi * (x * 0.6 + y * 0.8) / 0.3)  # every 0.3 mm, at an angle
        got = albedo_periodicity(torch.stack([0.6 * stripes, 0.25 * stripes])[:, None], PITCH)
        assert got.tolist() == pytest.approx([0.2, 0.2], rel=0.02)  # the dye does not change it
        from data_synth.fabric_dataset import albedo_pattern

        for seed in range(3):  # the recognition dataset's printed motifs have no spectral peak
            pattern, info = albedo_pattern(200, torch.Generator().manual_seed(seed), 1.0, PITCH)
            assert float(albedo_periodicity(pattern.to(device, dtype), PITCH)[0]) < 0.02, info
        assert float(albedo_periodicity(torch.full((1, 1, 64, 64), 0.5, dtype=dtype, device=device), PITCH)[0]) < 1e-6

    def test_data_synth_lurex_against_cotton(self):
        """The Lurex's metallic tape every third weft is a periodic albedo; a cotton's dye and print are not (its
        yarns' own tone and twist stripes stay below a few per cent)."""
        from data_synth.fabric_dataset import DatasetOptions, draw_fabric
        from psmini.fabric import albedo_periodicity

        options = DatasetOptions(size=192, print_probability=1.0)
        for seed in range(3):
            lurex, cotton = draw_fabric("lurex", seed, options).fabric, draw_fabric("cotton", seed, options).fabric
            p_lurex = float(albedo_periodicity(lurex.albedo, PITCH, lurex.mask)[0])
            p_cotton = float(albedo_periodicity(cotton.albedo, PITCH, cotton.mask)[0])
            assert p_lurex > 0.15 and p_cotton < 0.06, (seed, p_lurex, p_cotton)

    def test_errors(self):
        from psmini.fabric import albedo_periodicity

        with pytest.raises(ShapeError, match="albedo"):
            albedo_periodicity(torch.ones(8, 8), PITCH)
        with pytest.raises(InputError):
            albedo_periodicity(torch.ones(1, 1, 32, 32), 0.0)


def test_structure_survives_reconstruction_spikes():
    """Spikes of 2 mm on a few pixels (what near light leaves in the holes of a knit) on a 0.1 mm lattice: with the
    default spike fence the densities come out; without it the spikes bury the lattice."""
    x, y = grid(256)
    z = 0.05 * torch.cos(2 * math.pi * x / 0.3) + 0.05 * torch.cos(2 * math.pi * y / 0.25)
    gen = torch.Generator().manual_seed(0)
    seeds = (torch.rand(1, 1, 256, 256, generator=gen, dtype=torch.float64) < 0.003).double()
    spikes = torch.nn.functional.max_pool2d(seeds, 3, stride=1, padding=1)[0, 0] > 0  # 3 x 3 blobs, ~2.5 %
    depth = -2.0 * torch.rand(256, 256, generator=gen, dtype=torch.float64)
    z = torch.where(spikes, depth, z)[None, None]
    found = fabric_structure(z, PITCH)[0]
    assert found.found and found.threads_per_cm == pytest.approx([40.0, 33.333], rel=0.01)
    bare = fabric_structure(z, PITCH, options=StructureOptions(spike_fence=None))[0]
    assert not bare.found or bare.threads_per_cm != pytest.approx([40.0, 33.333], rel=0.01)
    with pytest.raises(InputError, match="spike_fence"):
        StructureOptions(spike_fence=0.0)


# --------------------------------------------------------------------------------------------------------------
# The thread lattice fitted to every peak, the repeat lattice of any weave, the ISO S-filter of the pixel
# --------------------------------------------------------------------------------------------------------------


def lattice_surface(n: int, f1: float, f2: float, angle_deg: float, waves: dict, dtype=torch.float64):
    """A sum of cosines at the points (i, j) of the thread lattice (frequencies f1 across u, f2 across v, cycles/mm;
    u at ``angle_deg`` from x), ``waves``: {(i, j): amplitude in mm}."""
    x, y = grid(n, dtype)
    a = math.radians(angle_deg)
    u, v = x * math.cos(a) + y * math.sin(a), -x * math.sin(a) + y * math.cos(a)
    z = torch.zeros_like(x)
    for (i, j), amplitude in waves.items():
        z = z + amplitude * torch.cos(2 * math.pi * (i * f1 * u + j * f2 * v))
    return z[None, None]


class TestLattice:
    def test_a_hidden_weft_from_its_lattice(self):
        """A warp-faced cloth hides its weft's own peak (0, 1); the lattice's (1, ±1) and (0, 2) still say it. The
        strongest peak across the warp is the weft's second harmonic: a single-peak reading gives twice the
        density."""
        waves = {(1, 0): 0.03, (1, 1): 0.01, (1, -1): 0.01, (0, 2): 0.012, (2, 0): 0.01, (1, 2): 0.004}
        z = lattice_surface(400, 3.6, 1.7, 25.0, waves)  # 36 ends/cm, 17 picks/cm
        found = fabric_structure(z, PITCH)[0]
        assert found.threads_per_cm == pytest.approx([36.0, 17.0], rel=2e-3)
        expected = [(25.0 + 90.0) % 180.0, 25.0]  # the ends run along v, the picks along u
        for got, want in zip(found.thread_angles_deg, expected, strict=True):
            assert abs((got - want + 90) % 180 - 90) < 0.1
        assert found.repeat_threads == [1, 1]

    def test_aliased_harmonics_are_not_a_finer_lattice(self):
        """Threads of 2.4 pixels: their 2nd and 3rd harmonics alias to 2/5 and 3/5 of the thread frequency (at
        25 um, 16.67/mm folds to 6.67 and 10 per mm), which a lattice of a fifth of it would hold; folded back, the
        thread lattice holds them itself."""
        f = 1 / 0.06
        waves = {(1, 0): 0.01, (0, 1): 0.01, (2, 0): 0.004, (0, 2): 0.004, (3, 0): 0.002, (0, 3): 0.002}
        found = fabric_structure(lattice_surface(400, f, f, 0.0, waves), PITCH)[0]
        assert found.threads_per_cm == pytest.approx([10 * f, 10 * f], rel=2e-3)

    def test_an_aliased_harmonic_stronger_than_its_fundamental(self):
        """Threads of 2.4 pixels along the axes fold their 2nd harmonic back to 2/5 of their frequency on the same
        axis; a reconstruction flattens the fundamental near Nyquist more than that alias, which can then be the
        stronger peak (psmini's silk from the classical pipeline at 0 and 90 deg): still the threads, not it."""
        f = 1 / 0.06
        waves = {(1, 0): 0.007, (0, 1): 0.007, (2, 0): 0.008, (0, 2): 0.008}
        found = fabric_structure(lattice_surface(400, f, f, 0.0, waves), PITCH)[0]
        assert found.threads_per_cm == pytest.approx([10 * f, 10 * f], rel=2e-3)

    def test_a_nets_fundamental_a_third_of_a_bin_below_its_harmonics(self):
        """Thin yarns far apart (a net, 9 per cm in a 10 mm field: nine frequency bins) have harmonics nearly as strong
        as the fundamental, and near light's depth put the fundamental a third of a bin (3.5 %) below a third of the
        third harmonic, the peak of most slope: beyond a 3 % tolerance, so the third harmonic was read as the yarn
        system, three times too dense (two of the five net captures of ``test_reconstructed_captures``)."""
        f = 0.909  # cycles/mm
        waves = {(0.965, 0): 0.03, (2, 0): 0.027, (3, 0): 0.022, (0, 0.965): 0.03, (0, 2): 0.027, (0, 3): 0.022}
        found = fabric_structure(lattice_surface(400, f, f, 37.0, waves), PITCH)[0]
        assert found.threads_per_cm == pytest.approx([10 * f, 10 * f], rel=0.05)
        from psmini.fabric.structure import SpectralPeak, _fundamental

        # in a field ten times as large the same 3.5 % is three bins: another peak, not the fundamental
        third, fundamental = SpectralPeak(0.0, 3 * f, 40.0, 0.025), SpectralPeak(0.0, 0.965 * f, 40.0, 0.03)
        assert _fundamental(third, [third, fundamental], StructureOptions(), field_mm=10.0) is fundamental
        assert _fundamental(third, [third, fundamental], StructureOptions(), field_mm=100.0) is third

    @pytest.mark.parametrize(("comb", "repeat"), [
        ({(0.32, 0.5): 0.003, (0.69, 0.5): 0.003, (0.86, 0.5): 0.003, (0.5, 0.63): 0.003, (0.5, 0.83): 0.003}, 2),
        ({(0.32, 0.41): 0.003, (0.69, 0.37): 0.003, (0.86, 0.62): 0.003, (0.41, 0.63): 0.003, (0.37, 0.83): 0.003}, 1),
    ])
    def test_a_comb_on_the_interlacings_rows(self, comb, repeat):
        """A plain weave whose half-weft and half-warp rows are modulated along the other system (peaks (x, 1/2) and
        (1/2, y), x and y anywhere: what integrated slopes of a 50 /cm plain weave carry) keeps its repeat of 2,
        although the comb outweighs the (1/2, 1/2) peak; the same comb off those rows is scattered: no repeat."""
        z = lattice_surface(400, 5.0, 5.0, 20.0, {(1, 0): 0.012, (0, 1): 0.012, (0.5, 0.5): 0.004, **comb})
        assert fabric_structure(z, PITCH)[0].weave_repeat == repeat

    @pytest.mark.parametrize(("name", "waves", "repeats", "regular"), [
        ("rib", {(0.5, 0.25): 0.006, (0.5, 0.75): 0.004}, [2, 4], False),
        ("basket", {(0.25, 0.25): 0.006, (0.25, 0.75): 0.006, (0.75, 0.25): 0.004, (0.75, 0.75): 0.004}, [4, 4],
         False),
        ("3/1 twill", {(0.25, 0.75): 0.006, (0.5, 0.5): 0.004, (0.75, 0.25): 0.006}, [4, 4], True),
        ("5-end satin", {(0.2, 0.6): 0.006, (0.4, 0.2): 0.006, (0.6, 0.8): 0.004, (0.8, 0.4): 0.004}, [5, 5], True),
    ])
    def test_repeat_lattices(self, name, waves, repeats, regular):
        """The interlacing peaks sit on the dual of the repeat's lattice: a rib's (1/2, 1/4) makes 2 ends by 4 picks,
        a basket's (1/4, 1/4) and (1/4, 3/4) no single shift generates (no float length), a 3/1 twill's one shift
        (1/4, 3/4) does."""
        z = lattice_surface(400, 3.0, 2.2, 35.0, {(1, 0): 0.02, (0, 1): 0.02, **waves})
        found = fabric_structure(z, PITCH)[0]
        assert found.threads_per_cm == pytest.approx([30.0, 22.0], rel=2e-3)
        assert found.repeat_threads == repeats, name
        assert found.weave_repeat == max(repeats)
        assert (found.float_length is not None) == regular
        vector = descriptor_vector(describe(z.float(), PITCH)[0])
        names = list(__import__("psmini.fabric", fromlist=["DESCRIPTOR_NAMES"]).DESCRIPTOR_NAMES)
        assert vector[names.index("repeat_min")] == min(repeats)
        assert vector[names.index("regular_weave")] == float(regular)
        # the larger repeat's indicator, on the side of its regularity: a basket's 4 is not a 3/1 twill's 4
        kind, other = ("regular", "irregular") if regular else ("irregular", "regular")
        indicators = [vector[names.index(f"{kind}_repeat_is_{k}")] for k in range(1, 9)]
        assert indicators == [float(k == max(repeats)) for k in range(1, 9)]
        assert [vector[names.index(f"{other}_repeat_is_{k}")] for k in range(1, 9)] == [0.0] * 8
        assert vector[names.index(f"repeat_min_is_{min(repeats)}")] == 1.0

    @pytest.mark.parametrize("weave", ["plain", "basket", "twill_2_1", "twill_3_1", "satin_5", "rib", "jersey"])
    def test_family_ground_truth(self, weave):
        """One member of each of the family's structures, unbalanced and turned: densities within 1%, directions
        within 0.5 deg, the repeat along each system exact (the randomised 200 are benchmarks/fabric_family.py's)."""
        from data_synth.weaves import WeaveParams, make_weave, weave_truth

        params = WeaveParams(weave, 31.0, 19.0, 127.0, crimp_ratio=0.4, randomness=0.2)
        found = fabric_structure(make_weave(params, size=400, seed=3).height_mm, PITCH)[0]
        truth = weave_truth(params)
        assert found.threads_per_cm == pytest.approx(list(truth.threads_per_cm), rel=0.01)
        for got, want in zip(found.thread_angles_deg, truth.thread_angles_deg, strict=True):
            assert abs((got - want + 90) % 180 - 90) < 0.5
        assert found.repeat_threads == list(truth.repeat_threads)


class TestSFilter:
    @pytest.mark.parametrize(("pitch", "cutoff"), [(0.025, 0.08), (0.008, 0.025), (0.0025, 0.008), (0.02, 0.08),
                                                   (0.0333, 0.1), (0.001, 0.005)])
    def test_iso_nesting_index_of_the_sampling(self, pitch, cutoff):
        from psmini.fabric import iso_s_cutoff_mm

        assert iso_s_cutoff_mm(pitch) == pytest.approx(cutoff, rel=1e-12)
        assert iso_s_cutoff_mm(pitch) >= 3 * pitch

    def test_describe_surface_options(self):
        from psmini.fabric import DESCRIBE_SURFACE_OPTIONS, describe_surface_options

        assert describe_surface_options(0.025) == SurfaceOptions(form_degree=1, s_cutoff_mm=0.08, l_cutoff_mm=2.5)
        assert describe_surface_options(1.0) == DESCRIBE_SURFACE_OPTIONS  # 5 mm would exceed the L-filter

    def test_errors(self):
        from psmini.fabric import describe_surface_options, iso_s_cutoff_mm

        for bad in (0.0, -1.0, float("inf"), "0.025"):
            with pytest.raises(InputError, match="pixel_pitch_mm"):
                iso_s_cutoff_mm(bad)
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            describe_surface_options(0.0)


def test_skewed_systems_are_found_within_ten_degrees():
    """Bow and skew turn the weft a few degrees off the warp's right angle: a lattice whose systems cross at 84°."""
    x, y = grid(400)
    a1, a2 = math.radians(20.0), math.radians(20.0 + 84.0)  # the two peaks' directions, 84° apart
    z = 0.03 * torch.cos(2 * math.pi * 3.0 * (x * math.cos(a1) + y * math.sin(a1))) \
        + 0.02 * torch.cos(2 * math.pi * 2.2 * (x * math.cos(a2) + y * math.sin(a2)))
    found = fabric_structure(z[None, None], PITCH)[0]
    assert found.threads_per_cm == pytest.approx([30.0, 22.0], rel=2e-3)
    expected = [(20.0 + 90.0) % 180.0, (104.0 + 90.0) % 180.0]
    for got, want in zip(found.thread_angles_deg, expected, strict=True):
        assert abs((got - want + 90) % 180 - 90) < 0.05
