"""Per-element re-initialisation: masked resets of the stages and of the tracker, and the tracker's loss
detector with its on_lost callback.

Oracle for a masked reset: the selected elements behave as in a module that was fully reset with the
same arguments, the others as in a module that was never reset; both fed the same inputs afterwards.
"""

import pytest
import torch

from torchevtrack import geometry as g
from torchevtrack.camera import Camera
from torchevtrack.stages import batch_mask
from torchevtrack.stages.eros import EROS
from torchevtrack.stages.flow import NEVER, TripletFlow
from torchevtrack.stages.ukf import PoseUKF
from torchevtrack.stages.velocity import VelocityKF

F64 = torch.float64
B = 3
MASK = torch.tensor([False, True, False])


def _events(gen, n, H, W, t0):
    x = torch.randint(0, W, (n,), generator=gen)
    y = torch.randint(0, H, (n,), generator=gen)
    t = t0 + torch.sort(torch.randint(0, 2000, (n,), generator=gen)).values
    p = torch.randint(0, 2, (n,), generator=gen)
    b = torch.randint(0, B, (n,), generator=gen)
    return x, y, t, p, b


def _buffers(m):
    return {k: v.clone() for k, v in m.named_buffers()}


def _check_rows(module, fresh, kept, names):
    """Rows of ``MASK`` equal ``fresh``'s, the other rows equal ``kept``'s, bit for bit."""
    for name in names:
        got, want_new, want_old = (getattr(m, name) for m in (module, fresh, kept))
        assert torch.equal(got[MASK], want_new[MASK]), name
        assert torch.equal(got[~MASK], want_old[~MASK]), name


def test_batch_mask_forms_and_errors():
    assert batch_mask(None, 3).tolist() == [True, True, True]
    assert batch_mask(torch.tensor([2, 0]), 3).tolist() == [True, False, True]
    assert batch_mask(torch.tensor([], dtype=torch.long), 2).tolist() == [False, False]
    assert batch_mask(MASK, 3) is MASK
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        batch_mask(torch.tensor([True, False]), 3)
    with pytest.raises(ValueError, match="indices"):
        batch_mask(torch.tensor([3]), 3)
    with pytest.raises(TypeError, match="bool"):
        batch_mask(torch.tensor([0.0]), 3)


@pytest.mark.parametrize("mask", [MASK, torch.tensor([1])])
def test_eros_masked_reset(mask):
    H, W = 20, 30
    gen = torch.Generator().manual_seed(0)
    before, after = _events(gen, 400, H, W, 0), _events(gen, 400, H, W, 2000)
    module, kept, fresh = (EROS(H, W, batch_size=B) for _ in range(3))
    for m in (module, kept):
        m(before[0], before[1], before[4])
    assert (module.surface.flatten(1) > 0).any(1).all()  # every element has something to clear
    module.reset(mask)
    assert (module.surface[1] == 0).all() and torch.equal(module.surface[~MASK], kept.surface[~MASK])
    for m in (module, kept, fresh):
        m(after[0], after[1], after[4])
    _check_rows(module, fresh, kept, ["surface"])


@pytest.mark.parametrize("per_polarity", [False, True])
def test_triplet_flow_masked_reset(per_polarity):
    H, W = 24, 30
    gen = torch.Generator().manual_seed(1)
    # Moving vertical edges give triplets; per element a different speed.
    def edges(k0, k1):
        xs, ys, ts, bs = [], [], [], []
        for k in range(k0, k1):
            for b in range(B):
                col = (k * (b + 1)) % W
                xs.append(torch.full((H,), col))
                ys.append(torch.arange(H))
                ts.append(torch.full((H,), 300 * k + 50 * b))
                bs.append(torch.full((H,), b))
        x, y, t, b = (torch.cat(v) for v in (xs, ys, ts, bs))
        order = torch.argsort(t, stable=True)
        p = torch.randint(0, 2, (len(x),), generator=gen)
        return x[order], y[order], t[order], p[order], b[order]

    before, after = edges(0, 12), edges(12, 20)
    module, kept, fresh = (TripletFlow(H, W, batch_size=B, block=10, min_samples=3, per_polarity=per_polarity)
                           for _ in range(3))
    for m in (module, kept):
        m(*before)
    module.reset(MASK)
    assert (module.sae[1] == NEVER).all() and torch.equal(module.sae[~MASK], kept.sae[~MASK])
    outs = [m(*after) for m in (module, kept, fresh)]
    _check_rows(module, fresh, kept, ["sae"])
    got, old, new = outs
    assert new.valid[1].any() and old.valid[0].any()  # flow was measured on both sides
    for field in ("count", "valid", "flow", "uv"):
        a, o, n = (getattr(f, field) for f in outs)
        assert torch.equal(a[MASK], n[MASK]) and torch.equal(a[~MASK], o[~MASK]), field
    assert not torch.equal(new.count[1], old.count[1])  # the reset element really forgot its history


def _velocity_step(kf, gen):
    G = 12
    uv = torch.rand(B, G, 2, dtype=F64, generator=gen) * torch.tensor([600.0, 440.0], dtype=F64) + 20.0
    depth = 0.3 + 0.5 * torch.rand(B, G, dtype=F64, generator=gen)
    flow = 300.0 * torch.randn(B, G, 2, dtype=F64, generator=gen)
    valid = torch.rand(B, G, generator=gen) < 0.8
    kf.predict()
    kf.update(uv, flow, depth, valid, 0.002)


def test_velocity_masked_reset():
    cam = Camera.default()
    twist = torch.randn(B, 6, dtype=F64, generator=torch.Generator().manual_seed(2))
    module, kept, fresh = (VelocityKF(cam, batch_size=B) for _ in range(3))
    gens = [torch.Generator().manual_seed(3) for _ in range(2)]
    for m, gen in zip((module, kept), gens):
        for _ in range(4):
            _velocity_step(m, gen)
    twist_nan = twist.clone()
    twist_nan[~MASK] = float("nan")  # rows of unselected elements are ignored
    module.reset(twist_nan, mask=MASK)
    fresh.reset(twist)
    assert torch.equal(module.x[1], twist[1]) and torch.equal(module.P[1], module.P0)
    _check_rows(module, fresh, kept, ["x", "P"])
    gens = [torch.Generator().manual_seed(4) for _ in range(3)]
    for m, gen in zip((module, kept, fresh), gens):
        for _ in range(3):
            _velocity_step(m, gen)
    _check_rows(module, fresh, kept, ["x", "P"])


def _ukf_step(ukf, gen):
    z = torch.cat((0.01 * torch.randn(B, 3, dtype=F64, generator=gen) + torch.tensor([0.0, 0.0, 0.5], dtype=F64),
                   g.quat_exp(0.05 * torch.randn(B, 3, dtype=F64, generator=gen))), -1)
    ukf.predict(0.002, 0.2 * torch.randn(B, 6, dtype=F64, generator=gen))
    ukf.update(z)


def test_ukf_masked_reset():
    gen = torch.Generator().manual_seed(5)
    pose = torch.cat((torch.tensor([[0.0, 0.0, 0.5]], dtype=F64).expand(B, 3),
                      g.quat_exp(0.3 * torch.randn(B, 3, dtype=F64, generator=gen))), -1)
    twist = torch.randn(B, 6, dtype=F64, generator=gen)
    module, kept, fresh = (PoseUKF(B) for _ in range(3))
    for m in (module, kept):
        m.reset(pose)
        for _ in range(4):
            _ukf_step(m, torch.Generator().manual_seed(6))
    fresh.reset(pose, twist)
    garbage = pose.clone()
    garbage[~MASK] = float("nan")
    module.reset(garbage, twist, mask=torch.tensor([1]))
    _check_rows(module, fresh, kept, ["x", "P"])
    for m in (module, kept, fresh):
        for _ in range(3):
            _ukf_step(m, torch.Generator().manual_seed(7))
    _check_rows(module, fresh, kept, ["x", "P"])
