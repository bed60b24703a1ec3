"""The wide suite's simulator effects, each against an independent computation, the suite's definition and the
per-factor report."""

import json
import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.ndimage import binary_dilation
from scipy.spatial.transform import Rotation

from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.mesh import load_mesh
from torchevtrack.render import make_renderer
from torchevtrack.report import factor_tables, sequence_factors
from torchevtrack.synth.esim import ESIM, refractory_filter
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.synth.suite import SPLIT_SEED_BASE, WIDE_OBJECTS, size_class, wide_suite
from torchevtrack.synth.trajectory import make_trajectory

CAM = Camera(96, 72, 80.0, 80.0, 48.0, 36.0)


def static_events(sim: ESIM, duration_us: int, step_us: int = 10_000):
    """Feed a constant grey frame every ``step_us``; return all events as numpy arrays (x, y, t)."""
    img = torch.full((sim.height, sim.width), 0.5)
    sim(img, 0)
    chunks = [sim(img, t) for t in range(step_us, duration_us + 1, step_us)]
    x = np.concatenate([c.x.numpy() for c in chunks]).astype(np.int64)
    y = np.concatenate([c.y.numpy() for c in chunks]).astype(np.int64)
    t = np.concatenate([c.t.numpy() for c in chunks])
    return x, y, t


def test_noise_only_background_rate_within_10_percent():
    sim = ESIM(48, 64, noise_rate_hz=2.0, seed=3)
    x, y, t = static_events(sim, 2_000_000)
    rate = len(t) / (48 * 64 * 2.0)  # events per pixel per second
    assert abs(rate - 2.0) <= 0.1 * 2.0
    # spread over the sensor, not piled on a few pixels: ~4 events per pixel
    counts = np.bincount(y * 64 + x, minlength=48 * 64)
    assert counts.max() < 20 and (counts > 0).mean() > 0.9


def test_hot_pixels_fire_at_their_rate_and_nowhere_else():
    sim = ESIM(40, 50, hot_pixels=6, hot_pixel_rate_hz=400.0, seed=5)
    coords = sim.hot_pixel_coords()
    assert len({tuple(c) for c in coords}) == 6
    x, y, t = static_events(sim, 1_000_000)
    fired = {}
    for xi, yi in zip(x.tolist(), y.tolist()):
        fired[(xi, yi)] = fired.get((xi, yi), 0) + 1
    assert set(fired) == {tuple(c) for c in coords}
    for c in coords:  # Poisson(400): 4 sigma = 80
        assert abs(fired[tuple(c)] - 400) < 80
    assert abs(sum(fired.values()) / 6 - 400) < 4 * math.sqrt(400 / 6)


def _min_gap_per_pixel(x, y, t):
    """Smallest time between two events of one pixel (independent of the simulator: a lexsort)."""
    pix = y.astype(np.int64) * 10_000 + x.astype(np.int64)
    order = np.lexsort((t, pix))
    p, tt = pix[order], t[order]
    same = p[1:] == p[:-1]
    return int(np.diff(tt)[same].min())


def test_refractory_filter_matches_sequential_reference():
    g = torch.Generator().manual_seed(0)
    n, pixels, refr = 3000, 40, 300
    pix = torch.randint(0, pixels, (n,), generator=g)
    t = torch.randint(0, 20_000, (n,), generator=g)
    last = torch.randint(-2000, 100, (pixels,), generator=g)
    order = torch.sort(t, stable=True).indices
    pix, t = pix[order], t[order]
    new_last = last.clone()
    keep = refractory_filter(pix, t, new_last, refr)
    # reference: per pixel, its own events in time order
    ref_keep = np.zeros(n, bool)
    ref_last = last.numpy().copy()
    for p in range(pixels):
        for i in np.nonzero(pix.numpy() == p)[0]:
            if int(t[i]) - ref_last[p] >= refr:
                ref_keep[i] = True
                ref_last[p] = int(t[i])
    assert keep.numpy().tolist() == ref_keep.tolist()
    assert new_last.numpy().tolist() == ref_last.tolist()
    assert 0 < keep.sum() < n


@pytest.mark.parametrize("refractory_us", [0, 400])
def test_refractory_applies_to_every_event(refractory_us):
    """Contrast, noise and hot-pixel events of a moving object: no pixel fires twice within the period."""
    seq = generate_sequence("can", "fast", 0.06, 2, CAM, refractory_us=refractory_us, noise_rate_hz=300.0,
                            hot_pixels=4, hot_pixel_rate_hz=3000.0, render_backend="raster", progress=False)
    ev = seq.events
    x, y, t = ev.x.numpy(), ev.y.numpy(), ev.t.numpy()
    gap = _min_gap_per_pixel(x, y, t)
    if refractory_us:
        assert gap >= refractory_us
    else:
        assert gap < 400  # the same world without a period does fire faster (the check above can fail)
    hot = {tuple(c) for c in seq.meta["hot_pixels"]}
    on_hot = sum((int(a), int(b)) in hot for a, b in zip(x, y))
    assert on_hot > 4 * 3000 * 0.06 * (0.3 if refractory_us else 0.8)
    assert seq.meta["generator"]["esim"]["refractory_us"] == refractory_us


@pytest.mark.parametrize("seed", range(4))
def test_turn_and_mixed_speeds_in_range(seed):
    mesh = load_mesh("can")
    cam = Camera.default()
    for motion, (img_lo, img_hi) in (("turn", (0.0, 400.0)), ("mixed", (600.0, 1500.0))):
        t_us, poses = make_trajectory(motion, 4.0, seed, cam, mesh, depth_range=(0.3, 1.0))
        dt = np.diff(t_us.numpy()) / 1e6
        q = poses[:, [4, 5, 6, 3]].numpy()  # scipy: x, y, z, w
        r = Rotation.from_quat(q)
        ang = np.degrees((r[1:] * r[:-1].inv()).magnitude()) / dt
        assert 200.0 <= np.median(ang) <= 500.0
        # the turning axis visits all directions: out-of-plane turns (about x and y) are a good share
        axes = (r[1:] * r[:-1].inv()).as_rotvec()
        assert np.abs(axes[:, :2]).sum() > np.abs(axes[:, 2]).sum()
        p = poses[:, :3].numpy()
        uv = np.stack((cam.fx * p[:, 0] / p[:, 2] + cam.cx, cam.fy * p[:, 1] / p[:, 2] + cam.cy), 1)
        speed = np.linalg.norm(np.diff(uv, axis=0), axis=1) / dt
        if motion == "turn":
            assert speed.max() <= img_hi
        else:
            assert img_lo <= np.median(speed) <= img_hi


def _outside_silhouette(seq, dilate: int = 2) -> float:
    """Share of events off the object's own silhouette (dilated), rendered at the ground-truth pose nearest each
    event's time."""
    ev = seq.events
    idx = np.clip(np.searchsorted(seq.gt_t_us.numpy(), ev.t.numpy()), 0, len(seq.gt_t_us) - 1)
    with make_renderer(seq.mesh, seq.camera, "raster") as r:
        masks = r.render(seq.gt_poses, shaded=False).depth.numpy() > 0
    masks = np.stack([binary_dilation(m, iterations=dilate) for m in masks])
    inside = masks[idx, ev.y.numpy().astype(int), ev.x.numpy().astype(int)]
    return 1.0 - inside.mean()


def test_hand_makes_events_off_the_object_and_hides_part_of_it():
    kw = dict(camera=CAM, depth_range=(0.4, 0.7), render_backend="raster", progress=False)
    bare = generate_sequence("box", "turn", 0.08, 11, **kw)
    held = generate_sequence("box", "turn", 0.08, 11, occluder="hand", **kw)
    assert torch.equal(bare.gt_poses, held.gt_poses)  # the hand does not change the object's motion
    assert bare.mesh.vertices.shape == held.mesh.vertices.shape  # nor the saved mesh
    assert _outside_silhouette(bare) < 0.01
    assert _outside_silhouette(held) > 0.04  # the hand's own events (here ~6 % of them)
    occ = held.meta["occluder"]
    assert occ["kind"] == "hand" and 0.0 < occ["occluded_fraction"]["median"] < 1.0
    assert "occluder" not in bare.meta


def test_camera_presets_and_overrides(tmp_path, capsys):
    args = ["--object", "can", "--duration", "0.02", "--quiet", "--render-backend", "raster"]
    assert main(["synth", *args, "--camera", "davis346", "--out", str(tmp_path / "d")]) == 0
    cam = json.loads((tmp_path / "d" / "camera.json").read_text())
    assert (cam["width"], cam["height"], cam["fx"], cam["fy"], cam["cx"], cam["cy"]) == (346, 260, 255, 255, 173, 130)
    assert main(["synth", *args, "--camera", "hd", "--width", "320", "--height", "200", "--fx", "300",
                 "--hot-pixels", "3", "--noise-rate", "0.5", "--texture", "random", "--out", str(tmp_path / "h")]) == 0
    cam = json.loads((tmp_path / "h" / "camera.json").read_text())
    assert (cam["width"], cam["height"], cam["fx"], cam["fy"], cam["cx"], cam["cy"]) == (320, 200, 300, 1000, 160, 100)
    meta = json.loads((tmp_path / "h" / "meta.json").read_text())
    assert len(meta["hot_pixels"]) == 3 and all(0 <= x < 320 and 0 <= y < 200 for x, y in meta["hot_pixels"])
    capsys.readouterr()
    assert main(["info", str(tmp_path / "h")]) == 0
    out = capsys.readouterr().out
    assert "noise 0.5 Hz/pixel" in out and "3 hot pixels at 100 Hz" in out and "occluder none" in out
    assert "texture random (its model: mesh_textured.glb)" in out and (tmp_path / "h" / "mesh_textured.glb").is_file()
    assert main(["info", str(tmp_path / "d")]) == 0
    assert "texture none;" in capsys.readouterr().out


def test_wide_suite_dry_run_and_disjoint_splits(tmp_path):
    for split in ("dev", "test"):
        assert main(["synth-benchmark", "--suite", "wide", "--split", split, "--out", str(tmp_path / split),
                     "--dry-run"]) == 0
        assert sorted(p.name for p in (tmp_path / split).iterdir()) == ["suite.json"]
    dev = json.loads((tmp_path / "dev" / "suite.json").read_text())
    test = json.loads((tmp_path / "test" / "suite.json").read_text())
    assert dev["suite"] == "wide" and dev["split"] == "dev" and dev["seed_base"] == SPLIT_SEED_BASE["dev"]
    e = dev["sequences"]
    keys = {"name", "object", "motion", "camera", "noise_rate", "hot_pixels", "refractory_us", "occluder", "texture",
            "seed", "duration"}
    assert len(e) >= 32 and all(keys <= set(x) for x in e)
    assert len({x["name"] for x in e}) == len(e)
    objects = {x["object"] for x in e}
    assert len(objects) >= 10 and {"009_gelatin_box", "007_tuna_fish_can", "021_bleach_cleanser",
                                   "035_power_drill"} <= objects
    assert {x["motion"] for x in e} == {"regular", "fast", "turn", "mixed"}
    assert {x["camera"] for x in e} == {"davis346", "vga", "hd"}
    assert all(0.0 <= x["noise_rate"] <= 2.0 for x in e) and max(x["noise_rate"] for x in e) == 2.0
    assert all(0 <= x["refractory_us"] <= 100 for x in e) and any(x["hot_pixels"] > 0 for x in e)
    assert sum(x["occluder"] == "hand" for x in e) * 4 >= len(e)
    assert sum(x["texture"] == "random" for x in e) * 2 >= len(e)
    assert all(x["duration"] == 4.0 for x in e)
    assert not {x["seed"] for x in e} & {x["seed"] for x in test["sequences"]}
    assert [x["name"] for x in e] != [x["name"] for x in test["sequences"]]
    # a deterministic function of (split, seed base)
    assert wide_suite("dev") == e and wide_suite("dev", 7) != e and wide_suite("dev", 7) == wide_suite("test", 7)


def test_wide_suite_over_other_objects_keeps_every_other_factor(tmp_path, capsys, monkeypatch):
    """--objects swaps the objects only: a built-in name and a mesh file (given relative, stored absolute), each
    drawn 16 times, sized from their meshes, named by the name or the file's stem; motion, camera, noise, hand,
    texture and seed stay the split's."""
    import trimesh

    trimesh.creation.box(extents=(0.3, 0.2, 0.1)).export(tmp_path / "big_crate.ply")
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "novel"
    assert main(["synth-benchmark", "--suite", "wide", "--split", "dev", "--out", str(out), "--dry-run",
                 "--objects", "can", "big_crate.ply"]) == 0
    e = json.loads((out / "suite.json").read_text())["sequences"]
    base = wide_suite("dev")
    assert [{k: v for k, v in x.items() if k not in ("name", "object", "size")} for x in e] == \
        [{k: v for k, v in x.items() if k not in ("name", "object", "size")} for x in base]
    assert [x["name"].split("_", 2)[::2] for x in e] == [x["name"].split("_", 2)[::2] for x in base]
    crate = [x for x in e if x["object"] == str(tmp_path / "big_crate.ply")]
    can = [x for x in e if x["object"] == "can"]
    assert len(crate) == len(can) == 16
    assert all(x["size"] == "large" and x["name"].split("_")[1] == "big-crate" for x in crate)  # 0.37 m diagonal
    assert all(x["size"] == size_class(load_mesh("can").extents) and x["name"].split("_")[1] == "can" for x in can)
    for argv, message in ((["--objects", "can", "can"], "each object once"),
                          (["--objects", "no_such_thing"], "no_such_thing")):
        assert main(["synth-benchmark", "--suite", "wide", "--split", "dev", "--out", str(tmp_path / "x"),
                     "--dry-run"] + argv) == 2
        assert message in capsys.readouterr().err
    with pytest.raises(ValueError, match="1 to 32 objects"):
        wide_suite("dev", objects={f"obj{i}.ply": "small" for i in range(33)})
    assert main(["synth-benchmark", "--out", str(tmp_path / "s"), "--dry-run", "--objects", "can"]) == 2
    assert "--objects choose a split of --suite wide" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "s").exists()


def test_standard_suite_dry_run(tmp_path):
    assert main(["synth-benchmark", "--out", str(tmp_path), "--dry-run"]) == 0
    e = json.loads((tmp_path / "suite.json").read_text())["sequences"]
    assert sorted(x["name"] for x in e) == sorted(f"{o}_{m}" for o in ("cracker", "mustard", "potted", "tomato")
                                                  for m in ("regular", "fast"))
    assert {x["seed"] for x in e} == {1000 + 10 * i + j for i in range(4) for j in range(2)}
    assert all(x["camera"] == "vga" and x["noise_rate"] == 0 and x["occluder"] == "none" for x in e)


def test_wide_objects_size_classes():
    for name, size in WIDE_OBJECTS.items():
        assert size_class(load_mesh(name).extents) == size


def _cells(md: str, section: str) -> dict:
    """``{(value, method): [cells...]}`` of one section of the factor tables."""
    block = md.split(f"## {section}\n", 1)[1].split("\n## ", 1)[0]
    rows = [r.strip("| ").split(" | ") for r in block.splitlines() if r.startswith("| ") and "---" not in r][1:]
    return {(r[0], r[1]): r[2:] for r in rows}


def test_factor_tables_on_fake_results(tmp_path):
    vals = {  # sequence: (e_p cm, e_r deg, ADD-S AUC, failed)
        "a": (1.0, 2.0, 0.9, False), "b": (3.0, 4.0, 0.5, True), "c": (10.0, 30.0, 0.1, True),
        "d": (0.5, 1.0, 0.95, False),
    }
    results = {"results": {"full": {s: {"metrics": {"rmse_t_cm": v[0], "rmse_r_deg": v[1], "adds_auc": v[2],
                                                     "failed": v[3]}} for s, v in vals.items()}}}
    factors = {"a": {"motion": "turn", "hand": "none"}, "b": {"motion": "turn", "hand": "hand"},
               "c": {"motion": "fast", "hand": "hand"}, "d": {"motion": "regular", "hand": "none"}}
    md = factor_tables(results, factors, factors_order=("motion", "hand"))
    overall = _cells(md, "Overall")[("all", "full")]
    assert overall == ["4", f"{np.mean([1, 3, 10, 0.5]):.2f}", f"{np.median([1, 3, 10, 0.5]):.2f}",
                       f"{np.mean([2, 4, 30, 1]):.2f}", f"{100 * np.mean([0.9, 0.5, 0.1, 0.95]):.1f}", "2/4"]
    motion = _cells(md, "Motion group")
    assert set(motion) == {("fast", "full"), ("regular", "full"), ("turn", "full")}
    assert motion[("turn", "full")] == ["2", "2.00", "2.00", "3.00", "70.0", "1/2"]
    hand = _cells(md, "Hand")
    assert hand[("hand", "full")] == ["2", "6.50", "6.50", "17.00", "30.0", "2/2"]
    assert hand[("none", "full")][-1] == "0/2"


def test_factor_tables_count_every_draw_and_the_symmetry_rule():
    def run(t, r, auc, failed, sym=None):
        m = {"rmse_t_cm": t, "rmse_r_deg": r, "adds_auc": auc, "failed": failed}
        if sym is not None:  # (e_r with the spin left out, failed by that rule)
            m["rmse_r_sym_deg"], m["failed_sym"] = sym
        return m

    trials = {"can": [run(1.0, 50.0, 0.9, True, (3.0, False)), run(2.0, 60.0, 0.8, True, (4.0, True))],
              "box": [run(0.5, 2.0, 0.95, False), run(9.0, 45.0, 0.2, True)]}
    results = {"results": {"full": {s: {"metrics": r[0]} for s, r in trials.items()},
                           "learned": {"box": {"metrics": run(3.0, 10.0, 0.5, False)}}},
               "trials": {"full": trials}}
    md = factor_tables(results, {"can": {"motion": "turn"}, "box": {"motion": "turn"}}, factors_order=("motion",))
    assert "| value | method | runs |" in md and "failed, sym." in md
    every = [x for rs in trials.values() for x in rs]  # all four draws, not the first of each sequence
    t = [x["rmse_t_cm"] for x in every]
    assert _cells(md, "Overall")[("all", "full")] == [
        "4", f"{np.mean(t):.2f}", f"{np.median(t):.2f}", f"{np.mean([50, 60, 2, 45]):.2f}",
        f"{100 * np.mean([0.9, 0.8, 0.95, 0.2]):.1f}", "3/4", f"{np.mean([3, 4, 2, 45]):.2f}", "2/4"]
    # a method without trials (scored from pose files) counts its one run per sequence, whole rotation as sym.
    assert _cells(md, "Motion group")[("turn", "learned")] == ["1", "3.00", "3.00", "10.00", "50.0", "0/1", "10.00",
                                                                "0/1"]


def test_factor_tables_count_the_failures_the_lost_flags_caught():
    """Per factor value: failed runs detected by the flags / failed runs, in brackets those within 50 ms; a row with a
    run scored without flags (another tracker's poses) shows none."""
    def run(failed, delay_ms=None, missed=False):
        verdict = {"first_failure_us": 100_000 if failed else None, "missed": missed,
                   "delay_us": None if delay_ms is None else delay_ms * 1000}
        return {"rmse_t_cm": 1.0, "rmse_r_deg": 2.0, "adds_auc": 0.9, "failed": failed, "loss": verdict}

    trials = {"a": [run(True, 20), run(True, 80)], "b": [run(True, missed=True), run(False)],
              "c": [run(True, -30), run(False)]}
    factors = {"a": {"hand": "hand"}, "b": {"hand": "hand"}, "c": {"hand": "none"}}
    results = {"results": {"full": {s: {"metrics": r[0]} for s, r in trials.items()},
                           "learned": {s: {"metrics": r[0]} for s, r in trials.items()}},
               "trials": {"full": trials}}
    hand = _cells(factor_tables(results, factors, factors_order=("hand",)), "Hand")
    assert hand[("hand", "full")][-1] == "2/3 (1)" and hand[("none", "full")][-1] == "1/1 (1)"
    assert hand[("hand", "learned")][-1] == "–"


def test_factor_tables_cross_motion_and_camera():
    def run(failed, failed_sym=None):
        m = {"rmse_t_cm": 1.0, "rmse_r_deg": 2.0, "adds_auc": 0.9, "failed": failed}
        if failed_sym is not None:
            m["failed_sym"] = failed_sym
        return m

    trials = {"a": [run(False), run(True)], "b": [run(True, False), run(True, True)], "c": [run(False), run(False)]}
    factors = {"a": {"motion": "turn", "camera": "vga"}, "b": {"motion": "turn", "camera": "hd"},
               "c": {"motion": "fast", "camera": "vga"}}
    results = {"results": {"full": {s: {"metrics": r[0]} for s, r in trials.items()}}, "trials": {"full": trials}}
    md = factor_tables(results, factors, factors_order=("motion", "camera"))
    rows = _cells(md, "Held runs by motion group and camera")
    # columns hd, vga, all; b's first draw is held by the symmetry rule though failed whole
    assert rows[("turn", "full")] == ["1/2", "1/2", "2/4"] and rows[("fast", "full")] == ["–", "2/2", "2/2"]
    assert "Held runs by" not in factor_tables(results, factors, factors_order=("motion",))


def test_sequence_factors_from_suite_json_and_meta(tmp_path):
    d = tmp_path / "bench"
    assert main(["synth-benchmark", "--suite", "wide", "--split", "dev", "--out", str(d), "--dry-run"]) == 0
    first = json.loads((d / "suite.json").read_text())["sequences"][0]
    f = sequence_factors(d, [first["name"]])[first["name"]]
    assert f["motion"] == first["motion"] and f["camera"] == first["camera"] and f["size"] == first["size"]
    assert f["object"] == first["object"]
    # a sequence that suite.json does not list: from its own files
    seq = generate_sequence("can", "turn", 0.02, 0, CAM, occluder="hand", noise_rate_hz=1.5,
                            render_backend="raster", progress=False)
    seq.save(d / "extra")
    f = sequence_factors(d, ["extra"])["extra"]
    assert f == {"motion": "turn", "camera": "96x72", "noise": "high", "hand": "hand", "texture": "none",
                 "size": size_class(trimesh.load(d / "extra" / "mesh.ply").extents), "object": "can"}
    # --objects with a mesh file: the table's row is the file's stem
    trimesh.creation.box(extents=(0.1, 0.05, 0.05)).export(tmp_path / "my_part.ply")
    assert main(["synth-benchmark", "--suite", "wide", "--split", "dev", "--out", str(tmp_path / "mine"), "--dry-run",
                 "--objects", str(tmp_path / "my_part.ply")]) == 0
    name = json.loads((tmp_path / "mine" / "suite.json").read_text())["sequences"][0]["name"]
    assert sequence_factors(tmp_path / "mine", [name])[name]["object"] == "my_part"


def _inside_events(seq, erode: int = 3) -> int:
    """Events well inside the object's silhouette (eroded by ``erode`` px) at the ground-truth pose nearest each
    event's time."""
    from scipy.ndimage import binary_erosion

    ev = seq.events
    idx = np.clip(np.searchsorted(seq.gt_t_us.numpy(), ev.t.numpy()), 0, len(seq.gt_t_us) - 1)
    with make_renderer(seq.mesh, seq.camera, "raster") as r:
        masks = r.render(seq.gt_poses, shaded=False).depth.numpy() > 0
    masks = np.stack([binary_erosion(m, iterations=erode) for m in masks])
    return int(masks[idx, ev.y.numpy().astype(int), ev.x.numpy().astype(int)].sum())


@pytest.mark.parametrize("backend", ["pyrender", "raster"])
def test_texture_makes_events_inside_the_silhouette(tmp_path, backend):
    path = tmp_path / "plain_box.ply"  # no colours: without a texture only its shading changes inside
    trimesh.creation.box((0.06, 0.08, 0.1)).export(path)
    cam = Camera(160, 120, 150.0, 150.0, 80.0, 60.0)
    kw = dict(camera=cam, render_backend=backend, progress=False)
    plain = generate_sequence(str(path), "regular", 0.1, 4, **kw)
    printed = generate_sequence(str(path), "regular", 0.1, 4, texture="random", **kw)
    assert torch.equal(plain.gt_poses, printed.gt_poses)
    assert printed.meta["texture"] == {"kind": "random", "seed": 4} and "texture" not in plain.meta
    assert printed.mesh.visual.kind is None  # the saved mesh stays the geometry
    assert plain.textured_mesh is None and printed.textured_mesh.visual.kind == "texture"  # the print beside it
    corners = printed.textured_mesh.vertices[printed.textured_mesh.faces]  # the same triangles (vertices split)
    assert np.allclose(corners, printed.mesh.vertices[printed.mesh.faces])
    n_plain, n_printed = _inside_events(plain), _inside_events(printed)
    assert n_printed > 3 * max(n_plain, 100)
