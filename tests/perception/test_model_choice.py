"""Which shipped model a config flies (issue 18: the safe model by default for real cameras)."""

from companion.app.assemble import real_frames
from companion.config import load_config
from perception.detector import SHIPPED_MODEL, SHIPPED_REAL_MODEL, Detector, model_path
from perception.pipeline import Pipeline


def test_a_real_camera_runs_the_real_world_model_unless_the_config_names_one():
    cam = load_config([], [])  # the default config: a camera device (perception.source "0")
    assert real_frames(cam) and model_path(cam.perception, real_frames(cam)) == SHIPPED_REAL_MODEL
    assert Pipeline.from_config(cam, real_frames=True).det.path == SHIPPED_REAL_MODEL
    syn = load_config([], ["app.camera=synthetic"])  # rendered frames: the model trained for them
    assert not real_frames(syn) and model_path(syn.perception, real_frames(syn)) == SHIPPED_MODEL
    named = load_config([], ["perception.model=gate_detector.onnx"])  # a named model always wins
    assert model_path(named.perception, True) == SHIPPED_MODEL
    assert Detector.from_config(named.perception, real_frames=True).path == SHIPPED_MODEL
    # The in-process studies and anything that does not say its frames are real keep the default model.
    assert Pipeline.from_config(cam).det.path == SHIPPED_MODEL


def test_the_appearance_descriptor_is_computed_only_when_its_rule_is_on():
    """Every box's histogram costs ~0.1 ms per frame; only verification's appearance rule reads it."""
    assert not Pipeline.from_config(load_config([], [])).appearance  # min_similarity 0: the rule is off
    assert Pipeline.from_config(load_config([], ["app.verify.min_similarity=0.5"])).appearance
    assert not Pipeline.from_config(load_config([], ["app.verify.min_similarity=0.5",
                                                     "app.verify.enabled=false"])).appearance
