"""The declared pipeline (minretarget.pipeline): configs, presets, and the weights' couplings."""
import json

import numpy as np

import pytest

from minretarget import FitSettings, FootLock, PipelineConfig, Retargeter, Smoothing
from minretarget.denoise import DenoiseState
from minretarget.stages import Denoising, Frame
from minretarget.pipeline import (DEFAULT_PRESET, LEGACY_COUPLINGS, PRESETS, UNCOUPLED,
                                  as_config, check_pipeline, preset)


def test_every_preset_survives_json_and_is_known_by_name():
    for name, config in PRESETS.items():
        again = PipelineConfig.from_json(config.to_json())
        assert again == config and again.preset_name() == name
        assert json.loads(config.to_json()) == config.to_dict()
    assert preset("default") == PRESETS[DEFAULT_PRESET] == as_config(None)
    assert PipelineConfig() == PRESETS["regressed"]
    assert PipelineConfig(foot_lock=None).preset_name() is None


def test_presets_are_the_stages_they_name():
    paper, fitted = PRESETS["paper"], PRESETS["fitted"]
    assert not any((paper.mirror_target, paper.refine, paper.facing_check, paper.denoise,
                    paper.rest_pose)) and paper.smoothing is paper.foot_lock is None
    assert paper.fit_source is None
    assert fitted.fit_source == FitSettings() and fitted.smoothing is None
    assert not fitted.denoise and fitted.refine and fitted.foot_lock == FootLock()


def test_bad_settings_are_named():
    with pytest.raises(TypeError, match="refine must be True or False"):
        PipelineConfig(refine="no")
    with pytest.raises(ValueError, match="smoothing must be"):
        PipelineConfig(smoothing=(0.5,))
    with pytest.raises(TypeError, match="fit_source must be"):
        PipelineConfig(fit_source={"iterations": 3})
    with pytest.raises(TypeError, match="has no setting smoothin"):
        PipelineConfig().replace(smoothin=None)
    with pytest.raises(ValueError, match="unknown pipeline settings"):
        PipelineConfig.from_dict({"denoiser": True})
    with pytest.raises(ValueError, match="must be null or an object of"):
        PipelineConfig.from_dict({"foot_lock": {"plant": 1.0}})
    with pytest.raises(ValueError, match="no pipeline preset 'fast'"):
        preset("fast")
    with pytest.raises(TypeError, match="config must be a PipelineConfig"):
        as_config({"refine": True})


def test_json_values_become_the_settings_types():
    config = PipelineConfig.from_dict({"smoothing": {"position_gain": 0.5, "velocity_gain": 0.2},
                                       "fit_source": {"iterations": 3}, "foot_lock": None})
    assert config.smoothing == Smoothing(0.5, 0.2) and config.fit_source.iterations == 3
    assert config.foot_lock is None and config.refine


def test_a_denoiser_refuses_skeletons_unlike_those_it_learned(tiny_weights):
    coupled = tiny_weights._replace(metadata={**tiny_weights.metadata,
                                              "pipeline": LEGACY_COUPLINGS})
    assert check_pipeline(coupled, PRESETS["regressed"]) is PRESETS["regressed"]
    for changes, named in (({"smoothing": None}, "smoothing"), ({"refine": False}, "refine"),
                           ({"fit_source": FitSettings()}, "fit_source"),
                           ({"smoothing": Smoothing(0.5, 0.2)}, "smoothing")):
        with pytest.raises(ValueError, match=f"trained on skeletons with {named}="):
            Retargeter(coupled, PipelineConfig(**changes))
        Retargeter(coupled, PipelineConfig(allow_untrained=True, **changes))  # on request
        Retargeter(coupled, PipelineConfig(denoise=False, **changes))         # no denoiser
    for name in PRESETS:                                     # every preset is trained for
        Retargeter(coupled, name)
    assert tiny_weights.metadata["pipeline"] == UNCOUPLED   # random weights: anything goes
    Retargeter(tiny_weights, PipelineConfig(smoothing=None))
    # weights without a denoiser have nothing to refuse
    Retargeter(coupled._replace(denoise=None, config=coupled.config.without_denoiser()),
               PipelineConfig(smoothing=None))


def test_a_config_changed_mid_stream_keeps_the_states_of_the_stages_it_keeps(tiny_weights,
                                                                             tiny_stream):
    """The stages both configs run go on; a stage switched off drops its state; one switched
    on starts as at a stream's start: switched off and on again, the denoiser restarts."""
    target, sources, _ = tiny_stream
    retargeter = Retargeter(tiny_weights, warn=False)
    retargeter.set_target(target)
    retargeter.config = "paper"
    assert retargeter.config == PRESETS["paper"]
    assert [stage.name for stage in retargeter.stages] == ["skr", "smrm", "fk", "lbs"]
    retargeter.config = "regressed"
    for points in sources[:3]:
        retargeter.step(points)
    smrm = retargeter.state.stages["smrm"]
    retargeter.config = retargeter.config.replace(denoise=False)
    assert "denoiser" not in retargeter.state.stages
    assert retargeter.state.stages["smrm"] is smrm
    retargeter.config = retargeter.config.replace(denoise=True)
    restarted = retargeter.step(sources[3])
    smoothed = retargeter.state.stages["smoothing"].joints          # the denoiser's input
    fresh, _ = Denoising(tiny_weights.denoise).step(None, Frame(0, None, smoothed))
    for field in DenoiseState._fields:
        np.testing.assert_array_equal(getattr(retargeter.state.stages["denoiser"], field),
                                      getattr(fresh, field))
    assert retargeter.state.frames_seen == 4 and np.isfinite(restarted.vertices).all()


def test_thinned_clouds_are_the_same_points_whichever_call_reads_them(tiny_weights, tiny_stream):
    """cloud_points: ``step``, ``skeleton`` + ``step_skeleton`` and ``retarget_sequence`` read
    the same seeded subset of each frame (seed: its index in the stream), as the fit does."""
    from minretarget.sampling import seeded_subset
    target, sources, _ = tiny_stream
    clouds = np.stack([cloud[:200] for cloud in sources[:5]])
    config = PipelineConfig(cloud_points=80, smoothing=None, foot_lock=None)
    streamed, by_parts, offline = (Retargeter(tiny_weights, config, warn=False)
                                   for _ in range(3))
    plain = Retargeter(tiny_weights, config.replace(cloud_points=None), warn=False)
    for retargeter in (streamed, by_parts, offline, plain):
        retargeter.set_target(target)
    readings = by_parts.skeleton(clouds)
    sequence = offline.retarget_sequence(clouds)
    for t, cloud in enumerate(clouds):
        subset = seeded_subset(cloud, 80, t)
        assert len(subset) == 80 and len(np.unique(subset, axis=0)) == 80
        want = plain.step(subset)
        np.testing.assert_allclose(streamed.step(cloud).vertices, want.vertices, atol=1e-6)
        np.testing.assert_allclose(by_parts.step_skeleton(readings[t], cloud).vertices,
                                   want.vertices, atol=1e-6)
        np.testing.assert_allclose(sequence.vertices[t], want.vertices, atol=1e-5)
    with pytest.raises(ValueError, match="cloud_points must be None or an integer >= 64"):
        PipelineConfig(cloud_points=10)
