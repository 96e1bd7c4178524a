"""Every shipped pretrained model loads and reproduces its recorded fixed-key AOE."""

from __future__ import annotations

import pytest

from gst_jax import load_pretrained, pretrained
from gst_jax.config import DataConfig
from gst_jax.pretrained.export import check_aoe


def test_at_least_one_model_is_shipped():
    assert pretrained.available()


@pytest.mark.parametrize("name", pretrained.available())
def test_pretrained_model_reproduces_its_recorded_aoe(name):
    meta = pretrained.load_meta(name)
    config, params = load_pretrained(name)
    aoe = check_aoe(config, params, DataConfig(**meta["data"]))
    assert abs(aoe - meta["check"]["aoe"]) < 1e-3
