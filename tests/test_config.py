"""The one configuration: validation before any work, JSON round trip, resolution against light models."""

import json

import pytest
import torch

from psmini import DirectionalLights, InputError, LEDLights, ReconstructionConfig, ring_lights
from psmini.nearlight import NearLightOptions
from psmini.nonlambertian import NonLambertianOptions
from psmini.robust import RobustOptions


def leds():
    ring = ring_lights(8, 58.0)
    return LEDLights(ring * 18.6, -ring)


class TestReconstructionConfig:
    def test_json_round_trip(self):
        config = ReconstructionConfig(solver="near", integrator="masked", near={"max_iterations": 3},
                                      dtype="float64")
        back = ReconstructionConfig.from_dict(json.loads(json.dumps(config.to_dict())))
        assert back == config and back.torch_dtype == torch.float64
        assert isinstance(back.near, NearLightOptions) and back.near.max_iterations == 3

    def test_auto_resolves_from_the_light_model(self):
        near = ReconstructionConfig().resolved(leds(), has_mask=False)
        assert (near.solver, near.estimator, near.integrator) == ("near", "auto", "masked")
        distant = ReconstructionConfig().resolved(DirectionalLights(ring_lights(8, 55.0)), has_mask=False)
        assert (distant.solver, distant.estimator, distant.integrator) == ("distant", "lstsq", "fc")
        outlined = ReconstructionConfig().resolved(DirectionalLights(ring_lights(8, 55.0)), has_mask=True)
        assert outlined.integrator == "masked"
        forced = ReconstructionConfig(solver="distant").resolved(leds(), has_mask=False)
        assert forced.solver == "distant"

    @pytest.mark.parametrize(
        "fields, match",
        [
            ({"solver": "far"}, "solver must be one of"),
            ({"estimator": "median"}, "estimator must be one of"),
            ({"integrator": "poisson"}, "integrator must be one of"),
            ({"dtype": "float16"}, "dtype must be one of"),
            ({"integrator": "fc", "integrator_options": {"iterations": 3}}, "frankot_chellappa takes"),
            ({"integrator": "bilateral", "integrator_options": {"boundary": "mirror"}}, "bilateral_integration takes"),
            ({"solver": "near", "estimator": "tukey"}, "near-light solver has its own"),
            ({"near": {"max_iterations": 3}, "solver": "distant"}, "solver is 'distant'"),
            ({"near": {"speed": "fast"}}, "speed"),
            ({"near": {"max_iterations": 0}}, "max_iterations"),
            ({"solver": "distant", "integrator": "fill"}, "integrator must be one of"),
            ({"estimator": "lstsq", "estimator_options": {"low": 0.2}}, "takes no options"),
            ({"estimator": "tukey", "estimator_options": {"window": 3}}, "window"),
            ({"estimator": "tukey", "estimator_options": {"iterations": 0}}, "iterations"),
            ({"min_reference": 1.5}, "min_reference"),
            ({"card_smoothing_px": 0.0}, "card_smoothing_px"),
            ({"device": "gpu0"}, "device must name"),
        ],
    )
    def test_bad_configurations_raise_before_work(self, fields, match):
        with pytest.raises(InputError, match=match):
            ReconstructionConfig(**fields)

    def test_estimator_options_round_trip(self):
        config = ReconstructionConfig(estimator="tukey", estimator_options=RobustOptions(iterations=5))
        back = ReconstructionConfig.from_dict(json.loads(json.dumps(config.to_dict())))
        assert back == config and back.estimator_options.iterations == 5
        with pytest.raises(InputError, match="takes a RobustOptions"):
            ReconstructionConfig(estimator="tukey", estimator_options=NonLambertianOptions())

    def test_near_with_directional_lights_raises(self):
        with pytest.raises(InputError, match="needs light positions"):
            ReconstructionConfig(solver="near").solver_for(DirectionalLights(ring_lights(8, 55.0)))

    def test_from_dict_refuses_unknown_keys(self):
        with pytest.raises(InputError, match="unknown \\['light_model'\\]"):
            ReconstructionConfig.from_dict({"light_model": "near"})
