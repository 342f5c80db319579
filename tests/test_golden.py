"""The runtime against torch outputs stored in tests/golden: runs without torch installed."""
import numpy as np

from minretarget.retargeter import Retargeter
from minretarget.pipeline import PipelineConfig

TOLERANCE = 1e-4   # metres


def test_runtime_reproduces_the_golden_torch_stream(tiny_weights, tiny_stream):
    target, sources, want = tiny_stream
    # The torch reference's pipeline: SKR once on the target, no facing check, no smoothing,
    # no foot contacts.
    retargeter = Retargeter(tiny_weights, PipelineConfig(smoothing=None, foot_lock=None,
                                                         mirror_target=False, facing_check=False))
    retargeter.set_target(target)
    np.testing.assert_allclose(retargeter.target.tpose_joints, want["torch_tpose_joints"],
                               atol=TOLERANCE)
    np.testing.assert_allclose(retargeter.target.skin_weights, want["torch_skin_weights"],
                               atol=1e-5)
    assert len(sources) == 60 and len({len(s) for s in sources}) > 1   # point counts vary
    for t, frame in enumerate(retargeter.run(sources)):
        for key in ("vertices", "joints", "root", "source_joints"):
            np.testing.assert_allclose(getattr(frame, key), want[f"torch_{key}"][t],
                                       atol=TOLERANCE, err_msg=f"frame {t} {key}")
        np.testing.assert_allclose(frame.rotations, want["torch_rotations"][t], atol=1e-5)
