"""A database as hloc writes it: keypoints and matches imported, verified by pycolmap.

hloc (cvg/Hierarchical-Localization, ``reconstruction.main``) creates an empty
database, imports the images (``pycolmap.import_images``, one SIMPLE_RADIAL camera per
image with COLMAP's guess f = 1.2·max(w, h)), writes its own keypoints (+0.5: COLMAP's
pixel centre) and matches, and runs ``pycolmap.verify_matches`` on the listed pairs.
There are no descriptors and no SIFT. Here OpenCV ORB keypoints stand in for the
learned ones (2000 per image, as SuperPoint gives), matched by mutual nearest
neighbours, on rendered views of a textured room corner with a known camera.
docs/hloc.md is the recipe.
"""

from __future__ import annotations

import itertools
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_trifocal import CalibrationOptions, calibrate_database

WIDTH, HEIGHT = 800, 600
#: The rendering camera (COLMAP's pixel convention): fx = fy, as SIMPLE_RADIAL has it.
TRUTH = np.array([700.0, 700.0, 410.0, 290.0])
#: A room corner seen from inside (no face hides another): each face as its corner,
#: width and height vectors, in metres, camera convention (x right, y down, z forward).
FACES = (
    (np.array([-2.0, -1.5, 0.5]), np.array([0.0, 0.0, 3.5]), np.array([0.0, 3.0, 0.0])),
    (np.array([-2.0, -1.5, 4.0]), np.array([4.0, 0.0, 0.0]), np.array([0.0, 3.0, 0.0])),
    (np.array([-2.0, 1.5, 0.5]), np.array([4.0, 0.0, 0.0]), np.array([0.0, 0.0, 3.5])),
)
NUM_IMAGES = 8
NUM_KEYPOINTS = 2000


def _texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """(size, size) uint8: smooth noise at three scales with random rectangles and discs."""
    texture = np.zeros((size, size), np.float32)
    for cells in (8, 32, 128):
        noise = rng.random((cells, cells), dtype=np.float32)
        texture += cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC) * cells**-0.3
    texture = (texture - texture.min()) / np.ptp(texture) * 160 + 40
    for x, y, w, h, grey in rng.integers(0, size, (400, 5)):
        cv2.rectangle(
            texture,
            (int(x), int(y)),
            (int(x + w % 54 + 6), int(y + h % 54 + 6)),
            int(grey % 256),
            -1,
        )
    for x, y, radius, grey in rng.integers(0, size, (300, 4)):
        cv2.circle(texture, (int(x), int(y)), int(radius % 22 + 3), int(grey % 256), -1)
    return np.clip(texture, 0, 255).astype(np.uint8)


def _look_at(centre: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """World-to-camera rotation of a camera at ``centre`` looking at ``target`` (y down)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.stack([x, np.cross(z, x), z])


def _render(
    rotation: np.ndarray, translation: np.ndarray, textures: list[np.ndarray]
) -> np.ndarray:
    """The grey image of the corner: each face its texture warped by its plane homography."""
    k_opencv = np.array([[TRUTH[0], 0, TRUTH[2] - 0.5], [0, TRUTH[1], TRUTH[3] - 0.5], [0, 0, 1]])
    image = np.zeros((HEIGHT, WIDTH), np.uint8)
    for (corner, across, down), texture in zip(FACES, textures, strict=True):
        size = texture.shape[0]
        plane = np.stack([across / size, down / size, corner], axis=1)  # texel -> world
        homography = k_opencv @ (rotation @ plane + np.outer(translation, [0.0, 0.0, 1.0]))
        warped = cv2.warpPerspective(texture, homography, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR)
        inside = cv2.warpPerspective(np.ones_like(texture), homography, (WIDTH, HEIGHT)) > 0
        image[inside] = warped[inside]
    return image


def render_corner(folder: Path, seed: int = 0) -> list[str]:
    """Write ``NUM_IMAGES`` views along an arc into ``folder`` (PNG, grey noise of std 2)."""
    rng = np.random.default_rng(seed)
    textures = [_texture(rng) for _ in FACES]
    folder.mkdir(parents=True)
    names = []
    for k in range(NUM_IMAGES):
        angle = np.deg2rad(-25.0 + 50.0 * k / (NUM_IMAGES - 1))
        centre = np.array(
            [0.3 + 1.2 * np.sin(angle), rng.uniform(-0.3, 0.3), -0.5 - 0.5 * np.cos(angle)]
        )
        target = np.array([-0.8, 0.3, 3.3]) + rng.normal(0.0, 0.2, 3)
        rotation = _look_at(centre, target, rng.uniform(-0.05, 0.05))
        image = _render(rotation, -rotation @ centre, textures).astype(np.float64)
        image = np.clip(image + rng.normal(0.0, 2.0, image.shape), 0, 255).astype(np.uint8)
        names.append(f"{k:04d}.png")
        cv2.imwrite(str(folder / names[-1]), image)
    return names


def orb_features(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) float32 keypoints (OpenCV's pixel convention, centre of a pixel at 0) and
    their binary descriptors: the ``NUM_KEYPOINTS`` strongest ORB features."""
    orb = cv2.ORB_create(nfeatures=NUM_KEYPOINTS)
    keypoints, descriptors = orb.detectAndCompute(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), None)
    return np.array([k.pt for k in keypoints], np.float32), descriptors


def mutual_nearest_neighbours(descriptors0: np.ndarray, descriptors1: np.ndarray) -> np.ndarray:
    """(m, 2) uint32 indices of mutual nearest neighbours (Hamming distance)."""
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(descriptors0, descriptors1)
    return np.array([[m.queryIdx, m.trainIdx] for m in matches], np.uint32).reshape(-1, 2)


def hloc_style_database(image_dir: Path, names: list[str], database: Path) -> Path:
    """hloc's stages 1-6: empty database, images, keypoints, matches, verification."""
    with pycolmap.Database.open(str(database)):
        pass  # an empty database with COLMAP's tables
    pycolmap.import_images(database, image_dir, pycolmap.CameraMode.AUTO, image_names=names)
    features = {name: orb_features(image_dir / name) for name in names}
    pairs = list(itertools.combinations(names, 2))
    with pycolmap.Database.open(str(database)) as db:
        image_ids = {image.name: image.image_id for image in db.read_all_images()}
        for name, (keypoints, _) in features.items():
            db.write_keypoints(image_ids[name], keypoints + 0.5)  # COLMAP's pixel centre
        for name0, name1 in pairs:
            matches = mutual_nearest_neighbours(features[name0][1], features[name1][1])
            db.write_matches(image_ids[name0], image_ids[name1], matches)
    pairs_file = database.with_name("pairs.txt")
    pairs_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.max_num_trials = 20000  # hloc's settings
    options.ransac.min_inlier_ratio = 0.1
    pycolmap.set_random_seed(0)
    pycolmap.verify_matches(database, pairs_file, options)
    return database


@pytest.fixture(scope="module")
def hloc_database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("hloc")
    names = render_corner(folder / "images")
    return hloc_style_database(folder / "images", names, folder / "database.db")


def test_hloc_style_database_calibrates(hloc_database: Path) -> None:
    """From COLMAP's guess (f 37 % long, centred) to within 0.5 % of the rendering camera.

    Measured 0.15 % (seed 0; 0.19 % and 0.11 % with seeds 1 and 2); SIFT keypoints
    through the same import gave 0.18 %."""
    con = sqlite3.connect(f"{hloc_database.as_uri()}?mode=ro", uri=True)
    try:
        assert con.execute("SELECT COUNT(*) FROM descriptors").fetchone()[0] == 0
        counts = [n for (n,) in con.execute("SELECT rows FROM keypoints")]
        cameras = con.execute("SELECT COUNT(*) FROM cameras").fetchone()[0]
    finally:
        con.close()
    assert counts == [NUM_KEYPOINTS] * NUM_IMAGES and cameras == NUM_IMAGES
    (result,) = calibrate_database(hloc_database, CalibrationOptions(seed=0))
    assert result.camera_ids == list(range(1, NUM_IMAGES + 1))  # one physical camera
    assert result.model == "SIMPLE_RADIAL"
    assert result.prior[0] == pytest.approx(1.2 * WIDTH)
    error = np.abs(result.intrinsics / TRUTH - 1)
    assert error.mean() <= 0.005, result.intrinsics
    assert result.num_inlier_triplets >= 0.75 * result.num_triplets


def _mapped_intrinsics(database: Path, image_dir: Path, output: Path, **options: bool) -> float:
    """Mean error (fraction) of the cameras' (f, f, cx, cy) after pycolmap's incremental
    mapping of ``database`` (one thread; ``options``: IncrementalPipelineOptions)."""
    settings = pycolmap.IncrementalPipelineOptions()
    settings.num_threads = 1
    for name, value in options.items():
        setattr(settings, name, value)
    models = pycolmap.incremental_mapping(database, image_dir, output, settings)
    model = max(models.values(), key=lambda m: m.num_reg_images())
    assert model.num_reg_images() == NUM_IMAGES
    params = np.array([c.params for c in model.cameras.values()])
    return float(np.mean(np.abs(params[:, [0, 0, 1, 2]] / TRUTH - 1)))


@pytest.mark.slow  # three mappings of the 8 images
def test_calibrate_between_verification_and_reconstruction(
    hloc_database: Path, tmp_path: Path
) -> None:
    """docs/hloc.md: mapping hloc's database as it is ends with K 3.4 % off (the centred
    principal point absorbed by a spurious k = -0.026); calibrated and written first,
    0.37 % (the mapper still refining f and k of every per-image camera), 0.15 %
    holding what the calibration determined. A model of the uncalibrated database
    keeps its spurious distortion: calibrating from its tracks gives 2.3 %."""
    import shutil

    from colmap_trifocal import calibrate_reconstruction

    images = hloc_database.parent / "images"
    plain = shutil.copyfile(hloc_database, tmp_path / "plain.db")
    assert _mapped_intrinsics(plain, images, tmp_path / "plain") > 0.02
    calibrated = shutil.copyfile(hloc_database, tmp_path / "calibrated.db")
    calibrate_database(calibrated, CalibrationOptions(seed=0, write=True))
    assert _mapped_intrinsics(calibrated, images, tmp_path / "default") < 0.008
    held = _mapped_intrinsics(
        calibrated,
        images,
        tmp_path / "held",
        ba_refine_focal_length=False,
        ba_refine_extra_params=False,
    )
    assert held < 0.004
    model = pycolmap.Reconstruction(tmp_path / "plain" / "0")
    (from_model,) = calibrate_reconstruction(model, CalibrationOptions(seed=0))
    assert np.mean(np.abs(from_model.intrinsics / TRUTH - 1)) > 0.01
