"""Waiting for readiness in tests: poll a condition up to a bound, never sleep a fixed time (not a test module)."""

import time


def wait_until(pred, timeout_s: float, poll_s: float = 0.05) -> bool:
    """Poll ``pred()`` every ``poll_s`` seconds until it is true (True) or ``timeout_s`` seconds passed (False)."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll_s)
    return True


#: how long a test waits for a process it started to be ready: the start of a service that imports torch and Warp,
#: several at once on a loaded 2-core machine, with room to spare. A process that exits ends the wait at once.
STARTUP_S = 180.0

#: how long a test lets an agent's own work take: mapping the frames it was sent, a push it waits for, a Finish (the
#: final pass and push, for which the share worker may start). The bound only keeps a hung agent from holding the
#: suite: beside a CPU-bound process on a 2-core machine, a Finish of a few frames has taken over 120 s.
WORK_S = 600.0


def wait_for_start(proc, ready, what: str, log=None, timeout_s: float = STARTUP_S) -> None:
    """Poll ``ready()`` until it is true while ``proc`` (a ``subprocess.Popen``) runs.

    Args:
        ready: callable -> bool, e.g. "the port file has a port".
        what: what the wait is for, as the failure message names it ("the fusion server's port file").
        log: optional path of the process's output, whose tail the failure message shows.
    Raises:
        AssertionError: ``proc`` exited first, or ``timeout_s`` passed (``proc`` is then killed); the message names
            ``what``, the seconds waited and the exit status.
    """
    t0 = time.monotonic()
    while not ready():
        waited = time.monotonic() - t0
        if proc.poll() is not None or waited > timeout_s:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
            tail = log.read_text(errors="replace")[-3000:] if log is not None and log.exists() else ""
            raise AssertionError(f"waited {waited:.0f} s (bound {timeout_s:.0f} s) for {what}; the process "
                                 f"{'exited ' + str(proc.returncode) if proc.returncode is not None else 'hung'}"
                                 + (f"; its output ends:\n{tail}" if tail else ""))
        time.sleep(0.05)
