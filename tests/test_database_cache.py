"""The test suite's database cache (``conftest.DatabaseCache``): one build per key, shared.

Small textured images (SIFT finds features in them in well under a second), a cache
folder of the test's own: two processes asking at once get one build; other image
bytes or other options get another entry; a cached database that was written to is
refused (and removed, so the next run rebuilds it).
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import DatabaseCache

TESTS = Path(__file__).resolve().parent


def _images(folder: Path, count: int = 3, seed: int = 0) -> Path:
    """``count`` views of one random texture, shifted by 8 px each (JPEG, 240 x 180)."""
    rng = np.random.default_rng(seed)
    texture = cv2.resize(rng.integers(0, 256, (60, 80), np.uint8), (320, 240), cv2.INTER_CUBIC)
    texture = cv2.GaussianBlur(texture, (3, 3), 0)
    folder.mkdir(parents=True)
    for k in range(count):
        cv2.imwrite(str(folder / f"{k:02d}.jpg"), texture[20 : 20 + 180, 8 * k : 8 * k + 240])
    return folder


_CHILD = """
import sys, time
sys.path.insert(0, {tests!r})
from pathlib import Path
from conftest import DatabaseCache

class Logged(DatabaseCache):
    def _build(self, *args):
        with open({log!r}, "a") as log:
            log.write(f"build {{time.monotonic()}}\\n")
        super()._build(*args)

print(Logged(Path({root!r})).get(Path({images!r}), max_image_size=400))
"""


def test_processes_asking_at_once_share_one_build(tmp_path: Path) -> None:
    images, root, log = _images(tmp_path / "images"), tmp_path / "cache", tmp_path / "builds"
    child = textwrap.dedent(
        _CHILD.format(tests=str(TESTS), root=str(root), images=str(images), log=str(log))
    )
    processes = [
        subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    paths = [p.communicate(timeout=300)[0].strip() for p in processes]
    assert [p.returncode for p in processes] == [0, 0]
    assert paths[0] == paths[1] and Path(paths[0]).is_file()
    assert len(log.read_text().splitlines()) == 1  # one built, the other waited
    entry = Path(paths[0]).parent
    assert sorted(p.name for p in root.iterdir()) == [entry.name, f"{entry.name}.lock"]
    meta = json.loads((entry / "meta.json").read_text())
    assert meta["images"] == ["00.jpg", "01.jpg", "02.jpg"]
    assert meta["options"] == {"max_image_size": 400}


def test_other_images_or_options_get_their_own_entry(tmp_path: Path) -> None:
    images = _images(tmp_path / "images")
    cache = DatabaseCache(tmp_path / "cache")
    first = cache.get(images, max_image_size=400)
    assert cache.get(images, max_image_size=400) == first  # found again
    assert cache.get(images, max_image_size=300) != first
    other = _images(tmp_path / "other", seed=1)  # the same names, other bytes
    assert cache.get(other, max_image_size=400) != first
    assert cache.get(images, ["00.jpg", "01.jpg", "02.jpg"], max_image_size=400) == first


def test_a_cached_database_that_was_written_is_refused(tmp_path: Path) -> None:
    images = _images(tmp_path / "images")
    cache = DatabaseCache(tmp_path / "cache")
    database = cache.get(images)
    copy = DatabaseCache.copy(database, tmp_path / "mine" / "database.db")
    with open(copy, "r+b") as handle:  # a copy may be written: the cache is not affected
        handle.seek(100)
        handle.write(b"\0")
    assert cache.get(images) == database
    with open(database, "r+b") as handle:
        handle.seek(100)
        handle.write(b"\0")
    with pytest.raises(pytest.fail.Exception, match="was changed after it was built"):
        cache.get(images)
    assert not database.exists()  # removed: the next request builds it again
    assert cache.get(images) == database and database.is_file()
