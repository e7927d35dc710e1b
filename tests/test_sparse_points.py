"""Sparse points from images + known poses (fmapping.sparse_points): ray intersection, the scene box of a
synthetic room whose extent is known, state round trip; and the sparse depth term of the mapper."""
import io

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from fmapping.camera import PinholeCamera
from fmapping.field import FieldConfig, build_field
from fmapping.losses import sparse_depth_loss
from fmapping.render import composite, raw_to_alpha, sample_deltas
from fmapping.sampling import stratified
from fmapping.sparse_points import (SparsePointsConfig, TrackTriangulator, aabb_from_points, fill_depths,
                                    triangulate_rays)
from fmapping.synthetic import camera_for_size, gt_cloud, make_scene, make_trajectory, render_view, visible_mask


pytestmark = pytest.mark.usefixtures("one_thread")


def test_triangulate_rays_meets_known_points():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (50, 3)) + [0, 0, 3]
    centres = rng.uniform(-0.3, 0.3, (50, 4, 3))
    dirs = (x[:, None] - centres) * rng.uniform(0.5, 2.0, (50, 4, 1))  # any length
    valid = np.ones((50, 4), bool)
    valid[:10, 3] = False
    dirs[:10, 3] = [1.0, 0.0, 0.0]  # an invalid ray pointing elsewhere must not count
    np.testing.assert_allclose(triangulate_rays(centres, dirs, valid), x, atol=1e-9)
    # parallel rays: no intersection
    par = triangulate_rays(np.array([[[0, 0, 0], [1, 0, 0]]], float), np.array([[[0, 0, 1], [0, 0, 1]]], float),
                           np.ones((1, 2), bool))
    assert np.isnan(par).all()


def test_aabb_from_points_robust_and_with_centres():
    rng = np.random.default_rng(1)
    pts = rng.uniform([-2, -1, 0], [3, 2, 2.5], (5000, 3))
    pts[:10] = [50.0, 50.0, 50.0]  # outliers (0.2 %) are cut by the 0.5 % percentile
    box = aabb_from_points(pts, centres=np.array([[0.0, 0.0, 4.0]]), margin=0.1, rel_margin=0.0)
    np.testing.assert_allclose(box[0], [-2 - 0.1, -1 - 0.1, 0 - 0.1], atol=0.1)
    np.testing.assert_allclose(box[1], [3 + 0.1, 2 + 0.1, 4.0 + 0.1], atol=0.1)  # z reaches the camera
    assert aabb_from_points(pts[:10]) is None


@pytest.fixture(scope="module")
def room_frames():
    scene = make_scene(0)
    cam = camera_for_size(160, 120)
    c2w = make_trajectory(scene, 60, 0)
    views = [render_view(scene, cam, p, supersample=1) for p in c2w]
    return scene, cam, c2w, views


def test_box_from_tracks_of_a_room_with_known_extent(room_frames):
    """KLT tracks of 60 frames triangulated with the GT poses lie on the room's surfaces, and their
    box covers what the cameras saw without reaching far past the room (the frusta would: 6 m)."""
    scene, cam, c2w, views = room_frames
    tri = TrackTriangulator(cam)
    for i, (rgb, _) in enumerate(views):
        tri.add(i, rgb, c2w[i])
    tri.flush()
    assert len(tri.points) > 500
    gt, _, _ = gt_cloud(scene, max_points=200_000, seed=0)
    dist, _ = cKDTree(gt).query(tri.points)
    # measured: median 3.0 cm, 90 % within 7.3 cm (160x120 frames, GT poses; the GT cloud's own spacing is ~2 cm)
    assert np.median(dist) < 0.04 and np.percentile(dist, 90) < 0.10, (np.median(dist), np.percentile(dist, 90))
    box = aabb_from_points(tri.points, c2w[:, :3, 3])
    seen = np.zeros(len(gt), bool)
    for p, (_, dep) in zip(c2w[::3], views[::3]):
        seen |= visible_mask(cam, p, dep, gt, tol=0.03)
    inside = ((gt[seen] >= box[0]) & (gt[seen] <= box[1])).all(1).mean()
    lo, hi = scene.bbox()
    assert inside > 0.97, inside
    # past the true room by at most 20 % of its extent on any side (the margin is 10 % of the points' extent;
    # measured: 0.84 m on x for a 5.0 m room); the frusta of these views would reach 6 m past the cameras
    pad = 0.2 * (hi - lo)
    assert (box[0] > lo - pad).all() and (box[1] < hi + pad).all(), (box, lo, hi)


def _degraded(rgb: np.ndarray, seed: int) -> np.ndarray:
    """A blurred (3x3 box), noisy (sigma 10 grey levels) copy of a frame: tracks drift on it."""
    x = rgb.astype(np.float64)
    pad = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
    blur = sum(pad[i:i + x.shape[0], j:j + x.shape[1]] for i in range(3) for j in range(3)) / 9.0
    noisy = blur + np.random.default_rng(seed).normal(0.0, 10.0, x.shape)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def test_point_weights_follow_the_depth_error(room_frames):
    """A point's weight comes from its reprojection residual and parallax: on frames degraded by blur
    and noise the tracks drift, the points land farther from the true surface and their weights fall;
    within one run the weight still ranks the points by their error."""
    scene, cam, c2w, views = room_frames
    gt, _, _ = gt_cloud(scene, max_points=200_000, seed=0)
    tree = cKDTree(gt)
    runs = {}
    degraded = [_degraded(v[0], i) for i, v in enumerate(views)]
    for name, frames in (("clean", [v[0] for v in views]), ("degraded", degraded)):
        tri = TrackTriangulator(cam)
        for i, rgb in enumerate(frames):
            tri.add(i, rgb, c2w[i])
        tri.flush()
        z = np.array([np.linalg.norm(p - c2w[:, :3, 3], axis=1).min() for p in tri.points])
        runs[name] = (tri.weights, tree.query(tri.points)[0] / z)
    (w_c, e_c), (w_d, e_d) = runs["clean"], runs["degraded"]
    # measured (160x120): median error 1.8 % -> 2.7 % of the distance, median weight 0.54 -> 0.14
    assert np.median(e_d) > 1.3 * np.median(e_c), (np.median(e_c), np.median(e_d))
    assert np.median(w_d) < 0.5 * np.median(w_c), (np.median(w_c), np.median(w_d))
    for w, e in ((w_c, e_c), (w_d, e_d)):
        hi = w >= np.median(w)
        assert np.median(e[hi]) < np.median(e[~hi]), (np.median(e[hi]), np.median(e[~hi]))
    assert ((w_c > 0) & (w_c <= 1)).all() and ((w_d > 0) & (w_d <= 1)).all()


def test_frame_depths_follow_the_frame_pose(room_frames):
    _, cam, c2w, views = room_frames
    tri = TrackTriangulator(cam)
    for i in range(12):
        tri.add(i, views[i][0], c2w[i])
    tri.flush()
    uv, z, w = tri.frame_depths(5)
    assert len(z) > 50 and (w > 0).all() and (w <= 1).all()
    gt_depth = views[5][1][np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
    ok = gt_depth > 0
    rel = np.abs(z[ok] - gt_depth[ok]) / gt_depth[ok]
    assert np.median(rel) < 0.02, np.median(rel)
    # every frame's pixels pair with their own points: lifted at their depth, each lands on a triangulated point
    # within the reprojection tolerance (a pixel paired with another track's point would be centimetres off)
    from scipy.spatial import cKDTree

    tree = cKDTree(tri.points)
    for f in range(12):
        uv_f, z_f, _ = tri.frame_depths(f)
        cam_pts = np.stack([(uv_f[:, 0] - cam.cx) / cam.fx * z_f, (uv_f[:, 1] - cam.cy) / cam.fy * z_f, z_f], -1)
        lifted = cam_pts @ c2w[f][:3, :3].T + c2w[f][:3, 3]
        tol = tri._reproj / cam.fx * z_f
        assert (tree.query(lifted)[0] <= tol * 1.001 + 1e-9).all(), f
    assert tri.depth_quantile(5) == pytest.approx(np.median(z), abs=1e-12)
    # a new pose for frame 5 moves its sparse depths with it (1 m back along the optical axis), and the
    # remembered median depth with them
    moved = c2w[5].copy()
    moved[:3, 3] -= moved[:3, 2]
    tri.set_poses({5: moved})
    _, z2, _ = tri.frame_depths(5)
    np.testing.assert_allclose(z2, z + 1.0, atol=1e-9)
    assert tri.depth_quantile(5) == pytest.approx(np.median(z) + 1.0, abs=1e-9)
    assert np.isnan(tri.depth_quantile(5, min_points=len(z) + 1))


def test_state_round_trip_continues_identically(room_frames):
    _, cam, c2w, views = room_frames
    a = TrackTriangulator(cam, SparsePointsConfig(max_track=6))
    for i in range(10):
        a.add(i, views[i][0], c2w[i])
    state = a.state_dict()
    buf = io.BytesIO()
    torch.save(state, buf)  # as a mapper checkpoint does, read back as it does
    b = TrackTriangulator(cam, SparsePointsConfig(max_track=6))
    b.load_state_dict(torch.load(io.BytesIO(buf.getvalue()), weights_only=True))
    # a checkpoint written before the packing (one tensor per observation, pose and frame) loads the same
    legacy = dict(state)
    legacy["obs"] = [[(int(f), torch.as_tensor(uv)) for f, uv in o] for o in a._obs]
    legacy["poses"] = {int(k): torch.from_numpy(v.copy()) for k, v in a._poses.items()}
    legacy["frame_obs"] = {int(k): (torch.from_numpy(i.copy()), torch.from_numpy(uv.copy()))
                           for k, (i, uv) in a._frame_obs.items()}
    del legacy["gain"]
    c = TrackTriangulator(cam, SparsePointsConfig(max_track=6))
    c.load_state_dict(legacy)
    c._gain = a._gain  # the old form did not keep the exposure ratio
    assert sum(len(o) for o in a._obs) > 100 and len(a._frame_obs) >= 5  # something to pack
    for t in (a, b, c):
        for i in range(10, 16):
            t.add(i, views[i][0], c2w[i])
        t.flush()
    for t in (b, c):
        np.testing.assert_array_equal(a.points, t.points)
        np.testing.assert_array_equal(a.frame_depths(12)[1], t.frame_depths(12)[1])


# ------------------------------------------------------------------ the sparse depth term
def _render(field, o, d, tn, tf, n=64, perturb=False, gen=None):
    t = stratified(tn, tf, n, perturb=perturb, generator=gen)
    xyz = o[:, None] + t[..., None] * d[:, None]
    raw = field.density_raw(xyz.reshape(-1, 3)).view(len(o), n)
    alpha = raw_to_alpha(raw, sample_deltas(t, d.norm(dim=-1)), field.cfg.alpha_mode, field.cfg.density_shift)
    return composite(alpha, t, None, None)


def test_sparse_depth_term_pulls_a_field_onto_a_plane():
    """From an empty field, only the sparse depth term: rays through sparse points at z = 1.5 m
    end on the plane z = 1.5, also between the points (the field is continuous)."""
    cam = PinholeCamera(60.0, 60.0, 31.5, 23.5, 64, 48)
    field = build_field(FieldConfig(resolution=48), [[-1.2, -1.0, 0.0], [1.2, 1.0, 2.5]])
    opt = torch.optim.Adam(field.grid_parameters(), lr=0.05)
    gen = torch.Generator().manual_seed(0)
    c2w = torch.eye(4)
    z_plane = 1.5
    for _ in range(150):
        uv = torch.rand(128, 2, generator=gen) * torch.tensor([63.0, 47.0])
        o, d = cam.rays(c2w.expand(128, 4, 4), uv)
        tn, tf = torch.full((128,), 0.1), torch.full((128,), 2.5)
        out = _render(field, o, d, tn, tf, perturb=True, gen=gen)
        loss = sparse_depth_loss(out.weights, out.t, out.acc, tf, torch.full((128,), z_plane), torch.ones(128))
        opt.zero_grad()
        loss.backward()
        opt.step()
    uv = cam.pixel_grid()[::7]
    o, d = cam.rays(c2w.expand(len(uv), 4, 4), uv)
    with torch.no_grad():
        out = _render(field, o, d, torch.full((len(uv),), 0.1), torch.full((len(uv),), 2.5), n=128)
    depth = out.depth / out.acc.clamp_min(1e-6)
    assert out.acc.min() > 0.9, float(out.acc.min())
    assert (depth - z_plane).abs().median() < 0.03, float((depth - z_plane).abs().median())


def test_sparse_depth_loss_bounds_outliers_and_weights():
    t = torch.linspace(0.1, 4.0, 40).expand(3, 40)
    w = torch.zeros(3, 40)
    w[:, 19] = 1.0  # all rays end at t[19] = 2.0
    acc = w.sum(-1)
    tf = torch.full((3,), 4.0)
    z = torch.tensor([2.0, 1.0, 40.0])
    per = torch.tensor([0.0, 1.0, 38.0 / 40.0])  # |2 - z| / z per ray
    pw = torch.tensor([1.0, 1.0, 2.0])
    got = sparse_depth_loss(w, t, acc, tf, z, pw, cap=0.5)
    want = (per / (1 + per / 0.5) * pw).sum() / 3  # over the number of rays, not the weights' sum
    torch.testing.assert_close(got, want)
    assert float(sparse_depth_loss(w, t, acc, tf, z, torch.zeros(3))) == 0.0
    # points that are all doubtful pull weakly: a tenth of the weights, a tenth of the term
    torch.testing.assert_close(sparse_depth_loss(w, t, acc, tf, z, 0.1 * pw, cap=0.5), 0.1 * want)


def test_seen_depth_box_holds_what_the_camera_saw_at_its_points_depth():
    """A camera looking down +z whose points lie 3 m away saw its whole image out to 3 m: the box holds
    that frustum's far corners (a plain upper wall without points still counts); a frame with too few
    points takes the others' median cut."""
    from fmapping.sparse_points import seen_depth_box

    cam = PinholeCamera(100.0, 100.0, 49.5, 39.5, 100, 80)
    a, b = np.eye(4), np.eye(4)
    b[:3, 3] = [1.0, 0.0, 0.0]
    box = seen_depth_box(np.stack([a, b]), [np.full(50, 3.0), np.full(3, 9.0)], cam)
    half_w, half_h = 50.0 / 100.0 * 3.0, 40.0 / 100.0 * 3.0  # corner rays at the pixel edges, 3 m out
    np.testing.assert_allclose(box, [[-half_w, -half_h, 0.0], [1.0 + half_w, half_h, 3.0]], atol=1e-9)
    assert seen_depth_box(np.stack([a]), [np.zeros(0)], cam) is None


@pytest.mark.slow
def test_fill_depths_is_exact_on_a_plane_and_skips_depth_edges():
    """Points on a tilted plane: the filled grid depths are the plane's own depths (inverse depth is
    affine in the pixel on a plane); a second plane 2x farther on the right half: triangles that span
    both are refused, so no filled depth lies between the two planes."""
    cam = PinholeCamera(100.0, 100.0, 79.5, 59.5, 160, 120)
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [160, 120], (300, 2))
    # plane n . X = 1 in the camera frame, n = (0.1, 0.05, 0.5): depth z = 1 / (n . (x, y, 1))
    n = np.array([0.1, 0.05, 0.5])

    def plane_z(p, scale=1.0):
        ray = np.stack([(p[:, 0] - cam.cx) / cam.fx, (p[:, 1] - cam.cy) / cam.fy, np.ones(len(p))], -1)
        return scale / (ray @ n)

    z = plane_z(uv)
    w = rng.uniform(0.5, 1.0, len(z))
    px, fz, fw = fill_depths(uv, z, w, 160, 120, step=4.0, max_edge_px=40.0, max_ratio=1.5)
    assert len(fz) > 0.8 * (40 * 30)  # most of the image lies inside small triangles
    np.testing.assert_allclose(fz, plane_z(px), rtol=1e-9)
    assert np.all((fw >= 0.5) & (fw <= 1.0))
    # right half twice as far: a depth edge at u = 80
    right = uv[:, 0] > 80
    z2 = np.where(right, 2 * z, z)
    px, fz, _ = fill_depths(uv, z2, w, 160, 120, step=4.0, max_edge_px=40.0, max_ratio=1.5)
    near, far = plane_z(px), 2 * plane_z(px)
    on_near = np.isclose(fz, near, rtol=1e-9)
    on_far = np.isclose(fz, far, rtol=1e-9)
    assert np.all(on_near | on_far)
    assert on_near.sum() > 100 and on_far.sum() > 100
    # long triangles are refused: with 5 points nothing is filled at a 10 px edge limit
    px, fz, _ = fill_depths(uv[:5], z[:5], w[:5], 160, 120, step=4.0, max_edge_px=10.0, max_ratio=1.5)
    assert len(fz) == 0


def test_a_box_guessed_from_the_frusta_gives_way_to_the_points_box(room_frames):
    """A camera that only turns on the spot for the init has no points to bound the scene: the box is the
    frusta's near..far guess (6 m past the camera). Once the camera moves and points triangulate, the first
    window's box is the points box, inside the guess and around the room, not the guess grown further."""
    from fmapping.mapping import Mapper, MapperConfig

    scene, cam, c2w, views = room_frames
    lo, hi = scene.bbox()
    cfg = MapperConfig(init_frames=8, init_iters_per_round=1, init_rays_per_iter=64, iters_per_window=1,
                       rays_per_iter=64, n_coarse=8, n_fine=4, final_global_iters=0, pc_weight=0.0, warp_weight=0.0,
                       device="cpu")
    m = Mapper(cfg, cam)
    for k in range(cfg.init_frames):  # turning on the spot at the first pose: 1.5 deg a frame about the camera's y
        a = np.radians(1.5 * k)
        turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        p = c2w[0].copy()
        p[:3, :3] = c2w[0][:3, :3] @ turn
        m.add_frame(render_view(scene, cam, p, supersample=1)[0], p)
    assert m.initialized
    guess = m.aabb.numpy().copy()
    assert (guess[1] - guess[0]).max() > 6.0, guess  # the frusta out to far = 6 m
    first = None
    for i in range(1, 40):
        m.add_frame(views[i][0], c2w[i])
        if first is None and m.stats()["box_refits"] == 1:
            first = m.aabb.numpy().copy()
    assert first is not None, "the box was never re-fitted to the points"
    # the first points box cuts the guess down (not grown past it) ...
    assert np.prod(first[1] - first[0]) < 0.25 * np.prod(guess[1] - guess[0]), (first, guess)
    # ... and the box ends around the room (5.0 x 4.2 x 3.0 m), grown with the points as the camera explored:
    # at most 25 % of the room's extent past it on any side (measured: 1.11 m on x, the points' margin and the
    # frusta out to their depth; growing from the guess would have kept its reach of 6 m past the cameras)
    box = m.aabb.numpy()
    pad = 0.25 * (hi - lo)
    assert (box[0] > lo - pad).all() and (box[1] < hi + pad).all(), (box, lo, hi)
