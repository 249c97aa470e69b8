"""A process that ends cleanly exits 0 even when an Open3D tensor is still alive at its end.

Open3D's end-of-program leak check calls ``exit(1)`` when any tensor it allocated is still alive
(here: one held by a daemon thread, as a service's volume can be); :mod:`openfusion.app.exit_status`
turns that check off at exit, and the ``openfusion`` command does it for every subcommand.
Bad input tried: none (a process-level behaviour); the control run without it shows the check is
real in this Open3D build, so the test cannot pass by accident."""

from __future__ import annotations

import subprocess
import sys
import textwrap

PROGRAM = textwrap.dedent("""
    import sys, threading
    import open3d as o3d
    if sys.argv[1] == "keep":
        from openfusion.app.exit_status import keep_exit_status
        keep_exit_status()
    holding = threading.Event()
    def hold():
        tensor = o3d.core.Tensor.zeros((1024,), o3d.core.float32)
        holding.set()
        threading.Event().wait()  # forever, holding the tensor
    threading.Thread(target=hold, daemon=True).start()
    holding.wait(60)
    sys.exit(0)
""")


def _run(mode: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", PROGRAM, mode], capture_output=True, text=True, timeout=120)


def test_a_live_tensor_at_exit_does_not_change_the_exit_status() -> None:
    control = _run("plain")
    assert control.returncode == 1 and "Memory Statistics" in control.stdout + control.stderr
    kept = _run("keep")
    assert kept.returncode == 0, kept.stdout + kept.stderr
    assert "Memory Statistics" not in kept.stdout + kept.stderr
