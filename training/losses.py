"""Losses of the stages. Lengths in metres; batch letters as in minretarget.conventions.

SMRM is trained without retargeting ground truth: a source clip A is retargeted onto another
body's skeleton B and back, and the losses judge only what can be known without knowing the
right answer (cycle consistency, realism, smoothness, consistency of rotations).
"""
import torch.nn.functional as F

from minretarget.conventions import JOINT_INDEX, UP_AXIS
from minretarget.metrics import FOOT_JOINTS
from training.kinematics import linear_blend_skinning, skinning_transforms, forward_kinematics
from training.models.smrm import leg_length, motion_features


def skr_loss(predicted, joints):
    """(B, J, 3) predicted and true joints -> mean squared error, m^2 (SKR and the refiner)."""
    return F.mse_loss(predicted, joints)


def skin_loss(skin_weights, tpose_points, posed_points, rotations, root, tpose_joints):
    """Mean distance between the true posed points and LBS of the T-pose points, metres.

    skin_weights (B, Q, J); tpose_points, posed_points (B, Q, 3); rotations (B, J, 4);
    root (B, 3); tpose_joints (B, J, 3) the skeleton LBS uses (jittered in training).
    """
    joints, global_rotations = forward_kinematics(rotations, root, tpose_joints)
    transforms = skinning_transforms(joints, global_rotations, tpose_joints)
    posed = linear_blend_skinning(tpose_points, skin_weights, transforms)
    return (posed - posed_points).norm(dim=-1).mean()


def discriminator_input(joints):
    """(B, T, J, 3) motion -> the discriminator's (features (B, T, J*3 + 3), scale (B,))."""
    features, _ = motion_features(joints, joints[:, 0, 0, :])
    return features, leg_length(joints[:, 0]).detach()


def rotation_distance(a, b):
    """(..., 4) unit quaternions -> (...,) 1 - |<a, b>|: 0 for the same rotation (q or -q)."""
    return 1.0 - (a * b).sum(-1).abs()


def acceleration(joints):
    """(B, T, J, 3) -> (B, T-2, J, 3) second finite differences, metres / frame^2."""
    return joints[:, 2:] - 2 * joints[:, 1:-1] + joints[:, :-2]


def smrm_losses(model, discriminator, source_joints, noisy_joints, source_tpose, target_tpose,
                weights):
    """The generator's losses for one batch of clips.

    Args:
        model: MotionRetargeter.
        discriminator: MotionDiscriminator.
        source_joints: (B, T, J, 3) clips A, as the data gives them.
        noisy_joints: (B, T, J, 3) the same with noise, as SKR would give them: the input.
        source_tpose, target_tpose: (B, J, 3) A's and another body B's T-pose skeletons.
        weights: SMRMStage with the loss weights.
    Returns:
        (total loss, dict of the unweighted terms as floats, the retargeted joints A -> B).
    """
    rotations_ab, _, joints_ab, _ = model(noisy_joints, target_tpose)
    rotations_aba, _, joints_aba, _ = model(joints_ab, source_tpose)
    _, _, joints_aa, _ = model(noisy_joints, source_tpose)
    terms = {
        "cycle": F.mse_loss(joints_aba, source_joints),
        "reconstruction": F.mse_loss(joints_aa, source_joints),
        "adversarial": ((discriminator(*discriminator_input(joints_ab)) - 1) ** 2).mean(),
        # A -> B and B -> A perform the same motion, so their local rotations agree.
        "rotation_cycle": rotation_distance(rotations_ab, rotations_aba).mean(),
        "smoothness": acceleration(joints_ab).pow(2).sum(-1).mean(),
    }
    total = sum(getattr(weights, name) * value for name, value in terms.items())
    return total, {k: v.item() for k, v in terms.items()}, joints_ab


def discriminator_loss(discriminator, real_joints, fake_joints):
    """Least-squares GAN loss: real clips score 1, retargeted clips 0."""
    real = discriminator(*discriminator_input(real_joints))
    fake = discriminator(*discriminator_input(fake_joints.detach()))
    return ((real - 1) ** 2).mean() + (fake ** 2).mean()


def denoise_losses(denoised, joints):
    """(B, T, J, 3) denoised and true joints -> (mean joint distance, mean distance of their
    accelerations), metres and metres per frame^2 (the benchmark's MPJPE and Acc)."""
    def acceleration(x):
        return x[:, 2:] - 2 * x[:, 1:-1] + x[:, :-2]
    return ((denoised - joints).norm(dim=-1).mean(),
            (acceleration(denoised) - acceleration(joints)).norm(dim=-1).mean())


def foot_velocity_error(denoised, joints, contact_height=0.03):
    """(B, T, J, 3) denoised and true joints -> the mean distance between their feet's
    horizontal steps t -> t+1 over the steps the true foot touches the ground, metres per
    frame. Contact as the benchmark's ``metrics.foot_contacts`` judges it, over each clip: the
    foot within ``contact_height`` of its lowest height in both frames. The benchmark's foot
    sliding follows the source feet's jitter through SMRM (README, Results), so this is the
    part of the denoiser's error it sees."""
    feet = [JOINT_INDEX[name] for name in FOOT_JOINTS]
    height = joints[:, :, feet, UP_AXIS]                                        # (B, T, F)
    low = height - height.min(dim=1, keepdim=True).values <= contact_height
    contact = (low[:, 1:] & low[:, :-1]).float()                                # (B, T-1, F)
    horizontal = [axis for axis in range(3) if axis != UP_AXIS]
    def steps(x):
        return (x[:, 1:, feet] - x[:, :-1, feet])[..., horizontal]
    error = (steps(denoised) - steps(joints)).norm(dim=-1)
    return (error * contact).sum() / contact.sum().clamp(min=1.0)
