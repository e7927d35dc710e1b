"""The SLAM loop (fmapping.slam.run_slam) end to end on a small synthetic scene."""
import json

import numpy as np
import pytest

from fmapping.job import Job
from fmapping.trajectory import read_tum_trajectory

TINY = """
mapper:
  init_iters_per_round: 2
  iters_per_window: 1
  rays_per_iter: 64
  init_rays_per_iter: 64
  n_coarse: 8
  n_fine: 4
  final_global_iters: 0
  init_frames: 8
  window_size: 8
  n_global_keyframes: 3
  new_frames_per_window: 5
"""


@pytest.fixture(scope="module")
def scene(room320, tmp_path_factory):
    cfg = tmp_path_factory.mktemp("slam") / "tiny.yaml"
    cfg.write_text(TINY)
    return room320, cfg


def _args(data, out, cfg, **kw):
    return Job(**{"data": str(data), "out": str(out), "config": str(cfg), "poses": "photometric", "device": "cpu",
                  "export": False, "quiet": True, **kw})


def test_slam_rgb_only_end_to_end(scene, tmp_path, monkeypatch):
    import fmapping.slam as slam
    import fmapping.slam.job as slam_job  # the module that calls write_map_outputs

    calls = []

    def fake_writer(mapper, poses, camera, out, **kw):  # the real export takes ~1 min here
        calls.append((mapper, poses, kw))
        return {"points": 0, "mesh_vertices": 0, "mesh_faces": 0, "seconds": 0.0}

    monkeypatch.setattr(slam_job, "write_map_outputs", fake_writer)
    root, cfg = scene
    stats = slam.run_slam(_args(root, tmp_path / "out", cfg, export=True))
    s = stats["summary"]
    # the export sees the keyframe and window views, written in the output frame: scaled about frame 0
    (mapper, poses, kw), = calls
    assert set(poses) == set(mapper.keyframe_ids()) | set(mapper.window_ids())
    _, gt = read_tum_trajectory(root / "groundtruth.txt")
    np.testing.assert_allclose(kw["center"], gt[0][:3, 3], atol=1e-6)
    assert kw["scale"] == stats["output_scale"]
    assert stats["export"]["points"] == 0 and "recon" not in stats  # an empty map is not scored
    ts, est = read_tum_trajectory(tmp_path / "out" / "traj.txt")
    assert len(ts) == 40
    on_disk = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert on_disk["summary"]["frames"] == 40 and "tracking_ms" in on_disk and "windows" in on_disk
    assert on_disk["init"]["frontend"] == "mono" and on_disk["init"]["scale_from"] == "anchor"
    # the scale was taken again at frame 14, before the mapper saw a frame (it holds the rescaled poses: below)
    assert on_disk["init"]["late_anchor"]["frame"] == 14 and "refused" not in on_disk["init"]["late_anchor"]
    assert s["tracking_loss_events"] == 0 and s["warnings"] == []  # nothing to warn a user about
    # measured: 0.25 cm (Sim3) / 0.59 cm (unaligned, GT-anchored scale) on this 40-frame 320x240 clip
    # (0.43 / 1.16 cm with the 21 px KLT window of before)
    assert s["ate_sim3_rmse_m"] < 0.01, s
    assert s["ate_none_rmse_m"] < 0.02, s
    assert len(stats["windows"]) >= 2  # the mapper ran its init and on-the-fly windows
    # the mapper trained on the bundle-adjusted poses: at the end it holds the written trajectory, to the
    # threshold below which a moved pose is not handed on (1 mm, 0.05 deg)
    from fmapping.geometry import pose_distance

    assert stats["output_scale"] == 1.0 and stats["mapper_pose_updates"] > 0
    held = mapper.frame_poses()
    assert len(held) == 40
    for i in range(40):
        dt, dr = pose_distance(held[i], est[i])
        assert dt <= 1e-3 + 1e-6 and dr <= 0.05 + 1e-4, (i, dt, dr)
    # the orientation-only fit is reported next to the position-aligned rotation error
    assert 0 <= s["ate_rot_fit_deg"] == stats["ate"]["se3"]["rot_fit_mean_deg"] < 5.0, s


def test_slam_cli_gt_poses_no_export_writes_trajectory_and_stats_only(scene, tmp_path, capsys):
    from fmapping.cli import build_parser, main

    root, cfg = scene
    assert build_parser().parse_args(["slam", "--data", "d", "--out", "o"]).export is True
    out = tmp_path / "gt"
    code = main(["slam", "--data", str(root), "--out", str(out), "--config", str(cfg), "--poses", "gt",
                 "--max-frames", "12", "--device", "cpu", "--no-export"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    _, est = read_tum_trajectory(out / "traj.txt")
    _, gt = read_tum_trajectory(root / "groundtruth.txt")
    assert len(est) == 12 and summary["frames"] == 12
    np.testing.assert_allclose(est, gt[:12], atol=1e-6)
    assert summary["ate_none_rmse_m"] < 1e-6 and summary["ate_rot_fit_deg"] < 1e-4
    stats = json.loads((out / "stats.json").read_text())
    assert stats["export"] is None and stats["config"]["export"] is False and "recon" not in stats
    assert not (out / "map.ply").exists() and not (out / "mesh.ply").exists()


def test_slam_starts_the_bootstrap_again_after_blank_frames(scene, tmp_path):
    """The camera sees a blank wall for its first 4 frames: the monocular bootstrap fails there and starts
    again further on. The frames before it have no pose and are left out of the trajectory; the world frame
    and scale come from the GT anchor of the bootstrap's own first frame."""
    import shutil

    import cv2

    import fmapping.slam as slam

    root, cfg = scene
    data = tmp_path / "blank_start"
    shutil.copytree(root, data)
    names = sorted((data / "rgb").iterdir())
    for f in names[:4]:
        cv2.imwrite(str(f), np.full((240, 320, 3), 128, np.uint8))
    stats = slam.run_slam(_args(data, tmp_path / "out", cfg))
    s = stats["summary"]
    ts, est = read_tum_trajectory(tmp_path / "out" / "traj.txt")
    gt_ts, gt = read_tum_trajectory(root / "groundtruth.txt")
    first = int(np.argmin(np.abs(gt_ts - ts[0])))
    assert first >= 4 and s["frames_posed"] == len(ts) == 40 - first
    assert stats["init"]["frontend"] == "mono" and stats["init"]["scale_from"] == "anchor"
    assert any("restarted" in n for n in stats["notes"]), stats["notes"]
    # the user is told, in the summary and the log, which share of the frames has no pose and why
    assert any(w.startswith(f"{first} of 40 frames have no pose") for w in s["warnings"]), s["warnings"]
    np.testing.assert_allclose(est[0], gt[first], atol=1e-6)  # the bootstrap's first frame at its anchor
    assert s["ate_sim3_rmse_m"] < 0.01 and s["ate_none_rmse_m"] < 0.02, s


class _Watched:
    """A dataset that records the highest frame index read."""

    def __init__(self, ds):
        self._ds, self.highest = ds, -1

    def __getattr__(self, name):
        return getattr(self._ds, name)

    def __len__(self):
        return len(self._ds)

    def __getitem__(self, i):
        self.highest = max(self.highest, int(i))
        return self._ds[i]


def test_slam_stopped_on_request_writes_the_frames_it_got_to(scene, tmp_path, monkeypatch):
    """A stop request once frame 25 has been read: the run ends before frame 26 without the closing
    optimisation, and writes those 26 poses (tracked as well as in the full run) and the map so far."""
    import fmapping.slam as slam
    import fmapping.slam.job as slam_job  # the module that calls open_job_dataset and write_map_outputs

    watched = []
    real_open = slam_job.open_job_dataset
    monkeypatch.setattr(slam_job, "open_job_dataset", lambda a: watched.append(_Watched(real_open(a))) or watched[-1])
    exported = []
    monkeypatch.setattr(slam_job, "write_map_outputs", lambda mapper, poses, *a, **kw: exported.append(poses) or
                        {"points": 0, "mesh_vertices": 0, "mesh_faces": 0, "seconds": 0.0})
    root, cfg = scene
    out = tmp_path / "stopped"
    stats = slam.run_slam(_args(root, out, cfg, export=True), should_stop=lambda: watched[0].highest >= 25)
    s = stats["summary"]
    assert s["stopped_at"] == 26 and s["frames"] == 40
    ts, est = read_tum_trajectory(out / "traj.txt")
    _, gt = read_tum_trajectory(root / "groundtruth.txt")
    assert len(ts) == 26 and len(exported) == 1
    assert any("stopped on request before frame 26" in n for n in stats["notes"])
    from fmapping.metrics import ate

    # measured: 0.230 cm, the full run's first 26 frames 0.231 cm
    assert ate(np.stack(est), np.stack(gt[:26]), "sim3")["rmse_m"] < 0.01  # the full run's bound
    assert json.loads((out / "stats.json").read_text())["summary"]["stopped_at"] == 26


def test_stop_on_signal_sets_the_event_once_then_lets_ctrl_c_through():
    import os
    import signal

    from fmapping.cli import stop_on_signal

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with stop_on_signal("test") as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.is_set()
        with pytest.raises(KeyboardInterrupt):  # the second signal, a Ctrl-C, aborts as usual
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):  # the handler runs at the next bytecode boundary
                pass
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_slam_bad_inputs_are_named(scene, tmp_path):
    from fmapping.slam import run_slam

    root, cfg = scene
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        run_slam(_args(root, tmp_path / "x", cfg, poses=str(tmp_path / "nope.txt")))
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracker:\n  no_such_key: 1\n")
    with pytest.raises(ValueError, match="no_such_key"):
        run_slam(_args(root, tmp_path / "y", bad))



# ---------------------------------------------------------------------------- output writing shared with `fmapping map`
def _fake_exporters(monkeypatch, cloud, mesh):
    """Replace the (slow, separately tested) exporters by functions returning ``cloud`` / ``mesh``
    and recording their arguments; the mesh one also calls the culling render it is given."""
    import fmapping.export as export

    seen = {}

    def point_cloud(source, poses, camera, near, far, n_samples=None, n_importance=None):
        seen["cloud"] = dict(source=source, poses=poses, near=near, far=far, samples=(n_samples, n_importance))
        return cloud[0].copy(), cloud[1]

    def mesh_fn(field, aabb, resolution, poses, camera, render, near, far):
        seen["mesh"] = dict(field=field, aabb=aabb, resolution=resolution, poses=poses, near=near, far=far)
        seen["render"] = render(next(iter(poses.values())), camera.resized(8, 6))  # tiny: a real render is slow
        return mesh[0].copy(), mesh[1], mesh[2]

    monkeypatch.setattr(export, "export_point_cloud", point_cloud)
    monkeypatch.setattr(export, "export_mesh", mesh_fn)
    return seen


def test_write_map_outputs_writes_both_plys_in_the_output_frame(tmp_path, monkeypatch):
    import types

    from fmapping.camera import PinholeCamera
    from fmapping.pipeline import write_map_outputs
    from fmapping.ply import read_ply

    rng = np.random.default_rng(0)
    pts, cols = rng.normal(size=(50, 3)), rng.integers(0, 256, (50, 3), dtype=np.uint8)
    verts, faces, vcols = rng.normal(size=(6, 3)), np.array([[0, 1, 2], [3, 4, 5]]), np.zeros((6, 3), np.uint8)
    seen = _fake_exporters(monkeypatch, (pts, cols), (verts, faces, vcols))
    renders = []

    def render(c2w, cam, samples=None):
        renders.append(samples)
        return {"rgb": np.zeros((2, 2, 3)), "depth": np.full((2, 2), 1.5), "depth_normalized": np.full((2, 2), 3.0),
                "acc": np.full((2, 2), 0.5)}

    mapper = types.SimpleNamespace(render=render, field="FIELD", aabb="AABB")
    cam = PinholeCamera(20.0, 20.0, 8.0, 6.0, 16, 12)
    poses = {3: np.eye(4), 7: np.eye(4)}
    c = np.array([1.0, -2.0, 0.5])
    res = write_map_outputs(mapper, poses, cam, tmp_path, near=0.2, far=5.0, cloud_samples=(8, 4),
                            mesh_samples=(6, 2), mesh_resolution=17, center=c, scale=2.0)
    assert {k: res[k] for k in ("points", "mesh_vertices", "mesh_faces")} == \
        {"points": 50, "mesh_vertices": 6, "mesh_faces": 2}
    cloud, mesh = read_ply(tmp_path / "map.ply"), read_ply(tmp_path / "mesh.ply")
    np.testing.assert_allclose(cloud.points, c + 2.0 * (pts - c), rtol=1e-6, atol=1e-6)  # PLY stores float32
    np.testing.assert_array_equal(cloud.colors, cols)
    np.testing.assert_allclose(mesh.points, c + 2.0 * (verts - c), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, faces)
    assert seen["cloud"]["samples"] == (8, 4) and seen["cloud"]["poses"] is poses and seen["cloud"]["near"] == 0.2
    assert seen["mesh"]["resolution"] == 17 and seen["mesh"]["field"] == "FIELD" and seen["mesh"]["far"] == 5.0
    # mesh culling sees the expected surface depth (depth / acc), rendered with the mesh samples
    assert renders == [(6, 2)] and seen["render"]["depth"][0, 0] == 3.0 and seen["render"]["acc"][0, 0] == 0.5
    # without a centre the points are written as given; without samples the exporter's defaults are used
    write_map_outputs(mapper, poses, cam, tmp_path, near=0.2, far=5.0)
    np.testing.assert_allclose(read_ply(tmp_path / "map.ply").points, pts, rtol=1e-6, atol=1e-6)
    assert seen["cloud"]["samples"] == (None, None)


def test_map_job_writes_outputs_and_scores_the_cloud(scene, tmp_path, monkeypatch):
    import textwrap

    import fmapping.pipeline as pipeline
    from fmapping.ply import read_ply

    monkeypatch.setattr(pipeline, "_heldout_psnr", lambda *a, **k: 12.5)  # 8 full renders: ~1 min on 2 cores

    root, _ = scene
    gt_cloud = read_ply(root / "gt_visible_cloud.ply")
    # the "exported" map is the visible GT cloud itself: accuracy and completion 0 cm, ratio 100 %
    seen = _fake_exporters(monkeypatch, (gt_cloud.points, np.full((len(gt_cloud.points), 3), 128, np.uint8)),
                           (np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)))
    cfg = tmp_path / "map.yaml"
    cfg.write_text(textwrap.dedent(TINY.replace("mapper:\n", "")))
    out = tmp_path / "map"
    args = Job(data=str(root), out=str(out), config=str(cfg), poses="gt", device="cpu", max_frames=12, quiet=True)
    stats = pipeline.run_map(args)
    s = json.loads((out / "stats.json").read_text())["summary"]
    assert s == json.loads(json.dumps(stats["summary"]))
    assert s["frames"] == 12 and s["points"] == len(gt_cloud.points) and s["psnr_heldout"] == 12.5
    assert s["accuracy_cm"] == 0.0 and s["completion_cm"] == 0.0 and s["completion_ratio"] == 100.0
    assert "recon_mesh" not in stats and stats["export"]["mesh_faces"] == 0  # an empty mesh is not scored
    assert sorted(seen["cloud"]["poses"]) == [0, 3, 6, 9]  # every 3rd frame's view
    _, traj = read_tum_trajectory(out / "traj.txt")
    _, gt = read_tum_trajectory(root / "groundtruth.txt")
    np.testing.assert_allclose(traj, gt[:12], atol=1e-6)
    assert (out / "map.ply").is_file() and (out / "mesh.ply").is_file()


def test_map_job_stopped_on_request_exports_the_map_so_far(scene, tmp_path, monkeypatch):
    """Stopped once frame 10 is read (after the init stage on frames 0-7): the map of frames 0-10 is
    exported without the closing stage. Stopped at frame 3, before the init stage ended: no map,
    and stats.json says where it stopped."""
    import textwrap

    import fmapping.pipeline as pipeline

    monkeypatch.setattr(pipeline, "_heldout_psnr", lambda *a, **k: 12.5)
    seen = _fake_exporters(monkeypatch, (np.zeros((1, 3)), np.zeros((1, 3), np.uint8)),
                           (np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)))
    root, _ = scene
    cfg = tmp_path / "map.yaml"
    cfg.write_text(textwrap.dedent(TINY.replace("mapper:\n", "")))
    real_open = pipeline.open_job_dataset
    for last, want_frames in ((10, 11), (3, 4)):
        watched = []
        monkeypatch.setattr(pipeline, "open_job_dataset",
                            lambda a: watched.append(_Watched(real_open(a))) or watched[-1])
        out = tmp_path / f"map{last}"
        seen.clear()
        args = Job(data=str(root), out=str(out), config=str(cfg), poses="gt", device="cpu", quiet=True)
        s = pipeline.run_map(args, should_stop=lambda: watched[0].highest >= last)["summary"]
        assert s["stopped_at"] == want_frames and s["frames"] == want_frames
        assert json.loads((out / "stats.json").read_text())["summary"]["stopped_at"] == want_frames
        if last == 10:
            _, traj = read_tum_trajectory(out / "traj.txt")
            assert len(traj) == want_frames and sorted(seen["cloud"]["poses"]) == [0, 3, 6, 9]
        else:
            assert "cloud" not in seen and not (out / "traj.txt").exists()


@pytest.mark.parametrize("job", ["map", "slam"])
def test_a_stop_during_the_closing_stage_still_writes_every_frame(job, scene, tmp_path, monkeypatch):
    """The stop request comes once every frame is mapped, inside the mapper's closing optimisation
    (Ctrl-C or SIGTERM there raised Cancelled out of fmapping map / slam, with nothing written): the run
    ends with every frame's pose, the map as far as it got, and stopped_at = the number of frames."""
    import textwrap

    import fmapping.pipeline as pipeline
    import fmapping.slam as slam
    from fmapping.mapping import Mapper

    monkeypatch.setattr(pipeline, "_heldout_psnr", lambda *a, **k: 12.5)
    seen = _fake_exporters(monkeypatch, (np.zeros((1, 3)), np.zeros((1, 3), np.uint8)),
                           (np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)))
    closing = []
    real_finish = Mapper.finish
    monkeypatch.setattr(Mapper, "finish", lambda self: closing.append(True) or real_finish(self))
    root, _ = scene
    tiny = TINY.replace("final_global_iters: 0", "final_global_iters: 5")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(tiny if job == "slam" else textwrap.dedent(tiny.replace("mapper:\n", "")))
    out = tmp_path / job
    args = _args(root, out, cfg, poses="gt", export=True, field=None, max_frames=12)
    stats = (pipeline.run_map if job == "map" else slam.run_slam)(args, should_stop=lambda: bool(closing))
    assert len(closing) == 1 and stats["summary"]["stopped_at"] == 12
    if job == "slam":
        assert "stopped on request during the closing optimisation" in stats["notes"]
    ts, traj = read_tum_trajectory(out / "traj.txt")
    _, gt = read_tum_trajectory(root / "groundtruth.txt")
    assert len(ts) == 12
    np.testing.assert_allclose(traj, gt[:12], atol=1e-6)  # given poses: written as given
    assert "cloud" in seen and json.loads((out / "stats.json").read_text())["summary"]["stopped_at"] == 12
