"""A method's options travel as one object: no public function of the pipeline's modules takes more than 8
parameters (an options dataclass counts as one)."""

import dataclasses
import importlib
import inspect

import pytest

MODULES = ["psmini.pipeline", "psmini.config", "psmini.robust", "psmini.nonlambertian", "psmini.nearlight",
           "psmini.ledcal", "psmini.evaluation"]


def _callables(module):
    for name in module.__all__:
        obj = getattr(module, name)
        if inspect.isclass(obj):
            init = obj.__dict__.get("__init__")
            # an options or result dataclass is the grouping itself: its fields are not a signature to shorten
            if init is not None and not dataclasses.is_dataclass(obj):
                yield f"{name}.__init__", init, 1  # self does not count
            for attr, member in vars(obj).items():
                if inspect.isfunction(member) and not attr.startswith("_"):
                    yield f"{name}.{attr}", member, 1
        elif inspect.isfunction(obj):
            yield name, obj, 0


@pytest.mark.parametrize("module_name", MODULES)
def test_no_public_function_takes_more_than_8_parameters(module_name):
    module = importlib.import_module(module_name)
    long = {name: len(inspect.signature(func).parameters) - skip for name, func, skip in _callables(module)
            if len(inspect.signature(func).parameters) - skip > 8}
    assert not long, f"{module_name}: {long} (group a method's options into one dataclass)"
