"""Pinhole projection and back-projection against analytic scenes (plane, sphere), and the renderer."""

import numpy as np
import pytest

from empm_gym.perception.cameras import Camera, backproject_depth, intrinsics_matrix, look_at, project_points


@pytest.fixture
def cam():
    K = intrinsics_matrix(120.0, 110.0, 79.5, 59.0)
    return Camera(K, look_at([0.4, -0.3, 0.35], [0.0, 0.0, 0.02]), 160, 120)


def test_look_at_opencv_convention(cam):
    rc, z = cam.project(np.array([[0.0, 0.0, 0.02], [0.0, 0.0, 0.12]]))
    np.testing.assert_allclose(rc[0], [59.0, 79.5], atol=1e-9)  # target at the principal point
    assert z[0] == pytest.approx(np.linalg.norm([0.4, -0.3, 0.33]))
    assert rc[1, 0] < rc[0, 0]  # world up is image up (smaller row)
    R = cam.c2w[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_project_backproject_round_trip(cam):
    rng = np.random.default_rng(0)
    pts = rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.1], (50, 3))
    rc, z = project_points(pts, cam.K, cam.c2w)
    # put each point's exact depth at a synthetic sub-pixel location: invert by hand
    x = (rc[:, 1] - cam.K[0, 2]) / cam.K[0, 0] * z
    y = (rc[:, 0] - cam.K[1, 2]) / cam.K[1, 1] * z
    back = np.stack([x, y, z], 1) @ cam.c2w[:3, :3].T + cam.c2w[:3, 3]
    np.testing.assert_allclose(back, pts, atol=1e-12)


def _plane_depth(cam, normal, offset):
    o, d = cam.world_rays()
    s = -(o @ normal + offset) / (d @ normal)
    return np.where(s > 0, s, 0.0)


def test_backprojected_plane_lies_on_plane(cam):
    n = np.array([0.1, -0.05, 1.0])
    n /= np.linalg.norm(n)
    depth = _plane_depth(cam, n, -0.01)
    assert np.all(depth > 0)
    pts = cam.backproject(depth)
    assert pts.shape == (160 * 120, 3)
    np.testing.assert_allclose(pts @ n - 0.01, 0.0, atol=1e-12)


def test_backprojected_sphere_and_mask(cam):
    c, r = np.array([0.02, -0.01, 0.05]), 0.04
    o, d = cam.world_rays()
    oc = o - c
    a = np.einsum("ijk,ijk->ij", d, d)
    b = 2 * d @ oc
    disc = b * b - 4 * a * (oc @ oc - r * r)
    hit = disc >= 0
    s = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0))) / (2 * a), 0.0)
    assert 200 < hit.sum() < 160 * 120 / 2
    pts, pix = backproject_depth(s, cam.K, cam.c2w, mask=hit, return_pixels=True)
    assert len(pts) == hit.sum()
    np.testing.assert_allclose(np.linalg.norm(pts - c, axis=1), r, atol=1e-12)
    # the front cap: every point is closer to the camera than the centre
    assert np.all(np.linalg.norm(pts - cam.position, axis=1) < np.linalg.norm(c - cam.position))
    # masked-out pixels never contribute
    partial = hit.copy()
    partial[:60] = False
    assert len(cam.backproject(s, partial)) == partial.sum()
    # depth range limits
    assert len(cam.backproject(s, hit, max_depth_m=0.0)) == 0


def test_backproject_rejects_bad_shapes(cam):
    with pytest.raises(ValueError, match="depth shape"):
        cam.backproject(np.ones((10, 10)))
    with pytest.raises(ValueError, match="mask shape"):
        backproject_depth(np.ones((4, 4)), cam.K, cam.c2w, mask=np.ones((3, 4), bool))


def test_renderer_sphere_and_table_are_metric(cam):
    """The synthesiser's renderer: back-projected table pixels lie at z = 0, sphere pixels at radius r."""
    from empm_gym.perception.synth import _StaticView, render_view

    view = _StaticView(cam)
    c, r = np.array([0.0, 0.0, 0.05]), 0.03
    ee = [{"shape": "sphere", "pos": c, "rot": np.eye(3), "radius": r, "half_extents": (0, 0, 0)}]
    depth, color, label, cosv = render_view(view, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), 0.001, ee)
    finite = np.where(np.isfinite(depth), depth, 0.0)
    table = cam.backproject(finite, label == 0)
    sphere = cam.backproject(finite, label == 2)
    assert len(table) > 1000 and len(sphere) > 100
    np.testing.assert_allclose(table[:, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(sphere - c, axis=1), r, atol=1e-9)
    assert color.min() >= 0 and color.max() <= 1 and np.all((cosv >= 0) & (cosv <= 1 + 1e-9))


def test_renderer_box_is_metric(cam):
    from empm_gym.perception.synth import _StaticView, render_view

    c, he = np.array([0.01, 0.0, 0.03]), np.array([0.02, 0.03, 0.025])
    ee = [{"shape": "box", "pos": c, "rot": np.eye(3), "radius": 0.0, "half_extents": he}]
    depth, _, label, _ = render_view(_StaticView(cam), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                                     0.001, ee)
    pts = cam.backproject(np.where(np.isfinite(depth), depth, 0.0), label == 2)
    assert len(pts) > 100
    local = np.abs(pts - c)
    # on the surface: inside the box and on at least one face
    assert np.all(local <= he + 1e-9)
    np.testing.assert_allclose(np.max(local / he, axis=1), 1.0, atol=1e-9)
