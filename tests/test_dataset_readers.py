"""Dataset readers on small hand-written scenes in each format."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import shared_dataset

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.datasets import DATASET_KINDS, DatasetScene, GroundTruthView, read_scene
from colmap_trifocal.datasets.base import from_opencv
from colmap_trifocal.datasets.dtu import decompose_projection

SQRT_HALF = np.sqrt(0.5)


def write_image(path: Path, width: int = 20, height: int = 12) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.zeros((height, width), np.uint8))


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def assert_rotation(R: np.ndarray) -> None:
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)


def read_error(kind: str, path: Path, **options) -> str:
    with pytest.raises(CalibrationError) as info:
        read_scene(kind, path, **options)
    message = str(info.value)
    assert "\n" not in message
    return message


# --- common types -------------------------------------------------------------------


def test_ground_truth_view_and_scene() -> None:
    R = np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    posed = GroundTruthView("a.png", np.array([1, 2, 3, 4]), rotation=R, translation=[2, 1.5, -3])
    np.testing.assert_allclose(posed.centre, [1.5, -2, 3])
    assert not posed.intrinsics.flags.writeable
    bare = GroundTruthView("b.png", [5, 6, 7, 8])
    assert bare.centre is None
    scene = DatasetScene("test", "s", Path("."), [posed, bare])
    assert scene.view("b.png") is bare
    np.testing.assert_allclose(scene.mean_intrinsics(), [3, 4, 5, 6])
    with pytest.raises(CalibrationError, match="no ground truth for image 'c.png' in test scene s"):
        scene.view("c.png")
    np.testing.assert_allclose(
        from_opencv(np.array([[500.0, 0, 319.5], [0, 510, 239.5], [0, 0, 1]])), [500, 510, 320, 240]
    )


def test_registry_errors(tmp_path: Path) -> None:
    kinds = (
        "strecha",
        "colmap",
        "blendedmvs",
        "kitti",
        "tum",
        "dtu",
        "middlebury",
        "euroc",
        "nerf",
    )
    assert DATASET_KINDS == kinds
    assert read_error("eth3d", tmp_path) == (
        f"unknown dataset kind 'eth3d' (expected one of: {', '.join(kinds)})"
    )
    missing = tmp_path / "nowhere"
    assert read_error("kitti", missing) == f"kitti dataset path {missing} does not exist"
    assert read_error("dtu", tmp_path, camera=2) == (
        "unknown option(s) camera for dataset kind 'dtu' (accepted: none)"
    )
    assert "accepted: camera, poses" in read_error("kitti", tmp_path, cam=2)


# --- strecha ------------------------------------------------------------------------


def test_strecha_scene(tmp_path: Path) -> None:
    for name in ("0001.jpg", "0000.jpg"):
        write_image(tmp_path / "images" / name)
        write(
            tmp_path / "gt_dense_cameras" / f"{name}.camera",
            "2759.48 0 1520.69\n0 2764.16 1006.81\n0 0 1\n0 0 0\n"
            "0 -1 0\n1 0 0\n0 0 1\n1.5 -2 3\n3072 2048\n",
        )
    write(tmp_path / "images" / "K.txt", "not an image")
    scene = read_scene("strecha", tmp_path)
    assert scene.kind == "strecha" and scene.name == tmp_path.name
    assert scene.image_dir == tmp_path / "images"
    assert [v.name for v in scene.views] == ["0000.jpg", "0001.jpg"]
    view = scene.views[0]
    np.testing.assert_allclose(view.intrinsics, [2759.48, 2764.16, 1520.69, 1006.81])  # no shift
    assert (view.width, view.height) == (3072, 2048)
    np.testing.assert_allclose(view.rotation, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(view.translation, [2, 1.5, -3])
    np.testing.assert_allclose(view.centre, [1.5, -2, 3])


def test_strecha_missing_camera_file(tmp_path: Path) -> None:
    write_image(tmp_path / "images" / "0000.jpg")
    message = read_error("strecha", tmp_path)
    assert message.startswith("cannot read Strecha camera file ")
    assert "0000.jpg.camera" in message


# --- colmap -------------------------------------------------------------------------

COLMAP_CAMERAS = """# Camera list
1 PINHOLE 640 480 500 510 320 240
2 SIMPLE_RADIAL 800 600 700 400 300 0.01
"""
COLMAP_IMAGES = f"""# Image list
1 1 0 0 0 1 2 3 1 b.jpg

2 {SQRT_HALF} 0 {SQRT_HALF} 0 0 0 5 2 a.jpg

"""


def write_colmap_model(folder: Path, cameras: str = COLMAP_CAMERAS) -> Path:
    write(folder / "cameras.txt", cameras)
    write(folder / "images.txt", COLMAP_IMAGES)
    write(folder / "points3D.txt", "")
    return folder


def check_colmap_views(scene: DatasetScene) -> None:
    assert [v.name for v in scene.views] == ["a.jpg", "b.jpg"]
    a, b = scene.views
    np.testing.assert_allclose(a.intrinsics, [700, 700, 400, 300])
    np.testing.assert_allclose(b.intrinsics, [500, 510, 320, 240])
    assert (a.width, a.height, b.width, b.height) == (800, 600, 640, 480)
    np.testing.assert_allclose(a.rotation, [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(a.centre, [5, 0, 0], atol=1e-12)
    np.testing.assert_allclose(b.centre, [-1, -2, -3])
    assert_rotation(a.rotation)


def test_colmap_text_and_binary_model(tmp_path: Path) -> None:
    model = write_colmap_model(tmp_path / "scene" / "sparse" / "0")
    (tmp_path / "scene" / "images").mkdir()
    scene = read_scene("colmap", model)
    assert scene.name == "scene"
    assert scene.image_dir == (tmp_path / "scene" / "images").resolve()
    check_colmap_views(scene)

    import pycolmap

    binary = tmp_path / "other" / "model"
    binary.mkdir(parents=True)
    pycolmap.Reconstruction(str(model)).write_binary(str(binary))
    assert (binary / "cameras.bin").is_file()
    scene = read_scene("colmap", binary, image_dir=tmp_path / "photos")
    assert scene.name == "other" and scene.image_dir == tmp_path / "photos"
    check_colmap_views(scene)
    default = read_scene("colmap", binary)
    assert default.image_dir == (tmp_path / "other" / "images").resolve()


def test_colmap_malformed_model(tmp_path: Path) -> None:
    model = write_colmap_model(tmp_path / "sparse", cameras="1 PINHOLE 640 480 500\n")
    assert read_error("colmap", model).startswith(f"cannot read COLMAP model {model}: ")
    assert read_error("colmap", tmp_path).startswith(f"cannot read COLMAP model {tmp_path}: ")


# --- blendedmvs ---------------------------------------------------------------------

ANGLE = np.deg2rad(30)
BLENDED_R = np.array(
    [[np.cos(ANGLE), 0, np.sin(ANGLE)], [0, 1, 0], [-np.sin(ANGLE), 0, np.cos(ANGLE)]]
)


def blended_cam(t: tuple[float, float, float], f: float) -> str:
    rows = np.c_[BLENDED_R, t]
    extrinsic = "\n".join(" ".join(repr(float(x)) for x in r) for r in rows)
    return (
        f"extrinsic\n{extrinsic}\n0.0 0.0 0.0 1.0\n\n"
        f"intrinsic\n{f} 0.0 384.0\n0.0 {f} 288.0\n0.0 0.0 1.0\n\n425.0 2.5 192 905.0\n"
    )


def write_blendedmvs(scene: Path) -> None:
    for i in range(3):
        write_image(scene / "blended_images" / f"{i:08d}.jpg", 32, 24)
        write(scene / "cams" / f"{i:08d}_cam.txt", blended_cam((i, -1.0, 4.0), 577.5 + i))
    write_image(scene / "blended_images" / "00000000_masked.jpg", 32, 24)
    write(
        scene / "cams" / "pair.txt",
        "3\n0\n2 1 1380.5 2 250.25\n1\n1 0 1380.5\n2\n1 0 250.25\n",
    )


def test_blendedmvs_scene(tmp_path: Path) -> None:
    write_blendedmvs(tmp_path)
    scene = read_scene("blendedmvs", tmp_path)
    assert scene.image_dir == tmp_path / "blended_images"
    assert [v.name for v in scene.views] == ["00000000.jpg", "00000001.jpg", "00000002.jpg"]
    view = scene.view("00000002.jpg")
    np.testing.assert_allclose(view.intrinsics, [579.5, 579.5, 384.5, 288.5])  # +0.5
    assert (view.width, view.height) == (32, 24)
    np.testing.assert_allclose(view.rotation, BLENDED_R)
    np.testing.assert_allclose(view.translation, [2, -1, 4])
    np.testing.assert_allclose(view.centre, -BLENDED_R.T @ [2, -1, 4])
    assert_rotation(view.rotation)
    assert scene.overlap == {
        "00000000.jpg": [("00000001.jpg", 1380.5), ("00000002.jpg", 250.25)],
        "00000001.jpg": [("00000000.jpg", 1380.5)],
        "00000002.jpg": [("00000000.jpg", 250.25)],
    }


def test_blendedmvs_malformed(tmp_path: Path) -> None:
    write_blendedmvs(tmp_path)
    cam = write(tmp_path / "cams" / "00000001_cam.txt", "extrinsic\n1 0 0\n")
    message = read_error("blendedmvs", tmp_path)
    assert message.startswith(f"cannot read BlendedMVS camera file {cam}: ")
    (tmp_path / "cams" / "00000001_cam.txt").unlink()
    assert read_error("blendedmvs", tmp_path) == f"BlendedMVS camera file {cam} not found"
    write_blendedmvs(tmp_path)
    pair = write(tmp_path / "cams" / "pair.txt", "3\n0\n2 1 1380.5\n")
    assert read_error("blendedmvs", tmp_path).startswith(
        f"cannot read BlendedMVS pair file {pair}: "
    )


# --- kitti --------------------------------------------------------------------------

KITTI_CALIB = """P0: 7.188560000000e+02 0 6.071928000000e+02 0 0 7.188560000000e+02 \
1.852157000000e+02 0 0 0 1 0
P1: 7.188560000000e+02 0 6.071928000000e+02 -3.861448000000e+02 0 7.188560000000e+02 \
1.852157000000e+02 0 0 0 1 0
P2: 7.188560000000e+02 0 6.071928000000e+02 4.538225000000e+01 0 7.188560000000e+02 \
1.852157000000e+02 -1.130887000000e-01 0 0 1 3.779761000000e-03
P3: 7.188560000000e+02 0 6.071928000000e+02 -3.372877000000e+02 0 7.188560000000e+02 \
1.852157000000e+02 2.369057000000e+00 0 0 1 4.915215000000e-03
Tr: 1 0 0 0 0 1 0 0 0 0 1 0
"""
# Frame 0 at the origin; frame 1 turned 90° about y, centre (0.5, -0.2, 3).
KITTI_POSES = "1 0 0 0 0 1 0 0 0 0 1 0\n0 0 1 0.5 0 1 0 -0.2 -1 0 0 3.0\n"


def write_kitti(root: Path, poses: str = KITTI_POSES) -> Path:
    sequence = root / "sequences" / "07"
    write(sequence / "calib.txt", KITTI_CALIB)
    for camera in (0, 2):
        for frame in (1, 0):
            write_image(sequence / f"image_{camera}" / f"{frame:06d}.png", 40 + camera, 10)
    write(root / "poses" / "07.txt", poses)
    return sequence


def test_kitti_camera_2_with_poses(tmp_path: Path) -> None:
    sequence = write_kitti(tmp_path)
    scene = read_scene("kitti", sequence)
    assert scene.name == "07" and scene.image_dir == sequence / "image_2"
    assert [v.name for v in scene.views] == ["000000.png", "000001.png"]
    view = scene.views[1]
    np.testing.assert_allclose(view.intrinsics, [718.856, 718.856, 607.6928, 185.7157])
    assert (view.width, view.height) == (42, 10)
    # Baseline of camera 2 in camera-0 coordinates: K⁻¹ P2[:, 3].
    bz = 3.779761e-03
    by = (-1.130887e-01 - 185.2157 * bz) / 718.856
    bx = (45.38225 - 607.1928 * bz) / 718.856
    np.testing.assert_allclose(scene.views[0].rotation, np.eye(3))
    np.testing.assert_allclose(scene.views[0].translation, [bx, by, bz])
    np.testing.assert_allclose(view.rotation, [[0, 0, -1], [0, 1, 0], [1, 0, 0]])
    np.testing.assert_allclose(view.centre, [0.5 - bz, -0.2 - by, 3.0 + bx])
    assert_rotation(view.rotation)


def test_kitti_camera_0_and_options(tmp_path: Path) -> None:
    sequence = write_kitti(tmp_path)
    scene = read_scene("kitti", sequence, camera=0)
    assert scene.image_dir == sequence / "image_0"
    view = scene.views[1]
    np.testing.assert_allclose(view.intrinsics, [718.856, 718.856, 607.6928, 185.7157])
    assert (view.width, view.height) == (40, 10)
    np.testing.assert_allclose(view.centre, [0.5, -0.2, 3.0])
    (tmp_path / "poses" / "07.txt").unlink()
    assert all(v.rotation is None for v in read_scene("kitti", sequence).views)
    other = write(tmp_path / "my_poses.txt", KITTI_POSES)
    scene = read_scene("kitti", sequence, camera=0, poses=other)
    np.testing.assert_allclose(scene.views[1].centre, [0.5, -0.2, 3.0])


def test_kitti_grayscale_only_sequence(tmp_path: Path) -> None:
    """A sequence with only image_0 and a calib.txt of P0 and P1 (as the shared drive)."""
    sequence = tmp_path / "sequences" / "02"
    write(sequence / "calib.txt", "".join(KITTI_CALIB.splitlines(keepends=True)[:2]))
    for frame in (0, 1):
        write_image(sequence / "image_0" / f"{frame:06d}.png", 40, 10)
    scene = read_scene("kitti", sequence)
    assert scene.image_dir == sequence / "image_0"
    np.testing.assert_allclose(scene.views[0].intrinsics, [718.856, 718.856, 607.6928, 185.7157])
    calib = sequence / "calib.txt"
    write_image(sequence / "image_2" / "000000.png", 40, 10)  # images without their P2 line
    assert read_error("kitti", sequence) == (
        f"cannot read KITTI calibration file {calib}: no P2 line"
    )


@pytest.mark.real_data
def test_shared_kitti_drive_is_read() -> None:
    """../shared/datasets/kitti: 51 grayscale frames, KITTI's K and a pose for each."""
    scene = read_scene("kitti", shared_dataset("kitti/sequences/seq2"))
    assert len(scene.views) == 51
    np.testing.assert_allclose(scene.views[0].intrinsics, [718.856, 718.856, 607.6928, 185.7157])
    assert (scene.views[0].width, scene.views[0].height) == (1241, 376)
    assert all(view.rotation is not None for view in scene.views)


def test_kitti_malformed(tmp_path: Path) -> None:
    sequence = write_kitti(tmp_path, poses=KITTI_POSES.splitlines()[0] + "\n")
    poses = tmp_path / "poses" / "07.txt"
    assert read_error("kitti", sequence) == f"{poses} has 1 poses for 2 images"
    write(poses, "1 0 0 0 0 1 0 0 0 0 1\n")
    assert read_error("kitti", sequence) == (
        f"cannot read KITTI poses file {poses}: expected 12 numbers per line"
    )
    calib = write(sequence / "calib.txt", KITTI_CALIB.replace("P2:", "P9:"))
    assert read_error("kitti", sequence) == (
        f"cannot read KITTI calibration file {calib}: no P2 line"
    )
    write(calib, "P0: 1 2 3\n")
    assert read_error("kitti", sequence).startswith(f"cannot read KITTI calibration file {calib}")
    assert read_error("kitti", sequence, camera=5) == "KITTI camera must be 0, 1, 2 or 3, not 5"


# --- tum ----------------------------------------------------------------------------

TUM_RGB = """# color images
# file: 'rgbd_dataset_freiburg1_xyz.bag'
# timestamp filename
1305031102.175304 rgb/1305031102.175304.png
1305031102.211214 rgb/1305031102.211214.png
1305031102.243211 rgb/1305031102.243211.png
1305031105.000000 rgb/1305031105.000000.png
"""
# Out of time order on purpose; the first pose is turned 90° about z.
TUM_GROUNDTRUTH = f"""# ground truth trajectory
# timestamp tx ty tz qx qy qz qw
1305031102.2500 7 8 9 0 0 0 1
1305031102.1758 1 2 3 0 0 {SQRT_HALF} {SQRT_HALF}
1305031102.2100 4 5 6 0 0 0 1
"""


def test_tum_freiburg1_sequence(tmp_path: Path) -> None:
    sequence = tmp_path / "rgbd_dataset_freiburg1_xyz"
    write(sequence / "rgb.txt", TUM_RGB)
    write(sequence / "groundtruth.txt", TUM_GROUNDTRUTH)
    scene = read_scene("tum", sequence)
    assert scene.name == "rgbd_dataset_freiburg1_xyz" and scene.image_dir == sequence
    assert [v.name for v in scene.views] == [
        "rgb/1305031102.175304.png",
        "rgb/1305031102.211214.png",
        "rgb/1305031102.243211.png",
        "rgb/1305031105.000000.png",
    ]
    first = scene.views[0]
    np.testing.assert_allclose(first.intrinsics, [517.3, 516.5, 319.1, 255.8])
    assert (first.width, first.height) == (640, 480)
    np.testing.assert_allclose(first.rotation, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(first.translation, [-2, 1, -3], atol=1e-12)
    np.testing.assert_allclose(scene.views[1].centre, [4, 5, 6])
    np.testing.assert_allclose(scene.views[2].centre, [7, 8, 9])  # 0.0068 s away, not 0.033
    assert scene.views[3].rotation is None and scene.views[3].centre is None


def test_tum_intrinsics_file_and_errors(tmp_path: Path) -> None:
    sequence = tmp_path / "my_sequence"
    write(sequence / "rgb.txt", TUM_RGB)
    assert read_error("tum", sequence) == (
        f"no intrinsics.txt in {sequence} and no freiburg1/2/3 in its name: "
        "cannot tell the TUM camera"
    )
    write(sequence / "intrinsics.txt", "# fx fy cx cy\n525.0 525.0 319.5 239.5\n")
    write_image(sequence / "rgb" / "1305031102.175304.png", 64, 48)
    scene = read_scene("tum", sequence)
    np.testing.assert_allclose(scene.views[3].intrinsics, [525, 525, 320, 240])
    assert (scene.views[3].width, scene.views[3].height) == (64, 48)
    assert scene.views[0].rotation is None
    fr3 = tmp_path / "rgbd_dataset_freiburg3_long_office_household"
    write(fr3 / "rgb.txt", TUM_RGB)
    np.testing.assert_allclose(
        read_scene("tum", fr3).views[0].intrinsics, [535.4, 539.2, 320.6, 248.1]
    )
    groundtruth = write(fr3 / "groundtruth.txt", "1305031102.2500 7 8 9 0 0 0\n")
    assert read_error("tum", fr3) == (
        f"cannot read TUM ground truth {groundtruth}: "
        "expected lines of 8 numbers: timestamp tx ty tz qx qy qz qw"
    )
    rgb = write(fr3 / "rgb.txt", "1305031102.x rgb/a.png\n")
    assert read_error("tum", fr3).startswith(f"cannot read TUM image list {rgb}: ")


# --- dtu ----------------------------------------------------------------------------

DTU_K = np.array([[2892.33, 0.0, 823.205], [0.0, 2883.18, 619.071], [0.0, 0.0, 1.0]])


def dtu_pose(angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    a = np.deg2rad(angle_deg)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    return R, np.array([10.0, -20.0, 500.0 + angle_deg])


def write_dtu(scene: Path, count: int = 2, name: str = "cameras_sphere.npz") -> None:
    mats = {}
    for i in range(count):
        write_image(scene / "image" / f"{i:06d}.png", 16, 12)
        R, t = dtu_pose(10.0 * i)
        world_mat = np.eye(4)
        world_mat[:3] = (-3.0 if i else 2.0) * DTU_K @ np.c_[R, t]  # any scale, any sign
        mats[f"world_mat_{i}"] = world_mat
        mats[f"scale_mat_{i}"] = np.eye(4) * 300
    np.savez(scene / name, **mats)


def test_dtu_scene(tmp_path: Path) -> None:
    write_dtu(tmp_path)
    scene = read_scene("dtu", tmp_path)
    assert scene.image_dir == tmp_path / "image"
    assert [v.name for v in scene.views] == ["000000.png", "000001.png"]
    view = scene.views[1]
    np.testing.assert_allclose(view.intrinsics, [2892.33, 2883.18, 823.705, 619.571])
    assert (view.width, view.height) == (16, 12)
    R, t = dtu_pose(10.0)
    np.testing.assert_allclose(view.rotation, R, atol=1e-12)
    np.testing.assert_allclose(view.translation, t, atol=1e-9)
    np.testing.assert_allclose(view.centre, -R.T @ t, atol=1e-9)
    assert_rotation(view.rotation)


def test_dtu_decomposition_fixes_signs() -> None:
    R, t = dtu_pose(35.0)
    K, R2, t2 = decompose_projection(-0.5 * DTU_K @ np.c_[R, t])  # negative overall scale
    np.testing.assert_allclose(K, DTU_K, atol=1e-9)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-9)


def test_dtu_errors(tmp_path: Path) -> None:
    write_dtu(tmp_path, count=1, name="cameras.npz")
    write_image(tmp_path / "image" / "000001.png", 16, 12)
    assert read_error("dtu", tmp_path) == (
        f"cannot read DTU camera file {tmp_path / 'cameras.npz'}: "
        "'world_mat_1 is not a file in the archive'"
    )
    (tmp_path / "cameras.npz").unlink()
    assert read_error("dtu", tmp_path) == (f"no cameras.npz or cameras_sphere.npz in {tmp_path}")


# --- middlebury ---------------------------------------------------------------------

TEMPLE_LINE = (
    "templeR0001.png 1520.400000 0.000000 302.320000 0.000000 1525.900000 246.870000 "
    "0.000000 0.000000 1.000000 0.01551372092999463300 0.99884343581246959000 "
    "-0.04550950666890610900 0.99922238739871228000 -0.01713749109757305200 "
    "-0.03550952062389494300 -0.03624837030900045700 -0.04492323120101910400 "
    "-0.99833258966392844000 -0.05998547900000000400 0.00400539180000000010 "
    "0.57088300000000002000"
)
SECOND_LINE = "templeR0002.png 1500 0 300 0 1510 250 0 0 1 1 0 0 0 1 0 0 0 1 0.1 0.2 0.3"


def test_middlebury_scene(tmp_path: Path) -> None:
    write(tmp_path / "templeR_par.txt", f"2\n{TEMPLE_LINE}\n{SECOND_LINE}\n")
    write(tmp_path / "templeSR_par.txt", f"1\n{SECOND_LINE}\n")
    write_image(tmp_path / "templeR0001.png", 64, 48)
    scene = read_scene("middlebury", tmp_path)
    assert scene.name == "templeR" and scene.image_dir == tmp_path
    assert [v.name for v in scene.views] == ["templeR0001.png", "templeR0002.png"]
    first, second = scene.views
    np.testing.assert_allclose(first.intrinsics, [1520.4, 1525.9, 302.82, 247.37])
    assert (first.width, first.height) == (64, 48)
    np.testing.assert_allclose(
        first.rotation[0], [0.015513720929994633, 0.9988434358124696, -0.04550950666890611]
    )
    np.testing.assert_allclose(first.translation, [-0.059985479, 0.0040053918, 0.570883])
    np.testing.assert_allclose(first.rotation @ first.rotation.T, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(second.intrinsics, [1500, 1510, 300.5, 250.5])
    np.testing.assert_allclose(second.centre, [-0.1, -0.2, -0.3])
    chosen = read_scene("middlebury", tmp_path, par_file="templeSR_par.txt")
    assert chosen.name == "templeSR" and [v.name for v in chosen.views] == ["templeR0002.png"]


def test_middlebury_images_in_a_folder(tmp_path: Path) -> None:
    """The par file beside an ``images/`` folder (the shared temple ring's layout)."""
    write(tmp_path / "templeR_par.txt", f"1\n{SECOND_LINE}\n")
    write_image(tmp_path / "images" / "templeR0002.png", 64, 48)
    scene = read_scene("middlebury", tmp_path)
    assert scene.image_dir == tmp_path / "images"
    assert (scene.views[0].width, scene.views[0].height) == (64, 48)


# --- euroc --------------------------------------------------------------------------

SENSOR_YAML = """# Kalibr calibration
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375]   # fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
resolution: [752, 480]
"""


def test_euroc_scene(tmp_path: Path) -> None:
    write(tmp_path / "sensor.yaml", SENSOR_YAML)
    for name in ("2.png", "1.png"):
        write_image(tmp_path / "data" / name, 752, 480)
    scene = read_scene("euroc", tmp_path)
    assert scene.image_dir == tmp_path / "data"
    assert [v.name for v in scene.views] == ["1.png", "2.png"]
    np.testing.assert_allclose(scene.views[0].intrinsics, [458.654, 457.296, 367.715, 248.875])
    assert (scene.views[0].width, scene.views[0].height) == (752, 480)
    assert scene.distortion == pytest.approx(
        {"k1": -0.28340811, "k2": 0.07395907, "p1": 0.00019359, "p2": 1.76187114e-05}
    )


def test_euroc_malformed(tmp_path: Path) -> None:
    assert (
        read_error("euroc", tmp_path) == f"EuRoC sensor file {tmp_path / 'sensor.yaml'} not found"
    )
    sensor = write(tmp_path / "sensor.yaml", SENSOR_YAML.replace("367.215, 248.375", "367.2"))
    assert read_error("euroc", tmp_path) == (
        f"cannot read EuRoC sensor file {sensor}: expected intrinsics: [4 numbers]"
    )
    write(sensor, SENSOR_YAML)
    assert read_error("euroc", tmp_path) == f"no images/ or data/ folder in {tmp_path}"


# --- nerf ---------------------------------------------------------------------------


def test_nerf_scene(tmp_path: Path) -> None:
    """fx = (W / 2) / tan(angle / 2), centred; OpenGL camera-to-world becomes OpenCV
    world-to-camera (a camera at (0, 0, 4) looking down -z sees the origin ahead)."""
    c2w = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]
    frames = [{"file_path": "./train/r_0", "transform_matrix": c2w}]
    write(tmp_path / "transforms_train.json", json.dumps({"camera_angle_x": 0.5, "frames": frames}))
    write_image(tmp_path / "train" / "r_0.png", 80, 60)
    scene = read_scene("nerf", tmp_path)
    (view,) = scene.views
    assert view.name == "train/r_0.png"
    focal = 40 / np.tan(0.25)
    np.testing.assert_allclose(view.intrinsics, [focal, focal, 40, 30])
    np.testing.assert_allclose(view.centre, [0, 0, 4])
    origin_in_camera = view.rotation @ np.zeros(3) + view.translation
    assert origin_in_camera[2] == pytest.approx(4.0)  # ahead (OpenCV: +z forward)


def test_nerf_malformed(tmp_path: Path) -> None:
    transforms = write(tmp_path / "transforms_train.json", json.dumps({"frames": []}))
    assert read_error("nerf", tmp_path).startswith(
        f"cannot read NeRF transforms file {transforms}: "
    )
    assert read_error("nerf", tmp_path, split="test") == (
        f"NeRF transforms file {tmp_path / 'transforms_test.json'} not found"
    )


def test_middlebury_malformed(tmp_path: Path) -> None:
    assert read_error("middlebury", tmp_path) == f"no *_par.txt file in {tmp_path}"
    par = write(tmp_path / "dino_par.txt", f"3\n{TEMPLE_LINE}\n{SECOND_LINE}\n")
    assert read_error("middlebury", tmp_path) == (
        f"cannot read Middlebury parameter file {par}: 3 images announced, 2 lines found"
    )
    write(par, f"1\n{SECOND_LINE[:-4]}\n")
    assert read_error("middlebury", tmp_path) == (
        f"cannot read Middlebury parameter file {par}: "
        "expected an image name and 21 numbers per line"
    )
    missing = tmp_path / "other_par.txt"
    assert read_error("middlebury", tmp_path, par_file="other_par.txt") == (
        f"Middlebury parameter file {missing} not found"
    )
