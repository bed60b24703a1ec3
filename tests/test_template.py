import doctest
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchevtrack import geometry as g
from torchevtrack.camera import Camera
from torchevtrack.mesh import load_mesh
from torchevtrack.render import Renderer
from torchevtrack import reference
from torchevtrack.stages import template as tm

CAM = Camera.default()
MARGIN = 24
# A generic view, 0.5 m away: three faces of the box visible, perspective not trivial.
POSE = torch.cat((torch.tensor([0.03, -0.02, 0.5]), g.quat_exp(torch.tensor([0.4, -0.6, 0.3]))))[None].double()
OPP = [0] + [k + 1 if k % 2 else k - 1 for k in range(1, 13)]  # index of the opposite hypothesis


def _radius(mesh):
    return float(np.linalg.norm(mesh.vertices, axis=1).max())


@pytest.fixture(scope="module")
def scenes():
    """Per object: renderer, render window around POSE and the base render there."""
    out = {}
    for name in ("box", "006_mustard_bottle"):
        mesh = load_mesh(name, decimate=4000)
        r = Renderer(mesh, CAM)
        roi = tuple(int(v) for v in tm.render_window(POSE, CAM, _radius(mesh), MARGIN)[0])
        out[name] = (r, roi, r.render(POSE.float(), roi=roi))
    yield out
    for r, _, _ in out.values():
        r.close()


def _steps(pose, render, roi):
    return reference.hypothesis_steps(pose, CAM, reference.radial_gain(render.depth, roi[:2], CAM))


def _edges(render):
    """Synthetic EROS: binary edges (grey + silhouette) of a render at full resolution."""
    return (reference.edge_map(render.gray, (render.depth > 0).float()) > 0.5).float()


def _ncc(a, b):
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / (a.norm() * b.norm()))


def test_doctests():
    assert doctest.testmod(tm).failed == 0


# -- (a) hypothesis poses ---------------------------------------------------------------------
def test_translation_steps_move_the_projected_centre_by_dp(scenes):
    _, roi, base = scenes["box"]
    for dp in (1.0, 2.5):
        hyp = tm.apply_steps(POSE, reference.hypothesis_steps(POSE, CAM, reference.radial_gain(base.depth, roi[:2], CAM), dp))[0]
        uv = CAM.project(hyp[:, :3])
        d = uv - uv[0]
        expected = torch.tensor([[dp, 0], [-dp, 0], [0, dp], [0, -dp]], dtype=d.dtype)
        assert torch.allclose(d[1:5], expected, atol=0.05)
        # rotations about the object origin do not move it
        assert torch.allclose(hyp[7:, :3], POSE[:, :3].expand(6, 3), atol=1e-12)


def test_z_step_moves_object_pixels_by_dp_on_average(scenes):
    _, roi, base = scenes["box"]
    hyp = tm.apply_steps(POSE, _steps(POSE, base, roi))[0]
    v, u = torch.nonzero(base.depth[0] > 0, as_tuple=True)
    uv = torch.stack((u + roi[0], v + roi[1]), -1).double()
    X = CAM.backproject(uv, base.depth[0, v, u].double())  # object points seen by the camera
    for k, sign in ((5, 1.0), (6, -1.0)):
        Xh = X + (hyp[k, :3] - POSE[0, :3])
        disp = CAM.project(Xh) - uv
        assert float(disp.norm(dim=-1).mean()) == pytest.approx(1.0, rel=0.03)
        # +z moves the object away: pixels move toward the principal point
        radial = ((uv - torch.tensor([CAM.cx, CAM.cy], dtype=uv.dtype)) * disp).sum(-1)
        assert float(radial.mean()) * sign < 0


def test_rotation_steps_are_dtheta_about_camera_axes():
    torch.manual_seed(0)
    pose = torch.cat((torch.randn(3, 3, dtype=torch.float64) * 0.1 + torch.tensor([0, 0, 0.6]),
                      g.quat_canonical(torch.randn(3, 4, dtype=torch.float64))), -1)
    for dth in (0.5, 2.0):
        hyp = tm.apply_steps(pose, reference.hypothesis_steps(pose, CAM, torch.full((3,), 200.0), 1.0, dth))
        for b in range(3):
            R0 = Rotation.from_quat(pose[b, [4, 5, 6, 3]].numpy())
            for a in range(3):
                for s, k in ((1, 7 + 2 * a), (-1, 8 + 2 * a)):
                    Rh = Rotation.from_quat(hyp[b, k, [4, 5, 6, 3]].numpy())
                    rel = (Rh * R0.inv()).as_rotvec()  # camera-frame rotation (left product)
                    assert np.linalg.norm(rel) == pytest.approx(math.radians(dth), rel=1e-9)
                    assert np.allclose(rel, s * math.radians(dth) * np.eye(3)[a], atol=1e-12)
                    assert torch.allclose(hyp[b, k, :3], pose[b, :3])
        assert torch.allclose(hyp[:, 0], torch.cat((pose[:, :3], g.quat_canonical(pose[:, 3:])), -1))


# -- (b) warp against re-rendering ------------------------------------------------------------
@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
def test_warped_templates_match_rerendered_templates(scenes, name):
    r, roi, base = scenes[name]
    N = 128
    hyp = tm.apply_steps(POSE, _steps(POSE, base, roi))
    renders = r.render(hyp[0].float(), roi=roi)
    cr0 = reference.prepare_canvas(base.depth, base.gray, roi[:2], CAM, N, 20)
    direct_cr = reference.prepare_canvas(renders.depth, renders.gray, roi[:2], CAM, N, box=cr0.box.expand(13, 3))
    direct = reference.dog(reference.edge_map(direct_cr.gray, direct_cr.mask), N)
    direct = direct * 0.5 / direct[0].abs().max()
    obs = tm.to_canvas(_edges(renders), cr0.box.expand(13, 3), N, roi[:2])  # observation at each hypothesis
    for warp, min_diff_ncc in (("template", 0.7), ("image", 0.6)):
        warped = reference.hypothesis_templates(cr0, POSE, hyp, warp=warp)[0]
        for k in range(13):
            assert _ncc(warped[k], direct[k]) > 0.95
        # the change a step makes to the template is reproduced, not just the template itself
        for k in range(1, 13):
            assert _ncc(warped[k] - warped[0], direct[k] - direct[0]) > min_diff_ncc, (warp, k)
        s_warp = reference.score(warped[None].expand(13, -1, -1, -1), obs)
        s_direct = reference.score(direct[None].expand(13, -1, -1, -1), obs)
        assert torch.equal(s_warp.argmax(1), s_direct.argmax(1)), warp
        assert torch.equal(s_warp.argmax(1), torch.arange(13)), warp


# -- (c) recovering a known offset ------------------------------------------------------------
@pytest.mark.parametrize("rule", ["argmax", "group"])
def test_one_step_offsets_are_recovered_in_every_direction(scenes, rule):
    r, roi, base = scenes["box"]
    obs = _edges(base)  # the object seen at the true pose POSE
    truth_hyp = tm.apply_steps(POSE, _steps(POSE, base, roi))[0]
    starts = truth_hyp[OPP[1:]]  # start k - 1 lies one step in the direction opposite to k
    renders = r.render(starts.float(), roi=roi)
    out = reference.correct(starts, renders.depth, renders.gray, roi[:2], obs.expand(12, -1, -1), CAM,
                            observation_origin=roi[:2], rule=rule)
    assert torch.equal(out.index, torch.arange(1, 13))
    assert out.applied[torch.arange(12), torch.arange(1, 13)].all()
    assert (out.score > out.scores[:, 0]).all()
    if rule == "argmax":  # exactly back at the truth (the group rule may add a step of another group)
        back = g.pose_compose(g.pose_inverse(out.pose), POSE.expand(12, 7))
        assert float(back[:, :3].norm(dim=-1).max()) < 2e-4  # within a fifth of a step (~1 mm)
        angle = 2 * torch.atan2(back[:, 4:].norm(dim=-1), back[:, 3].abs())
        assert float(angle.max()) < math.radians(0.1)


@pytest.mark.parametrize("rule", ["argmax", "group", "newton"])
def test_iterating_converges_from_three_pixels(scenes, rule):
    r, roi, base = scenes["box"]
    obs = _edges(base)
    z = float(POSE[0, 2])
    starts = POSE.repeat(2, 1)
    starts[0, 0] += 3 * z / CAM.fx
    starts[1, 0] -= 2 * z / CAM.fx
    starts[1, 1] += 2 * z / CAM.fy
    renders = r.render(starts.float(), roi=roi)
    uv_true = CAM.project(POSE[:, :3])
    err0 = (CAM.project(starts[:, :3]) - uv_true).norm(dim=-1)
    one = reference.correct(starts, renders.depth, renders.gray, roi[:2], obs.expand(2, -1, -1), CAM,
                            observation_origin=roi[:2], rule=rule, iterations=1)
    out = reference.correct(starts, renders.depth, renders.gray, roi[:2], obs.expand(2, -1, -1), CAM,
                            observation_origin=roi[:2], rule=rule, iterations=8)
    err = (CAM.project(out.pose[:, :3]) - uv_true).norm(dim=-1)
    assert (err <= 1.0).all(), err
    assert (err0 >= 2.8).all()
    assert (out.iterations >= 2).all() and (one.iterations == 1).all()
    assert torch.equal(out.scores, one.scores)  # first-iteration diagnostics do not depend on iterations
    if rule != "newton":  # newton's scores are model values at sub-step poses, each from another centre
        assert (out.score > one.score).all()


def test_group_rule_applies_steps_of_two_groups_at_once(scenes):
    r, roi, base = scenes["box"]
    obs = _edges(base)
    steps = _steps(POSE, base, roi)
    # one step off along -x and along -rz (roll): different groups
    start = tm.apply_steps(tm.apply_steps(POSE, -steps[:, 1:2])[:, 0], -steps[:, 11:12])[:, 0]
    rd = r.render(start.float(), roi=roi)
    grp = reference.correct(start, rd.depth, rd.gray, roi[:2], obs, CAM, observation_origin=roi[:2], rule="group")
    arg = reference.correct(start, rd.depth, rd.gray, roi[:2], obs, CAM, observation_origin=roi[:2], rule="argmax")
    assert grp.applied[0, [1, 11]].all() and int(grp.applied.sum()) == 2
    assert int(arg.applied.sum()) == 1
    assert float(grp.score) > float(arg.score)


# -- (d) update rules against a sequential reference ------------------------------------------
def _reference_select(pose, steps, scores, rule):
    """Obvious per-element loop, rotations with scipy (camera-frame steps, left product)."""
    out = []
    for b in range(pose.shape[0]):
        t = pose[b, :3].numpy().copy()
        R = Rotation.from_quat(pose[b, [4, 5, 6, 3]].numpy())
        s = scores[b].tolist()
        if rule == "argmax":
            chosen = [max(range(13), key=lambda k: (s[k], -k))]
        else:
            chosen = []
            for axes in ((0, 4), (1, 3), (5,), (2,)):  # {x, yaw}, {y, pitch}, {roll}, {z}
                cands = [1 + 2 * a + sgn for a in axes for sgn in (0, 1)]
                best = max(cands, key=lambda k: (s[k], -k))
                if s[best] > s[0]:
                    chosen.append(best)
        for k in chosen:
            t = t + steps[b, k, :3].numpy()
            R = Rotation.from_rotvec(steps[b, k, 3:].numpy()) * R
        q = R.as_quat()
        out.append(np.concatenate((t, np.sign(q[3] or 1) * q[[3, 0, 1, 2]])))
    return torch.tensor(np.stack(out))


@pytest.mark.parametrize("rule", ["argmax", "group"])
def test_select_matches_sequential_reference(rule):
    torch.manual_seed(1)
    B = 64
    pose = torch.cat((torch.randn(B, 3, dtype=torch.float64) * 0.1 + torch.tensor([0, 0, 0.6]),
                      g.quat_canonical(torch.randn(B, 4, dtype=torch.float64))), -1)
    steps = reference.hypothesis_steps(pose, CAM, torch.rand(B, dtype=torch.float64) * 300 + 50, 1.0, 3.0)
    scores = torch.randn(B, 13, dtype=torch.float64)
    scores[:8, 0] = 10.0  # null best: nothing applied
    scores[8:12] = scores[8:12].round()  # ties
    new, applied = reference.select(pose, steps, scores, rule)
    ref = _reference_select(pose, steps, scores, rule)
    assert torch.allclose(new, ref, atol=1e-12)
    assert not applied[:8].any() and not applied[:, 0].any()
    if rule == "group":
        assert (applied.sum(1) > 1).any()


def _quadratic_scorer(s0, g, H, unit):
    """score_steps of ``s0 + g . u + u^T H u / 2`` with ``u = steps / unit`` (step units)."""
    def score_steps(steps):
        u = steps / unit[:, None]
        return s0[:, None] + (u * g[:, None]).sum(-1) + 0.5 * torch.einsum("bki,bij,bkj->bk", u, H, u)
    return score_steps


def test_newton_step_is_the_maximiser_of_a_concave_quadratic():
    torch.manual_seed(4)
    B = 5
    A = torch.randn(B, 6, 6, dtype=torch.float64)
    H = -(A @ A.transpose(1, 2) + 6 * torch.eye(6, dtype=torch.float64))  # concave
    u_star = (torch.rand(B, 6, dtype=torch.float64) - 0.5) * 1.6  # inside one step per axis
    g = -(H @ u_star[..., None])[..., 0]  # gradient at 0 of a quadratic peaking at u_star
    unit = torch.rand(B, 6, dtype=torch.float64) * 0.01 + 0.001
    score = _quadratic_scorer(torch.randn(B, dtype=torch.float64), g, H, unit)
    step = reference.newton_step(score, unit, damping=0.0)
    assert torch.allclose(step / unit, u_star, atol=1e-9)
    # damping shortens the step along the same direction of improvement; the score still improves
    damped = reference.newton_step(score, unit, damping=0.5)
    assert (score(damped[:, None])[:, 0] > score(torch.zeros(B, 1, 6, dtype=torch.float64))[:, 0]).all()
    assert ((damped / unit).norm(dim=-1) < u_star.norm(dim=-1)).all()


def test_newton_step_is_clipped_to_one_step_and_flat_scores_do_not_move():
    B = 2
    unit = torch.full((B, 6), 0.002, dtype=torch.float64)
    H = -torch.eye(6, dtype=torch.float64).expand(B, 6, 6).clone()
    g = torch.zeros(B, 6, dtype=torch.float64)
    g[0, 2] = 5.0  # the peak is 5 steps away along +tz
    score = _quadratic_scorer(torch.zeros(B, dtype=torch.float64), g, H, unit)
    step = reference.newton_step(score, unit)
    assert torch.allclose(step[0] / unit[0], torch.tensor([0, 0, 1.0, 0, 0, 0], dtype=torch.float64))
    assert torch.equal(step[1], torch.zeros(6, dtype=torch.float64))  # zero gradient: stay
    convex = _quadratic_scorer(torch.zeros(B, dtype=torch.float64), g, -H, unit)  # a minimum, not a peak
    step = reference.newton_step(convex, unit)
    assert (step[0, 2] > 0) and float(convex(step[:1, None])[0, 0]) > 0  # still uphill


def test_newton_rule_recovers_sub_step_offsets_that_argmax_cannot(scenes):
    r, roi, base = scenes["box"]
    obs = _edges(base)
    steps = _steps(POSE, base, roi)[0]
    # half a step off along x and along pitch at once: argmax can only move whole steps along one axis
    start = tm.apply_steps(POSE, -(0.5 * steps[1] + 0.5 * steps[7])[None, None])[:, 0]
    rd = r.render(start.float(), roi=roi)
    err = {}
    for rule in ("argmax", "newton"):
        out = reference.correct(start, rd.depth, rd.gray, roi[:2], obs, CAM, observation_origin=roi[:2], rule=rule,
                                iterations=3)
        d = tm.pose_delta(POSE, out.pose[:, None])[0, 0] / steps[1:13:2].diagonal()
        err[rule] = float(d.abs().max())  # largest remaining offset, in steps
    assert err["newton"] < 0.25 < err["argmax"], err


# -- (e) batching -----------------------------------------------------------------------------
@pytest.mark.parametrize("rule", ["argmax", "group", "newton"])
def test_batch_equals_separate_runs(scenes, rule):
    r, roi, base = scenes["box"]
    obs = _edges(base)
    steps = _steps(POSE, base, roi)
    poses = torch.cat((tm.apply_steps(POSE, -steps[:, 3:4])[:, 0], tm.apply_steps(POSE, 0.7 * steps[:, 10:11])[:, 0]))
    windows = [roi, (roi[0] + 5, roi[1] - 3, roi[2], roi[3])]
    rds = [r.render(poses[b : b + 1].float(), roi=windows[b]) for b in range(2)]
    obs2 = torch.cat((obs, torch.flip(obs, dims=(2,))))
    corr = tm.TemplateCorrector(CAM, rule=rule, iterations=3)
    batch = corr(poses, torch.cat([x.depth for x in rds]), torch.cat([x.gray for x in rds]),
                 torch.tensor([w[:2] for w in windows]), obs2, roi[:2])
    for b in range(2):
        single = corr(poses[b : b + 1], rds[b].depth, rds[b].gray, windows[b][:2], obs2[b : b + 1], roi[:2])
        for x, y in zip(batch, single):
            assert torch.allclose(x[b : b + 1].double(), y.double(), atol=1e-5, rtol=1e-5)


# -- regions, templates and inputs ------------------------------------------------------------
def test_render_window_contains_the_object_and_a_window_corrects_as_the_full_frame(scenes):
    r, roi, base = scenes["box"]
    full = r.render(POSE.float())
    v, u = torch.nonzero(full.depth[0] > 0, as_tuple=True)
    assert roi[0] <= int(u.min()) - MARGIN and int(u.max()) + MARGIN < roi[0] + roi[2]
    assert roi[1] <= int(v.min()) - MARGIN and int(v.max()) + MARGIN < roi[1] + roi[3]
    crop = full.depth[0, roi[1] : roi[1] + roi[3], roi[0] : roi[0] + roi[2]]
    assert torch.equal(base.depth[0] > 0, crop > 0) and torch.allclose(base.depth[0], crop, atol=1e-4)
    # the box of a window render equals the box of the full frame, and so does the correction
    box_w = reference.canvas_box(base.depth, roi[:2], 20)
    box_f = reference.canvas_box(full.depth, (0, 0), 20)
    assert torch.equal(box_w, box_f)
    assert float(box_f[0, 2]) == max(int(u.max() - u.min()), int(v.max() - v.min())) + 1 + 40
    obs = torch.zeros(1, CAM.height, CAM.width)
    obs[0, roi[1] : roi[1] + roi[3], roi[0] : roi[0] + roi[2]] = _edges(base)[0]
    corr = tm.TemplateCorrector(CAM, rule="argmax", iterations=1, interior=0.0)
    a = corr(POSE, base.depth, base.gray, roi[:2], obs)
    b = corr(POSE, full.depth, full.gray, (0, 0), obs)
    # (the renderer's window and full-frame grey differ by up to ~2/255 on a few % of pixels)
    assert torch.allclose(a.scores, b.scores, rtol=2e-3) and int(a.index) == 0



def test_render_window_takes_one_radius_per_pose():
    poses = torch.tensor([[0.01, -0.02, 0.5, 1.0, 0.0, 0.0, 0.0], [0.1, 0.05, 0.3, 0.0, 1.0, 0.0, 0.0],
                          [-0.2, 0.0, 0.04, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    radius = torch.tensor([0.05, 0.12, 0.03])  # the last pose is inside its sphere: z clamped to 1.05 r
    per_pose = tm.render_window(poses, CAM, radius, 24)
    for i in range(3):
        assert torch.equal(per_pose[i], tm.render_window(poses[i : i + 1], CAM, float(radius[i]), 24)[0])
    with pytest.raises(ValueError, match="radius"):
        tm.render_window(poses, CAM, radius[:2])
    with pytest.raises(ValueError, match="radius"):
        tm.render_window(poses, CAM, torch.tensor([0.05, 0.0, 0.03]))

def test_window_of_is_the_projected_sphere_and_clips_into_the_frame():
    """Against the formula per pose and axis: the square ``floor(c - h) .. ceil(c + h)`` around the projected centre
    ``c`` with half-size ``h = f r / (max(z, 1.05 r) - r) + margin``; clipped: cut to the frame, then moved in."""
    gen = np.random.default_rng(0)
    t = np.c_[gen.normal(0, 0.4, (200, 2)), gen.uniform(0.03, 1.5, 200)]
    radius = gen.uniform(0.01, 0.3, 200)
    got, clipped = tm.window_of(t, CAM, radius, 24), tm.window_of(t, CAM, radius, 24, clip=True)
    for b in range(200):
        z = max(t[b, 2], 1.05 * radius[b])
        for a, (f, c, n) in enumerate(((CAM.fx, CAM.cx, CAM.width), (CAM.fy, CAM.cy, CAM.height))):
            centre, half = f * t[b, a] / t[b, 2] + c, f * radius[b] / (z - radius[b]) + 24
            lo, size = math.floor(centre - half), math.ceil(centre + half) - math.floor(centre - half) + 1
            assert (got[b, a], got[b, 2 + a]) == (lo, size)
            assert clipped[b, 2 + a] == min(size, n) and clipped[b, a] == min(max(lo, 0), n - min(size, n))
    assert (clipped[:, 2] < got[:, 2]).any() and (clipped[:, 0] != got[:, 0]).any()  # both clips happened


def test_to_canvas_samples_the_box_at_its_scale():
    img = torch.arange(40 * 60, dtype=torch.float64).reshape(1, 40, 60)  # value = 60 v + u: linear
    box = torch.tensor([[30.0, 20.0, 16.0]], dtype=torch.float64)
    c = tm.to_canvas(img, box, 8)
    i = torch.arange(8, dtype=torch.float64) + 0.5 - 4
    u, v = 30 + 2 * i, 20 + 2 * i
    assert torch.allclose(c[0], 60 * v[:, None] + u[None, :])
    # a window of the image placed at its origin gives the same canvas
    assert torch.allclose(tm.to_canvas(img[:, 5:, 10:], box, 8, (10, 5)), c)
    # canvas intrinsics: a frame point lands at the canvas pixel that sampled it
    K = tm.canvas_intrinsics(box, Camera(60, 40, 50.0, 50.0, 25.0, 18.0), 8)[0]
    assert float(K[0]) == 25.0 and float(K[2] + (30 - 25) / 2) == pytest.approx(3.5)


def test_template_is_dog_of_edges_scaled_to_half():
    yy, xx = torch.meshgrid(torch.arange(128.0), torch.arange(128.0), indexing="ij")
    disk = (((xx - 64) ** 2 + (yy - 64) ** 2) < 30**2).float()[None]
    depth = disk * 0.4
    cam = Camera(128, 128, 200.0, 200.0, 63.5, 63.5)
    cr = reference.prepare_canvas(depth, disk * 0.6, (0, 0), cam, 128, 34)
    t = reference.hypothesis_templates(cr, POSE.float(), POSE.float()[:, None])[0, 0]
    assert float(t.max()) == pytest.approx(0.5, abs=1e-4) and float(t.min()) < -0.05 and float(t.min()) >= -0.5
    r = ((xx - 63.5) ** 2 + (yy - 63.5) ** 2).sqrt()
    on_edge = t[(r - 30).abs() < 1].mean()
    ring_out = t[(r - 36).abs() < 1].mean()
    far = t[r > 50]
    assert on_edge > 0.3 and ring_out < 0 and float(far.abs().max()) < 1e-6


def test_bad_inputs(scenes):
    _, roi, base = scenes["box"]
    obs = torch.zeros(1, CAM.height, CAM.width)
    args = (POSE, base.depth, base.gray, roi[:2], obs, CAM)
    with pytest.raises(ValueError, match="rule"):
        reference.correct(*args, rule="best")
    with pytest.raises(ValueError, match="warp"):
        reference.correct_warp(*args, warp="flow")
    model = tm.template_model(POSE, base.depth, base.gray, roi[:2], CAM)
    with pytest.raises(ValueError, match="pose"):
        reference.correct_model(model, POSE.repeat(2, 1), obs, CAM)
    with pytest.raises(ValueError, match="observation"):
        model.fit(obs.repeat(2, 1, 1))
    with pytest.raises(ValueError, match="iterations"):
        reference.correct(*args, iterations=0)
    with pytest.raises(ValueError, match="pose"):
        reference.correct(POSE[:, :6], *args[1:])
    with pytest.raises(ValueError, match="observation"):
        reference.correct(POSE, base.depth, base.gray, roi[:2], obs.repeat(2, 1, 1), CAM)
    with pytest.raises(ValueError, match="gray"):
        reference.correct(POSE, base.depth, base.gray[:, 1:], roi[:2], obs, CAM)
    with pytest.raises(ValueError, match="origin"):
        reference.correct(POSE, base.depth, base.gray, (1, 2, 3), obs, CAM)
    with pytest.raises(TypeError, match="depth"):
        reference.correct(POSE, base.depth.bool(), base.gray, roi[:2], obs, CAM)
    with pytest.raises(TypeError, match="camera"):
        tm.TemplateCorrector((640, 480))
    with pytest.raises(ValueError, match="silhouette"):
        reference.correct(*args[:2], None, *args[3:], silhouette=False)


@pytest.mark.parametrize("rule", ["argmax", "group", "newton"])
def test_object_out_of_view_leaves_the_pose_unchanged(rule):
    depth = torch.zeros(2, 40, 50)
    obs = torch.rand(2, CAM.height, CAM.width)
    pose = POSE.float().repeat(2, 1)
    out = reference.correct(pose, depth, depth.clone(), (100, 80), obs, CAM, rule=rule, iterations=3)
    assert torch.equal(out.pose, pose) and (out.index == 0).all() and not out.applied.any()
    assert torch.equal(out.scores, torch.zeros(2, 13)) and (out.iterations == 0).all()


# -- dense oracle of the second-order score model: every pixel, plain tensor algebra ----------
def dense_spline_derivatives(img):
    """``[T_u, T_v, T_uu, T_uv, T_vv]`` of the warp's B-spline interpolant at the pixels, ``(B, 5, N, N)``:
    3 x 3 kernels of the spline's value / first / second derivative weights at a knot on the coefficients."""
    val, d1, d2 = (torch.tensor(k, dtype=img.dtype) for k in ((1 / 6, 4 / 6, 1 / 6), (-0.5, 0.0, 0.5), (1.0, -2.0, 1.0)))
    kern = torch.stack((torch.outer(val, d1), torch.outer(d1, val), torch.outer(val, d2), torch.outer(d1, d1),
                        torch.outer(d2, val)))[:, None]  # rows: v kernel, columns: u kernel
    return torch.nn.functional.conv2d(reference._spline_prefilter(img[:, None]), kern, padding=1)


def dense_canvas_jacobian(depth, K, pose):
    """Image motion ``(B, 6, 2, N * N)`` of every canvas pixel per step ``[dt, phi]``: the interaction matrix of
    the canvas camera at ``depth``, rotation columns moved to a rotation about the pose origin (v = dt - phi x t)."""
    B, N, _ = depth.shape
    out = torch.zeros(B, 6, 2, N, N, dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(N, dtype=torch.float64), torch.arange(N, dtype=torch.float64), indexing="ij")
    for b in range(B):
        fx, fy, cx, cy = K[b].double().tolist()
        x, y, Z = (u - cx) / fx, (v - cy) / fy, depth[b].double()
        L = torch.stack((torch.stack((-1 / Z, 0 * Z, x / Z, x * y, -(1 + x * x), y)),
                         torch.stack((0 * Z, -1 / Z, y / Z, 1 + y * y, -x * y, -x))))  # (2, 6, N, N), camera motion
        L = -L  # object motion is the opposite camera motion
        t = pose[b, :3].double()
        tx = torch.tensor([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]], dtype=torch.float64)
        rot = L[:, 3:] + torch.einsum("rkhw,kj->rjhw", L[:, :3], tx)  # v = dt - phi x t = dt + [t]x phi
        out[b, :3] = L[:, :3].transpose(0, 1)
        out[b, 3:] = rot.transpose(0, 1)
        out[b, :, 0] *= fx
        out[b, :, 1] *= fy
    return out.reshape(B, 6, 2, N * N)


def dense_quadratic(template, depth, K, pose, obs):
    """``(s0, g, M)`` of the Taylor score model at the template's own pose, summed over every canvas pixel."""
    B, N, _ = template.shape
    D = dense_spline_derivatives(template.double()).reshape(B, 5, N * N)
    J = dense_canvas_jacobian(depth, K, pose)  # (B, 6, 2, P)
    o = obs.double()
    grad = torch.stack((D[:, 0], D[:, 1]), 1)  # (B, 2, P)
    hess = torch.stack((torch.stack((D[:, 2], D[:, 3]), 1), torch.stack((D[:, 3], D[:, 4]), 1)), 1)  # (B, 2, 2, P)
    s0 = (template.reshape(B, -1).double() * o).sum(1)
    g_ = torch.einsum("bjrp,brp,bp->bj", J, grad, o)
    M = torch.einsum("bjrp,brsp,bksp,bp->bjk", J, hess, J, o)
    return s0, g_, M


# -- (f) second-order score model against the exact warp (reference) -------------------
def test_dog_and_edges_match_kornia_filters():
    from kornia.filters import gaussian_blur2d, spatial_gradient

    torch.manual_seed(3)
    x = (torch.rand(2, 96, 96) > 0.9).float()
    ref = None
    for sign, k in ((1, 5), (-1, 13)):  # odd(96 / 20), odd(96 / 8)
        s = 0.3 * ((k - 1) / 2 - 1) + 0.8
        b = gaussian_blur2d(x[:, None], (k, k), (s, s), border_type="constant")[:, 0]
        ref = b if ref is None else ref + sign * b
    assert torch.allclose(reference.dog(x, 96), ref, atol=1e-6)
    gray, mask = torch.rand(2, 40, 50), (torch.rand(2, 40, 50) > 0.5).float()
    gk = spatial_gradient(torch.stack((gray, mask), 1), mode="sobel", order=1, normalized=True)
    edges = (gk.square().sum(2).sqrt().amax(1) / 0.1).clamp(max=1.0)
    assert torch.allclose(reference.edge_map(gray, mask, 0.1), edges, atol=1e-6)


def test_canvas_box_and_radial_gain_match_their_definitions():
    gen = torch.Generator().manual_seed(13)
    depth = (torch.rand(3, 30, 41, generator=gen) + 0.3) * (torch.rand(3, 30, 41, generator=gen) > 0.97)
    depth[2] = 0.0  # no object pixels
    origin = torch.tensor([[5.0, 7.0], [100.0, 20.0], [0.0, 0.0]])
    box, gain = reference.canvas_box(depth, origin, 4.0), reference.radial_gain(depth, origin, CAM)
    for b in range(3):
        v, u = torch.nonzero(depth[b] > 0, as_tuple=True)
        if len(u) == 0:
            assert box[b].tolist() == [20.0, 14.5, 41.0] and float(gain[b]) == 0.0
            continue
        cu, cv = (u.min() + u.max()) / 2 + origin[b, 0], (v.min() + v.max()) / 2 + origin[b, 1]
        side = max(u.max() - u.min(), v.max() - v.min()) + 1 + 8
        assert box[b].tolist() == pytest.approx([float(cu), float(cv), float(side)])
        r = torch.hypot(u + origin[b, 0] - CAM.cx, v + origin[b, 1] - CAM.cy) / depth[b, v, u]
        assert float(gain[b]) == pytest.approx(float(r.double().mean()), rel=1e-6)


@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
@pytest.mark.parametrize("grey, silhouette, interior", [(True, True, 0.0), (False, True, 0.0), (True, False, 0.0),
                                                        (True, True, 0.7)])
def test_template_model_is_the_template_of_the_canvas_render(scenes, name, grey, silhouette, interior):
    # the oracle: the tensor functions the compiled model builder fuses (prepare_canvas, edge_map, dog, ...)
    _, roi, base = scenes[name]
    depth, gray = base.depth.expand(2, -1, -1), base.gray.expand(2, -1, -1) if grey else None
    origin = torch.tensor([roi[:2], [roi[0] - 3, roi[1] + 5]])  # the second window seen at another place
    pose = POSE.expand(2, 7)
    model = tm.template_model(pose, depth, gray, origin, CAM, silhouette=silhouette, interior=interior)
    cr = reference.prepare_canvas(depth, gray, origin, CAM, 128, 20.0)
    edges = reference.dog(reference.edge_map(cr.gray, cr.mask if silhouette else None, 0.1), 128)[:, None]
    T = reference._scale(edges, edges)[:, 0] + interior * cr.mask
    assert torch.equal(model.box, cr.box) and torch.allclose(model.K, cr.K, rtol=1e-6)  # K: float64, then rounded
    assert torch.allclose(model.gain, reference.radial_gain(depth, origin, CAM))
    assert torch.allclose(model.render_template, T, atol=1e-5)
    coef = torch.nn.functional.pad(reference._spline_prefilter(T[:, None])[:, 0], (3,) * 4)
    # float32 sums of the prefilter's taps: their rounding grows with the template's values (up to 0.5 + interior)
    assert torch.allclose(model.coef, coef, atol=1e-5 * (1 + 4 * interior)), float((model.coef - coef).abs().max())
    assert torch.allclose(model.depth, reference._fill_depth(cr.depth, pose[:, 2], 8), atol=1e-6)
    assert (model.render_template.abs() > 0.1).any()  # a template, not an empty canvas


def test_fill_depth_matches_a_pixel_loop():
    torch.manual_seed(4)
    depth = torch.zeros(1, 20, 24, dtype=torch.float64)
    depth[0, 5:12, 6:15] = 0.4 + 0.1 * torch.rand(7, 9, dtype=torch.float64)
    out = reference._fill_depth(depth, torch.tensor([0.7], dtype=torch.float64), 3)
    for v in range(20):
        for u in range(24):
            win = depth[0, max(v - 3, 0) : v + 4, max(u - 3, 0) : u + 4]
            obj = win[win > 0]
            expected = depth[0, v, u] if depth[0, v, u] > 0 else (obj.mean() if obj.numel() else 0.7)
            assert float(out[0, v, u]) == pytest.approx(float(expected), abs=1e-12)


def test_spline_derivatives_are_those_of_the_warp_interpolant():
    torch.manual_seed(5)
    img = reference.dog((torch.rand(1, 48, 48) > 0.85).float(), 64).double()
    D = dense_spline_derivatives(img)[0]
    coef = reference._spline_prefilter(img[:, None])
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    uv = torch.stack((u, v)).double()[None]
    h = 1e-3

    def at(du, dv):
        return reference._spline_sample(coef, uv + torch.tensor([du, dv], dtype=uv.dtype).view(1, 2, 1, 1))[0, 0]

    fd = torch.stack((
        (at(h, 0) - at(-h, 0)) / (2 * h),
        (at(0, h) - at(0, -h)) / (2 * h),
        (at(h, 0) - 2 * at(0, 0) + at(-h, 0)) / h**2,
        (at(h, h) - at(h, -h) - at(-h, h) + at(-h, -h)) / (4 * h * h),
        (at(0, h) - 2 * at(0, 0) + at(0, -h)) / h**2,
    ))
    inner = (slice(None), slice(4, -4), slice(4, -4))
    assert torch.allclose(D[inner], fd[inner], atol=1e-3 * float(img.abs().max()))  # O(h) at the knots


@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
def test_canvas_jacobian_is_the_first_order_warp_displacement(scenes, name):
    _, roi, base = scenes[name]
    N = 128
    cr = reference.prepare_canvas(base.depth.double(), base.gray.double(), roi[:2], CAM, N, 20)
    Z = reference._fill_depth(cr.depth, POSE[:, 2], N // 16)
    steps = _steps(POSE, base, roi)[0, 1:] * 0.02  # (12, 6): 2 % of the hypothesis steps
    v, u = torch.meshgrid(torch.arange(float(N)), torch.arange(float(N)), indexing="ij")
    coords = torch.stack((u, v))[None].double()
    w = reference.warp_canvas(coords, Z, cr.K, POSE, tm.apply_steps(POSE, torch.cat((steps, -steps))[None]))[0]
    disp = (w[:12] - w[12:]).reshape(12, 2, -1) / 2  # central difference of the source coordinates
    J = dense_canvas_jacobian(Z, cr.K, POSE)[0]  # (6, 2, N * N)
    pred = -torch.einsum("jrn,kj->krn", J, steps)  # the source of pixel q is q - J delta
    inner = torch.zeros(N, N, dtype=torch.bool)
    inner[16:-16, 16:-16] = True
    err = (disp - pred)[:, :, inner.flatten()].abs().amax((1, 2))
    mag = pred[:, :, inner.flatten()].abs().amax((1, 2))
    assert (err < 1e-3 * mag + 1e-6).all(), err / mag



@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
def test_quadratic_score_equals_the_dense_terms_at_the_render_pose(scenes, name):
    _, roi, base = scenes[name]
    model = tm.template_model(POSE, base.depth, base.gray, roi[:2], CAM)
    N = model.depth.shape[-1]
    gen = torch.Generator().manual_seed(11)
    obs = torch.rand(2, N * N, generator=gen) * (torch.rand(2, N * N, generator=gen) > 0.7)  # sparse, two draws
    rep = lambda x: x.expand(2, *x.shape[1:])  # noqa: E731
    quad = tm.quadratic_score(rep(model.coef), rep(model.depth), rep(model.K), rep(model.render_pose), rep(POSE), obs)
    s0, g_, M = dense_quadratic(rep(model.render_template), rep(model.depth), rep(model.K), rep(POSE), obs)
    # s0 samples the spline at the knots, which reproduces the template up to its prefilter's truncation (1e-5)
    assert torch.allclose(quad.s0, s0, atol=1e-5 * float((obs * model.render_template.abs().reshape(1, -1)).sum()))
    assert torch.allclose(quad.g, g_, rtol=1e-5, atol=1e-5 * float(g_.abs().max()))
    assert torch.allclose(quad.M, M, rtol=1e-5, atol=1e-5 * float(M.abs().max()))
    assert torch.equal(quad.M, quad.M.transpose(1, 2)) and torch.equal(quad.pose, rep(POSE))


@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
def test_quadratic_score_away_from_the_render_is_the_taylor_model_of_the_warp(scenes, name):
    _, roi, base = scenes[name]
    model = tm.template_model(POSE, base.depth, base.gray, roi[:2], CAM)
    N = model.depth.shape[-1]
    obs = model.observe(_edges(base), roi[:2])
    unit = _steps(POSE, base, roi)[0, 1::2].diagonal()
    centre = tm.apply_steps(POSE, (unit * torch.tensor([1.5, -1.0, 0.8, 1.0, -1.5, 0.7], dtype=torch.float64))[None, None])[:, 0]
    quad = model.at(centre).fit_canvas(obs)

    def warp_score(deltas):  # the reference: the render's template warped to centre (+) delta, then scored
        t = reference.warp_canvas(model.render_template[:, None].double(), model.depth.double(), model.K, POSE,
                           tm.apply_steps(centre, deltas[None]))[0, :, 0]
        return (t * obs.view(1, N, N).double()).flatten(1).sum(1)

    h = 0.1
    d = torch.diag(unit * h)
    s = warp_score(torch.cat((torch.zeros(1, 6, dtype=torch.float64), d, -d)))
    assert float(quad.s0[0]) == pytest.approx(float(s[0]), rel=1e-4)
    g_fd = -(s[1:7] - s[7:]) / (2 * h) / unit  # per metre / radian, like g
    M_fd = (s[1:7] + s[7:] - 2 * s[0]) / h**2 / unit**2
    # g is the warp's exact first derivative; M leaves out the warp's own curvature (a few % of it)
    assert torch.allclose(quad.g[0] * unit, g_fd * unit, atol=0.01 * float((g_fd * unit).abs().max()))
    assert torch.allclose(quad.M[0].diagonal() * unit**2, M_fd * unit**2, atol=0.03 * float((M_fd * unit**2).abs().max()))


SIX = [1, 4, 5, 8, 9, 12]  # +tx, -ty, +tz, -rx, +ry, -rz


def _both_scores(r, roi, start, obs):
    """Warp and taylor scores of the 13 hypotheses around ``start`` (B, 7) from a render there."""
    rd = r.render(start.float(), roi=roi)
    B = start.shape[0]
    cr = reference.prepare_canvas(rd.depth, rd.gray, roi[:2], CAM, 128, 20)
    steps = reference.hypothesis_steps(start, CAM, reference.radial_gain(rd.depth, roi[:2], CAM))
    o = tm.to_canvas(obs.expand(B, -1, -1), cr.box, 128, roi[:2])
    warp = reference.score(reference.hypothesis_templates(cr, start.float(), tm.apply_steps(start, steps).float()), o)
    model = tm.template_model(start, rd.depth, rd.gray, roi[:2], CAM)
    return warp.double(), model.fit(obs.expand(B, -1, -1), roi[:2]).scores(start, steps), model


def _corr(a, b):
    a, b = a - a.mean(-1, keepdim=True), b - b.mean(-1, keepdim=True)
    return (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1))


@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
def test_taylor_scores_match_warp_scores(scenes, name):
    r, roi, base = scenes[name]
    obs = _edges(base)
    steps = _steps(POSE, base, roi)
    # one step off along each axis (alternating signs): both must pick the step back
    back = torch.tensor(SIX)
    starts = tm.apply_steps(POSE, -steps[:, back])[0]
    warp, fast, model = _both_scores(r, roi, starts, obs)
    assert (_corr(warp, fast) > 0.95).all()
    assert torch.equal(warp.argmax(1), back) and torch.equal(fast.argmax(1), back)
    # the null score is the template against the observation, exactly
    assert torch.allclose(fast[:, 0], warp[:, 0], rtol=1e-4)
    # random offsets up to ~1.5 px and 0.75 deg: same ranking up to near-ties
    g_ = torch.Generator().manual_seed(7)
    off = (torch.rand(4, 6, generator=g_, dtype=torch.float64) * 2 - 1) * steps[0, 1::2].diagonal() * 0.75
    warp, fast, _ = _both_scores(r, roi, tm.apply_steps(POSE, off[None])[0], obs)
    assert (_corr(warp, fast) > 0.95).all()
    best = warp.amax(1)
    chosen = warp.gather(1, fast.argmax(1, keepdim=True))[:, 0]
    assert ((best - chosen) <= 0.05 * (best - warp.amin(1))).all()


def test_taylor_model_quadratic_form():
    # the model is exactly S(d) = s0 - g.d + d^T M d / 2 in the step coordinates of apply_steps
    torch.manual_seed(8)
    B = 3
    pose = torch.cat((torch.randn(B, 3, dtype=torch.float64) * 0.05 + torch.tensor([0, 0, 0.5]),
                      g.quat_canonical(torch.randn(B, 4, dtype=torch.float64))), -1)
    A = torch.randn(B, 6, 6, dtype=torch.float64)
    quad = tm.QuadraticScore(pose, torch.randn(B, dtype=torch.float64), torch.randn(B, 6, dtype=torch.float64),
                             A + A.transpose(1, 2))
    d = torch.randn(B, 5, 6, dtype=torch.float64) * 0.01
    expected = quad.s0[:, None] - (d * quad.g[:, None]).sum(-1) + 0.5 * torch.einsum("bpi,bij,bpj->bp", d, quad.M, d)
    assert torch.allclose(quad.scores(pose, d), expected, atol=1e-12)
    assert torch.allclose(tm.pose_delta(pose, tm.apply_steps(pose, d)), d, atol=1e-12)


@pytest.mark.parametrize("rule", ["argmax", "group"])
def test_correct_taylor_equals_warp_on_one_step_offsets(scenes, rule):
    r, roi, base = scenes["006_mustard_bottle"]
    obs = _edges(base)
    starts = tm.apply_steps(POSE, -_steps(POSE, base, roi)[:, SIX])[0]
    rd = r.render(starts.float(), roi=roi)
    outs = [f(starts, rd.depth, rd.gray, roi[:2], obs.expand(6, -1, -1), CAM, observation_origin=roi[:2], rule=rule)
            for f in (reference.correct, reference.correct_warp)]
    assert torch.equal(outs[0].index, outs[1].index) and torch.equal(outs[0].applied, outs[1].applied)
    assert torch.allclose(outs[0].pose, outs[1].pose, atol=1e-6)
    # argmax: the score of one hypothesis step; group: of up to four composed steps, where the
    # quadratic's third-order error reaches a few %
    assert torch.allclose(outs[0].score, outs[1].score, rtol=0.02 if rule == "argmax" else 0.08)



def _search_case(scene, seed: int, interior: float = 0.0, texture: float = 0.0):
    """A float64 model of ``scene``'s render (no rounding), six starts up to 1.5 steps off on every axis, and the
    observation of its edges (plus, on the object, ``texture`` on a random fifth of its pixels) for each start."""
    _, roi, base = scene
    model = tm.template_model(POSE, base.depth.double(), base.gray.double(), roi[:2], CAM, interior=interior)
    unit = _steps(POSE, base, roi)[0, 1::2].diagonal()
    gen = torch.Generator().manual_seed(seed)
    off = (torch.rand(6, 6, generator=gen, dtype=torch.float64) * 2 - 1) * unit * 1.5
    starts = tm.apply_steps(POSE, off[None])[0]
    B = len(starts)
    model = tm.TemplateModel(*(x.expand(B, *x.shape[1:]) for x in model))
    inside = (base.depth > 0).double() * (torch.rand(base.depth.shape, generator=gen) < 0.2)
    obs = model.observe((_edges(base).double() + texture * inside).expand(B, -1, -1), roi[:2])
    return model, starts, obs


@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
def test_compiled_newton_search_equals_the_generic_search(scenes, name):
    # the oracle: search() with rule="newton" on the refitted quadratic, step from the 28-score fit
    model, starts, obs = _search_case(scenes[name], 12)

    def scorer(centre):
        quad = model.at(centre).fit_canvas(obs)
        return quad.at_steps, quad.evaluate

    for iterations in (1, 4):
        ref = reference.search(starts, scorer, model.gain, CAM, rule="newton", iterations=iterations)
        out = tm.newton_search(model, starts, obs, CAM, iterations=iterations)
        assert torch.equal(out.iterations, ref.iterations) and (ref.iterations > 0).any()
        assert torch.allclose(out.pose, ref.pose, atol=1e-9)
        assert torch.allclose(out.score, ref.score, rtol=1e-9) and torch.allclose(out.scores, ref.scores, rtol=1e-9)
        assert torch.equal(out.index, ref.index) and not out.applied.any()


def test_area_weight_is_the_two_rate_density_threshold_times_the_area():
    # the oracle: the object's cells of the model's point grid spread over the canvas, then the two means
    N, step = 64, 4
    gen = torch.Generator().manual_seed(3)
    valid = torch.zeros(16, 16, dtype=torch.bool)
    valid[4:11, 5:13] = True
    on = torch.repeat_interleave(torch.repeat_interleave(valid, step, 0), step, 1)
    obs = torch.rand(N, N, generator=gen, dtype=torch.float64) * torch.where(on, 0.2, 0.01)
    rho_f, rho_b = float(obs[on].mean()), float(obs[~on].mean())
    want = 0.8 * (rho_f - rho_b) / math.log(rho_f / rho_b) * int(on.sum())
    got = tm.area_weight(obs.flatten().numpy(), valid.flatten().numpy(), N, 0.8)
    assert got == pytest.approx(want, rel=1e-12)
    assert tm.area_weight(obs.flatten().numpy(), valid.flatten().numpy(), N, 0.0) == 0.0
    flipped = torch.where(on, 0.0, obs).flatten().numpy()  # no more events on the object than off it: no area term
    assert tm.area_weight(flipped, valid.flatten().numpy(), N, 0.8) == 0.0


@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
def test_compiled_newton_search_with_interior_equals_the_generic_search(scenes, name):
    # the oracle: reference.rule_search with the newton rule, search() on the refitted quadratic of the template (with
    # its interior) minus the area term's second-order Taylor model in tz around each centre (a from area_weight)
    interior = 0.8
    model, starts, obs = _search_case(scenes[name], 5, interior, texture=0.3)  # events on the object too
    a = [tm.area_weight(obs[b].numpy(), model.valid[b].numpy(), 128, interior) for b in range(len(starts))]
    assert min(a) > 0  # the area term is on
    for iterations in (1, 4):
        ref = reference.rule_search(model, starts, obs, CAM, dp_px=1.0, dtheta_deg=0.5, rule="newton",
                                    iterations=iterations)
        out = tm.newton_search(model, starts, obs, CAM, iterations=iterations)
        assert torch.equal(out.iterations, ref.iterations) and (ref.iterations > 0).any()
        assert torch.allclose(out.pose, ref.pose, atol=1e-9)
        # the scores carry the area term's constant (hundreds): the 28-score fit of the oracle rounds at ~1e-8 of it
        assert torch.allclose(out.score, ref.score, rtol=1e-7) and torch.allclose(out.scores, ref.scores, rtol=1e-7)


@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
@pytest.mark.parametrize("shift", [None, 0.5])
def test_compiled_depth_bound_clips_each_newton_step_as_the_generic_search(scenes, name, shift):
    # the oracle: reference.rule_search's newton rule with the same bound (each step's depth clipped before it is
    # scored); the bound is half the depth the unbounded search moves, so it binds, and no pose leaves it. The band
    # is centred at the start depths (None) or at a given depth per element half a bound away, alternately nearer
    # and farther (the tracker's last measurement moved on by the prediction)
    model, starts, obs = _search_case(scenes[name], 12, 0.8, texture=0.3)
    free = tm.newton_search(model, starts, obs, CAM, iterations=4)
    max_dz = 0.5 * float((free.pose[:, 2] - starts[:, 2]).abs().max())
    side = torch.tensor([1.0, -1.0], dtype=torch.float64).repeat(len(starts) // 2)
    z_ref = None if shift is None else starts[:, 2].double() + side * shift * max_dz
    ref = reference.rule_search(model, starts, obs, CAM, dp_px=1.0, dtheta_deg=0.5, rule="newton", iterations=4,
                                max_dz=max_dz, z_ref=z_ref)
    out = tm.newton_search(model, starts, obs, CAM, iterations=4, max_dz=max_dz, z_ref=z_ref)
    assert torch.equal(out.iterations, ref.iterations)
    assert torch.allclose(out.pose, ref.pose, atol=1e-9) and torch.allclose(out.score, ref.score, rtol=1e-7)
    dz = (out.pose[:, 2] - (starts[:, 2] if z_ref is None else z_ref)).abs()
    assert (dz <= max_dz * (1 + 1e-9)).all() and (dz >= max_dz * (1 - 1e-9)).any()
    assert not torch.equal(out.pose, free.pose)
    far = tm.newton_search(model, starts, obs, CAM, iterations=4, max_dz=100 * max_dz)  # a bound never reached
    assert torch.equal(far.pose, free.pose) and torch.equal(far.score, free.score)


@pytest.mark.parametrize("rule", ["argmax", "group"])
def test_depth_bound_keeps_the_hypothesis_rules_within_it(scenes, rule):
    # the chosen pose's depth is clipped and scored there: the element moves only while that beats the centre
    model, starts, obs = _search_case(scenes["box"], 12)
    free = tm.correct_canvas(model, starts, obs, CAM, rule=rule, iterations=4)
    max_dz = 0.5 * float((free.pose[:, 2] - starts[:, 2]).abs().max())
    out = tm.correct_canvas(model, starts, obs, CAM, rule=rule, iterations=4, max_dz=max_dz)
    dz = (out.pose[:, 2] - starts[:, 2]).abs()
    assert (dz <= max_dz * (1 + 1e-6)).all() and (dz >= max_dz * (1 - 1e-6)).any()
    assert (out.score >= out.scores[:, 0]).all() and (out.iterations > 0).any()


def test_a_bad_depth_bound_is_a_one_line_error(scenes):
    model, starts, obs = _search_case(scenes["box"], 2)
    for bad in (0.0, -1.0, float("nan"), "1"):
        with pytest.raises(ValueError, match="max_dz"):
            tm.correct_canvas(model, starts, obs, CAM, max_dz=bad)
    z = starts[:, 2].double()
    for bad in (z[:1], torch.where(torch.arange(len(z)) == 1, float("nan"), z), z.tolist()):
        with pytest.raises(ValueError, match="z_ref"):
            tm.correct_canvas(model, starts, obs, CAM, max_dz=0.01, z_ref=bad)


@pytest.mark.parametrize("name", ["box", "006_mustard_bottle"])
def test_interior_term_keeps_a_printed_texture_from_pulling_the_depth(scenes, name):
    # events on the object's side of its outline, plus a texture the mesh does not have (a fifth of the object's
    # pixels): the edge template alone takes the texture for outline and moves the object away as the texture
    # thickens; with the interior term the texture moves it less than half as far
    _, roi, base = scenes[name]
    m = (base.depth > 0).double()
    outline = m + torch.nn.functional.max_pool2d(-m[:, None], 3, 1, 1)[:, 0]  # the object's outermost pixels
    gen = torch.Generator().manual_seed(7)
    texture = m * (torch.rand(m.shape, generator=gen, dtype=torch.float64) < 0.2)
    moves = {}
    for interior in (0.0, 1.0):
        c = tm.TemplateCorrector(CAM, iterations=5, interior=interior)
        moves[interior] = [float(c(POSE, base.depth.double(), base.gray.double(), roi[:2], obs, roi[:2]).pose[0, 2]
                                 - POSE[0, 2]) for obs in (outline, torch.maximum(outline, texture))]
    pulled = {k: v[1] - v[0] for k, v in moves.items()}
    assert pulled[0.0] > 0.003  # the texture takes the edge template's object 3+ mm away
    assert abs(pulled[1.0]) < 0.5 * pulled[0.0]


# -- (g) reusing a render at a nearby pose ----------------------------------------------------
def test_reused_model_matches_a_fresh_render(scenes):
    r, roi, base = scenes["box"]
    obs = _edges(base)
    steps = _steps(POSE, base, roi)
    back = torch.tensor(SIX)
    starts = tm.apply_steps(POSE, -steps[:, back])[0]  # one step off along each axis
    # the render was made up to ~1 px away from where it is used
    g_ = torch.Generator().manual_seed(9)
    wobble = (torch.rand(6, 6, generator=g_, dtype=torch.float64) * 2 - 1) * steps[0, 1::2].diagonal() * 0.3
    refs = tm.apply_steps(starts, wobble[:, None])[:, 0]
    rd = r.render(refs.float(), roi=roi)
    corr = tm.TemplateCorrector(CAM, rule="argmax", iterations=1, interior=0.0, dtheta_deg=0.5)  # as _steps
    model = corr.template_model(refs, rd.depth, rd.gray, roi[:2])
    shift = model.shift_px(starts)
    assert (shift > 0.2).all() and (shift < 1.3).all()
    assert torch.allclose(model.shift_px(refs), torch.zeros(6, dtype=torch.float64), atol=1e-9)
    reused = corr.correct_model(model, starts, obs.expand(6, -1, -1), roi[:2])
    fresh_warp, fresh_fast, _ = _both_scores(r, roi, starts, obs)
    assert (_corr(reused.scores, fresh_warp) > 0.95).all()
    assert torch.equal(reused.index, back) and torch.equal(fresh_warp.argmax(1), back)
    assert (_corr(reused.scores, fresh_fast) > 0.95).all()
    # the model is re-centred on the pose it corrects (the render's template warped there)
    assert torch.equal(corr.correct_model(model.at(starts), starts, obs.expand(6, -1, -1), roi[:2]).scores,
                       reused.scores)


def test_shift_px_is_the_largest_image_motion_of_object_points(scenes):
    _, roi, base = scenes["box"]
    model = tm.template_model(POSE, base.depth, base.gray, roi[:2], CAM)
    v, u = torch.nonzero(base.depth[0] > 0, as_tuple=True)
    uv = torch.stack((u + roi[0], v + roi[1]), -1).double()
    X = CAM.backproject(uv, base.depth[0, v, u].double())
    for delta in ([0.001, 0, 0, 0, 0, 0], [0, 0, 0.004, 0, 0, 0], [0, 0, 0, 0, 0, 0.01], [0, 0, 0, 0.008, -0.004, 0]):
        d = torch.tensor([[delta]], dtype=torch.float64)
        moved = tm.apply_steps(POSE, d)[:, 0]
        Xm = g.quat_rotate(g.quat_exp(d[0, :, 3:]).expand(len(X), 4), X - POSE[:, :3]) + moved[:, :3]
        exact = float((CAM.project(Xm) - uv).norm(dim=-1).max())
        assert float(model.shift_px(moved)) == pytest.approx(exact, rel=0.1)
