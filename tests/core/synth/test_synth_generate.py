"""Writing sequences: TUM layout readable by the loader, determinism, skipping, the CLI."""

from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest
import trimesh

from neb_slam_core.cli.main import main as cli_main
from neb_slam_core.datasets import open_dataset
from neb_slam_core.errors import DatasetError
from neb_slam_core.io.trajectory import read_tum_trajectory
from neb_slam_core.synth import generate as gen
from neb_slam_core.synth.noise import axial_sigma_m
from neb_slam_core.synth.render import Renderer

FILES = ("rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.json", "mesh.ply", "scene.json")


def _digest(folder):
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_folder_has_the_tum_layout(small_folder):
    for f in FILES:
        assert (small_folder / f).is_file(), f
    rgb = [ln.split() for ln in (small_folder / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    depth = [ln.split() for ln in (small_folder / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    gt = read_tum_trajectory(small_folder / "groundtruth.txt")
    assert len(rgb) == len(depth) == len(gt) == 5
    assert [r[0] for r in rgb] == [d[0] for d in depth]  # identical stamps
    assert [r[1] for r in rgb] == [f"rgb/{r[0]}.png" for r in rgb]
    raw = cv2.imread(str(small_folder / depth[0][1]), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (48, 64)
    meta = json.loads((small_folder / "scene.json").read_text())
    assert meta["seed"] == 0 and meta["preset"] == "small" and meta["n_frames"] == 5
    assert meta["options"]["camera"]["width"] == 64 and meta["options"]["trajectory"]["n_frames"] == 5
    assert np.allclose(meta["bounds_m"]["size"], [3.9, 3.9, 2.6], atol=0.25)


def test_tum_loader_reads_back_what_was_rendered(small_folder):
    ds = open_dataset(small_folder)
    assert ds.name == "tum" and len(ds) == 5 and ds.has_ground_truth
    seq = gen.build_sequence(gen.resolve_spec("small", n_frames=5, size=(64, 48)))
    intr = seq.spec.camera.intrinsics()
    assert ds.intrinsics == intr
    r = Renderer.for_scene(seq.scene, intr)
    for i in (0, 3):
        frame = ds[i]
        view = r.render(seq.trajectory.poses[i])
        assert frame.stamp_ns == seq.trajectory.stamps_ns[i]
        assert np.array_equal(frame.rgb, view.rgb)
        # 16-bit PNG at 5000 per metre: within half a step (0.1 mm)
        assert np.abs(frame.depth_m - view.depth_m).max() <= 0.5 / 5000 + 1e-6
        assert np.array_equal(frame.depth_m > 0, view.depth_m > 0)
        assert np.allclose(frame.T_world_cam, seq.trajectory.poses[i], atol=1e-7)


def test_mesh_file_is_the_scene_surface_with_colours(small_folder):
    mesh = trimesh.load(small_folder / "mesh.ply", process=False)
    seq = gen.build_sequence(gen.resolve_spec("small", n_frames=5, size=(64, 48)))
    assert mesh.area == pytest.approx(seq.scene.mesh.area, rel=1e-6)
    assert np.allclose(mesh.bounds, seq.scene.mesh.bounds)
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.shape == (len(mesh.vertices), 4) and colors[:, :3].std() > 20
    # its vertices lie on the render mesh
    _, dist, _ = trimesh.proximity.closest_point(seq.scene.mesh, mesh.vertices[::50])
    assert dist.max() < 1e-6


def test_same_seed_same_bytes_other_seed_differs(small_folder, tmp_path):
    again = gen.generate("small", tmp_path / "again", n_frames=5, size=(64, 48), progress=False)
    assert _digest(again) == _digest(small_folder)
    other = gen.generate("small", tmp_path / "other", n_frames=5, size=(64, 48), seed=1, progress=False)
    a, b = open_dataset(small_folder)[2], open_dataset(other)[2]
    assert not np.array_equal(a.rgb, b.rgb) and not np.array_equal(a.depth_m, b.depth_m)


def test_skips_a_complete_folder_and_regenerates_on_change(tmp_path):
    out = tmp_path / "s"
    gen.generate("small", out, n_frames=3, size=(32, 24), progress=False)
    stamp = (out / "scene.json").stat().st_mtime_ns
    gen.generate("small", out, n_frames=3, size=(32, 24), progress=False)
    assert (out / "scene.json").stat().st_mtime_ns == stamp  # untouched
    gen.generate("small", out, n_frames=4, size=(32, 24), progress=False)  # other options: rewritten
    assert len(open_dataset(out)) == 4 and len(list((out / "rgb").glob("*.png"))) == 4
    (out / "rgb" / sorted(p.name for p in (out / "rgb").iterdir())[0]).unlink()  # incomplete: rewritten
    assert not gen.is_complete(out, gen.resolve_spec("small", n_frames=4, size=(32, 24)))
    gen.generate("small", out, n_frames=4, size=(32, 24), progress=False)
    assert gen.is_complete(out, gen.resolve_spec("small", n_frames=4, size=(32, 24)))


def test_refuses_a_foreign_non_empty_folder(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not empty"):
        gen.generate("small", tmp_path, n_frames=2, size=(16, 12), progress=False)
    gen.generate("small", tmp_path, n_frames=2, size=(16, 12), progress=False, force=True)
    assert (tmp_path / "notes.txt").read_text() == "mine" and len(open_dataset(tmp_path)) == 2


def test_noise_option_perturbs_depth_by_the_model(small_folder, tmp_path):
    noisy = gen.generate("small", tmp_path / "noisy", n_frames=5, size=(64, 48), noise=True, progress=False)
    meta = json.loads((noisy / "scene.json").read_text())
    assert meta["options"]["noise"]["enabled"] is True
    clean_ds, noisy_ds = open_dataset(small_folder), open_dataset(noisy)
    spec = gen.resolve_spec("small", noise=True)
    residuals = []
    for i in range(5):
        c, n = clean_ds[i], noisy_ds[i]
        assert np.array_equal(c.rgb, n.rgb)  # colour untouched
        both = (c.depth_m > 0) & (n.depth_m > 0)
        assert both.mean() > 0.8  # dropout is the exception
        z = c.depth_m[both].astype(np.float64)
        # expected spread: axial sigma and the disparity quantisation step (uniform: step^2 / 12)
        scale = np.sqrt(axial_sigma_m(z, spec.noise) ** 2 + (spec.noise.disparity_step_per_m * z**2) ** 2 / 12)
        residuals.append((n.depth_m[both] - c.depth_m[both]) / scale)
    r = np.concatenate(residuals)
    assert abs(r.mean()) < 0.1 and r.std() == pytest.approx(1.0, abs=0.15)


def test_cli_synth(tmp_path, capsys):
    out = tmp_path / "cli"
    assert (
        cli_main(
            ["synth", str(out), "--preset", "small", "--frames", "3", "--size", "32x24", "--seed", "2", "--no-progress"]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "scene 'small' seed 2" in text and "frames/s" in text
    assert len(open_dataset(out)) == 3
    assert cli_main(["synth", str(out), "--preset", "small", "--frames", "3", "--size", "32x24", "--seed", "2"]) == 0
    assert "nothing to do" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli_main(["synth", str(out), "--size", "big"])


def test_an_interrupted_run_is_regenerated_not_refused(tmp_path, monkeypatch):
    # Ctrl-C while the frames are written: the folder holds some PNGs and no index; the next run must
    # recognise it as its own (not "not empty"), not take it for complete, and write it whole.
    out = tmp_path / "s"
    written = []
    real_write = gen._write_png

    def interrupt_after_three(path, image):
        if len(written) == 3:
            raise KeyboardInterrupt
        written.append(path)
        real_write(path, image)

    monkeypatch.setattr(gen, "_write_png", interrupt_after_three)
    with pytest.raises(KeyboardInterrupt):
        gen.generate("small", out, n_frames=3, size=(32, 24), progress=False)
    monkeypatch.setattr(gen, "_write_png", real_write)
    spec = gen.resolve_spec("small", n_frames=3, size=(32, 24))
    assert len(list(out.rglob("*.png"))) == 3 and not (out / "rgb.txt").exists()
    assert not gen.is_complete(out, spec)
    gen.generate("small", out, n_frames=3, size=(32, 24), progress=False)
    assert gen.is_complete(out, spec) and len(open_dataset(out)) == 3
    assert "complete" not in json.loads((out / "scene.json").read_text())
