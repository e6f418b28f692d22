"""Losses and metrics against brute-force references on random inputs."""

import numpy as np
import pytest
import torch

from empm_gym.identification import losses as L
from empm_gym.identification import render as R
from empm_gym.perception.cameras import Camera, intrinsics_matrix, look_at


def brute_chamfer(p, o, squared=False):
    def one_way(a, b):
        out = []
        for x in a:
            best = min(float(np.sum((x - y) ** 2)) for y in b)
            out.append(best if squared else np.sqrt(best))
        return np.mean(out)
    return one_way(p, o), one_way(o, p)


@pytest.mark.parametrize("squared", [False, True])
def test_chamfer_matches_double_loop(squared):
    rng = np.random.default_rng(0)
    p = rng.normal(size=(57, 3))
    o = rng.normal(size=(43, 3)) * 0.7 + 0.2
    po, op = brute_chamfer(p, o, squared)
    assert L.chamfer_numpy(p, o, squared=squared) == pytest.approx(0.5 * (po + op), rel=1e-10)
    assert L.chamfer_numpy(p, o, direction="pred_to_obs", squared=squared) == pytest.approx(po, rel=1e-10)
    assert L.chamfer_numpy(p, o, direction="obs_to_pred", squared=squared) == pytest.approx(op, rel=1e-10)
    t = L.chamfer_distance(torch.tensor(p), o, squared=squared)
    assert float(t) == pytest.approx(0.5 * (po + op), rel=1e-10)
    assert float(L.chamfer_distance(p, o, direction="obs_to_pred", squared=squared)) == pytest.approx(op, rel=1e-10)


def test_chamfer_gradient_matches_dense_autograd():
    rng = np.random.default_rng(1)
    p = torch.tensor(rng.normal(size=(300, 3)), requires_grad=True)
    o = torch.tensor(rng.normal(size=(200, 3)))
    L.chamfer_distance(p, o).backward()
    g_kd = p.grad.clone()
    p.grad = None
    d = torch.cdist(p, o)
    dense = 0.5 * (d.min(1).values.mean() + d.min(0).values.mean())
    dense.backward()
    assert torch.allclose(g_kd, p.grad, atol=1e-9)
    # gradient with respect to the observed set when it is the tensor that requires grad
    o2 = o.clone().requires_grad_(True)
    L.chamfer_distance(p.detach().numpy(), o2, direction="obs_to_pred").backward()
    o3 = o.clone().requires_grad_(True)
    torch.cdist(p.detach(), o3).min(0).values.mean().backward()
    assert torch.allclose(o2.grad, o3.grad, atol=1e-9)


def test_chamfer_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        L.chamfer_numpy(np.zeros((4, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="empty"):
        L.chamfer_distance(torch.zeros((0, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="direction"):
        L.chamfer_numpy(np.zeros((4, 3)), np.zeros((3, 3)), direction="sideways")


@pytest.mark.parametrize("direction", ["both", "obs_to_pred", "pred_to_obs"])
def test_chamfer_frames_on_padded_sets_matches_kd_trees(direction):
    """The all-pairs Chamfer of padded frames (the GPU path, run here on torch's CPU) equals the KD-tree one on
    ragged observed sets, the padding ignored; the small pair budget forces several chunks of frames."""
    rng = np.random.default_rng(3)
    pred = rng.normal(size=(5, 40, 3)) * 0.05
    obs = [rng.normal(size=(n, 3)) * 0.05 + 0.01 for n in (7, 33, 1, 60, 12)]
    want = [L.chamfer_numpy(p, o, direction=direction) for p, o in zip(pred, obs)]
    padded = L.PaddedFrames(obs, torch.device("cpu"))
    got = L.chamfer_frames(pred, padded, direction=direction, max_pairs=2 * 40 * 60)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(L.chamfer_frames(pred, obs, direction=direction, device="cpu"), want, rtol=0, atol=0)
    assert L.pad_frames(obs, "cpu") is None  # the CPU keeps its KD-trees
    with pytest.raises(ValueError, match="empty observed point set in frame 1"):
        L.PaddedFrames([obs[0], np.zeros((0, 3))], torch.device("cpu"))
    with pytest.raises(ValueError, match="pred must be"):
        L.chamfer_frames(pred[:3], padded)


@pytest.mark.parametrize("direction", ["both", "obs_to_pred", "pred_to_obs"])
def test_differentiable_chamfer_frames_match_chamfer_distance(direction):
    """The differentiable all-pairs Chamfer of padded frames (Adam's loss on the GPU, here on torch's CPU) has
    the value and the gradient of :func:`chamfer_distance` frame by frame, over several chunks of frames."""
    rng = np.random.default_rng(5)
    pred = rng.normal(size=(4, 30, 3)) * 0.05
    obs = [rng.normal(size=(n, 3)) * 0.05 for n in (9, 1, 41, 20, 17)]  # frame 0 is skipped (first=1)
    ref = torch.tensor(pred, requires_grad=True)
    want = torch.stack([L.chamfer_distance(ref[t], obs[t + 1], direction=direction) for t in range(4)])
    (want * torch.arange(1.0, 5.0, dtype=torch.float64)).sum().backward()
    got_p = torch.tensor(pred, requires_grad=True)
    got = L.chamfer_frames_torch(got_p, L.PaddedFrames(obs, torch.device("cpu")), direction=direction, first=1,
                                 max_pairs=30 * 41)
    (got * torch.arange(1.0, 5.0, dtype=torch.float64)).sum().backward()
    np.testing.assert_allclose(got.detach().numpy(), want.detach().numpy(), rtol=1e-12)
    np.testing.assert_allclose(got_p.grad.numpy(), ref.grad.numpy(), rtol=1e-9, atol=1e-12)
    assert torch.count_nonzero(got_p.grad) > 0


def test_tracking_loss_ignores_occluded_points():
    rng = np.random.default_rng(2)
    pred = torch.tensor(rng.normal(size=(5, 7, 3)), requires_grad=True)
    tgt = rng.normal(size=(5, 7, 3))
    vis = rng.random((5, 7)) > 0.4
    tgt_far = tgt.copy()
    tgt_far[~vis] += 100.0  # occluded targets must not matter
    val = L.tracking_loss(pred, tgt_far, vis)
    ref = np.mean([np.sum((pred.detach().numpy()[t, j] - tgt[t, j]) ** 2) for t in range(5) for j in range(7) if vis[t, j]])
    assert float(val.detach()) == pytest.approx(ref, rel=1e-10)
    val.backward()
    assert torch.all(pred.grad[torch.as_tensor(~vis)] == 0)
    assert torch.any(pred.grad[torch.as_tensor(vis)] != 0)
    err = np.mean([np.linalg.norm(pred.detach().numpy()[t, j] - tgt[t, j]) for t in range(5) for j in range(7) if vis[t, j]])
    assert L.tracking_error(pred, tgt_far, vis) == pytest.approx(err, rel=1e-10)
    assert np.isnan(L.tracking_error(pred, tgt, np.zeros((5, 7), bool)))


def test_mask_iou_matches_set_logic():
    rng = np.random.default_rng(3)
    for _ in range(5):
        a = rng.random((31, 23)) > 0.6
        b = rng.random((31, 23)) > 0.5
        sa = {tuple(x) for x in np.argwhere(a)}
        sb = {tuple(x) for x in np.argwhere(b)}
        assert L.mask_iou(a, b) == pytest.approx(len(sa & sb) / len(sa | sb), rel=1e-12)
    assert L.mask_iou(np.zeros((3, 3)), np.zeros((3, 3))) == 1.0
    with pytest.raises(ValueError, match="shapes differ"):
        L.mask_iou(np.zeros((3, 3)), np.zeros((3, 4)))


def _camera(W=64, H=48):
    return Camera(intrinsics_matrix(60.0, 60.0, W / 2 - 0.5, H / 2 - 0.5), look_at((0.4, -0.3, 0.5), (0, 0, 0.03)), W, H)


def test_splat_mask_matches_per_pixel_loop():
    cam = _camera()
    rng = np.random.default_rng(4)
    pts = rng.uniform(-0.08, 0.08, size=(40, 3))
    radius = 0.006
    for ds in (1, 2):
        m = R.splat_mask(pts, cam, radius, ds)
        K = R.scaled_intrinsics(cam.K, ds)
        w2c = np.linalg.inv(cam.c2w)
        pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        f = 0.5 * (K[0, 0] + K[1, 1])
        ref = np.zeros_like(m)
        for (x, y, z) in pc:
            row, col = K[1, 1] * y / z + K[1, 2], K[0, 0] * x / z + K[0, 2]
            r = np.clip(f * radius / z, 0.5, 12)
            for i in range(ref.shape[0]):
                for j in range(ref.shape[1]):
                    if (i - row) ** 2 + (j - col) ** 2 <= r * r:
                        ref[i, j] = True
        assert m.sum() > 20
        assert np.array_equal(m, ref)


def test_splat_depth_keeps_the_nearest_point():
    cam = _camera()
    centre = np.array([0.0, 0.0, 0.03])
    towards = (cam.position - centre) / np.linalg.norm(cam.position - centre)
    pts = np.stack([centre, centre + 0.05 * towards])  # the second point hides the first
    depth, owner = R.splat_depth(pts, cam, 0.01)
    hit = owner >= 0
    assert hit.any()
    assert np.all(owner[hit] == 1)
    assert np.all(depth[~hit] == np.inf)
    img, cov = R.render_colors(pts, np.array([[1, 0, 0], [0, 1, 0]]), cam, 0.01, np.zeros((48, 64, 3)))
    assert np.array_equal(cov, hit) and np.all(img[cov] == [0, 1, 0]) and np.all(img[~cov] == 0)


def test_soft_mask_tracks_binary_mask_and_has_gradients():
    cam = _camera()
    rng = np.random.default_rng(5)
    pts = torch.tensor(rng.uniform(-0.05, 0.05, size=(60, 3)), requires_grad=True)
    soft = R.soft_mask(pts, cam, 0.006, 2)
    hard = R.splat_mask(pts.detach().numpy(), cam, 0.006, 2)
    assert soft.shape == hard.shape
    soft = soft.detach()
    assert float(soft[torch.as_tensor(hard)].mean()) > 0.8
    assert float(soft[torch.as_tensor(~hard)].mean()) < 0.1
    # shifting the target mask sideways must pull the points towards it
    target = np.roll(hard, 3, axis=1)
    loss = L.soft_mask_loss(pts, [cam], [target], 0.006, 2)
    loss.backward()
    step = pts.detach() - 1e-3 * pts.grad / pts.grad.abs().max()
    assert float(L.soft_mask_loss(step, [cam], [target], 0.006, 2)) < float(loss.detach())


def test_downsample_mask():
    m = np.zeros((8, 8), np.uint8)
    m[:4, :2] = 255
    d = R.downsample_mask(m, 2)
    assert d.shape == (4, 4)
    assert d[:2, 0].all() and not d[:, 1:].any() and not d[2:, 0].any()


def test_psnr_and_ssim():
    rng = np.random.default_rng(6)
    a = rng.random((20, 20))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    mse = np.mean((a - b) ** 2)
    assert L.psnr(a, b) == pytest.approx(10 * np.log10(1 / mse))
    assert L.psnr(a, a) == float("inf")
    assert L.ssim(a, a) == pytest.approx(1.0)
    # brute-force SSIM over the pixels whose 11 x 11 Gaussian window lies inside the image
    sigma, r = 1.5, 5
    w1 = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    w1 /= w1.sum()
    w = np.outer(w1, w1)
    n = (2 * r + 1) ** 2
    vals = []
    for i in range(r, 20 - r):
        for j in range(r, 20 - r):
            pa, pb = a[i - r:i + r + 1, j - r:j + r + 1], b[i - r:i + r + 1, j - r:j + r + 1]
            ma, mb = np.sum(w * pa), np.sum(w * pb)
            va = n / (n - 1) * (np.sum(w * pa * pa) - ma**2)
            vb = n / (n - 1) * (np.sum(w * pb * pb) - mb**2)
            cab = n / (n - 1) * (np.sum(w * pa * pb) - ma * mb)
            c1, c2 = 0.01**2, 0.03**2
            vals.append((2 * ma * mb + c1) * (2 * cab + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    assert L.ssim(a, b) == pytest.approx(np.mean(vals), rel=1e-9)
    c = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    assert L.ssim(a, c) < L.ssim(a, b) < 1.0
    rgb = np.stack([a, b, c], -1)
    assert L.ssim(rgb, rgb) == pytest.approx(1.0)
