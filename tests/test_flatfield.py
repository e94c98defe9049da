import pytest
import torch

from psmini import InputError, ShapeError
from psmini.flatfield import FlatField, fill_saturated_card, flatfield, smooth_card
from tests.conftest import BaseTester


class TestFlatField(BaseTester):
    def test_cancels_falloff(self, device, dtype):
        """Cloth = albedo * shading * falloff + dark; card = card_albedo * falloff + dark."""
        torch.manual_seed(0)
        falloff = torch.rand(1, 8, 16, 16, device=device, dtype=dtype) + 0.2
        shading = torch.rand(2, 8, 16, 16, device=device, dtype=dtype)
        dark = torch.full((2, 1, 16, 16), 0.05, device=device, dtype=dtype)
        images = 0.6 * shading * falloff + dark
        reference = 0.8 * falloff + 0.05
        result = flatfield(images, reference[0], dark, dark[:1], card_albedo=0.8)
        self.assert_close(result.images, 0.6 * shading)
        assert bool(result.valid.all())

    def test_gain_is_the_factor_applied_to_each_reading(self, device, dtype):
        """The gain multiplies the dark-subtracted reading into the flat-fielded one (and its noise with it): the
        card's albedo over its signal, 0 where the card is not trusted; none without a card."""
        torch.manual_seed(0)
        reference = torch.rand(8, 6, 6, device=device, dtype=dtype) + 0.3
        reference[2, 1, 1] = 0.001  # untrusted
        dark = torch.full((1, 1, 6, 6), 0.05, device=device, dtype=dtype)
        images = torch.rand(2, 8, 6, 6, device=device, dtype=dtype) * 0.5 + 0.1
        result = flatfield(images, reference, dark, dark, card_albedo=0.8, min_reference=0.05)
        expected = 0.8 / (reference - 0.05)
        expected[2, 1, 1] = 0.0
        self.assert_close(result.gain.expand(1, 8, 6, 6)[0], expected)
        self.assert_close(result.images, (images - dark).clamp_min(0) * result.gain)
        images[0, 0, 0, 0] = 2.5  # saturated: the other path, the same gain
        saturated = flatfield(images, reference, dark, dark, card_albedo=0.8, min_reference=0.05, saturation_level=2.0)
        assert not bool(saturated.valid[0, 0, 0, 0])
        self.assert_close(saturated.gain, result.gain)
        assert flatfield(images, dark=dark).gain is None

    def test_dark_reference_untrusted(self, device, dtype):
        reference = torch.ones(8, 4, 4, device=device, dtype=dtype)
        reference[3, 0, 0] = 0.01
        result = flatfield(torch.ones(1, 8, 4, 4, device=device, dtype=dtype), reference, min_reference=0.05)
        assert not bool(result.valid[0, 3, 0, 0]) and float(result.images[0, 3, 0, 0]) == 0.0
        assert int((~result.valid).sum()) == 1

    def test_saturation(self, device, dtype):
        images = torch.full((1, 8, 4, 4), 0.5, device=device, dtype=dtype)
        images[0, 2, 1, 1] = 1.0
        reference = torch.full((8, 4, 4), 0.5, device=device, dtype=dtype)
        reference[5, 2, 2] = 1.0
        result = flatfield(images, reference, saturation_level=0.99)
        assert not bool(result.valid[0, 2, 1, 1]) and not bool(result.valid[0, 5, 2, 2])
        assert int((~result.valid).sum()) == 2

    def test_no_reference_subtracts_dark_and_clamps(self, device, dtype):
        images = torch.tensor([0.2, 0.05], device=device, dtype=dtype).view(1, 2, 1, 1)
        result = flatfield(images, dark=torch.full((1, 1, 1, 1), 0.1, device=device, dtype=dtype))
        self.assert_close(result.images.flatten(), torch.tensor([0.1, 0.0], device=device, dtype=dtype))

    def test_module_equals_functional(self, device, dtype):
        reference = torch.rand(8, 6, 6, device=device, dtype=dtype) + 0.1
        images = torch.rand(2, 8, 6, 6, device=device, dtype=dtype)
        a = FlatField(reference, card_albedo=0.7)(images)
        b = flatfield(images, reference, card_albedo=0.7)
        self.assert_close(a.images, b.images)
        assert torch.equal(a.valid, b.valid)

    @pytest.mark.parametrize("case", ["card", "no card", "no dark", "saturated"])
    def test_out_equals_new_tensor(self, device, dtype, case):
        """The flat-fielded images written into ``out`` are the new tensor's on every path, and are ``out``."""
        images = torch.rand(2, 8, 6, 5, device=device, dtype=dtype)
        dark = None if case == "no dark" else torch.rand(2, 1, 6, 5, device=device, dtype=dtype) * 0.05
        reference = None if case == "no card" else torch.rand(8, 6, 5, device=device, dtype=dtype) * 0.5 + 0.4
        level = 0.9 if case == "saturated" else None
        expected = flatfield(images, reference, dark, card_albedo=0.8, saturation_level=level)
        out = torch.full_like(images, torch.nan)
        got = flatfield(images, reference, dark, card_albedo=0.8, saturation_level=level, out=out)
        assert got.images is out
        self.assert_close(got.images, expected.images, rtol=0, atol=0)
        assert torch.equal(got.valid, expected.valid)

    def test_bad_out_raise(self):
        images, card = torch.rand(2, 8, 4, 4), torch.full((8, 4, 4), 0.5)
        with pytest.raises(ShapeError, match=r"out images .*\(2, 8, 4, 4\).*\(1, 8, 4, 4\)"):
            flatfield(images, card, out=torch.empty(1, 8, 4, 4))
        with pytest.raises(InputError, match="share memory"):
            flatfield(images, card, out=images)
        with pytest.raises(InputError, match="requires grad"):
            flatfield(images.clone().requires_grad_(), card, out=torch.empty(2, 8, 4, 4))

    def test_bad_shapes_raise(self):
        with pytest.raises(ShapeError, match="reference must broadcast"):
            flatfield(torch.rand(1, 8, 4, 4), torch.rand(7, 4, 4))
        with pytest.raises(ShapeError, match="dark must broadcast"):
            flatfield(torch.rand(1, 8, 4, 4), dark=torch.rand(1, 1, 4, 5))

    def test_nan_raise(self):
        reference = torch.rand(8, 4, 4)
        reference[0, 0, 0] = float("nan")
        with pytest.raises(InputError, match="reference must be finite"):
            flatfield(torch.rand(1, 8, 4, 4), reference)

    def test_nan_written_into_a_kept_card_raises(self):
        # the card's finiteness is tested with its kept terms: an in-place change must be tested again
        reference = torch.rand(8, 4, 4) + 0.1
        flatfield(torch.rand(1, 8, 4, 4), reference)
        reference[3, 2, 1] = float("inf")
        with pytest.raises(InputError, match="reference must be finite, got 1"):
            flatfield(torch.rand(1, 8, 4, 4), reference)

    def test_bad_options_raise(self):
        with pytest.raises(InputError, match="min_reference"):
            flatfield(torch.rand(1, 8, 4, 4), min_reference=1.5)
        with pytest.raises(InputError, match="card_albedo"):
            flatfield(torch.rand(1, 8, 4, 4), card_albedo=0.0)

    def test_gradcheck(self):
        images = torch.rand(1, 3, 3, 3, dtype=torch.float64, requires_grad=True)
        reference = (torch.rand(3, 3, 3, dtype=torch.float64) + 0.5).requires_grad_()
        self.gradcheck(lambda i, r: flatfield(i, r, card_albedo=0.8).images, (images, reference))

    def test_gradcheck_module(self):
        module = FlatField(torch.rand(3, 3, 3, dtype=torch.float64) + 0.5, card_albedo=0.8)
        images = torch.rand(1, 3, 3, 3, dtype=torch.float64, requires_grad=True)
        dark = torch.full((1, 1, 3, 3), 0.01, dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda i, d: module(i, d).images, (images, dark))

    def test_saturated_card_unsaturated_images(self, device, dtype):
        # no image reaches the level (the one-read shortcut), but the card does at one pixel: only the card decides
        images = torch.rand(2, 4, 5, 6, device=device, dtype=dtype) * 0.9
        reference = torch.full((4, 5, 6), 0.5, device=device, dtype=dtype)
        reference[2, 1, 3] = 1.0
        result = flatfield(images, reference, saturation_level=1.0)
        expected = torch.ones(2, 4, 5, 6, dtype=torch.bool, device=device)
        expected[:, 2, 1, 3] = False
        assert torch.equal(result.valid, expected) and result.all_valid is False
        self.assert_close(result.images, torch.where(expected, images / 0.5, 0.0))

    def test_card_terms_follow_the_card(self, device, dtype):
        # the card's terms are kept for the same, unmodified reference object: an in-place change, another card
        # object with other values, or another dark frame must each give their own result
        images = torch.rand(2, 3, 4, 5, device=device, dtype=dtype) + 0.1
        reference = torch.full((3, 4, 5), 0.5, device=device, dtype=dtype)
        first = flatfield(images, reference).images
        self.assert_close(flatfield(images, reference).images, first)
        reference.mul_(2.0)  # in place: a new version of the same tensor
        self.assert_close(flatfield(images, reference).images, first / 2)
        self.assert_close(flatfield(images, torch.full_like(reference, 0.25)).images, first * 2)
        dark = torch.full((1, 1, 4, 5), 0.05, device=device, dtype=dtype)
        self.assert_close(flatfield(images, reference, reference_dark=dark).images, images / 0.95)
        from psmini.flatfield import _kept_cards  # the list of kept terms, updated in place

        assert _kept_cards  # kept while the card lives ...
        del reference, dark
        assert not _kept_cards  # ... and dropped with it

    def test_card_terms_kept_for_fresh_views_of_the_same_data(self, device, dtype):
        """``darks[:1]`` sliced afresh in every call reuses the card's terms; a change through any view, or another
        slice, does not."""
        from psmini.flatfield import _kept_cards

        images = torch.rand(2, 3, 4, 5, device=device, dtype=dtype) + 0.3
        reference = torch.full((1, 3, 4, 5), 0.6, device=device, dtype=dtype)
        darks = torch.stack([torch.full((1, 4, 5), value, device=device, dtype=dtype) for value in (0.1, 0.2)])
        first = flatfield(images, reference, darks, darks[:1]).images
        terms = _kept_cards[0].terms
        self.assert_close(flatfield(images, reference, darks, darks[:1]).images, first)
        assert _kept_cards[0].terms is terms  # the same data: not recomputed
        other = flatfield(images, reference, darks, darks[1:]).images  # another slice: its own terms
        self.assert_close(other, (images - darks).clamp_min(0) / 0.4)
        darks[:1].fill_(0.3)  # a change through a view bumps the shared version
        self.assert_close(flatfield(images, reference, darks, darks[:1]).images, (images - darks).clamp_min(0) / 0.3)

    def test_two_cards_terms_are_kept_in_turn(self, device, dtype):
        """Near light and the distant pipeline flat-field one card with different terms (a smoothed card): called in
        turn, each recomputed the card (0.34 s at 400², where a warm distant call takes 12 ms). The last two sets of
        terms are kept; a third evicts the oldest."""
        from psmini.flatfield import _kept_cards

        images = torch.rand(1, 3, 16, 16, device=device, dtype=dtype) + 0.3
        reference = torch.rand(3, 16, 16, device=device, dtype=dtype) + 0.5
        smoothed = flatfield(images, reference, card_smoothing_px=2.0).images
        plain = flatfield(images, reference).images
        terms = {id(entry.terms) for entry in _kept_cards}
        assert len(terms) == 2
        self.assert_close(flatfield(images, reference, card_smoothing_px=2.0).images, smoothed)
        self.assert_close(flatfield(images, reference).images, plain)
        assert {id(entry.terms) for entry in _kept_cards} == terms  # neither recomputed
        assert not torch.equal(smoothed, plain)
        flatfield(images, reference, card_smoothing_px=3.0)
        assert len(_kept_cards) == 2 and _kept_cards[0].key[6] == 3.0 and _kept_cards[1].key[6] is None

    def test_gradcheck_with_dark_and_saturation(self):
        """The in-place path (difference, clamp, scale, saturation fill on one new tensor) keeps its gradients."""
        torch.manual_seed(0)
        images = (0.3 + 0.6 * torch.rand(2, 3, 3, 3, dtype=torch.float64)).requires_grad_()
        dark = torch.full((2, 1, 3, 3), 0.1, dtype=torch.float64, requires_grad=True)
        reference = (torch.rand(3, 3, 3, dtype=torch.float64) + 0.5).requires_grad_()
        with torch.no_grad():
            images[0, 0, 0, 0] = 0.05  # below the dark frame: clamped to 0
        self.gradcheck(
            lambda i, d, r: flatfield(i, r, d, torch.zeros(1, 1, 3, 3, dtype=torch.float64), 0.8,
                                      saturation_level=0.85).images,
            (images, dark, reference),
        )

    def test_single_pass_equals_reference_formula(self, device, dtype):
        """max(I - D, 0) * albedo / (R - D_R) where trusted, 0 elsewhere, with saturated observations zeroed."""
        torch.manual_seed(1)
        images = torch.rand(3, 8, 12, 10, device=device, dtype=dtype)
        dark = 0.05 * torch.rand(3, 1, 12, 10, device=device, dtype=dtype)
        reference = 0.2 + torch.rand(8, 12, 10, device=device, dtype=dtype)
        reference[2, :3] = 0.001  # untrusted corner under LED 2
        reference_dark = torch.full((1, 1, 12, 10), 0.01, device=device, dtype=dtype)
        result = flatfield(images, reference, dark, reference_dark, 0.8, 0.02, saturation_level=0.97)
        card = reference - reference_dark
        trusted = (card > 0.02 * card.amax(dim=(-2, -1), keepdim=True)) & (reference < 0.97)
        ok = trusted & (images < 0.97)
        expected = torch.where(ok, 0.8 * (images - dark).clamp_min(0) / card, torch.zeros_like(images))
        self.assert_close(result.images, expected)
        assert torch.equal(result.valid, ok)

    @pytest.mark.parametrize("with_card", [True, False])
    def test_saturation_in_a_strided_stack(self, device, dtype, with_card):
        """A transposed (non-contiguous) stack, saturated in one batch item only, gives the element-wise
        formula's images and valid map, and the contiguous stack's."""
        torch.manual_seed(2)
        images = torch.rand(2, 5, 9, 7, device=device, dtype=dtype).transpose(-1, -2)  # (2, 5, 7, 9), strided
        images[0] = images[0].clamp_max(0.9)  # item 0 unsaturated: the positions come from item 1 alone
        reference = 0.3 + torch.rand(5, 7, 9, device=device, dtype=dtype) * 0.5 if with_card else None
        result = flatfield(images, reference, saturation_level=0.95)
        ok = images < 0.95
        expected = images.clamp_min(0) if reference is None else images * (1.0 / reference)
        self.assert_close(result.images, torch.where(ok, expected, torch.zeros_like(images)))
        assert torch.equal(result.valid, ok) and int((~ok[1]).sum()) > 0
        assert torch.equal(flatfield(images.contiguous(), reference, saturation_level=0.95).images, result.images)

    def test_all_valid_known_from_the_card(self):
        images = torch.rand(2, 4, 5, 5)
        card = torch.full((4, 5, 5), 0.5)
        assert flatfield(images, card).all_valid is True
        assert flatfield(images).all_valid is True
        card[1, 0, 0] = 0.0  # one untrusted card pixel
        result = flatfield(images, card)
        assert result.all_valid is False and not bool(result.valid.all())
        assert flatfield(images, card, saturation_level=0.99).all_valid is None


def linear_card(size: int = 24, dtype=torch.float64, seed: int = 0) -> torch.Tensor:
    """Three LEDs whose irradiance ratios to their mean are linear across the field, times a pixel-to-pixel gain
    common to the LEDs (vignetting and the pixels' response): what smooth_card must keep exactly."""
    gen = torch.Generator().manual_seed(seed)
    u = torch.linspace(-1, 1, size, dtype=dtype).view(1, 1, 1, size)
    v = torch.linspace(-1, 1, size, dtype=dtype).view(1, 1, size, 1)
    shapes = torch.cat([(1 + 0.3 * u + 0.1 * v), (1 - 0.3 * u + 0 * v), (1 - 0.1 * v + 0 * u)], dim=1)
    gain = 0.7 + 0.2 * torch.rand(1, 1, size, size, generator=gen, dtype=dtype)
    return gain * shapes


class TestSmoothCard(BaseTester):
    def test_keeps_a_common_gain_times_linear_shapes(self):
        """Local linear fits reproduce linear ratios to the mean, borders included, and the per-pixel gain common
        to the LEDs (not smooth) is fitted back exactly."""
        card = linear_card()
        self.assert_close(smooth_card(card, 2.0), card, rtol=1e-12, atol=0)

    def test_removes_the_noise_of_a_simulated_card(self):
        """On the simulator's card (inverse square, LED beams, vignetting), 8-bit noise: the smoothed card is far
        closer to the noise-free card than the noisy one is, and the noise-free card comes back as it was."""
        from data_synth.rig import RigConfig, render_card

        config = RigConfig(size=96, pixel_pitch_mm=0.1, noise=False, bit_depth=16)
        clean = render_card(config, 0.8)
        noisy = render_card(config.replace(noise=True, bit_depth=8), 0.8)
        truth = (clean.images - clean.dark)[None].double()
        raw = (noisy.images - noisy.dark)[None].double()
        usable = (noisy.images < 1.0)[None] & (clean.images < 1.0)[None]
        smoothed = smooth_card(raw, 3.0, usable)
        every = usable.all(dim=1, keepdim=True).expand_as(usable)

        def shape_error(card):  # the LED-dependent part: each LED's ratio to the mean (the mean leaves normals alone)
            relative = (card / card.mean(dim=1, keepdim=True)) / (truth / truth.mean(dim=1, keepdim=True)) - 1
            return float(relative[every].square().mean().sqrt())

        assert shape_error(smoothed) < 0.2 * shape_error(raw)
        kept = smooth_card(truth, 3.0, (clean.images < 1.0)[None])
        assert float(((kept - truth) / truth)[usable].abs().median()) < 5e-4  # 1e-5 on the rig's 400 px

    def test_unusable_readings_are_kept_and_stay_untrusted(self):
        card = 0.5 * linear_card(size=20).float()
        card[0, 1, 5:9, 5:9] = 1.0  # a saturated patch of LED 1
        usable = card < 1.0
        smoothed = smooth_card(card, 2.0, usable)
        assert torch.equal(smoothed[~usable], card[~usable])
        images = torch.full((1, 3, 20, 20), 0.5)
        result = flatfield(images, card, card_smoothing_px=2.0, saturation_level=1.0)
        assert not bool(result.valid[0, 1, 5:9, 5:9].any()) and bool(result.valid[0, 0].all())

    def test_flatfield_divides_by_the_smoothed_card(self):
        card = linear_card(size=20)
        noisy = card + 0.01 * torch.randn(card.shape, generator=torch.Generator().manual_seed(1), dtype=card.dtype)
        images = 0.5 * card
        plain = flatfield(images, noisy, card_albedo=0.8).images
        smoothed = flatfield(images, noisy, card_albedo=0.8, card_smoothing_px=3.0).images
        self.assert_close(smoothed, flatfield(images, smooth_card(noisy, 3.0), card_albedo=0.8).images)
        # what the normals see: each LED's share of a pixel's readings (a common factor per pixel cancels)
        share = lambda x: x / x.mean(dim=1, keepdim=True)  # noqa: E731
        assert float((share(smoothed) - 1).abs().mean()) < 0.3 * float((share(plain) - 1).abs().mean())

    def test_keeps_curved_shapes_that_a_linear_fit_bends(self):
        """Each LED's share quadratic across the field (a near LED's falloff curves): the local quadratic fit keeps
        it to rounding, where a local linear fit over the same window errs by sigma^2 / 2 times its curvature."""
        u = torch.linspace(-1, 1, 32, dtype=torch.float64).view(1, 1, 1, 32)
        v = torch.linspace(-1, 1, 32, dtype=torch.float64).view(1, 1, 32, 1)
        a, b = 0.3 * u + 0.4 * u**2 + 0 * v, -0.2 * v + 0.3 * u * v
        shares = torch.cat([1 + a, 1 + b, 1 - a - b], dim=1)  # each LED's ratio to the mean (1): quadratic
        gain = 0.7 + 0.2 * torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
        card = gain * shares
        smoothed = smooth_card(card, 3.0)
        self.assert_close(smoothed, card, rtol=1e-9, atol=1e-12)

    def test_gradcheck(self):
        card = (linear_card(size=7) + 0.01 * torch.rand(1, 3, 7, 7, dtype=torch.float64)).requires_grad_()
        self.gradcheck(lambda c: smooth_card(c, 1.0), (card,))

    def test_errors(self):
        card = linear_card(size=8)
        with pytest.raises(InputError, match="sigma_px"):
            smooth_card(card, 0.0)
        with pytest.raises(InputError, match="finite"):
            smooth_card(card.index_fill(3, torch.tensor([2]), float("nan")), 2.0)
        with pytest.raises(ShapeError, match="card must have shape"):
            smooth_card(card[0], 2.0)
        with pytest.raises(ShapeError, match="usable"):
            smooth_card(card, 2.0, torch.ones(1, 3, 8, 7, dtype=torch.bool))
        with pytest.raises(InputError, match="card_smoothing_px"):
            flatfield(torch.rand(1, 3, 8, 8), card, card_smoothing_px=-1.0)


def shaded_card(size: int = 6, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """A card that reads a pixel gain times each LED's shading, three LEDs, and that shading: the third LED's
    shading reaches 1.5 at one corner, where a card of gain 0.8 clips at 1."""
    u = torch.linspace(0, 1, size, dtype=dtype)
    ramp = (u.view(1, -1) + u.view(-1, 1)) / 2  # 0 at one corner, 1 at the other
    shading = torch.stack([torch.full_like(ramp, 0.6), 0.9 - 0.3 * ramp, 0.5 + ramp])[None]
    gain = 0.8 + 0.1 * torch.cos(7 * u).view(1, -1) * torch.sin(5 * u).view(-1, 1)
    return gain * shading, shading


class TestFillSaturatedCard(BaseTester):
    def test_predicts_the_clipped_readings_exactly(self):
        """With the shading the card was made of, the readings that clipped come back as the card read them before
        the clip, and the flat-field keeps every reading there instead of dropping the saturating LED's."""
        card, shading = shaded_card()
        clipped = card.clamp(max=1.0)
        assert bool((card > 1.0).any()) and bool((card > 1.0).float().mean() < 0.5)
        filled, usable = fill_saturated_card(clipped, clipped < 1.0, shading)
        self.assert_close(filled, card)
        assert bool(usable.all())
        images = 0.5 * card  # a cloth of albedo 0.4 under the same light, unsaturated
        kept = flatfield(images, clipped, card_albedo=0.8, saturation_level=1.0, card_shading=shading)
        self.assert_close(kept.images, torch.full_like(images, 0.4))
        assert bool(kept.valid.all())
        dropped = flatfield(images, clipped, card_albedo=0.8, saturation_level=1.0)
        assert torch.equal(dropped.valid, (card < 1.0).expand_as(images))

    def test_pixel_saturated_under_every_led_stays_untrusted(self):
        card, shading = shaded_card()
        clipped = card.clamp(max=1.0)
        clipped[:, :, 0, 0] = 1.0  # nothing left to fit the gain to
        filled, usable = fill_saturated_card(clipped, clipped < 1.0, shading)
        assert not bool(usable[:, :, 0, 0].any()) and torch.equal(filled[:, :, 0, 0], clipped[:, :, 0, 0])
        result = flatfield(0.5 * card, clipped, card_albedo=0.8, saturation_level=1.0, card_shading=shading)
        assert not bool(result.valid[:, :, 0, 0].any())

    def test_a_wrong_model_errs_by_its_error_between_leds(self):
        """The prediction is as good as the model's shading of the saturating LED relative to the others."""
        card, shading = shaded_card()
        clipped = card.clamp(max=1.0)
        wrong = shading * torch.tensor([1.0, 1.0, 1.02], dtype=shading.dtype).view(1, 3, 1, 1)
        filled, _ = fill_saturated_card(clipped, clipped < 1.0, wrong)
        over = card > 1.0
        self.assert_close(filled[over], 1.02 * card[over])

    def test_a_reference_file_s_untrusted_pixels_are_predicted_too(self):
        """`psmini calibrate flatfield` writes the card's saturated pixels as the dark frame (a reference of 0):
        those readings are predicted as the clipped ones are."""
        card, shading = shaded_card()
        written = torch.where(card >= 1.0, torch.zeros_like(card), card)
        images = 0.5 * card
        result = flatfield(images, written, card_albedo=0.8, saturation_level=1.0, card_shading=shading)
        assert bool(result.valid.all())
        self.assert_close(result.images, torch.full_like(images, 0.4))

    def test_a_dark_frame_per_sample_broadcasts_with_the_card(self):
        """A card (1, K, H, W) with a dark frame per sample (2, 1, H, W): the completed card follows the broadcast."""
        card, shading = shaded_card()
        dark = torch.tensor([0.01, 0.02], dtype=card.dtype).view(2, 1, 1, 1).expand(2, 1, 6, 6)
        raw = (card + 0.01).clamp(max=1.0)  # the card's frames were taken with the first sample's dark level
        images = 0.5 * card + dark
        result = flatfield(images, raw, dark, dark, card_albedo=0.8, saturation_level=1.0, card_shading=shading)
        assert bool(result.valid.all())
        self.assert_close(result.images[0], torch.full_like(card[0], 0.4))

    def test_gradcheck(self):
        card, shading = shaded_card(size=4)
        unsaturated = card < 1.0
        card = card.clamp(max=1.0).requires_grad_()
        self.gradcheck(lambda c, s: fill_saturated_card(c, unsaturated, s)[0], (card, shading.clone().requires_grad_()))

    def test_errors(self):
        card, shading = shaded_card()
        with pytest.raises(ShapeError, match="unsaturated"):
            fill_saturated_card(card, torch.ones(1, 3, 6, 5, dtype=torch.bool), shading)
        with pytest.raises(ShapeError, match="shading"):
            fill_saturated_card(card, card < 1.0, shading[..., :5])
        with pytest.raises(ShapeError, match="card must have shape"):
            fill_saturated_card(card[0], card[0] < 1.0, shading)
        with pytest.raises(ShapeError, match="card_shading"):
            flatfield(card, card, saturation_level=1.0, card_shading=shading[..., :5])
        unknown = shading.index_fill(3, torch.tensor([1]), float("nan"))
        with pytest.raises(InputError, match="card_shading"):
            flatfield(card, card, saturation_level=1.0, card_shading=unknown)

    def test_card_terms_kept_while_the_shading_is_equal(self):
        """A batch run passes the same card with every batch and near light an equal shading (computed afresh from
        its light model): the card's terms (its smoothing and prediction, half a second at 400²) are computed once;
        a shading of other values is another card."""
        card, shading = shaded_card()
        clipped = card.clamp(max=1.0)
        images = 0.5 * card
        first = flatfield(images, clipped, card_albedo=0.8, saturation_level=1.0, card_shading=shading)
        again = flatfield(images, clipped, card_albedo=0.8, saturation_level=1.0, card_shading=shading.clone())
        assert again.gain is first.gain
        moved = shading * torch.tensor([1.0, 1.0, 1.01], dtype=shading.dtype).view(1, 3, 1, 1)
        other = flatfield(images, clipped, card_albedo=0.8, saturation_level=1.0, card_shading=moved)
        assert other.gain is not first.gain
        assert not torch.allclose(other.gain, first.gain)
