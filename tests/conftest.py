"""Shared fixtures: real COLMAP databases (built once, cached), synthetic ones, the CLI in process.

Markers (``pyproject.toml``):

* ``real_data``: the test reads ``../shared/datasets`` (or ``$COLMAP_TRIFOCAL_DATASETS``).
  Every other test runs with ``COLMAP_TRIFOCAL_DATASETS`` pointing at a folder that does
  not exist (set before its fixtures, so notebooks and subprocesses inherit it), and
  :func:`shared_dataset` fails in a test without the marker: ``-m "not real_data"``
  reads no real data.
* ``slow``: more than about 10 s on 2 cores: notebook executions, databases built from
  real images, real signals sent over whole runs, mapping runs, sweeps over seeds.
  Sweeps whose point is a statistic (coverage, means over many seeds) are benchmarks
  (``benchmarks/``); a test keeps one or two seeds of the same code.

Databases built from images (SIFT, matching: about a minute per Strecha scene on 2
cores) come from :class:`DatabaseCache`: one build per key, shared by the xdist workers
of a run and kept for the next runs in pytest's cache folder (``.pytest_cache``,
``pytest --cache-clear`` empties it). Cached databases are read-only for the tests: a
test that writes copies first (:meth:`DatabaseCache.copy`), and every fetch checks the
cached file's sha256 against the one recorded when it was built.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_trifocal.database import features as features_module
from colmap_trifocal.database.cameras import CameraInfo
from colmap_trifocal.database.features import build_database
from colmap_trifocal.database.snapshot import DatabaseContents
from colmap_trifocal.datasets.strecha import DATASETS_ENV, default_datasets_root
from colmap_trifocal.intrinsics.inputs.prior import default_guess
from colmap_trifocal.synthetic.database import CAMERA_ID, scene_contents
from colmap_trifocal.synthetic.lenses import with_radial_distortion
from colmap_trifocal.synthetic.motions import handheld_indoor

PROJECT_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PROJECT_ROOT / "benchmarks"))  # real_scenes: the benchmark's scenes
#: Where the datasets are for ``real_data`` tests (read before any test changes the variable).
DATASETS_ROOT = default_datasets_root(PROJECT_ROOT)
#: ``$COLMAP_TRIFOCAL_DATASETS`` during a test without the ``real_data`` marker.
NO_REAL_DATA = Path("/nonexistent/colmap-trifocal-tests/real-data-needs-the-real_data-marker")

_current_item: pytest.Item | None = None


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() == "true"


def skip_or_fail(message: str) -> None:
    """Skip with ``message``; under ``CI=true`` fail with it (CI must have everything)."""
    if in_ci():
        pytest.fail(message)
    pytest.skip(message)


# --------------------------------------------------------------------------- real data


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Outside ``real_data`` tests the datasets variable names a missing folder.

    Set around the whole test (its fixtures too, whatever their scope), restored after.
    """
    global _current_item
    _current_item = item
    real = item.get_closest_marker("real_data") is not None
    saved = os.environ.get(DATASETS_ENV)
    if not real:
        os.environ[DATASETS_ENV] = str(NO_REAL_DATA)
    try:
        yield
    finally:
        _current_item = None
        if saved is None:
            os.environ.pop(DATASETS_ENV, None)
        else:
            os.environ[DATASETS_ENV] = saved


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The ``slow`` tests first, in their collected order, then the rest.

    Under pytest-xdist the workers then start on the minute-long tests together and fill
    in with the short ones, rather than one worker running a long test alone at the end.
    """
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


def strecha_root() -> Path:
    """The ``strecha`` folder, or skip (fail under CI=true) when it is absent."""
    return shared_dataset("strecha")


def shared_dataset(relative: str) -> Path:
    """A folder of ``../shared/datasets``, or skip (fail under CI=true) when it is absent.

    Only for tests marked ``real_data`` (anything else fails: mark the test).
    """
    item = _current_item
    if item is not None and item.get_closest_marker("real_data") is None:
        pytest.fail(f"{item.nodeid} reads {relative} from the shared datasets: mark it real_data")
    root = DATASETS_ROOT / relative
    if not root.is_dir():
        skip_or_fail(f"{relative} not found at {root} (set {DATASETS_ENV})")
    return root


# --------------------------------------------------------------------------- database cache

#: Part of every key: bump it to rebuild every cached database.
CACHE_FORMAT = 1


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class DatabaseCache:
    """COLMAP databases built by :func:`build_database`, one per key, shared and kept.

    The key hashes the images (name, size and sha256 of each file: content, not mtime,
    so a test that writes the same images again finds its database), the build
    options, the pycolmap version and the source of ``database/features.py`` (the code
    that builds). One process builds while the others wait on an ``fcntl.flock`` of
    the key's lock file; the build goes to a temporary folder renamed into place when
    complete, so a killed build never leaves a partial entry.
    """

    root: Path

    def key(self, image_dir: Path, names: list[str], options: dict) -> str:
        images = [
            [name, (image_dir / name).stat().st_size, _sha256_file(image_dir / name)]
            for name in names
        ]
        recipe = {
            "format": CACHE_FORMAT,
            "pycolmap": pycolmap.__version__,
            "builder": _sha256_file(Path(features_module.__file__)),
            "options": options,
            "images": images,
        }
        return hashlib.sha256(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:24]

    def get(self, image_dir: Path, names: list[str] | None = None, **options: object) -> Path:
        """The cached database of ``names`` in ``image_dir`` (default: every file there),
        built with ``build_database(image_dir, db, names, **options)`` on first use.

        The path is shared: read it, never write it (:meth:`copy` first).
        """
        image_dir = Path(image_dir)
        if names is None:
            names = sorted(p.name for p in image_dir.iterdir() if p.is_file())
        key = self.key(image_dir, names, options)
        entry = self.root / key
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / f"{key}.lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file is closed
            if not (entry / "meta.json").is_file():
                self._build(entry, image_dir, names, options)
            meta = json.loads((entry / "meta.json").read_text())
            database = entry / "database.db"
            if _sha256_file(database) != meta["sha256"]:
                shutil.rmtree(entry)
                pytest.fail(
                    f"the cached database {database} was changed after it was built: a test "
                    "wrote to it (copy it first: DatabaseCache.copy); removed, rebuilt next time"
                )
        return database

    def _build(self, entry: Path, image_dir: Path, names: list[str], options: dict) -> None:
        for stale in self.root.glob(f"{entry.name}.building-*"):  # a build that was killed
            shutil.rmtree(stale, ignore_errors=True)
        staging = Path(tempfile.mkdtemp(prefix=f"{entry.name}.building-", dir=self.root))
        try:
            database = build_database(image_dir, staging / "database.db", names, **options)
            meta = {
                "image_dir": str(image_dir),
                "images": names,
                "options": options,
                "sha256": _sha256_file(database),
            }
            (staging / "meta.json").write_text(json.dumps(meta, indent=1))
            staging.chmod(0o755)  # mkdtemp made it 0700
            os.rename(staging, entry)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise

    def model(self, database: Path, image_dir: Path) -> Path:
        """The largest model of pycolmap's incremental mapping of ``database`` (``sparse/0``).

        Default mapper options on one thread (the same model on every machine), built
        on a copy of the database; cached like the databases, keyed by the database's
        sha256 and the pycolmap version. Read it, never write it.
        """
        recipe = {
            "format": CACHE_FORMAT,
            "pycolmap": pycolmap.__version__,
            "database": _sha256_file(database),
            "mapping": "incremental, 1 thread",
        }
        key = (
            "model-" + hashlib.sha256(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:24]
        )
        entry = self.root / key
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / f"{key}.lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (entry / "meta.json").is_file():
                for stale in self.root.glob(f"{key}.building-*"):
                    shutil.rmtree(stale, ignore_errors=True)
                staging = Path(tempfile.mkdtemp(prefix=f"{key}.building-", dir=self.root))
                try:
                    copy = self.copy(database, staging / "database.db")
                    options = pycolmap.IncrementalPipelineOptions()
                    options.num_threads = 1
                    models = pycolmap.incremental_mapping(
                        copy, image_dir, staging / "mapping", options
                    )
                    if not models:
                        pytest.fail(f"incremental mapping of {database} gave no model")
                    best = max(models.values(), key=lambda m: m.num_reg_images())
                    (staging / "sparse" / "0").mkdir(parents=True)
                    best.write(staging / "sparse" / "0")
                    shutil.rmtree(staging / "mapping")
                    copy.unlink()
                    (staging / "meta.json").write_text(json.dumps(recipe, indent=1))
                    staging.chmod(0o755)
                    os.rename(staging, entry)
                except BaseException:
                    shutil.rmtree(staging, ignore_errors=True)
                    raise
        return entry / "sparse" / "0"

    def derived(self, database: Path, recipe: str, derive: Callable[[Path, Path], Path]) -> Path:
        """``derive(database, target)`` of a cached database, cached like it (keyed by its
        sha256 and ``recipe``, the name of what ``derive`` does). Read it, never write it."""
        key_recipe = {"format": CACHE_FORMAT, "database": _sha256_file(database), "recipe": recipe}
        key = (
            "derived-"
            + hashlib.sha256(json.dumps(key_recipe, sort_keys=True).encode()).hexdigest()[:24]
        )
        entry = self.root / key
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / f"{key}.lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (entry / "meta.json").is_file():
                for stale in self.root.glob(f"{key}.building-*"):
                    shutil.rmtree(stale, ignore_errors=True)
                staging = Path(tempfile.mkdtemp(prefix=f"{key}.building-", dir=self.root))
                try:
                    derived = derive(database, staging / "database.db")
                    meta = {**key_recipe, "sha256": _sha256_file(derived)}
                    (staging / "meta.json").write_text(json.dumps(meta, indent=1))
                    staging.chmod(0o755)
                    os.rename(staging, entry)
                except BaseException:
                    shutil.rmtree(staging, ignore_errors=True)
                    raise
            meta = json.loads((entry / "meta.json").read_text())
            result = entry / "database.db"
            if _sha256_file(result) != meta["sha256"]:
                shutil.rmtree(entry)
                pytest.fail(f"the cached database {result} was changed after it was built")
        return result

    @staticmethod
    def copy(database: Path, target: Path) -> Path:
        """A private copy of a cached database (for a test that writes)."""
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(database, target)
        return target


def cache_root(config: pytest.Config, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """pytest's cache folder (``.pytest_cache/d/...``, kept between runs); without the
    cache plugin (``-p no:cacheprovider``) the folder all xdist workers of this run share."""
    cache = getattr(config, "cache", None)
    if cache is not None:
        return cache.mkdir("colmap_trifocal_databases")
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # .../pytest-N/popen-gwK: the parent is the run's
    return base / "colmap_trifocal_databases"


@pytest.fixture(scope="session")
def database_cache(
    pytestconfig: pytest.Config, tmp_path_factory: pytest.TempPathFactory
) -> DatabaseCache:
    return DatabaseCache(cache_root(pytestconfig, tmp_path_factory))


@pytest.fixture(scope="session")
def real_scene_database(database_cache: DatabaseCache) -> Callable[[str, str], Path]:
    """Factory: (scene name, ``default`` or ``pinhole``) -> the scene's database as
    ``benchmarks/real_scenes.py`` defines it (COLMAP's default extraction; the same matches
    on one PINHOLE camera at COLMAP's guess), a subset's too. Cached
    (:class:`DatabaseCache`): read it, copy it to write. Only for ``real_data`` tests."""
    from real_scenes import SCENES_BY_NAME, derive_pinhole_database

    def get(name: str, kind: str) -> Path:
        scene = SCENES_BY_NAME[name]
        data = scene.read(shared_dataset(""))
        names = scene.image_names(data)
        images = scene.image_folder(shared_dataset(""), database_cache.root / "lens-images")
        default = database_cache.get(images, names, **scene.build_options())
        if kind == "default":
            return default
        assert kind == "pinhole", kind
        return database_cache.derived(default, "one PINHOLE camera", derive_pinhole_database)

    return get


@pytest.fixture(scope="session")
def strecha_database(
    real_scene_database: Callable[[str, str], Path],
) -> Callable[[str], tuple[Path, Path]]:
    """Factory: scene name -> (database path, scene folder), SIFT at 1600 px, exhaustive,
    one PINHOLE camera at COLMAP's guess (``real_scene_database``'s ``pinhole``). Cached
    (:class:`DatabaseCache`): read it, copy it to write."""

    def get(scene: str) -> tuple[Path, Path]:
        return real_scene_database(scene, "pinhole"), strecha_root() / scene

    return get


@pytest.fixture(scope="session")
def strecha_model(
    database_cache: DatabaseCache, strecha_database: Callable[[str], tuple[Path, Path]]
) -> Callable[[str], tuple[Path, Path, Path]]:
    """Factory: scene name -> (model folder, database, scene folder): pycolmap's incremental
    mapping of :func:`strecha_database`'s database (:meth:`DatabaseCache.model`)."""

    def get(scene: str) -> tuple[Path, Path, Path]:
        database, folder = strecha_database(scene)
        return database_cache.model(database, folder / "images"), database, folder

    return get


# --------------------------------------------------------------------------- the CLI in process


@dataclass
class CliResult:
    """What ``colmap-trifocal ARGS`` did: exit status, stdout and stderr (C output too)."""

    returncode: int
    stdout: str
    stderr: str


def run_cli(
    *args: object,
    preexec_fn: Callable[[], None] | None = None,
    env: dict[str, str | None] | None = None,
) -> CliResult:
    """``python -m colmap_trifocal.cli ARGS`` as a subprocess (where the process is the point:
    signals, resource limits, pipes, the environment, another process's view).

    ``env``: variables set (None: removed) on top of this process's environment. The
    output is decoded as UTF-8 whatever the child's locale.
    """
    environment = dict(os.environ)
    for key, value in (env or {}).items():
        if value is None:
            environment.pop(key, None)
        else:
            environment[key] = value
    process = subprocess.Popen(
        [sys.executable, "-X", "faulthandler", "-m", "colmap_trifocal.cli", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        encoding="utf-8",
        errors="backslashreplace",
        preexec_fn=preexec_fn,
        env=environment,
    )
    try:
        stdout, stderr = process.communicate(timeout=CLI_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"no end after {CLI_TIMEOUT_S} s; where it waited:\n{stacks_of(process)}")
    return CliResult(process.returncode, stdout, stderr)


#: Seconds a command of :func:`run_cli` may take before it is ended with its stacks shown.
CLI_TIMEOUT_S = 300


def stacks_of(process: subprocess.Popen) -> str:
    """The Python stacks of a hung ``process`` (started with ``-X faulthandler``) and of
    its children (forked workers inherit the handler): SIGABRT to each, children first,
    so each prints its threads' stacks to the shared stderr and aborts; that stderr."""
    try:
        children = Path(f"/proc/{process.pid}/task/{process.pid}/children").read_text().split()
    except OSError:
        children = []
    for pid in [*map(int, children), process.pid]:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGABRT)
        time.sleep(0.5)
    try:
        _, stderr = process.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        process.kill()
        _, stderr = process.communicate()
    return stderr


@contextmanager
def restored_process_state() -> Iterator[None]:
    """Undo what :func:`colmap_trifocal.cli.main` changes in the process: the handlers of
    SIGINT/SIGTERM/SIGHUP and the signal mask (it restores them itself; this also covers a
    run that raised), the package logger (``-v`` adds a handler), COLMAP's and OpenCV's log
    levels."""
    signums = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    handlers = {signum: signal.getsignal(signum) for signum in signums}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, set())
    logger = logging.getLogger("colmap_trifocal")
    log_state = (list(logger.handlers), logger.level, logger.propagate)
    minloglevel = pycolmap.logging.minloglevel
    opencv_level = cv2.utils.logging.getLogLevel()
    try:
        yield
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        logger.handlers[:], logger.level, logger.propagate = log_state
        pycolmap.logging.minloglevel = minloglevel
        cv2.utils.logging.setLogLevel(opencv_level)


@pytest.fixture
def run_main(capfd: pytest.CaptureFixture) -> Callable[..., CliResult]:
    """``colmap-trifocal ARGS`` in this process: :func:`colmap_trifocal.cli.main`, with the
    file descriptors captured (glog's C++ output too) and the process state restored.

    ``SystemExit`` (argparse's usage errors) gives its code, as the console script does.
    For what only a real process shows (signals, the entry point, resource limits, another
    process holding a lock) use a subprocess.
    """
    from colmap_trifocal import cli

    def run(*args: object) -> CliResult:
        capfd.readouterr()  # what earlier steps of the test printed is not this run's
        with restored_process_state():
            try:
                status = cli.main([str(a) for a in args])
            except SystemExit as exc:
                code = exc.code
                status = code if isinstance(code, int) else (0 if code is None else 1)
        out, err = capfd.readouterr()
        return CliResult(status, out, err)

    return run


def database_rows(data: Path | bytes) -> dict[str, list[tuple]]:
    """Every table's rows (sorted) of a database file or its bytes: what a backup holds
    (SQLite's backup API copies the pages; the header's change counters differ)."""
    import sqlite3

    raw = bytearray(data if isinstance(data, bytes) else Path(data).read_bytes())
    raw[18:20] = b"\x01\x01"  # read a WAL-mode file as a plain one, in memory
    con = sqlite3.connect(":memory:")
    try:
        con.deserialize(bytes(raw))
        tables = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        quoted = {t: '"' + t.replace('"', '""') + '"' for t in tables}  # any table name
        return {t: sorted(con.execute(f"SELECT * FROM {quoted[t]}").fetchall()) for t in tables}
    finally:
        con.close()


def assert_one_error_line(result: CliResult, fragment: str, status: int = 2) -> None:
    """Exit ``status``, stderr exactly one line ``error: ...`` containing ``fragment``."""
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: "), lines[0]
    assert fragment in lines[0], lines[0]
    assert result.returncode == status, result.stderr


# --------------------------------------------------------------------------- rendering


def require_open3d() -> ModuleType:
    """The open3d module; skip (fail under CI=true) where it cannot be imported (its import
    needs ``libusb-1.0-0``). Import it only through this, inside the tests that need it."""
    try:
        import open3d
    except (ImportError, OSError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        skip_or_fail(f"open3d cannot be imported here: {reason}")
    return open3d


def require_rendering() -> None:
    """Skip (fail under CI=true) where Open3D cannot be imported or cannot render offscreen."""
    from colmap_trifocal.reconstruction.visualize import offscreen_problem

    problem = offscreen_problem()
    if problem is not None:
        skip_or_fail(f"offscreen rendering impossible here: {problem}")


# --------------------------------------------------------------------------- synthetic data


@pytest.fixture(autouse=True)
def fresh_pycolmap_random_state() -> None:
    """Every test starts from pycolmap's random state of a fresh process (seed 0), the
    state it has when run alone. pycolmap's generator is global: without this, a synthetic
    scene depended on which tests the same xdist worker ran before (``test_model_folder``
    once drew a scene from which nothing is determined)."""
    pycolmap.set_random_seed(0)


def synthesize(
    path: Path,
    model: str = "SIMPLE_RADIAL",
    params: list[float] | None = None,
    cameras: int = 1,
    frames: int = 6,
    points: int = 400,
    *,
    rigs: int = 1,
    seed: int | None = None,
    noise: float = 0.0,
) -> pycolmap.Reconstruction:
    """A pycolmap synthetic database (exact keypoints) and its ground truth.

    ``seed``: pycolmap's random seed, set first (None: whatever state it is in); ``noise``:
    then that many px of Gaussian noise on the keypoints (0: exact).
    """
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=rigs,
        num_cameras_per_rig=cameras,
        num_frames_per_rig=frames,
        num_points3D=points,
        camera_model_id=getattr(pycolmap.CameraModelId, model),
    )
    if params is not None:
        options.camera_params = params
    if seed is not None:
        pycolmap.set_random_seed(seed)
    with pycolmap.Database.open(str(path)) as db:
        truth = pycolmap.synthesize_dataset(options, db)
        if noise > 0:
            noise_options = pycolmap.SyntheticNoiseOptions(point2D_stddev=noise)
            pycolmap.synthesize_noise(noise_options, truth, db)
    return truth


def synthesize_per_image(
    path: Path,
    images: int = 6,
    points: int = 400,
    params: list[float] | None = None,
    noise: float = 0.0,
) -> pycolmap.Reconstruction:
    """:func:`synthesize` as COLMAP's default import makes a database: one SIMPLE_RADIAL
    camera (and rig) per image, all with the same params; random seed 0, so the same scene
    whatever ran before in this process."""
    return synthesize(
        path, params=params, frames=1, points=points, rigs=images, seed=0, noise=noise
    )


def intrinsics_of(params: list[float], model: str) -> np.ndarray:
    """(fx, fy, cx, cy) of COLMAP params."""
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        return np.array([params[0], params[0], params[1], params[2]])
    return np.array(params[:4])


def handheld_lens_contents(
    k1: float, seed: int, k2: float = 0.0, model: str = "SIMPLE_RADIAL"
) -> tuple[DatabaseContents, np.ndarray]:
    """The 17-frame synthetic handheld set through a ``(k1, k2)`` lens, stored as COLMAP
    stores a new camera (``SIMPLE_RADIAL`` at its guess f = 1.2 · max(w, h), centred,
    k = 0) or as a ``PINHOLE`` camera at that guess; and its true (fx, fy, cx, cy)."""
    scene = with_radial_distortion(handheld_indoor(seed=seed), k1, k2)
    contents = scene_contents(scene)
    width, height = scene.width, scene.height
    fx, fy, cx, cy = default_guess(width, height)
    default = [fx, cx, cy, 0.0] if model == "SIMPLE_RADIAL" else [fx, fy, cx, cy]
    contents.cameras[CAMERA_ID] = CameraInfo(CAMERA_ID, model, width, height, default)
    return contents, scene.intrinsics


# --------------------------------------------------------------------------- images, privileges


def texture_views(count: int, seed: int = 0) -> list[np.ndarray]:
    """``count`` views of one random texture, shifted by 8 px each (240 x 180, 8 bits).

    Pure translation: SIFT matches them and ``run`` maps them, while the calibration
    determines nothing (the prior is kept).
    """
    rng = np.random.default_rng(seed)
    texture = cv2.resize(rng.integers(0, 256, (60, 80), np.uint8), (320, 240), cv2.INTER_CUBIC)
    return [texture[20:200, 8 * k : 8 * k + 240] for k in range(count)]


#: pycolmap's CPU matcher searches the descriptors of an image with fewer SIFT features
#: than this exactly (a flat FAISS index), and of one with this many or more through an
#: IVF index whose cells k-means trains: a build COLMAP's maintainers found not perfectly
#: deterministic even on one thread (colmap/colmap#3874). Two builds are compared row for
#: row only on images below it (docs/reliability.md, "Determinism").
EXACT_SEARCH_FEATURES = 512


def small_texture_views(count: int) -> list[np.ndarray]:
    """:func:`texture_views` shrunk to 100 x 75 (about 250 SIFT features each, under
    :data:`EXACT_SEARCH_FEATURES`): every pair still verifies, and two builds of them
    hold the same matches."""
    return [
        cv2.resize(view, (100, 75), interpolation=cv2.INTER_AREA) for view in texture_views(count)
    ]


def without_root_file_access() -> None:
    """In a child process (``preexec_fn``): file permissions bind even as root.

    Root's capabilities that bypass them (CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH) are
    dropped from the bounding set, so the program executed next does not get them.
    """
    if os.geteuid() != 0:
        return
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    for capability in (1, 2):  # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH
        if libc.prctl(24, capability, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")
