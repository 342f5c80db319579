"""training.body_model: the PCA body model on hand-made bodies (a box scaled along one axis)."""
import numpy as np

from minretarget.fit import BodyModel
from training.body_model import build_body_model
from training.data.bodies import Body

BOX = np.array([[x, y, z] for x in (-0.2, 0.2) for y in (0.0, 1.7) for z in (-0.1, 0.1)])
FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def box_body(height):
    joints = np.linspace([0.0, 0.9, 0.0], [0.0, 1.6, 0.0], 22) * [1.0, height, 1.0]
    weights = np.zeros((8, 22), np.float32)
    weights[:, 0], weights[4:, 0], weights[4:, 3] = 1.0, 0.5, 0.5
    return Body(f"box {height}", {}, (BOX * [1.0, height, 1.0]).astype(np.float32),
                FACES.astype(np.int32), joints.astype(np.float32), weights)


def test_one_component_holds_a_one_way_family_of_bodies():
    bodies = [box_body(height) for height in (0.8, 0.9, 1.0, 1.1, 1.2)]
    arrays, kept = build_body_model(bodies, points=64, components=1)
    assert set(arrays) == set(BodyModel._fields) and kept > 0.999999
    model = BodyModel(**arrays)
    assert model.points.shape == (64, 3) and model.points_basis.shape == (1, 64, 3)
    # the model's joints move along its one component as the bodies' do
    direction = model.joints_basis[0] / np.linalg.norm(model.joints_basis[0])
    change = (bodies[-1].joints - bodies[0].joints) / np.linalg.norm(bodies[-1].joints
                                                                     - bodies[0].joints)
    assert abs(np.sum(direction * change)) > 0.999
    np.testing.assert_allclose(model.bone_weight.sum(axis=1), 1.0, atol=1e-6)
    assert set(np.unique(model.bone_index[model.bone_weight > 0])) <= {0, 3}
    np.testing.assert_allclose(np.linalg.norm(model.normals, axis=1), 1.0, atol=1e-6)
