"""Tests of sim.cameras (intrinsics, extrinsics, projection), sim.renderer (RGB-D + segmentation) and the oracle
pose detector of sim.detector (visibility, occlusion, lifting to 3D, output layout)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core.errors import ConfigError
from sim.cameras import (
    backproject,
    depth_from_buffer,
    pose_matrix,
    project,
    world_to_camera,
)
from sim.detector import CameraFrame, Detections, DetectorConfig, OracleDetector
from sim.env import CameraConfig, CrowdNavEnv
from sim.geometry import Box
from sim.humans import COCO_KEYPOINTS, Bodies, BodyConfig
from sim.renderer import WorldRenderer
from sim.scene import load_scene

KP = {name: i for i, name in enumerate(COCO_KEYPOINTS)}
ROBOT = (1.0, 2.0, 0.3)


def axes(spec):
    """World directions (forward, left, up) of a camera on a robot at ROBOT, from its mounting angles alone."""
    yaw = ROBOT[2] + math.radians(spec.yaw_deg)
    p = math.radians(spec.pitch_deg)
    fwd = np.array([math.cos(p) * math.cos(yaw), math.cos(p) * math.sin(yaw), -math.sin(p)])
    left = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    up = np.cross(fwd, left)
    return fwd, left, up


def camera_origin(spec):
    return (pose_matrix(*ROBOT) @ np.append(np.array(spec.mount_xyz_m), 1.0))[:3]


# --------------------------------------------------------------------------------------------- camera model
@pytest.mark.parametrize("pitch", [0.0, 12.0])
@pytest.mark.parametrize("which", [0, 1])
def test_known_points_project_to_expected_pixels_and_back(which, pitch):
    spec = CameraConfig(width_px=160, height_px=120, pitch_deg=pitch).specs()[which]
    assert spec.name == ("left", "right")[which]
    assert spec.yaw_deg == (35.0 if which == 0 else -35.0)
    fx = 160 / (2 * math.tan(math.radians(35.0)))
    np.testing.assert_allclose(spec.K, [[fx, 0, 80], [0, fx, 60], [0, 0, 1]])
    T = pose_matrix(*ROBOT) @ spec.T_base_cam
    r = T[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    o = camera_origin(spec)
    np.testing.assert_allclose(T[:3, 3], o, atol=1e-12)
    fwd, left, up = axes(spec)
    pts = np.array([o + 3.0 * fwd, o + 3.0 * fwd + 0.5 * left, o + 2.0 * fwd + 0.4 * up,
                    o + 4.0 * fwd - 1.0 * left - 0.3 * up])
    expected = np.array([[80, 60], [80 - fx * 0.5 / 3, 60], [80, 60 - fx * 0.4 / 2],
                         [80 + fx * 1.0 / 4, 60 + fx * 0.3 / 4]])
    uv, z = project(world_to_camera(pts, T), spec.K)
    np.testing.assert_allclose(uv, expected, atol=1e-9)
    np.testing.assert_allclose(z, [3.0, 3.0, 2.0, 4.0], atol=1e-12)
    back_c = backproject(uv, z, spec.K)
    back_w = back_c @ r.T + T[:3, 3]
    np.testing.assert_allclose(back_w, pts, atol=1e-9)


def test_camera_mounts_and_fields_of_view():
    cfg = CameraConfig()
    left, right = cfg.specs()
    assert left.mount_xyz_m == (0.1, 0.03, 0.8) and right.mount_xyz_m == (0.1, -0.03, 0.8)
    assert left.vfov_deg == pytest.approx(math.degrees(2 * math.atan(120 / (2 * left.fx))))
    # the two views overlap in the middle: combined ~140 degrees
    # the two views meet in the middle (no blind seam): ~140 degrees combined
    assert left.yaw_deg - left.hfov_deg / 2 <= 0 <= right.yaw_deg + right.hfov_deg / 2
    assert (left.yaw_deg + left.hfov_deg / 2) - (right.yaw_deg - right.hfov_deg / 2) == pytest.approx(140.0)
    d = left.to_dict()
    assert d["width"] == 160 and np.array(d["K"]).shape == (3, 3) and np.array(d["T_base_cam"]).shape == (4, 4)


def test_depth_from_buffer_inverts_the_opengl_depth():
    spec = CameraConfig().specs()[0]
    n, f = spec.near_m, spec.far_m
    z = np.array([0.1, 0.31, 1.0, 4.5, 9.9, 10.5])
    buf = (f - f * n / z) / (f - n)
    d = depth_from_buffer(buf, spec)
    assert d.dtype == np.float32
    np.testing.assert_allclose(d, [0.0, 0.31, 1.0, 4.5, 9.9, 0.0], rtol=1e-5)  # outside [0.3, 10] m -> 0
    assert depth_from_buffer(np.ones(3), spec).tolist() == [0.0, 0.0, 0.0]


# ------------------------------------------------------------------------------------------------ rendering
def plate_scene(width_px: int, height_px: int):
    """A thin plate facing the left camera 3 m ahead; returns spec, T_world_cam, seg id, rendered images and the
    plate's projected pixel rectangle."""
    spec = CameraConfig(width_px=width_px, height_px=height_px).specs()[0]
    robot = (0.0, 0.0, -math.radians(35.0))  # the left camera looks along +x
    T = pose_matrix(*robot) @ spec.T_base_cam
    cam = T[:3, 3]
    r = WorldRenderer()
    try:
        r.build([], (-10, 10, -10, 10), (0.5, 0.5, 0.5), np.zeros((0, 11, 3)), np.zeros((0, 11, 3)))
        y0, y1, z0, z1 = cam[1] - 0.4, cam[1] + 0.2, cam[2] - 0.3, cam[2] + 0.5
        pid = r._box(cam[0] + 3.0, (y0 + y1) / 2, (z0 + z1) / 2, 0.0, (0.005, (y1 - y0) / 2, (z1 - z0) / 2),
                     (0.9, 0.1, 0.1))
        rgb, depth, seg = r.render(spec, T, segmentation=True)
    finally:
        r.close()
    corners = np.array([[cam[0] + 2.995, y1, z1], [cam[0] + 2.995, y0, z0]])
    uv, _ = project(world_to_camera(corners, T), spec.K)
    return spec, seg, depth, pid, uv  # uv[0] = top-left, uv[1] = bottom-right


def _plate_mask_errors(width_px, height_px, margin_px):
    spec, seg, depth, pid, uv = plate_scene(width_px, height_px)
    cols = np.arange(width_px) + 0.5
    rows = np.arange(height_px) + 0.5
    (u0, v0), (u1, v1) = uv
    inner = ((cols[None] > u0 + margin_px) & (cols[None] < u1 - margin_px)
             & (rows[:, None] > v0 + margin_px) & (rows[:, None] < v1 - margin_px))
    outer = ((cols[None] < u0 - margin_px) | (cols[None] > u1 + margin_px)
             | (rows[:, None] < v0 - margin_px) | (rows[:, None] > v1 + margin_px))
    hit = seg == pid
    return int((inner & ~hit).sum()), int((outer & hit).sum()), hit, depth


@pytest.mark.parametrize("size", [(160, 120), (64, 48)])
def test_rendered_object_matches_its_projection_within_a_pixel(size):
    missing, extra, hit, depth = _plate_mask_errors(*size, margin_px=0.75)
    assert hit.sum() > 20
    assert missing == 0 and extra == 0
    assert float(np.median(depth[hit])) == pytest.approx(2.995, abs=0.01)


@pytest.mark.parametrize("size", [(160, 120), (640, 480)])
def test_rendered_object_matches_its_projection_to_a_fraction_of_a_pixel(size):
    missing, extra, _, _ = _plate_mask_errors(*size, margin_px=0.2)
    assert missing == 0 and extra == 0


@pytest.fixture(scope="module")
def one_person_env():
    """open_crowd with exactly one pedestrian, placed 3 m in front of the left camera, mid-stride."""
    fa = load_scene("open_crowd").layout().free_area_m2
    env = CrowdNavEnv(scene="open_crowd", density=1.0 / fa, obs_mode="visual")
    env.reset(seed=0)
    assert env.crowd.n == 1
    yield env
    env.close()


def place(env, robot, person_xy, body_yaw, amp=0.6, phase=1.0):
    env.robot[:] = robot
    env.crowd.pos[0] = person_xy
    env.crowd.vel[0] = 0.0
    env.bodies.body_yaw[0] = env.bodies.torso_yaw[0] = env.bodies.head_yaw[0] = body_yaw
    env.bodies.amp[0] = amp
    env.bodies.phase[0] = phase
    env._skel = None


def frames_of(env, renders):
    return [CameraFrame(spec, T, spec.T_base_cam, rgb, depth)
            for spec, T, (rgb, depth, _) in zip(env.cameras, env.camera_poses(), renders, strict=True)]


@pytest.mark.parametrize("body_yaw", [math.pi, 0.3, -1.2])
def test_visible_keypoints_land_on_the_persons_pixels(one_person_env, body_yaw):
    env = one_person_env
    robot = np.array([2.0, 6.0, 0.0])
    yaw_c = math.radians(35.0)
    place(env, robot, robot[:2] + 3.0 * np.array([math.cos(yaw_c), math.sin(yaw_c)]), body_yaw)
    renders = env.render_cameras(segmentation=True)
    frames = frames_of(env, renders)
    kp = env.keypoints_world()
    det = OracleDetector(DetectorConfig())
    ids = set(env._renderer.human_ids[0].tolist())
    assert len(ids) == 11
    uv, z, vis = det.visible_2d(frames[0], kp)
    assert vis[0].sum() >= 12  # most joints of a person 3 m ahead are visible
    seg = renders[0][2]
    depth = renders[0][1]
    for j in np.nonzero(vis[0])[0]:
        c, r = int(uv[0, j, 0]), int(uv[0, j, 1])
        win = seg[max(r - 2, 0):r + 3, max(c - 2, 0):c + 3]
        assert ids & set(win.ravel().tolist()), COCO_KEYPOINTS[j]
        hits = np.argwhere(np.isin(win, list(ids)))
        # depth at the nearest of the person's pixels is within 0.3 m of the joint's depth
        rr, cc = hits[np.argmin(np.abs(hits - [min(r, 2), min(c, 2)]).sum(1))]
        d = depth[max(r - 2, 0) + rr, max(c - 2, 0) + cc]
        assert abs(d - z[0, j]) < 0.3, COCO_KEYPOINTS[j]
    # the person is at +35 degrees: outside the right camera's view
    _, _, vis_r = det.visible_2d(frames[1], kp)
    assert not vis_r.any()


def test_rgb_shows_the_person_where_segmentation_says(one_person_env):
    env = one_person_env
    robot = np.array([2.0, 6.0, 0.0])
    place(env, robot, robot[:2] + 3.0 * np.array([math.cos(0.61), math.sin(0.61)]), math.pi)
    (rgb, depth, seg), _ = env.render_cameras(segmentation=True)
    ids = env._renderer.human_ids[0]
    shirt = np.round(env.bodies.colors[0, 0] * 255)
    torso = seg == ids[0]
    assert torso.sum() > 30
    # shaded, but the hue of the shirt: the mean torso colour is a scaled copy of the shirt colour
    mean = rgb[torso].mean(0)
    cos = mean @ shirt / (np.linalg.norm(mean) * np.linalg.norm(shirt))
    assert cos > 0.95
    assert np.all(depth[torso] > 2.3) and np.all(depth[torso] < 3.2)


def occlusion_render(wall: bool, second_person: bool = False, height: float = 1.75):
    """WorldRenderer with one (or two) people straight ahead of the left camera and optionally a 1 m wall."""
    spec = CameraConfig().specs()[0]
    robot = np.array([0.0, 0.0, -math.radians(35.0)])  # left camera looks along +x
    T = pose_matrix(*robot) @ spec.T_base_cam
    cam = T[:3, 3]
    n = 2 if second_person else 1
    bodies = Bodies(BodyConfig(), np.random.default_rng(0), n, np.full(n, math.pi))
    bodies.height[:] = height
    pos = np.array([[cam[0] + 4.0, cam[1]]] if not second_person else [[cam[0] + 5.0, cam[1]],
                                                                      [cam[0] + 3.0, cam[1]]])
    skel = bodies.skeleton(pos)
    centers, quats, half = bodies.primitives(pos, skel)
    obstacles = [Box((float(cam[0] + 1.5), float(cam[1])), (0.1, 3.0), 0.0, 1.0)] if wall else []
    r = WorldRenderer()
    try:
        r.build(obstacles, (-10, 10, -10, 10), (0.5, 0.5, 0.5), half, bodies.colors)
        r.set_humans(centers, quats)
        rgb, depth, _ = r.render(spec, T)
    finally:
        r.close()
    frame = CameraFrame(spec, T, spec.T_base_cam, rgb, depth)
    return frame, bodies.keypoints(pos, skel)


LOW = ["left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle"]
HIGH = ["nose", "left_eye", "right_eye"]


def test_a_wall_hides_the_joints_behind_it():
    det = OracleDetector(DetectorConfig())
    frame, kp = occlusion_render(wall=False)
    _, _, vis_open = det.visible_2d(frame, kp)
    frame_w, kp_w = occlusion_render(wall=True)
    np.testing.assert_array_equal(kp, kp_w)
    _, _, vis_wall = det.visible_2d(frame_w, kp_w)
    low = [KP[k] for k in LOW]
    high = [KP[k] for k in HIGH]
    assert vis_open[0, low].all() and vis_open[0, high].all()
    assert not vis_wall[0, low].any()  # the 1 m wall 1.5 m ahead hides everything below ~1.33 m at 4 m
    assert vis_wall[0, high].all()
    # the detector reports only what it sees
    cfg = DetectorConfig(miss_prob=0.0, pixel_noise_px_at_640=0.0)
    d = OracleDetector(cfg).detect([frame_w], {"keypoints_world": kp_w}, np.random.default_rng(0))
    assert d.person_mask[0] and d.track_id[0] == 0
    assert not d.joint_mask[0, low].any() and d.joint_mask[0, high].all()
    d_open = OracleDetector(cfg).detect([frame], {"keypoints_world": kp}, np.random.default_rng(0))
    assert d_open.joint_mask[0, low].all()


def test_a_person_in_front_hides_the_one_behind():
    det = OracleDetector(DetectorConfig())
    frame, kp = occlusion_render(wall=False, second_person=True)
    _, _, vis = det.visible_2d(frame, kp)
    upper = [KP[k] for k in ("nose", "left_eye", "right_eye", "left_shoulder", "right_shoulder")]
    assert vis[1, upper].all()  # the near person
    assert not vis[0, upper].any()  # the far one, straight behind
    assert vis[1].sum() >= 14 and vis[0].sum() <= 5  # only a limb or two of the far one peeks out


# ------------------------------------------------------------------------------------------------ detector
def test_detector_config_validation():
    DetectorConfig().validate()
    for bad in (DetectorConfig(max_people=0), DetectorConfig(min_joints=18),
                DetectorConfig(pixel_noise_px_at_640=-1.0), DetectorConfig(occlusion_tol_m=0.0)):
        with pytest.raises(ConfigError):
            bad.validate()


def test_detect_with_nobody_is_empty():
    spec = CameraConfig(width_px=32, height_px=24).specs()[0]
    frame = CameraFrame(spec, np.eye(4), spec.T_base_cam, np.zeros((24, 32, 3), np.uint8), np.zeros((24, 32),
                                                                                                   np.float32))
    d = OracleDetector(DetectorConfig()).detect([frame], {"keypoints_world": np.zeros((0, 17, 3))},
                                                np.random.default_rng(0))
    e = Detections.empty(6)
    for name in ("poses", "joint_mask", "confidence", "person_mask", "track_id"):
        np.testing.assert_array_equal(getattr(d, name), getattr(e, name))
    assert d.poses.shape == (6, 17, 3) and (d.track_id == -1).all()


def to_base(env, kp_world):
    x, y, yaw = env.robot
    c, s = math.cos(yaw), math.sin(yaw)
    rel = kp_world - np.array([x, y, 0.0])
    return np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], -1)


@pytest.fixture(scope="module")
def crowded_detections():
    """Detections of a dense crowd (open_crowd at 0.3 ped/m2, ~40 people) over a few seeds and steps."""
    env = CrowdNavEnv(scene="open_crowd", density=0.3, obs_mode="visual")
    out = []
    for seed in range(3):
        obs, info = env.reset(seed=seed)
        for _ in range(4):
            obs, _, _, _, info = env.step(env.encode_command(0.3, 0.0))
        out.append((obs, env.last_detections, to_base(env, info["privileged"]["keypoints_world"]), env.crowd.n))
    env.close()
    return out


def test_detector_output_layout(crowded_detections):
    for obs, det, _, n in crowded_detections:
        assert n > 30
        assert det.poses.shape == (6, 17, 3) and det.joint_mask.shape == (6, 17)
        assert det.confidence.shape == (6, 17) and det.person_mask.shape == (6,) and det.track_id.shape == (6,)
        np.testing.assert_array_equal(obs["poses"], det.poses.astype(np.float32))
        np.testing.assert_array_equal(obs["pose_mask"], det.joint_mask.astype(np.uint8))
        k = int(det.person_mask.sum())
        assert 1 <= k <= 6
        assert det.person_mask[:k].all() and not det.person_mask[k:].any()  # people first, then padding
        assert (det.track_id[k:] == -1).all() and len(set(det.track_id[:k].tolist())) == k
        assert (det.poses[~det.joint_mask] == 0).all() and (det.confidence[~det.joint_mask] == 0).all()
        assert not det.joint_mask[k:].any()
        assert (det.joint_mask[:k].sum(1) >= DetectorConfig().min_joints).all()
        assert ((det.confidence[det.joint_mask] >= 0.3) & (det.confidence[det.joint_mask] <= 1)).all()
        dist = [np.linalg.norm(det.poses[m][det.joint_mask[m], :2].mean(0)) for m in range(k)]
        assert np.all(np.diff(dist) >= 0)  # nearest first
    assert max(int(d.person_mask.sum()) for _, d, _, _ in crowded_detections) == 6  # capped at 6


def test_lifted_keypoints_are_close_to_the_truth(crowded_detections):
    errors = []
    for _, det, kp_base, _ in crowded_detections:
        for m in np.nonzero(det.person_mask)[0]:
            i = det.track_id[m]
            e = np.linalg.norm(det.poses[m] - kp_base[i], axis=-1)[det.joint_mask[m]]
            errors.extend(e.tolist())
    errors = np.array(errors)
    assert len(errors) > 100
    assert np.median(errors) < 0.15
    assert np.mean(errors < 0.25) > 0.9


@pytest.mark.parametrize("facing", [True, False], ids=["facing-the-camera", "back-to-the-camera"])
def test_a_face_turned_away_is_hidden_by_its_own_head(one_person_env, facing):
    """Nose and eyes lie on the head's front surface: seen from behind, the back of the head is ~0.2 m in front of
    them, within the body joints' 0.25 m tolerance; ``face_occlusion_tol_m`` hides them (and keeps them seen from
    the front)."""
    env = one_person_env
    robot = np.array([2.0, 6.0, 0.0])
    yaw_c = math.radians(35.0)
    place(env, robot, robot[:2] + 3.0 * np.array([math.cos(yaw_c), math.sin(yaw_c)]),
          yaw_c + math.pi if facing else yaw_c)
    frames = frames_of(env, env.render_cameras())
    face = [COCO_KEYPOINTS.index(n) for n in ("nose", "left_eye", "right_eye")]
    _, _, vis = OracleDetector(DetectorConfig()).visible_2d(frames[0], env.keypoints_world())
    assert vis[0, face].all() == facing and vis[0, face].any() == facing
    _, _, loose = OracleDetector(DetectorConfig(face_occlusion_tol_m=0.25)).visible_2d(frames[0], env.keypoints_world())
    assert loose[0, face].sum() >= 1  # with the body joints' tolerance the hidden face would pass
