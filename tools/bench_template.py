"""Speed and accuracy of the template correction: second-order score model vs exact warped templates.

Cases: the box and 006_mustard_bottle rendered ~0.5 m away at a few generic views, observed as the
binary edges of a render at the true pose ("edges"), and, with ``--sequence``, the median-blurred
EROS of a synthetic sequence at ground-truth times ("eros"; make one with ``torchevtrack synth
--object 006_mustard_bottle --motion regular --duration 0.3 --seed 5 --out /tmp/x``). Each trial
starts from the true pose moved by a random offset (up to ``--max-px`` image pixels along x, y and
z, up to ``--max-deg`` about a random axis), renders there and scores the 13 hypotheses both ways.

Prints per case: median / minimum Pearson correlation of the 13 scores, argmax agreement, the
score the model's choice loses against the exact best (in units of the spread of the 13 exact
scores), and agreement of the group rule's applied sets. Then per-call timings (1 thread, B = 1,
canvas 128): min and median ms of ``reference.correct_warp`` and ``reference.correct`` and of its parts.
With ``--reuse`` also the render-reuse path (a model of the render at P_ref scoring hypotheses
around P_ref + delta, by its quadratic at P_ref or re-centred there) against re-rendering at the new pose.

    PYOPENGL_PLATFORM=egl .venv/bin/python tools/bench_template.py [--trials 40] [--sequence /tmp/x] [--reuse]
"""

from __future__ import annotations

import argparse
import math
import os
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchevtrack import geometry as g  # noqa: E402
from torchevtrack.camera import Camera  # noqa: E402
from torchevtrack.mesh import load_mesh  # noqa: E402
from torchevtrack.render import Renderer  # noqa: E402
from torchevtrack import reference as ref
from torchevtrack.stages import template as tm  # noqa: E402

CAM = Camera.default()
VIEWS = ([0.03, -0.02, 0.5, 0.4, -0.6, 0.3], [-0.04, 0.03, 0.45, -1.2, 0.3, 0.9], [0.0, 0.01, 0.55, 2.0, 1.0, -0.4])


def _pose(v) -> torch.Tensor:
    v = torch.tensor(v, dtype=torch.float64)
    return torch.cat((v[:3], g.quat_exp(v[3:])))[None]


def _edges(render) -> torch.Tensor:
    return (ref.edge_map(render.gray, (render.depth > 0).float()) > 0.5).float()


def _radius(mesh) -> float:
    return float(np.linalg.norm(mesh.vertices, axis=1).max())


def random_offset(truth, gain, rng, max_px, max_deg) -> torch.Tensor:
    """Step ``[dt, phi]`` (1, 6): x, y, z moves of up to ``max_px`` image pixels, rotation up to ``max_deg``."""
    z = float(truth[0, 2])
    px = rng.uniform(-max_px, max_px, 3)
    axis = rng.normal(size=3)
    phi = axis / np.linalg.norm(axis) * math.radians(rng.uniform(0, max_deg))
    dt = [z * px[0] / CAM.fx, z * px[1] / CAM.fy, px[2] / gain]
    return torch.tensor([dt + list(phi)], dtype=torch.float64)


def scores_both(renderer, roi, start, obs, obs_origin):
    """Exact (warp) and model (taylor) scores of the 13 hypotheses around ``start``; steps."""
    rd = renderer.render(start.float(), roi=roi)
    pose = start.float()
    cr = ref.prepare_canvas(rd.depth, rd.gray, roi[:2], CAM, 128, 20)
    steps = ref.hypothesis_steps(pose, CAM, ref.radial_gain(rd.depth, roi[:2], CAM))
    hyp = tm.apply_steps(pose, steps)
    o = tm.to_canvas(obs, cr.box, 128, obs_origin)
    exact = ref.score(ref.hypothesis_templates(cr, pose, hyp), o)[0].double()
    model = tm.template_model(pose, rd.depth, rd.gray, roi[:2], CAM)
    fast = model.fit(obs, obs_origin).scores(pose, steps)[0]
    return exact, fast, steps, model, rd


def compare(name, trials):
    """trials: list of (exact, fast, steps) -> summary line."""
    corr, agree, loss, group = [], [], [], []
    for exact, fast, steps in trials:
        corr.append(float(np.corrcoef(exact.numpy(), fast.numpy())[0, 1]))
        ie, i_f = int(exact.argmax()), int(fast.argmax())
        agree.append(ie == i_f)
        loss.append(float(exact[ie] - exact[i_f]) / max(float(exact.max() - exact.min()), 1e-12))
        p = torch.zeros(1, 7, dtype=torch.float64)
        p[0, 2], p[0, 3] = 0.5, 1.0
        group.append(torch.equal(ref.select(p, steps.double(), exact[None], "group")[1],
                                 ref.select(p, steps.double(), fast[None], "group")[1]))
    c = np.array(corr)
    print(f"{name:28s} n={len(c):3d}  corr median {np.median(c):.4f} min {c.min():.4f}  "
          f"argmax agree {np.mean(agree) * 100:5.1f}%  loss median {np.median(loss):.3f} max {max(loss):.3f}  "
          f"group agree {np.mean(group) * 100:5.1f}%")


def eros_cases(seq_dir, times_ms):
    """(mesh, [(truth pose, observation (1, H, W))]) from a synthetic sequence's events."""
    from torchevtrack.stages.eros import EROS
    from torchevtrack.synth.sequence import Sequence

    seq = Sequence.load(seq_dir)
    ev = seq.events
    eros = EROS(seq.camera.height, seq.camera.width)
    out, t_prev = [], 0
    for t_ms in times_ms:
        t_us = int(t_ms * 1000)
        # EROS is order-exact per packet; feed 2 ms packets as the tracker does
        for a in range(t_prev, t_us, 2000):
            k = (ev.t >= a) & (ev.t < min(a + 2000, t_us))
            eros(ev.x[k].long(), ev.y[k].long())
        t_prev = t_us
        truth = g.interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t_us]))
        out.append((truth, eros.observation().clone()))
    return seq.mesh, out


def accuracy(args, rng):
    print(f"accuracy: offsets up to {args.max_px} px (x, y, z) and {args.max_deg} deg; 13 scores per trial")
    cases = []
    for obj in ("box", "006_mustard_bottle"):
        mesh = load_mesh(obj, decimate=4000)
        cases.append((f"{obj} edges", mesh, [(_pose(v), None) for v in VIEWS]))
    if args.sequence:
        mesh, items = eros_cases(args.sequence, [60, 120, 180, 240, 290])
        cases.append(("sequence eros", mesh, items))
    for name, mesh, items in cases:
        r = Renderer(mesh, CAM)
        trials, reuse = [], []
        for k in range(args.trials):
            truth, obs = items[k % len(items)]
            roi = tuple(int(v) for v in tm.render_window(truth, CAM, _radius(mesh), 24)[0])
            base = r.render(truth.float(), roi=roi)
            if obs is None:
                o, origin = _edges(base), roi[:2]
            else:
                o, origin = obs, (0, 0)
            off = random_offset(truth, float(ref.radial_gain(base.depth, roi[:2], CAM)), rng, args.max_px, args.max_deg)
            start = tm.apply_steps(truth, off[:, None])[:, 0]
            exact, fast, steps, model, _ = scores_both(r, roi, start, o, origin)
            trials.append((exact, fast, steps))
            if args.reuse:  # the render at start reused at a pose ~reuse_px away: vs a fresh render there
                d = random_offset(start, float(model.gain), rng, args.reuse_px, args.reuse_px / 2)
                moved = tm.apply_steps(start, d[:, None])[:, 0]
                exact2, fast2, steps2, _, _ = scores_both(r, roi, moved, o, origin)
                reused = model.fit(o, origin).scores(moved, steps2)[0]
                recentred = model.at(moved).fit(o, origin).scores(moved, steps2)[0]
                reuse.append(((exact2, reused, steps2), (exact2, recentred, steps2), (exact2, fast2, steps2)))
        compare(name, trials)
        if reuse:
            compare(f"  reuse quadratic ({args.reuse_px} px)", [x[0] for x in reuse])
            compare(f"  reuse re-centred ({args.reuse_px} px)", [x[1] for x in reuse])
            compare("  fresh render, taylor", [x[2] for x in reuse])
        r.close()


def timeit(fn, n):
    for _ in range(3):
        fn()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts) * 1e3, float(np.median(ts)) * 1e3


def speed(args):
    print(f"speed: B=1, canvas 128, {torch.get_num_threads()} thread(s), {args.runs} runs (min / median ms)")
    mesh = load_mesh("006_mustard_bottle", decimate=4000)
    r = Renderer(mesh, CAM)
    truth = _pose(VIEWS[0])
    roi = tuple(int(v) for v in tm.render_window(truth, CAM, _radius(mesh), 24)[0])
    obs = _edges(r.render(truth.float(), roi=roi))
    start = truth.clone()
    start[0, 0] += 0.002
    start = start.float()
    rd = r.render(start, roi=roi)
    print(f"  render window {roi[2]}x{roi[3]}; render itself: {'%.2f / %.2f' % timeit(lambda: r.render(start, roi=roi), 10)}")
    for rule in ("argmax", "group"):
        for it in (1, 3):
            for scoring, correct in (("warp", ref.correct_warp), ("taylor", ref.correct)):
                t = timeit(lambda: correct(start, rd.depth, rd.gray, roi[:2], obs, CAM, observation_origin=roi[:2],
                                           rule=rule, iterations=it), args.runs)
                print(f"  correct {scoring:6s} rule={rule:6s} iterations={it}: {t[0]:7.2f} / {t[1]:7.2f}")
    corr = tm.TemplateCorrector(CAM)
    model = corr.template_model(start, rd.depth, rd.gray, roi[:2])
    o = model.observe(obs, roi[:2])
    parts = {
        "template_model (render side)": lambda: corr.template_model(start, rd.depth, rd.gray, roi[:2]),
        "observe (obs -> canvas)": lambda: model.observe(obs, roi[:2]),
        "fit_canvas": lambda: model.fit_canvas(o),
        "fit_canvas at a moved centre": lambda: model.at(truth).fit_canvas(o),
        "correct_model (reuse: observe + fit + search)": lambda: corr.correct_model(model, start, obs, roi[:2]),
        "newton_search, 5 iterations (compiled)": lambda: tm.newton_search(model, start, o, CAM, iterations=5),
    }
    for k, fn in parts.items():
        print(f"  {k:46s} {'%7.2f / %7.2f' % timeit(fn, args.runs)}")
    r.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--max-px", type=float, default=2.0)
    ap.add_argument("--max-deg", type=float, default=1.0)
    ap.add_argument("--sequence", help="synthetic sequence directory for real EROS observations")
    ap.add_argument("--reuse", action="store_true", help="also measure the render-reuse path")
    ap.add_argument("--reuse-px", type=float, default=1.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--skip-speed", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if not args.skip_accuracy:
        accuracy(args, np.random.default_rng(args.seed))
    if not args.skip_speed:
        speed(args)


if __name__ == "__main__":
    main()
