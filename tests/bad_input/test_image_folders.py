"""The image folder of ``run``: unusable files are skipped (as COLMAP skips them); fewer
than 3 usable images is the error, naming the skipped files.
"""

from __future__ import annotations

import os

import numpy as np
from conftest import texture_views, without_root_file_access

from bad_input.builders import (
    JPEG,
    PNG16,
    PROGRESSIVE_JPEG,
    cut_file,
    encoded,
    image_folder,
    run_image_folder,
    unix_socket,
    write_file,
)
from bad_input.table import (
    Case,
    table_test,
)

CASES: dict[str, Case] = {
    "run: non-UTF-8 image name": Case(
        image_folder(
            write_file(os.fsdecode(b"caf\xe9.png"), encoded(".png", texture_views(1)[0])), good=3
        ),
        "/data/images/caf\\xe9.png (COLMAP stores image names as UTF-8",
        argv=run_image_folder(),
    ),
    "run: 1x1 image": Case(
        image_folder(write_file("x.png", encoded(".png", np.zeros((1, 1), np.uint8)))),
        "x.png: 1 x 1 px: sides under 8 px",
        argv=run_image_folder(),
    ),
    "run: 20000x1 image": Case(
        image_folder(write_file("x.png", encoded(".png", np.zeros((1, 20000), np.uint8)))),
        "x.png: 20000 x 1 px",
        argv=run_image_folder(),
    ),
    "run: 3000x30 image with --max-image-size 100": Case(
        image_folder(write_file("x.tif", encoded(".tif", np.zeros((30, 3000), np.uint8)))),
        "3000 x 30 px, 100 x 1 px once downscaled",
        argv=run_image_folder("--max-image-size", "100"),
    ),
    "run: FIFO named x.png": Case(
        image_folder(lambda images: os.mkfifo(images / "x.png")),
        "x.png: not a regular file (a FIFO)",
        argv=run_image_folder(),
    ),
    "run: socket named x.png": Case(
        image_folder(unix_socket), "x.png: not a regular file (a socket)", argv=run_image_folder()
    ),
    "run: symlink to a device": Case(
        image_folder(lambda images: os.symlink("/dev/null", images / "x.jpg")),
        "x.jpg: not a regular file (a character device)",
        argv=run_image_folder(),
    ),
    "run: folder named x.jpg": Case(
        image_folder(lambda images: (images / "x.jpg").mkdir()),
        "x.jpg: not a regular file (a folder)",
        argv=run_image_folder(),
    ),
    "run: symlink loop": Case(
        image_folder(lambda images: os.symlink("x.jpg", images / "x.jpg")),
        "x.jpg: a symlink loop",
        argv=run_image_folder(),
    ),
    "run: dangling symlink": Case(
        image_folder(lambda images: os.symlink("gone.jpg", images / "x.jpg")),
        "x.jpg: a dangling symlink",
        argv=run_image_folder(),
    ),
    "run: truncated JPEG": Case(
        image_folder(cut_file("x.jpg", JPEG)), "x.jpg: truncated JPEG", argv=run_image_folder()
    ),
    "run: truncated progressive JPEG": Case(
        image_folder(cut_file("x.jpg", PROGRESSIVE_JPEG, 0.9)),
        "x.jpg: truncated JPEG",
        argv=run_image_folder(),
    ),
    "run: JPEG without its last byte": Case(
        image_folder(write_file("x.jpg", JPEG[:-1])),
        "x.jpg: truncated JPEG",
        argv=run_image_folder(),
    ),
    "run: truncated 16-bit PNG": Case(
        image_folder(cut_file("x.png", PNG16, 0.8)), "x.png: truncated PNG", argv=run_image_folder()
    ),
    "run: truncated BMP": Case(
        image_folder(cut_file("x.bmp", encoded(".bmp", texture_views(1)[0]), 0.9)),
        "x.bmp: truncated BMP",
        argv=run_image_folder(),
    ),
    "run: truncated float TIFF": Case(
        image_folder(
            cut_file("x.tif", encoded(".tif", texture_views(1)[0].astype(np.float32) / 255))
        ),
        "x.tif: not an image COLMAP can decode",
        argv=run_image_folder(),
    ),
    "run: empty image file": Case(
        image_folder(write_file("x.png", b"")), "x.png: empty file", argv=run_image_folder()
    ),
    "run: text named x.jpg": Case(
        image_folder(write_file("x.jpg", b"not a jpeg\n")),
        "x.jpg: not an image COLMAP can decode",
        argv=run_image_folder(),
    ),
    "run: no usable image": Case(
        image_folder(
            lambda images: [
                os.mkfifo(images / "a.png"),
                (images / "b.jpg").write_bytes(JPEG[:-2]),
                (images / "c.png").write_bytes(b""),
                (images / "d.tif").write_bytes(b"II*\x00"),
                os.symlink("d.tif", images / "e.jpg"),
            ],
            good=0,
        ),
        "has 0 usable image(s); at least 3 are needed (5 skipped: a.png: not a regular file "
        "(a FIFO); b.jpg: truncated JPEG (no end-of-image marker); c.png: empty file; and 2 more)",
        argv=run_image_folder(),
    ),
    "run: unreadable image (chmod 000)": Case(
        image_folder(lambda _: None, good=3),
        "02.jpg: cannot be read (Permission denied)",
        argv=run_image_folder(),
        preexec_fn=without_root_file_access,
        unreadable="images/02.jpg",
    ),
}


test_bad_input = table_test(CASES)
