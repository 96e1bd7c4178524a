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
from gst_jax.errors import DataError

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
    # vmap hands XLA the same arithmetic batched, which it fuses and orders otherwise, so the
    # two differ by float32 rounding (by how much depends on the CPU): each of the rollout's
    # obs_len + pred_len sequential steps may add about an ulp of the magnitudes it carries,
    # up to the largest predicted output (metres; the -999 of those not predicted is exact),
    # in the mean and again in the accumulated Gaussian terms.
    predicted = np.asarray(first[1])[..., 0] == 1
    largest = float(np.abs(np.asarray(first[0])[predicted]).max())
    steps = model.config.obs_len + model.config.pred_len
    rounding = 2 * steps * np.finfo(np.float32).eps * largest
    np.testing.assert_allclose(np.asarray(stacked[0][1]), np.asarray(first[0]), rtol=0,
                               atol=rounding)
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


def test_one_non_finite_detection_is_refused_in_one_line_naming_env_human_and_step():
    model = predictor("seed1000")
    traj, mask = FIXTURE["input_traj"], FIXTURE["input_mask"]
    for value, shown in ((np.nan, "nan"), (-np.inf, "-inf")):
        broken = traj.copy()
        broken[1, 2, 3, 1] = value
        with pytest.raises(DataError, match=rf"^input_traj\[env 1, human 2, step 3\] is {shown} "
                                            r"where input_mask is 1 \(or non_finite="):
            model(broken, mask)
    half = mask.copy()
    half[0, 1, 2] = 0.5
    with pytest.raises(DataError, match=r"^input_mask\[env 0, human 1, step 2\] is 0.5; "
                                        "input_mask must be 0 or 1$"):
        model(traj, half)
    with pytest.raises(ValueError, match="non_finite must be one of"):
        crowdnav.Predictor(model.params, model.config, non_finite="drop")


def test_non_finite_detections_can_be_read_as_missed_and_never_spread():
    model = predictor("seed1000")
    lenient = crowdnav.Predictor(model.params, model.config, non_finite="undetected")
    traj, mask = FIXTURE["input_traj"], FIXTURE["input_mask"]
    expected = np.asarray(lenient(traj, mask)[0])
    broken = traj.copy()
    broken[1, 2, 3] = np.nan
    missed_traj, missed_mask = traj.copy(), mask.copy()
    missed_traj[1, 2, 3], missed_mask[1, 2, 3] = crowdnav.MISSING, 0
    output_traj, output_mask = map(np.asarray, lenient(broken, mask))
    missed = [np.asarray(a) for a in lenient(missed_traj, missed_mask)]
    np.testing.assert_array_equal(output_traj, missed[0])
    np.testing.assert_array_equal(output_mask, missed[1])
    assert np.isfinite(output_traj).all()
    np.testing.assert_array_equal(output_traj[[0, 2, 3]], expected[[0, 2, 3]])
    assert not np.array_equal(output_traj[1], expected[1])
    # NaN where a human is not detected (mask 0) reads as CrowdNav++'s -999, in either mode.
    unseen = traj.copy()
    unseen[0, 7] = np.nan                               # a padding slot
    unseen[0, 6, 2] = np.inf                            # missed once
    np.testing.assert_array_equal(np.asarray(lenient(unseen, mask)[0]), expected)
    np.testing.assert_array_equal(np.asarray(model(unseen, mask)[0]), expected)


def test_no_humans_in_view_gives_empty_outputs():
    model = predictor("seed1000")
    traj, mask = FIXTURE["input_traj"][:, :0], FIXTURE["input_mask"][:, :0]
    output_traj, output_mask = model(traj, mask)
    assert output_traj.shape == (4, 0, 5, 5) and output_mask.shape == (4, 0, 1)
