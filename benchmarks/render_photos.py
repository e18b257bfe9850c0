"""Render photo-like 3072x2048 JPEGs of a textured 3D scene with a known pinhole camera.

The scene is a walled courtyard (a floor, four walls at different distances, an
open sky) with three boxes standing in it. Every face is a rectangle textured
with a crop of a real Strecha photograph (fountain-P11, Herz-Jesus-P8), so SIFT
finds real-looking features. Each pixel is rendered by casting its ray and taking
the nearest positive hit over all faces (a z-buffer over ray-plane
intersections, vectorised numpy), then sampling the face's texture with
``cv2.remap`` from a mip-map level chosen by the pixel's footprint (trilinear, no
aliasing on distant walls). Faces are Lambert-shaded by one sun direction; the
images get vignetting, sensor noise and JPEG compression.

Cameras stand on an arc around the courtyard centre (default 330°, so 30 images
are ~11° apart), at varying radius and height, each looking at a jittered point
near the centre, with extra yaw / pitch jitter and a random roll: real 3D
structure, real rotation, and optical axes that do not meet in one point.

The camera is the Strecha one by default: PINHOLE fx=2759.48, fy=2764.16,
cx=1520.69, cy=1006.81 at 3072x2048, COLMAP pixel convention (the centre of the
top-left pixel is at (0.5, 0.5); the ray of pixel column i, row j goes through
(i + 0.5, j + 0.5)).

Outputs in OUT: ``images/NNNN.jpg`` and ``ground_truth.json``::

    {"model": "PINHOLE", "width": 3072, "height": 2048,
     "intrinsics": {"fx", "fy", "cx", "cy"}, "K": 3x3,
     "images": [{"name": "0000.jpg", "R": 3x3, "t": 3, "center": 3}, ...]}

with world-to-camera poses ``x_cam = R X + t`` (camera +z forward, +x right, +y
down), world units metres, world +z up.

    python benchmarks/render_photos.py /work/bench_data/render30 --images 30 --seed 0
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TEXTURES = ROOT.parent / "shared" / "datasets" / "strecha"
STRECHA_K = (2759.48, 2764.16, 1520.69, 1006.81)
WIDTH, HEIGHT = 3072, 2048
#: Texture resolution cap, texels per metre (more is never seen at these distances).
MAX_TEXELS_PER_METRE = 700.0
MIP_LEVELS = 7
SKY_TOP = np.array([235.0, 200.0, 160.0])  # BGR: pale blue at the zenith
SKY_BOTTOM = np.array([245.0, 235.0, 225.0])


@dataclass
class Face:
    """A textured rectangle ``origin + a·u + b·v`` (a, b in [0, 1]), seen from side ``normal``."""

    origin: np.ndarray  # (3,)
    u: np.ndarray  # (3,) edge vector, texture x
    v: np.ndarray  # (3,) edge vector, texture y
    normal: np.ndarray  # (3,) unit, pointing to the side the cameras see
    texture: int  # index into the texture list


def box_faces(
    center: tuple[float, float], size: tuple[float, float, float], first: int
) -> list[Face]:
    """The four sides and the top of a box standing on the floor (z = 0)."""
    cx, cy = center
    hx, hy, sz = size[0] / 2, size[1] / 2, size[2]
    x0, x1, y0, y1 = cx - hx, cx + hx, cy - hy, cy + hy
    up = np.array([0.0, 0.0, sz])
    faces = [
        # Texture y runs downwards in images, so v points down (from the top edge).
        Face(np.array([x0, y0, sz]), np.array([x1 - x0, 0, 0]), -up, np.array([0.0, -1, 0]), first),
        Face(
            np.array([x1, y0, sz]), np.array([0, y1 - y0, 0]), -up, np.array([1.0, 0, 0]), first + 1
        ),
        Face(
            np.array([x1, y1, sz]), np.array([x0 - x1, 0, 0]), -up, np.array([0.0, 1, 0]), first + 2
        ),
        Face(
            np.array([x0, y1, sz]),
            np.array([0, y0 - y1, 0]),
            -up,
            np.array([-1.0, 0, 0]),
            first + 3,
        ),
        Face(
            np.array([x0, y1, sz]),
            np.array([x1 - x0, 0, 0]),
            np.array([0, y0 - y1, 0]),
            np.array([0.0, 0, 1]),
            first + 4,
        ),
    ]
    return [
        Face(f.origin.astype(float), f.u.astype(float), f.v.astype(float), f.normal, f.texture)
        for f in faces
    ]


def courtyard(half_x: float = 9.0, half_y: float = 7.0, wall: float = 5.0) -> list[Face]:
    """Floor (3 x 3 tiles), four walls of two panels each (seen from inside), three boxes.

    Every face has its own texture index (0..31), so that no texture is stretched
    over a large area.
    """
    X, Y, Z = half_x, half_y, wall
    down = np.array([0.0, 0.0, -Z])
    up_normal = np.array([0.0, 0.0, 1.0])
    faces = []
    tiles = 3
    for i in range(tiles):
        for j in range(tiles):
            origin = np.array([-X + 2 * X * i / tiles, Y - 2 * Y * j / tiles, 0.0])
            u = np.array([2 * X / tiles, 0.0, 0.0])
            v = np.array([0.0, -2 * Y / tiles, 0.0])
            faces.append(Face(origin, u, v, up_normal, len(faces)))
    # Wall corners counter-clockwise seen from above; each wall faces the inside.
    corners = [(-X, Y), (X, Y), (X, -Y), (-X, -Y)]
    for k in range(4):
        (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
        edge = np.array([x1 - x0, y1 - y0, 0.0])
        normal = np.array([-(y1 - y0), x1 - x0, 0.0])
        normal = -normal / np.linalg.norm(normal)
        if np.dot(normal, [-x0, -y0, 0.0]) < 0:
            normal = -normal
        for half in range(2):
            origin = np.array([x0, y0, Z]) + edge * half / 2
            faces.append(Face(origin, edge / 2, down, normal, len(faces)))
    faces += box_faces((0.9, 0.6), (1.6, 1.2, 1.4), len(faces))
    faces += box_faces((-1.1, -0.7), (1.1, 1.5, 0.9), len(faces))
    faces += box_faces((0.2, -1.7), (0.7, 0.7, 2.1), len(faces))
    return faces


def load_textures(
    folder: Path, faces: list[Face], rng: np.random.Generator
) -> list[list[np.ndarray]]:
    """One mip-map pyramid per face: a random crop of a Strecha photo at the face's aspect.

    Photos are assigned round-robin over both scenes (shuffled by the seed); crops
    are flipped for odd faces and tinted slightly, so that no two faces look alike.
    """
    photos = sorted(folder.glob("*/images/*.jpg"))
    if not photos:
        raise SystemExit(f"error: no Strecha photos under {folder} (use --textures)")
    order = rng.permutation(len(photos))
    pyramids = []
    for index, face in enumerate(faces):
        photo = cv2.imread(str(photos[order[index % len(photos)]]), cv2.IMREAD_COLOR)
        width_m, height_m = np.linalg.norm(face.u), np.linalg.norm(face.v)
        aspect = width_m / height_m
        h, w = photo.shape[:2]
        crop_w = min(w, int(h * aspect)) if aspect >= w / h else int(rng.uniform(0.5, 1.0) * w)
        crop_h = min(h, int(crop_w / aspect))
        crop_w = min(w, int(crop_h * aspect))
        x0 = int(rng.integers(0, w - crop_w + 1))
        y0 = int(rng.integers(0, h - crop_h + 1))
        texture = photo[y0 : y0 + crop_h, x0 : x0 + crop_w]
        if index % 2:
            texture = texture[:, ::-1]
        texels = min(MAX_TEXELS_PER_METRE, crop_w / width_m)
        size = (max(8, int(texels * width_m)), max(8, int(texels * height_m)))
        texture = cv2.resize(texture, size, interpolation=cv2.INTER_AREA).astype(np.float32)
        texture *= rng.uniform(0.85, 1.15, 3).astype(np.float32)
        pyramid = [np.clip(texture, 0, 255).astype(np.uint8)]
        for _ in range(MIP_LEVELS - 1):
            if min(pyramid[-1].shape[:2]) < 4:
                break
            pyramid.append(cv2.pyrDown(pyramid[-1]))
        pyramids.append(pyramid)
    return pyramids


def look_at(center: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """World-to-camera rotation (rows: camera x, y, z in world) looking at ``target``, +z up."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z])


def camera_path(
    count: int, rng: np.random.Generator, arc_deg: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(R, t) per image: an arc around the centre with varying radius, height, target, roll."""
    angles = np.deg2rad(-arc_deg / 2 + arc_deg * np.arange(count) / max(count - 1, 1))
    poses = []
    for angle in angles:
        radius = rng.uniform(4.2, 5.4)
        center = np.array([radius * np.cos(angle), radius * np.sin(angle), rng.uniform(1.2, 2.2)])
        target = np.array([rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8), rng.uniform(0.3, 1.3)])
        R = look_at(center, target, np.deg2rad(rng.uniform(-10, 10)))
        # Extra yaw / pitch about the camera's own axes.
        yaw, pitch = np.deg2rad(rng.uniform(-5, 5, 2))
        Ry = cv2.Rodrigues(np.array([0.0, yaw, 0.0]))[0]
        Rx = cv2.Rodrigues(np.array([pitch, 0.0, 0.0]))[0]
        R = Rx @ Ry @ R
        poses.append((R, -R @ center))
    return poses


def face_bbox(
    face: Face, K: np.ndarray, R: np.ndarray, t: np.ndarray, size: tuple[int, int]
) -> tuple[int, int, int, int] | None:
    """Pixel box (col0, col1, row0, row1) that contains the face's image; None if unseen.

    The face polygon is clipped against the plane z = 0.01 in front of the camera
    before projecting its corners, so faces partly behind the camera are bounded too.
    """
    corners = [
        face.origin,
        face.origin + face.u,
        face.origin + face.u + face.v,
        face.origin + face.v,
    ]
    cam = [R @ c + t for c in corners]
    near = 0.01
    clipped = []
    for k in range(4):
        p, q = cam[k], cam[(k + 1) % 4]
        if p[2] >= near:
            clipped.append(p)
        if (p[2] >= near) != (q[2] >= near):
            clipped.append(p + (q - p) * (near - p[2]) / (q[2] - p[2]))
    if not clipped:
        return None
    pts = np.array(clipped)
    x = K[0, 0] * pts[:, 0] / pts[:, 2] + K[0, 2]
    y = K[1, 1] * pts[:, 1] / pts[:, 2] + K[1, 2]
    width, height = size
    col0, col1 = max(0, int(np.floor(x.min())) - 1), min(width, int(np.ceil(x.max())) + 1)
    row0, row1 = max(0, int(np.floor(y.min())) - 1), min(height, int(np.ceil(y.max())) + 1)
    if col0 >= col1 or row0 >= row1:
        return None
    return col0, col1, row0, row1


def render(
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    faces: list[Face],
    pyramids: list[list[np.ndarray]],
    rng: np.random.Generator,
    size: tuple[int, int] = (WIDTH, HEIGHT),
) -> np.ndarray:
    """One uint8 BGR image: nearest-hit ray casting, mip-mapped texture sampling, shading.

    The ray of pixel (col, row) is ``d = Rᵀ (xn, yn, 1)`` with ``xn = (col + 0.5 − cx) / fx``,
    ``yn = (row + 0.5 − cy) / fy``: its parameter at a hit is the camera-frame depth.
    Every per-face quantity is linear in (xn, yn), so it is formed by broadcasting a
    column and a row vector over the face's pixel box only.
    """
    width, height = size
    center = -R.T @ t
    xn = ((np.arange(width) + 0.5 - K[0, 2]) / K[0, 0]).astype(np.float32)
    yn = ((np.arange(height) + 0.5 - K[1, 2]) / K[1, 1]).astype(np.float32)
    depth = np.full((height, width), np.inf, np.float32)
    owner = np.full((height, width), -1, np.int16)
    coords_a = np.zeros((height, width), np.float32)
    coords_b = np.zeros((height, width), np.float32)
    boxes: dict[int, tuple[int, int, int, int]] = {}

    def linear(vector: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
        """``vector · d`` over the box: (R vector) · (xn, yn, 1)."""
        c = (R @ vector).astype(np.float32)
        col0, col1, row0, row1 = box
        return c[0] * xn[None, col0:col1] + (c[1] * yn[row0:row1, None] + c[2])

    for index, face in enumerate(faces):
        # Seen from the front only (the camera is on the normal's side).
        distance = float(np.dot(face.origin - center, face.normal))
        if distance >= 0:
            continue
        box = face_bbox(face, K, R, t, size)
        if box is None:
            continue
        boxes[index] = box
        col0, col1, row0, row1 = box
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = np.float32(distance) / linear(face.normal, box)
            offset = center - face.origin
            uu, vv = np.dot(face.u, face.u), np.dot(face.v, face.v)
            a = np.float32(np.dot(offset, face.u) / uu) + tt * linear(face.u / uu, box)
            b = np.float32(np.dot(offset, face.v) / vv) + tt * linear(face.v / vv, box)
        window = (slice(row0, row1), slice(col0, col1))
        hit = (tt > 1e-3) & (tt < depth[window])
        hit &= (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        np.copyto(depth[window], tt, where=hit)
        np.copyto(owner[window], np.int16(index), where=hit)
        np.copyto(coords_a[window], a, where=hit)
        np.copyto(coords_b[window], b, where=hit)

    image = np.zeros((height, width, 3), np.float32)
    sun = np.array([0.45, -0.35, 0.82])
    sun /= np.linalg.norm(sun)
    focal = float(np.sqrt(K[0, 0] * K[1, 1]))
    for index, box in boxes.items():
        face = faces[index]
        col0, col1, row0, row1 = box
        window = (slice(row0, row1), slice(col0, col1))
        mask = owner[window] == index
        if not mask.any():
            continue
        pyramid = pyramids[face.texture]
        base = pyramid[0]
        texels = base.shape[1] / np.linalg.norm(face.u)
        # |cos| between ray and normal: the pixel footprint on the face is stretched by 1/cos.
        ray_norm = np.sqrt(xn[None, col0:col1] ** 2 + yn[row0:row1, None] ** 2 + 1.0)
        slant = np.abs(linear(face.normal, box))[mask] / ray_norm[mask]
        footprint = (
            depth[window][mask] * ray_norm[mask] / focal * texels / np.sqrt(np.maximum(slant, 0.05))
        )
        level = np.clip(np.log2(np.maximum(footprint, 1.0)), 0, len(pyramid) - 1)
        xa = coords_a[window][mask] * base.shape[1]
        xb = coords_b[window][mask] * base.shape[0]
        colour = np.zeros((len(level), 3), np.float32)
        for lv in range(int(np.floor(level.min())), int(np.ceil(level.max())) + 1):
            weight = np.maximum(0.0, 1.0 - np.abs(level - lv))
            use = weight > 0
            if not use.any():
                continue
            scale = 2.0**lv
            colour[use] += weight[use, None] * sample(
                pyramid[lv], xa[use] / scale - 0.5, xb[use] / scale - 0.5
            )
        shade = 0.62 + 0.38 * max(0.0, float(np.dot(face.normal, sun)))
        image[window][mask] = colour * shade
    sky = owner < 0
    if sky.any():
        rows, cols = np.nonzero(sky)
        d = R.T @ np.stack([xn[cols], yn[rows], np.ones(len(rows), np.float32)])
        elevation = np.clip(d[2] / np.linalg.norm(d, axis=0), 0, 1)
        image[sky] = SKY_BOTTOM + (SKY_TOP - SKY_BOTTOM) * elevation[:, None]
    # Camera: slight blur (lens), vignetting, noise.
    image = cv2.GaussianBlur(image, (0, 0), 0.6)
    r2 = ((xn * K[0, 0]) ** 2)[None, :] + ((yn * K[1, 1]) ** 2)[:, None]
    image *= (1.0 - 0.3 * r2 / ((width / 2) ** 2 + (height / 2) ** 2))[..., None]
    image += rng.normal(0.0, 2.0, image.shape).astype(np.float32)
    return np.clip(image, 0, 255).astype(np.uint8)


def sample(texture: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear texture samples (n, 3) at texel coordinates (centre of texel 0 at 0)."""
    n = len(x)
    width = 4096
    rows = -(-n // width)
    pad = rows * width - n
    map_x = np.concatenate([x, np.zeros(pad, np.float32)]).reshape(rows, width).astype(np.float32)
    map_y = np.concatenate([y, np.zeros(pad, np.float32)]).reshape(rows, width).astype(np.float32)
    out = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out.reshape(-1, 3)[:n].astype(np.float32)


#: Scene shared with the forked render processes (inherited, never pickled: the
#: texture pyramids are hundreds of MB).
_STATE: dict = {}


def _render_job(job: tuple[int, np.ndarray, np.ndarray, int, str, int]) -> str:
    index, R, t, seed, path, quality = job
    cv2.setNumThreads(1)
    image = render(
        _STATE["K"], R, t, _STATE["faces"], _STATE["pyramids"], np.random.default_rng(seed)
    )
    cv2.imwrite(path, image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("out", type=Path, help="output folder (images/ and ground_truth.json)")
    parser.add_argument("--images", type=int, default=30, help="number of images")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arc", type=float, default=330.0, help="arc of camera positions, degrees")
    parser.add_argument(
        "--textures",
        type=Path,
        default=DEFAULT_TEXTURES,
        help="folder with */images/*.jpg photographs (default: the Strecha scenes)",
    )
    parser.add_argument(
        "--intrinsics",
        default=",".join(map(str, STRECHA_K)),
        help="FX,FY,CX,CY in pixels (default: the Strecha camera)",
    )
    parser.add_argument("--quality", type=int, default=92, help="JPEG quality")
    parser.add_argument("--workers", type=int, default=2, help="render processes")
    args = parser.parse_args(argv)

    # OpenCV's thread pool does not survive fork(): keep it single-threaded in the
    # parent too (the render processes give the parallelism).
    cv2.setNumThreads(1)
    fx, fy, cx, cy = (float(v) for v in args.intrinsics.split(","))
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(args.seed)
    faces = courtyard()
    pyramids = load_textures(args.textures, faces, rng)
    poses = camera_path(args.images, rng, args.arc)
    seeds = rng.integers(0, 2**31, args.images)
    (args.out / "images").mkdir(parents=True, exist_ok=True)
    names = [f"{i:04d}.jpg" for i in range(args.images)]
    jobs = [
        (i, R, t, int(s), str(args.out / "images" / name), args.quality)
        for i, ((R, t), s, name) in enumerate(zip(poses, seeds, names, strict=True))
    ]
    start = time.perf_counter()
    _STATE.update(K=K, faces=faces, pyramids=pyramids)
    with ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("fork")) as pool:
        for _ in tqdm(pool.map(_render_job, jobs), total=len(jobs), desc="rendering"):
            pass
    truth = {
        "model": "PINHOLE",
        "width": WIDTH,
        "height": HEIGHT,
        "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy},
        "K": K.tolist(),
        "convention": "x_cam = R X + t (world to camera, camera +z forward, +y down); pixel "
        "centres at (i + 0.5, j + 0.5) (COLMAP); world metres, +z up",
        "seed": args.seed,
        "images": [
            {"name": name, "R": R.tolist(), "t": t.tolist(), "center": (-R.T @ t).tolist()}
            for name, (R, t) in zip(names, poses, strict=True)
        ],
    }
    (args.out / "ground_truth.json").write_text(json.dumps(truth, indent=1))
    print(
        f"rendered {args.images} images to {args.out / 'images'} in "
        f"{time.perf_counter() - start:.1f} s; ground truth: {args.out / 'ground_truth.json'}"
    )


if __name__ == "__main__":
    main()
