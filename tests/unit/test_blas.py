"""``magkf.blas.one_thread``: BLAS held to one thread while an entry point runs, the caller's setting back after."""

import numpy  # noqa: F401  (numpy's and scipy's BLAS loaded, as they are when magkf computes)
import scipy.special  # noqa: F401
from threadpoolctl import threadpool_info, threadpool_limits

from magkf.blas import one_thread


def _threads() -> list:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_one_thread_inside_and_restored_after():
    seen = []

    @one_thread
    def work(value):
        seen.append(_threads())
        return value * 2

    with threadpool_limits(limits=2, user_api="blas"):
        before = _threads()
        assert before and all(n == 2 for n in before)
        assert work(21) == 42
        assert _threads() == before  # the caller's setting is back
    assert seen[0] and all(n == 1 for n in seen[0])  # numpy's and scipy's BLAS alike


def test_restored_after_an_error():
    @one_thread
    def fails():
        raise ValueError("bad input")

    with threadpool_limits(limits=2, user_api="blas"):
        before = _threads()
        try:
            fails()
        except ValueError:
            pass
        assert _threads() == before


def test_entry_points_are_wrapped():
    from magkf.diagnostics.diagnose import diagnose
    from magkf.diagnostics.report import build_report
    from magkf.diagnostics.validate import validate
    from magkf.online.batch import solve_batch
    from magkf.online.chunked import calibrate_file
    from magkf.online.run import calibrate_log

    for entry in (calibrate_log, solve_batch, calibrate_file, diagnose, build_report, validate):
        assert entry.__code__ is one_thread(len).__code__, entry.__name__


def test_concurrent_and_nested_calls_restore_the_setting_once_all_return():
    import threading

    import magkf.blas

    started, release = threading.Barrier(3), threading.Event()

    @one_thread
    def inner():
        return magkf.blas._running

    @one_thread
    def work(out):
        started.wait(timeout=30)
        release.wait(timeout=30)
        out.append(inner())  # nested: counted, not limited again

    with threadpool_limits(limits=2, user_api="blas"):
        before, counts = _threads(), []
        threads = [threading.Thread(target=work, args=(counts,)) for _ in range(2)]
        for t in threads:
            t.start()
        started.wait(timeout=30)  # both inside
        assert magkf.blas._running == 2
        release.set()
        for t in threads:
            t.join(timeout=30)
        assert sorted(counts) in ([2, 3], [3, 3])  # the nested call ran while its caller was counted
        assert magkf.blas._running == 0 and magkf.blas._limiter is None
        assert _threads() == before  # restored once, by the last to end, to what the first found
