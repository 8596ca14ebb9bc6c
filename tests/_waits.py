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
