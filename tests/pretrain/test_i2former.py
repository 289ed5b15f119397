"""I²Former and the policy extractors: shapes, masks, permutation invariance, variants."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from pipeline.core.errors import ConfigError
from pretrain.i2former import I2Former, I2FormerConfig
from rl.networks import StudentExtractor, TeacherExtractor, variant_keys
from rl.policy import N_ACTIONS, build_policy


def _batch(b=3, k=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    poses = torch.randn(b, k, 17, 3, generator=g) * 2
    mask = torch.rand(b, k, 17, generator=g) > 0.3
    mask[:, -2:] = False  # two absent people per sample
    poses = poses * mask.unsqueeze(-1)  # zero-padded like the detector
    state = torch.randn(b, 5, generator=g)
    return poses, mask, state


def test_shapes_and_finite():
    m = I2Former(I2FormerConfig(dim=32, heads=4))
    poses, mask, state = _batch()
    z = m(poses, mask, state)
    assert z.shape == (3, 32) and torch.isfinite(z).all()


def test_all_masked_crowd_is_finite_and_ignores_padding_values():
    m = I2Former(I2FormerConfig(dim=32, heads=4)).eval()
    poses, mask, state = _batch()
    mask[:] = False
    z0 = m(torch.zeros_like(poses), mask, state)
    z1 = m(poses * 100.0, mask, state)  # garbage under a full mask must not leak
    assert torch.isfinite(z0).all()
    assert torch.allclose(z0, z1, atol=1e-6)


def test_masked_joint_values_do_not_matter():
    m = I2Former(I2FormerConfig(dim=32, heads=4)).eval()
    poses, mask, state = _batch()
    noisy = poses + (~mask).unsqueeze(-1) * torch.randn_like(poses) * 10
    assert torch.allclose(m(poses, mask, state), m(noisy, mask, state), atol=1e-5)


def test_permuting_pedestrians_keeps_z_interact():
    m = I2Former(I2FormerConfig(dim=32, heads=4)).eval()
    poses, mask, state = _batch(b=2, seed=3)
    perm = torch.tensor([4, 0, 5, 2, 1, 3])
    z = m(poses, mask, state)
    zp = m(poses[:, perm], mask[:, perm], state)
    assert torch.allclose(z, zp, atol=1e-5)


def test_people_change_the_output():
    m = I2Former(I2FormerConfig(dim=32, heads=4)).eval()
    poses, mask, state = _batch(b=1)
    empty = torch.zeros_like(mask)
    assert not torch.allclose(m(poses, mask, state), m(poses, empty, state), atol=1e-4)


def test_absent_people_padded_and_masked_equal_removing_them():
    torch.manual_seed(0)
    m = I2Former(I2FormerConfig(dim=32, heads=4)).eval()
    poses, mask, state = _batch(b=3, k=6, seed=5)
    mask[:, -2:] = True  # everyone present, then a different set of people absent in each sample
    mask[:, :, 0] = True
    absent = [[1, 4], [0, 2, 5], []]
    for i, gone in enumerate(absent):
        mask[i, gone] = False
    garbage = torch.randn(poses.shape, generator=torch.Generator().manual_seed(9)) * 50
    padded = torch.where(mask.any(-1)[..., None, None], poses, garbage)  # absent slots hold garbage, not zeros
    with torch.no_grad():
        z = m(padded, mask, state)
        z_zeros = m(poses * mask.any(-1)[..., None, None], mask, state)
        for i, gone in enumerate(absent):
            keep = [k for k in range(6) if k not in gone]
            z_removed = m(poses[i:i + 1, keep], mask[i:i + 1, keep], state[i:i + 1])
            assert torch.allclose(z[i:i + 1], z_removed, atol=1e-5), (i, (z[i] - z_removed[0]).abs().max())
        assert torch.allclose(z, z_zeros, atol=1e-5)  # what sits in an absent slot does not matter
        # ... because of the mask: the same garbage flagged as present does change the output
        shown = mask.clone()
        shown[0, 1] = True
        assert (m(padded, shown, state)[0] - z[0]).abs().max() > 1e-3


def test_joint_order_matters_through_the_joint_type_embedding():
    torch.manual_seed(0)
    m = I2Former(I2FormerConfig(dim=32, heads=4)).eval()
    poses, mask, state = _batch(b=2, seed=7)
    perm = torch.randperm(17, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        z = m(poses, mask, state)
        z_perm = m(poses[:, :, perm], mask[:, :, perm], state)
        # a wrist listed as a knee is a different pose: the output moves
        assert (z - z_perm).abs().max() > 1e-3, (z - z_perm).abs().max()
        # ... and only through the joint-type embedding: permuting it along with the joints gives z back
        m.joint_embedding.copy_(m.joint_embedding[perm])
        assert torch.allclose(m(poses[:, :, perm], mask[:, :, perm], state), z, atol=1e-5)


def test_bad_sizes_are_config_errors():
    with pytest.raises(ConfigError, match="divisible"):
        I2Former(I2FormerConfig(dim=30, heads=4))


def _student_space(keys):
    d = {"state": gym.spaces.Box(-1e4, 1e4, (5,), np.float32)}
    if "bev" in keys:
        d["bev"] = gym.spaces.Box(-1e4, 1e4, (8, 30, 48), np.float32)
    if "occ" in keys:
        d["occ"] = gym.spaces.Box(0, 1, (1, 30, 48), np.float32)
    if "poses" in keys:
        d["poses"] = gym.spaces.Box(-1e4, 1e4, (6, 17, 3), np.float32)
        d["pose_mask"] = gym.spaces.Box(0, 1, (6, 17), np.float32)
    return gym.spaces.Dict(d)


@pytest.mark.parametrize("variant", ["full", "no_i2", "no_bev"])
def test_student_policy_variants(variant):
    space = _student_space(variant_keys(variant))
    policy = build_policy("student", variant, space, {"bev_width": 8})
    ext = policy.features_extractor
    assert isinstance(ext, StudentExtractor)
    assert hasattr(ext, "i2former") == (variant != "no_i2")
    assert hasattr(ext, "bev") == (variant != "no_bev") and hasattr(ext, "occ") == (variant == "no_bev")
    obs = {k: torch.as_tensor(np.stack([s.sample() for _ in range(2)])) for k, s in space.spaces.items()}
    dist = policy.get_distribution(obs)
    assert dist.distribution.logits.shape == (2, N_ACTIONS)
    assert policy.predict_values(obs).shape == (2, 1)


def test_student_without_needed_key_is_config_error():
    with pytest.raises(ConfigError, match="needs observation keys"):
        build_policy("student", "full", _student_space(("state",)), {})


def test_unknown_variant_is_config_error():
    with pytest.raises(ConfigError, match="variant"):
        variant_keys("no_everything")


def test_bev_stats_are_saved_buffers():
    space = _student_space(variant_keys("no_i2"))
    policy = build_policy("student", "no_i2", space, {"bev_width": 8})
    policy.features_extractor.set_bev_stats(torch.full((8,), 2.0), torch.full((8,), 3.0))
    sd = policy.state_dict()
    assert torch.all(sd["features_extractor.bev_mean"] == 2.0) and torch.all(sd["features_extractor.bev_std"] == 3.0)


def test_teacher_extractor_scales_inputs():
    space = gym.spaces.Dict({"state": gym.spaces.Box(-1e4, 1e4, (5,), np.float32),
                             "odom": gym.spaces.Box(-1e4, 1e4, (3,), np.float32),
                             "peds": gym.spaces.Box(-1e4, 1e4, (10, 6), np.float32),
                             "scan": gym.spaces.Box(0, 10, (72,), np.float32)})
    ext = TeacherExtractor(space, scan_range_m=10.0)
    obs = {"state": torch.tensor([[5.0, 0, 10.0, 1, 0]]), "odom": torch.zeros(1, 3),
           "peds": torch.zeros(1, 10, 6), "scan": torch.full((1, 72), 10.0)}
    obs["peds"][0, 0] = torch.tensor([5.0, -5.0, 1.0, 0.0, 0.3, 1.0])
    f = ext(obs)
    assert f.shape == (1, 5 + 60 + 72)
    assert torch.allclose(f[0, :5], torch.tensor([1.0, 0, 1.0, 1, 0]))
    assert torch.allclose(f[0, 5:11], torch.tensor([1.0, -1.0, 1.0, 0.0, 0.3, 1.0]))
    assert torch.allclose(f[0, -72:], torch.ones(72))


def test_the_cpu_training_kernel_gives_the_default_kernels_outputs_and_gradients(monkeypatch):
    """With gradients on the CPU the attention runs torch's math kernel (faster backward under bf16 autocast); it
    must compute what torch's own choice computes — outputs and every parameter's gradient — and without gradients
    torch's own choice stays."""
    import contextlib

    import pretrain.i2former as i2

    poses, mask, state = _batch(b=8, k=5)

    def outputs_and_grads():
        torch.manual_seed(0)
        m = I2Former(I2FormerConfig(dim=32, heads=4))
        z = m(poses, mask, state)
        z.square().sum().backward()
        return z.detach(), {n: p.grad.clone() for n, p in m.named_parameters()}

    z_math, g_math = outputs_and_grads()
    used = []
    monkeypatch.setattr(i2, "attention_kernel", lambda x: used.append(x) or contextlib.nullcontext())
    z_default, g_default = outputs_and_grads()
    assert used  # the patched kernel choice was the one consulted
    assert torch.allclose(z_math, z_default, atol=1e-5)
    assert g_math.keys() == g_default.keys()
    for name, g in g_math.items():
        assert torch.allclose(g, g_default[name], atol=1e-5, rtol=1e-4), name
    monkeypatch.undo()
    with torch.no_grad():
        assert isinstance(i2.attention_kernel(poses), contextlib.nullcontext)
    assert not isinstance(i2.attention_kernel(poses), contextlib.nullcontext)  # CPU, gradients on: the math kernel
