"""``show MODEL``'s window opens only where a display answers.

Open3D's viewer, given a ``DISPLAY`` that nobody serves (``DISPLAY=:99``), falls back to an
invisible EGL window and runs for ever; its C++ event loop never returns to Python, so
the process ignores Ctrl-C and SIGTERM. So before anything opens, a child process
connects to the display (Xlib's ``XOpenDisplay``, or Wayland's ``wl_display_connect``),
time-boxed by :data:`DISPLAY_TIMEOUT_S`: no answer is one :class:`CalibrationError` line.
"""

from __future__ import annotations

import os
import subprocess
import sys

#: Seconds the display has to answer a connection.
DISPLAY_TIMEOUT_S = 10.0

_DISPLAY_PROBE = r"""
import ctypes, os, sys
if os.environ.get("WAYLAND_DISPLAY"):
    try:
        wayland = ctypes.CDLL("libwayland-client.so.0")
        wayland.wl_display_connect.restype = ctypes.c_void_p
        wayland.wl_display_connect.argtypes = [ctypes.c_char_p]
        if wayland.wl_display_connect(None):
            sys.exit(0)
    except OSError:
        pass
if os.environ.get("DISPLAY"):
    try:
        x11 = ctypes.CDLL("libX11.so.6")
    except OSError:
        print("libX11.so.6 cannot be loaded")
        sys.exit(3)
    x11.XOpenDisplay.restype = ctypes.c_void_p
    x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
    if x11.XOpenDisplay(None):
        sys.exit(0)
    print("no X server answers there")
    sys.exit(4)
print("no display server answers")
sys.exit(5)
"""


def display_problem() -> str | None:
    """None where a display answers (``WAYLAND_DISPLAY`` or ``DISPLAY``), else why not."""
    names = {key: os.environ.get(key) for key in ("WAYLAND_DISPLAY", "DISPLAY")}
    shown = ", ".join(f"{key}={value!r}" for key, value in names.items() if value)
    if not shown:
        return "no display (DISPLAY and WAYLAND_DISPLAY are not set)"
    try:
        probe = subprocess.run(
            [sys.executable, "-c", _DISPLAY_PROBE],
            capture_output=True,
            text=True,
            timeout=DISPLAY_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        return f"the display ({shown}) did not answer within {DISPLAY_TIMEOUT_S:g} s"
    if probe.returncode != 0:
        reason = (probe.stdout.strip().splitlines() or [f"exit status {probe.returncode}"])[-1]
        return f"cannot open the display ({shown}): {reason}"
    return None
