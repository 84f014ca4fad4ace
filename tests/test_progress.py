"""Progress through callbacks (``oapcal.progress``): the counting object the library uses."""

import threading

import pytest

from oapcal.progress import Stages, progress_callback


def test_threads_sharing_one_counter_report_every_step_once_and_in_order():
    calls = []
    with Stages(lambda *a: calls.append(a), total=4000, description="frames") as s:
        threads = [threading.Thread(target=lambda: [s.advance() for _ in range(1000)]) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert s.done == 4000 and calls[-1] == (4000, 4000, "frames")
    assert [c[0] for c in calls] == list(range(4001))  # the start, then each step exactly once


def test_done_is_never_reported_beyond_the_total():
    calls = []
    with Stages(lambda *a: calls.append(a), total=2) as s:
        s.advance(3, "retry")
    assert calls[-1] == (2, 2, "retry")


@pytest.mark.parametrize("bad", [True, 1, "yes"])
def test_a_progress_that_is_not_a_callback_is_refused(bad):
    with pytest.raises(TypeError, match="give a callback"):
        progress_callback(bad)
    assert progress_callback(False) is None and progress_callback(None) is None
