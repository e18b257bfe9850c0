"""Tests of colmap_trifocal.reconstruction.visualize on a pycolmap synthetic reconstruction.

Reading models needs no Open3D. The geometry tests need ``import open3d`` (which fails
without ``libusb-1.0-0``), the rendering tests an offscreen renderer (Mesa's EGL/Vulkan
drivers): where they are missing those tests skip with the reason, and fail under
``CI=true``. Open3D is imported only inside them.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
from pathlib import Path
from types import ModuleType

import numpy as np
import pycolmap
import pytest
from conftest import require_open3d, require_rendering, synthesize

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.reconstruction import visualize

FAR_POINTS = np.array([[1e4, 0.0, 0.0], [0.0, -2e4, 0.0], [3e3, 3e3, 3e3]])


@pytest.fixture
def o3d() -> ModuleType:
    """The open3d module; skip (fail under CI=true) where it cannot be imported."""
    return require_open3d()


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pycolmap.Reconstruction]:
    """A written synthetic model (2 cameras x 5 frames, 1000 coloured points + 3 far ones)."""
    folder = tmp_path_factory.mktemp("visualize")
    reconstruction = synthesize(folder / "database.db", cameras=2, frames=5, points=1000)
    rng = np.random.default_rng(0)
    for point in reconstruction.points3D.values():
        point.color = rng.integers(0, 256, 3).astype(np.uint8)
    for xyz in FAR_POINTS:
        reconstruction.add_point3D(xyz, pycolmap.Track(), np.array([255, 0, 0], np.uint8))
    sparse = folder / "sparse" / "0"
    sparse.mkdir(parents=True)
    reconstruction.write(str(sparse))
    return sparse, reconstruction


def test_load_model_reads_binary_and_text(model, tmp_path: Path) -> None:
    sparse, reconstruction = model
    loaded = visualize.load_model(sparse)
    assert loaded.num_points3D() == reconstruction.num_points3D()
    assert sorted(loaded.reg_image_ids()) == sorted(reconstruction.reg_image_ids())
    reconstruction.write_text(str(tmp_path))
    assert visualize.load_model(tmp_path).num_reg_images() == reconstruction.num_reg_images()


def test_load_model_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not found"):
        visualize.load_model(tmp_path / "sparse" / "0")


def test_load_model_not_a_model(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not a COLMAP model"):
        visualize.load_model(tmp_path)
    for name in ("cameras", "images", "points3D"):
        (tmp_path / f"{name}.txt").write_text("garbage that is not a model\n")
    with pytest.raises(CalibrationError) as error:
        visualize.load_model(tmp_path)
    assert "\n" not in str(error.value)


def test_scene_geometry_points_and_colours(model, o3d: ModuleType) -> None:
    _, reconstruction = model
    geometries = visualize.scene_geometry(reconstruction)
    clouds = [g for g in geometries if isinstance(g, o3d.geometry.PointCloud)]
    assert len(clouds) == 1
    xyz, rgb = np.asarray(clouds[0].points), np.asarray(clouds[0].colors)
    total = reconstruction.num_points3D()
    assert 0.95 * total <= len(xyz) <= total
    # The far outliers are gone; every kept point carries its own colour, 0-255 -> 0-1.
    assert np.abs(xyz).max() < 100
    colour_of = {p.xyz.tobytes(): p.color for p in reconstruction.points3D.values()}
    expected = np.array([colour_of[x.tobytes()] for x in xyz]) / 255.0
    np.testing.assert_allclose(rgb, expected)


def test_scene_geometry_frustums(model, o3d: ModuleType) -> None:
    _, reconstruction = model
    scale = 0.7
    geometries = visualize.scene_geometry(reconstruction, frustum_scale=scale)
    frustums = [g for g in geometries if isinstance(g, o3d.geometry.LineSet)]
    image_ids = sorted(reconstruction.reg_image_ids())
    assert len(frustums) == len(image_ids) == reconstruction.num_reg_images() > 0
    for frustum, image_id in zip(frustums, image_ids, strict=True):
        image = reconstruction.image(image_id)
        camera = image.camera
        vertices = np.asarray(frustum.points)
        assert vertices.shape == (5, 3) and len(frustum.lines) == 8
        np.testing.assert_allclose(vertices[0], image.projection_center(), atol=1e-9)
        # Corners lie on the plane at depth `scale` and project to the image corners.
        cam_from_world = image.cam_from_world()
        in_cam = vertices[1:] @ cam_from_world.rotation.matrix().T + cam_from_world.translation
        np.testing.assert_allclose(in_cam[:, 2], scale, rtol=1e-9)
        w, h = camera.width, camera.height
        np.testing.assert_allclose(
            camera.img_from_cam(in_cam), [[0, 0], [w, 0], [w, h], [0, h]], atol=1e-6
        )
    # Registration order: first blue, last red, one colour per frustum.
    np.testing.assert_allclose(np.asarray(frustums[0].colors), np.tile([0, 0, 1], (8, 1)))
    np.testing.assert_allclose(np.asarray(frustums[-1].colors), np.tile([1, 0, 0], (8, 1)))


def test_default_frustum_scale_follows_scene_size(model, o3d: ModuleType) -> None:
    _, reconstruction = model
    small = visualize.scene_geometry(reconstruction)[1]
    reconstruction_x10 = pycolmap.Reconstruction(reconstruction)
    reconstruction_x10.transform(pycolmap.Sim3d(10.0, pycolmap.Rotation3d(), np.zeros(3)))
    large = visualize.scene_geometry(reconstruction_x10)[1]
    size = np.ptp(np.asarray(small.points), axis=0).max()
    assert size > 0
    np.testing.assert_allclose(np.ptp(np.asarray(large.points), axis=0).max(), 10 * size)


def _assert_not_blank(o3d: ModuleType, path: Path, width: int, height: int) -> None:
    pixels = np.asarray(o3d.io.read_image(str(path)))
    assert pixels.shape[:2] == (height, width)
    rgb = pixels[..., :3].astype(float)
    foreground = np.any(rgb < 250, axis=-1)  # background is white
    assert foreground.mean() > 0.005
    assert rgb.std() > 5.0


def test_render_png(model, tmp_path: Path, o3d: ModuleType) -> None:
    require_rendering()
    _, reconstruction = model
    out = visualize.render_png(
        visualize.scene_geometry(reconstruction), tmp_path / "view.png", width=640, height=480
    )
    assert out == tmp_path / "view.png" and out.is_file()
    _assert_not_blank(o3d, out, 640, 480)


def test_show_png(model, tmp_path: Path, o3d: ModuleType) -> None:
    require_rendering()
    sparse, _ = model
    out = visualize.show(sparse, tmp_path / "show.png")
    assert out == tmp_path / "show.png"
    _assert_not_blank(o3d, out, 1280, 960)


def test_show_without_display(model, monkeypatch: pytest.MonkeyPatch, o3d: ModuleType) -> None:
    sparse, _ = model
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(CalibrationError, match="no display: use --png OUT"):
        visualize.show(sparse)


def test_show_opens_a_window_with_a_display(model, tmp_path: Path) -> None:
    """``colmap-trifocal show MODEL`` with a display hands the model to Open3D's viewer.

    No window can open on a headless machine, and Open3D is not replaced by a stand-in:
    a real process gets a ``DISPLAY`` that nobody serves. Open3D's viewer then starts
    (its first log line) and keeps the process waiting (measured: a window-less EGL
    fallback that never closes and ignores Ctrl-C, so it is killed here). The geometry
    it gets is ``scene_geometry``'s, checked above.
    """
    require_rendering()
    sparse, _ = model
    env = {**os.environ, "DISPLAY": ":97", "XDG_RUNTIME_DIR": str(tmp_path)}
    env.pop("WAYLAND_DISPLAY", None)
    process = subprocess.Popen(
        [sys.executable, "-m", "colmap_trifocal.cli", "show", str(sparse)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,
    )
    lines: queue.Queue[str] = queue.Queue()
    assert process.stdout is not None

    def read() -> None:
        for line in iter(process.stdout.readline, ""):
            lines.put(line)
        lines.put("")  # the end of the output: the process ended

    threading.Thread(target=read, daemon=True).start()
    try:
        seen: list[str] = []
        while not (seen and "[Open3D" in seen[-1]):
            try:
                line = lines.get(timeout=120)
            except queue.Empty:
                break
            if not line:
                break  # it ended without reaching the viewer
            seen.append(line)
        assert seen and "[Open3D" in seen[-1], "".join(seen)
        assert process.poll() is None, "".join(seen)  # in the viewer, not ended
        assert not any(line.startswith("error:") for line in seen), "".join(seen)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=60)


def test_show_missing_model(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError):
        visualize.show(tmp_path / "nope", tmp_path / "x.png")
