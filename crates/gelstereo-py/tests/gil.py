"""Measures whether a call releases the GIL: the share of the call's time the main thread spends
running Python meanwhile."""

import sys
import threading
import time


def main_thread_share_while(call) -> float:
    """Runs `call` in a worker thread while the main thread counts, and returns the main thread's
    count during the call as a share of what it counts alone in as long. A call holding the GIL
    leaves about one switch interval (set to 0.1 ms here) of counting: a share near 0."""
    rate = _count_rate()
    count = [0]
    window = {}
    started = threading.Event()

    def work():
        started.set()
        window["start"], before = time.perf_counter(), count[0]
        call()
        window["s"], window["counted"] = time.perf_counter() - window["start"], count[0] - before

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-4)
    try:
        worker = threading.Thread(target=work)
        worker.start()
        started.wait()
        while worker.is_alive():
            count[0] += 1
        worker.join()
    finally:
        sys.setswitchinterval(old)
    return window["counted"] / (rate * window["s"])


def _count_rate() -> float:
    """Counts per second of the loop in `main_thread_share_while`, the main thread alone."""
    count = [0]
    start = time.perf_counter()
    while time.perf_counter() - start < 0.05:
        count[0] += 1
    return count[0] / (time.perf_counter() - start)
