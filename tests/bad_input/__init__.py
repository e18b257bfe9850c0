"""Bad input through the command line: one table grouped by kind of input, one error line each.

Each ``test_*.py`` here holds the rows of one kind of input in its ``CASES`` and runs them
with ``test_bad_input`` (:func:`.table.check_case`):

* ``test_databases.py``: database files (missing, not SQLite, not COLMAP's, corrupt blobs,
  stored cameras no calibration can use) and the valid databases that must be accepted;
* ``test_model_folders.py``: COLMAP model folders (truncated, huge or sparse files, FIFOs,
  non-finite cameras);
* ``test_report_files.py``: files read back beside a model (``report.json``);
* ``test_output_paths.py``: outputs (``--json``, ``--png``, WORKSPACE, ``--keep``,
  ``--output``) that are inputs, cannot be made, or are pipes and FIFOs;
* ``test_image_folders.py``: the image folder of ``run``;
* ``test_command_line.py``: numbers and values on the command line (priors, seeds, sizes,
  counts, ``--dask`` addresses) and flags that do not go together;
* ``test_file_systems.py``: full disks and file size limits (``/dev/full``,
  ``RLIMIT_FSIZE``, a small tmpfs where the tests run as root);
* ``test_environment.py``: the process's environment: text encodings, displays, closed or
  full standard streams, numerical warnings;
* ``test_concurrency_signals.py``: locks held by other processes, Ctrl-C, SIGTERM and SIGHUP
  during ``--write``, another process opening the database meanwhile.

A row builds its input (with pycolmap where it is a COLMAP database or model), runs the
command line (``calibrate PATH ARGS`` unless the row gives another command) and checks: the
exit status (2), exactly one stderr line ``error: ...`` containing the row's fragment, no
traceback, every file below the row's folder byte-identical (sha256) and none added or
removed (no ``.bak``, no ``-wal``/``-shm`` left behind), and no ``run`` workspace created.
A row marked ``warning`` is an input the command uses without the bad part: exit 0 and
exactly one ``warning:`` line instead. ``pytest --collect-only -q tests/bad_input -k
"test_bad_input["`` counts the rows.

The rows run ``colmap_trifocal.cli.main`` in this process (``conftest.run_main``: file
descriptors captured, so pycolmap's C++ log counts as stderr; signal handlers, logging
and COLMAP's log level restored after each row). A row whose point is the process runs a
subprocess: a file-size limit (``setrlimit``) would bind the test runner itself, and an
environment (a locale, a display) is the process's. A lock is held by another process:
pycolmap has its own SQLite, and POSIX locks taken by Python's ``sqlite3`` in this process
would not bind it.
"""
