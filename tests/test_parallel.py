"""The calibration's worker processes (``common.parallel.map_jobs`` with ``processes``).

Forking is safe only from the main thread of a process that runs no other thread, which a
pytest-xdist worker is not (it runs a thread for its channel): the forked paths are
therefore checked in fresh interpreters (subprocesses), as the command line runs them.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from colmap_trifocal.common.parallel import WORKER_DIED, can_fork, map_jobs

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from outlier_stress import make_outlier_database  # noqa: E402


def _python(script: str, *args: str) -> subprocess.CompletedProcess[str]:
    """``script`` run by a fresh interpreter (the package importable), its output."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script), *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_forked_workers_run_closures_in_order_in_other_processes() -> None:
    """From a fresh interpreter's main thread, 3 workers: the caller and 2 forked
    processes each take jobs; a closure over local data (which pickle cannot send) works,
    as the children inherit it; the results come back in the jobs' order."""
    run = _python(
        """
        import json, os, time
        from colmap_trifocal.common.parallel import can_fork, map_jobs
        def jobs_adding(offset):
            def job(value):  # a local function: pickle cannot send it
                time.sleep(0.05)  # long enough for every worker to take some
                return value + offset, os.getpid()
            return job
        results = map_jobs(jobs_adding(1000), list(range(12)), 3, processes=True)
        print(json.dumps({"can_fork": can_fork(), "parent": os.getpid(), "results": results}))
        """
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["can_fork"] is True
    assert [value for value, _ in out["results"]] == list(range(1000, 1012))
    pids = {pid for _, pid in out["results"]}
    assert out["parent"] in pids
    assert len(pids) == 3


def test_beside_another_thread_the_jobs_run_in_threads() -> None:
    """From a thread other than the main one (a caller's pool, a notebook, this xdist
    worker) nothing is forked: the jobs run in this process."""
    seen: list[object] = []
    worker = threading.Thread(
        target=lambda: seen.extend(
            [can_fork(), map_jobs(lambda _: os.getpid(), [0, 1, 2], 2, processes=True)]
        )
    )
    worker.start()
    worker.join()
    assert seen == [False, [os.getpid()] * 3]


@pytest.mark.parametrize(
    ("in_a_worker", "caught", "expected"),
    [
        ('raise ValueError("bad job in a worker")', "ValueError", "bad job in a worker"),
        ("os.kill(os.getpid(), signal.SIGKILL)", "CalibrationError", WORKER_DIED),
    ],
    ids=["error", "killed"],
)
def test_a_worker_failure_reaches_the_caller(in_a_worker: str, caught: str, expected: str) -> None:
    """An exception raised in a forked worker is raised in the caller, type and message;
    a worker killed mid-job (out of memory, say) ends the map with CalibrationError, which
    names the way to keep the work in one process, not with a hang."""
    run = _python(
        f"""
        import os, signal, time
        from colmap_trifocal import CalibrationError
        from colmap_trifocal.common.parallel import map_jobs
        parent = os.getpid()
        def job(value):
            time.sleep(0.05)
            if os.getpid() != parent:
                {in_a_worker}
            return value
        try:
            map_jobs(job, list(range(6)), 2, processes=True)
        except {caught} as error:
            print("caught:", error)
        """
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == f"caught: {expected}"


def _exit_pause(seconds: float) -> str:
    """Script lines (for :func:`_python`) that give every worker forked after them a pause
    of ``seconds`` in its exit, armed as it starts (whatever jobs it then takes)."""
    return f"""
        import time
        from multiprocessing import util
        class Hook:
            pass
        hook = Hook()  # kept alive: util holds it weakly
        util.register_after_fork(
            hook, lambda _: util.Finalize(None, time.sleep, args=({seconds},), exitpriority=0)
        )
        """


def test_the_caller_does_not_wait_for_a_worker_to_exit() -> None:
    """A worker that has sent its results is neither killed nor waited for while it exits
    (here a 3-second pause in each worker's exit, armed as it starts): ``map_jobs`` and
    ``Beside.result`` return with the results while both workers are still exiting, and
    once exited they are reaped (by ``active_children``, as by the next fork). Ending and
    waiting for a worker took 8 ms of every forked call (its exit unmaps a copy of the
    caller's memory)."""
    run = _python(
        _exit_pause(3)
        + """
        import json, multiprocessing
        from colmap_trifocal.common.parallel import Beside, map_jobs
        def job(value):
            time.sleep(0.05)
            return value
        start = time.monotonic()
        results = map_jobs(job, list(range(6)), 2, processes=True)
        mapped = time.monotonic() - start
        start = time.monotonic()
        with Beside(lambda: job("beside"), workers=2) as beside:
            value = beside.result()
        beside_seconds = time.monotonic() - start
        exiting = len(multiprocessing.active_children())
        time.sleep(4)
        print(json.dumps({"results": results, "mapped": mapped, "value": value,
                          "beside": beside_seconds, "exiting": exiting,
                          "left": len(multiprocessing.active_children())}))
        """
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["results"] == list(range(6)) and out["value"] == "beside"
    assert out["mapped"] < 2.5 and out["beside"] < 2.5  # not the 3 s of an exit
    assert out["exiting"] == 2  # both still exiting when the caller went on
    assert out["left"] == 0  # and reaped once exited


def test_a_worker_stuck_in_its_exit_does_not_hold_the_callers_exit() -> None:
    """A worker that has sent its results and then hangs in its exit (here a 10-minute
    pause) is ended by the caller's own exit (``multiprocessing`` ends daemonic children
    with SIGTERM, which the worker no longer ignores once its work is sent), instead of
    holding it: the caller exits at once, with its output and status."""
    start = time.monotonic()
    run = _python(
        _exit_pause(600)
        + """
        from colmap_trifocal.common.parallel import map_jobs
        print(map_jobs(lambda job: job, list(range(6)), 2, processes=True))
        """
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[0, 1, 2, 3, 4, 5]"
    assert time.monotonic() - start < 60  # not the worker's 600 s


@pytest.fixture(scope="module")
def database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 images of one PINHOLE camera, 0.5 px of noise and 20 % wrong matches."""
    path = tmp_path_factory.mktemp("parallel") / "database.db"
    make_outlier_database(path, 0.2, seed=4, num_images=8, num_points=600)
    return path


def test_tensors_in_worker_processes_give_the_same_bits(database: Path) -> None:
    """The calibration with its tensors fitted in 2 forked processes and with 1 worker
    (everything in process): the same intrinsics, std and tensors, bit for bit."""
    run = _python(
        """
        import json, sys
        from colmap_trifocal import CalibrationOptions, calibrate_database
        from colmap_trifocal.common import parallel
        forked = []
        in_processes = parallel._in_processes
        def counted(function, jobs, workers, bar):
            forked.append(len(jobs))
            return in_processes(function, jobs, workers, bar)
        parallel._in_processes = counted
        out = {}
        for workers in (2, 1):
            (result,) = calibrate_database(sys.argv[1], CalibrationOptions(seed=3, workers=workers))
            out[workers] = {
                "intrinsics": result.intrinsics.tobytes().hex(),
                "std": result.std,
                "tensors": [t.tensor.tobytes().hex() for t in result.tensors],
                "forked": list(forked),
            }
        print(json.dumps(out))
        """,
        str(database),
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert sum(out["2"]["forked"]) >= 8  # the tensor jobs went to worker processes
    assert out["1"]["forked"] == out["2"]["forked"]  # and none with one worker
    for key in ("intrinsics", "std", "tensors"):
        assert out["1"][key] == out["2"][key], key


#: A script's start: ``seen`` keeps the messages of the package logger's records (INFO).
_KEEP_LOG = """
        import json, logging, os, time
        from colmap_trifocal.common.log import logger
        from colmap_trifocal.common.parallel import Beside
        seen = []
        class Keep(logging.Handler):
            def emit(self, record):
                seen.append(record.getMessage())
        logger.addHandler(Keep())
        logger.setLevel(logging.INFO)
"""


def test_beside_runs_in_another_process_and_its_log_comes_back() -> None:
    """``Beside``: the function runs in a forked process while the caller works; its
    value and its log records (emitted through the caller's handlers) come back when
    asked for; its exception is raised in the caller."""
    run = _python(
        _KEEP_LOG
        + """
        def work():
            logger.info("worked in %d", os.getpid())
            return os.getpid()
        def fail():
            raise KeyError("beside")
        with Beside(work, workers=2) as beside:
            pid = beside.result()
        try:
            with Beside(fail, workers=2) as beside:
                beside.result()
        except KeyError as error:
            caught = str(error)
        print(json.dumps({"parent": os.getpid(), "pid": pid, "seen": seen, "caught": caught}))
        """
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["pid"] != out["parent"]
    assert out["seen"] == [f"worked in {out['pid']}"]
    assert out["caught"] == "'beside'"


def test_beside_not_asked_for_is_ended_and_says_nothing() -> None:
    """A ``Beside`` whose result is not asked for is ended when its block ends (here one
    that would sleep a minute), and its log records are not emitted; one worker
    runs the function in the caller, when asked for."""
    run = _python(
        _KEEP_LOG
        + """
        def slow():
            logger.info("slow started")
            time.sleep(60)
        start = time.monotonic()
        with Beside(slow, workers=2) as beside:
            process = beside._process
            time.sleep(0.2)
        ended = time.monotonic() - start
        with Beside(os.getpid, workers=1) as beside:
            pid = beside.result()
        print(json.dumps({"ended": ended, "alive": process.is_alive(), "seen": seen,
                          "same": pid == os.getpid()}))
        """
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["ended"] < 10
    assert out["alive"] is False
    assert out["seen"] == []
    assert out["same"] is True


def test_a_signal_between_the_fork_and_the_workers_set_up_is_ignored_by_the_worker() -> None:
    """A terminal's signal reaches the whole process group, forked workers included. One
    that reaches a worker after the fork but before the worker ignores such signals (here
    sent by an after-fork hook, which runs in that window) is discarded: the parent's
    handler (as the command line's, raising KeyboardInterrupt) never runs in the worker,
    which does its work; stderr stays empty (CI once saw ``Process ForkProcess-3:``
    printed beside the command's one ``error:`` line)."""
    run = _python(
        """
        import json, os, signal
        from multiprocessing import util
        from colmap_trifocal.common.parallel import Beside, map_jobs
        def interrupt(signum, frame):
            raise KeyboardInterrupt
        for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(signum, interrupt)
        class Hook:
            pass
        hook = Hook()  # kept alive: util holds it weakly
        util.register_after_fork(hook, lambda _: os.kill(os.getpid(), signal.SIGHUP))
        with Beside(os.getpid, workers=2) as beside:
            pid = beside.result()
        results = map_jobs(lambda job: (job, os.getpid()), list(range(40)), 3, processes=True)
        print(json.dumps({"parent": os.getpid(), "pid": pid, "results": results}))
        """
    )
    assert run.returncode == 0, run.stderr
    assert run.stderr == ""
    out = json.loads(run.stdout)
    assert out["pid"] != out["parent"]
    assert [job for job, _ in out["results"]] == list(range(40))


def test_a_signal_to_the_caller_during_a_fork_ends_the_new_worker() -> None:
    """A signal that reaches the caller while it forks (held back there until the fork is
    done; here sent by an after-fork hook of the parent) raises the handler's exception
    from the fork's call, which has ended the new worker: no caller holds it yet."""
    run = _python(
        """
        import json, multiprocessing, os, signal, time
        from colmap_trifocal.common.parallel import Beside
        def interrupt(signum, frame):
            raise KeyboardInterrupt
        signal.signal(signal.SIGHUP, interrupt)
        fired = []
        def once():
            if not fired:
                fired.append(True)
                os.kill(os.getpid(), signal.SIGHUP)
        os.register_at_fork(after_in_parent=once)
        try:
            Beside(lambda: time.sleep(30), workers=2)
            outcome = "returned"
        except KeyboardInterrupt:
            outcome = "interrupted"
        print(json.dumps({"outcome": outcome, "alive": len(multiprocessing.active_children())}))
        """
    )
    assert run.returncode == 0, run.stderr
    assert run.stderr == ""
    assert json.loads(run.stdout) == {"outcome": "interrupted", "alive": 0}


def _running(pid: int) -> bool:
    """Whether process ``pid`` exists and has not ended (a zombie has)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")


def test_workers_end_with_a_caller_killed_mid_run(tmp_path: Path) -> None:
    """A caller killed without its clean-up (SIGKILL, or a signal it does not handle: a
    script's SIGTERM) cannot end its workers, which ignore the signals that end a run.
    Each ends with it, rather than finishing its jobs or waiting forever to send results
    nobody reads (a benchmark's worker was found blocked in a pipe write nine minutes
    after its caller was terminated)."""
    pids = tmp_path / "pids"
    script = """
        import os, sys, time
        from colmap_trifocal.common.parallel import map_jobs
        def job(k):
            with open(sys.argv[1], "a") as f:
                f.write(f"{os.getpid()}\\n")
            time.sleep(0.2)
            return k
        map_jobs(job, list(range(200)), 2, processes=True)
        """
    caller = subprocess.Popen([sys.executable, "-c", textwrap.dedent(script), str(pids)])
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 120
        while not workers and time.monotonic() < deadline and caller.poll() is None:
            if pids.exists():
                workers = {int(pid) for pid in pids.read_text().split()} - {caller.pid}
            time.sleep(0.05)
        assert workers, "no worker process took a job"
    finally:
        caller.kill()
        caller.wait()
    deadline = time.monotonic() + 10
    while any(map(_running, workers)) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [pid for pid in workers if _running(pid)]
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert not left, "a worker outlived its caller"


@pytest.mark.real_data
def test_lens_fits_side_by_side_give_the_same_bits(
    real_scene_database: Callable[[str, str], Path],
) -> None:
    """EuRoC's real lens behind COLMAP's default camera: its ``RADIAL`` fit runs in a
    forked process beside the ``SIMPLE_RADIAL`` one (``parallel.Beside``) and gives the
    result of the two fits one after the other (1 worker), bit for bit."""
    run = _python(
        """
        import json, sys
        from colmap_trifocal import CalibrationOptions, calibrate_database
        from colmap_trifocal.common import parallel
        forked = []
        init = parallel.Beside.__init__
        def counted(self, function, **kwargs):
            init(self, function, **kwargs)
            forked.append(self._process is not None)
        parallel.Beside.__init__ = counted
        out = {}
        for workers in (2, 1):
            (result,) = calibrate_database(sys.argv[1], CalibrationOptions(workers=workers))
            out[workers] = {
                "intrinsics": result.intrinsics.tobytes().hex(),
                "std": result.std,
                "richer": (result.lens_distortion or {}).get("richer_model"),
                "forked": sum(forked),
            }
        print(json.dumps(out))
        """,
        str(real_scene_database("euroc-V1_01", "default")),
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["2"]["richer"] == "RADIAL"  # the second fit's result was used
    assert out["2"]["forked"] >= 1 and out["1"]["forked"] == out["2"]["forked"]
    for key in ("intrinsics", "std"):
        assert out["1"][key] == out["2"][key], key


def _with_forks_counted(database: Path) -> dict[str, dict]:
    """One calibration of ``database`` with 2 workers and one with 1, in a fresh Python:
    per worker count ("2", "1"), the estimate's bytes, its std, whether the polish was
    kept, and every call that went to forked processes as [job function, jobs]."""
    run = _python(
        """
        import json, sys
        from colmap_trifocal import CalibrationOptions, calibrate_database
        from colmap_trifocal.common import parallel
        forked = []
        in_processes = parallel._in_processes
        def counted(function, jobs, workers, bar):
            forked.append((function.__name__, len(jobs)))
            return in_processes(function, jobs, workers, bar)
        parallel._in_processes = counted
        out = {}
        for workers in (2, 1):
            forked.clear()
            (result,) = calibrate_database(sys.argv[1], CalibrationOptions(workers=workers))
            out[workers] = {
                "intrinsics": result.intrinsics.tobytes().hex(),
                "std": result.std,
                "polished": result.triplet_bundle is not None and result.triplet_bundle["used"],
                "forked": list(forked),
            }
        print(json.dumps(out))
        """,
        str(database),
    )
    assert run.returncode == 0, run.stderr
    out: dict[str, dict] = json.loads(run.stdout)
    for key in ("intrinsics", "std"):
        assert out["1"][key] == out["2"][key], key
    assert out["1"]["forked"] == []
    return out


@pytest.mark.real_data
def test_polish_jobs_in_worker_processes_give_the_same_bits(
    real_scene_database: Callable[[str, str], Path],
) -> None:
    """entry-P10's 20 triplets: the tracks' plane parallax, the polish's projective
    refits with its calibrated cameras (one call: ``shared_camera.observed_at``) and the
    Schur complements run in forked processes with 2 workers (``MIN_FORKED_JOBS``), and
    the result is the one worker's, bit for bit."""
    out = _with_forks_counted(real_scene_database("entry-P10", "pinhole"))
    forked = [name for name, _ in out["2"]["forked"]]
    assert {"_parallax_job", "_observed_at_job", "_information_job"} <= set(forked)
    # The refits and the cameras at K went to the workers together, not in two calls.
    assert forked.count("_observed_at_job") == 1
    assert "_observed_job" not in forked and "_cameras_job" not in forked
    assert out["2"]["polished"]  # the polish ran and was kept: its jobs decided the result


@pytest.mark.real_data
def test_the_released_polish_jobs_in_worker_processes_give_the_same_bits(
    real_scene_database: Callable[[str, str], Path],
) -> None:
    """lego's 19 triplets, whose principal point the constraint solve holds and the polish
    estimates (``stage.release_held``): the release's projective refits and its calibrated
    cameras go to the forked workers in one call, not two, and the result is the one
    worker's, bit for bit."""
    out = _with_forks_counted(real_scene_database("lego", "pinhole"))
    forked = [name for name, _ in out["2"]["forked"]]
    assert forked.count("_observed_at_job") == 1
    assert "_observed_job" not in forked and "_cameras_job" not in forked
    assert out["2"]["polished"]


@pytest.mark.real_data
def test_the_rings_small_tensor_calls_run_in_worker_processes_with_the_same_bits(
    real_scene_database: Callable[[str, str], Path],
) -> None:
    """The temple ring's tensor calls have 6, 3 and 1 refinement starts: with 2 workers
    each of two or more starts runs in forked processes (``MIN_STARTS_IN_PROCESSES``),
    the single one in the caller, and the result is the one worker's, bit for bit."""
    out = _with_forks_counted(real_scene_database("temple-ring", "pinhole"))
    assert [jobs for name, jobs in out["2"]["forked"] if name == "_call"] == [6, 3]


def test_the_focal_search_runs_in_worker_processes_with_the_same_bits(database: Path) -> None:
    """The focal search's two calls (the coarse grid; the fine grid with the start's focal
    length), one job per triplet of its six, run in forked processes with 2 workers (their
    numpy holds the GIL: threads ran on 1.3–1.6 cores), and the result is the one
    worker's, bit for bit."""
    out = _with_forks_counted(database)
    assert [jobs for name, jobs in out["2"]["forked"] if name == "_costs_job"] == [6, 6]
