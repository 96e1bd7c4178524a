"""The CrowdNav++ drop-in against CrowdNav++'s own predictor.

tests/fixtures/crowdnav_parity.npz was made by experiments/crowdnav_fixture.py from CrowdNav++'s
public code and checkpoints (github.com/Shuijing725/CrowdNav_Prediction_AttnGraph, MIT licence:
(c) 2021 Zhe Huang for gst_updated/, (c) 2023 Shuijing Liu): both checkpoints' weights and
`args.pickle`, the inputs (humans entering late, leaving, seen only at the last two steps,
missed once, padding slots) and `CrowdNavPredInterfaceMultiEnv.forward`'s outputs.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from gst_jax import crowdnav
from gst_jax.compiles import count_compiles

FIXTURE = np.load(Path(__file__).parent / "fixtures" / "crowdnav_parity.npz")
CHECKPOINTS = ("seed1000", "seed1000_rand")


def predictor(name: str) -> crowdnav.Predictor:
    prefix = f"{name}/state_dict/"
    state_dict = {key[len(prefix):]: FIXTURE[key] for key in FIXTURE.files
                  if key.startswith(prefix)}
    return crowdnav.from_state_dict(state_dict, json.loads(str(FIXTURE[f"{name}/args"])))


@pytest.mark.parametrize("name", CHECKPOINTS)
def test_both_public_checkpoints_predict_as_crowdnav_does(name):
    output_traj, output_mask = predictor(name)(FIXTURE["input_traj"], FIXTURE["input_mask"])
    expected = FIXTURE[f"{name}/output_traj"]
    assert output_traj.shape == expected.shape == (4, 8, 5, 5)
    np.testing.assert_allclose(np.asarray(output_traj), expected, atol=1e-5, rtol=0)
    np.testing.assert_array_equal(np.asarray(output_mask), FIXTURE[f"{name}/output_mask"])
    # Those not predicted (leaving, never seen, padding) get -999, as in CrowdNav++.
    assert (np.asarray(output_traj)[..., :2][np.asarray(output_mask)[..., 0] == 0] == -999).all()


def test_the_predictor_compiles_once_per_shape_and_its_function_vmaps_and_jits():
    model = predictor("seed1000")
    traj, mask = FIXTURE["input_traj"], FIXTURE["input_mask"]
    with count_compiles() as compiles:
        first = model(traj, mask)
        model(traj + 0.5, mask)
    assert compiles.count == 1
    with count_compiles() as compiles:
        model(traj[:2], mask[:2])                 # another number of environments
    assert compiles.count == 1

    # The pure function underneath: a planner vmaps it over candidate futures, or jits it.
    stacked = jax.vmap(lambda t, m: crowdnav.predict(model.params, model.config, t, m))(
        np.stack([traj, traj]), np.stack([mask, mask]))
    np.testing.assert_allclose(np.asarray(stacked[0][1]), np.asarray(first[0]), atol=1e-6)
    inside = jax.jit(lambda p, t, m: crowdnav.predict(p, model.config, t, m)[0].sum())
    assert np.isclose(float(inside(model.params, traj, mask)), float(np.asarray(first[0]).sum()),
                      rtol=1e-5)


def test_bad_inputs_and_unsupported_runs_are_refused_in_one_line():
    model = predictor("seed1000")
    traj, mask = FIXTURE["input_traj"], FIXTURE["input_mask"]
    with pytest.raises(ValueError, match=r"input_mask must be \(n_env, N, obs_len, 1\)"):
        model(traj, mask[..., 0])
    with pytest.raises(ValueError, match="the model observes 5 steps, input_traj has 4"):
        model(traj[:, :, :4], mask[:, :, :4])
    args = json.loads(str(FIXTURE["seed1000/args"]))
    with pytest.raises(ValueError, match="spatial_num_heads_edges=4: gst_jax serves "
                                         "spatial_num_heads_edges=0"):
        crowdnav.model_config({**args, "spatial_num_heads_edges": 4})
    config = crowdnav.model_config(args)
    assert (config.obs_len, config.pred_len, config.step_s) == (5, 5, 0.25)
    assert (config.node_dim, config.lstm_hidden, config.encoder_layers) == (64, 64, 1)
    assert config.temporal == "faster_lstm" and not config.selects_edges
