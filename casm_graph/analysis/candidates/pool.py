"""Where a diagnosis's fits run: worker processes on this machine or tasks on a Dask cluster, one implementation for
every kind of action model's candidates. A task is a (function, arguments) pair of module-level names, so that it
pickles by reference."""
from __future__ import annotations

import multiprocessing
import os
import pickle
import signal

STOP = (signal.SIGINT, signal.SIGTERM)       # the signals the command line's handler stops on


def call(task):
    """Run one (function, arguments) task."""
    fn, args = task
    return fn(*args)


def _worker_signals():
    """Workers leave interrupts to the parent (which terminates them), die quietly on SIGTERM and run their BLAS
    on one thread (the workers share the cores)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP)


def _pool(n: int):
    """A pool of ``n`` workers started with the stop signals held: one landing while a worker forks waits until the
    parent knows every worker, so its handler terminates them all (a worker forked but not yet counted outlived a
    SIGTERM, blocked on the task queue and holding the caller's output pipes open)."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, STOP)
    try:
        return multiprocessing.Pool(n, initializer=_worker_signals)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


def _call_packed(blob: bytes):
    """Run one task that travelled as :func:`packed` bytes."""
    return call(pickle.loads(blob))


def packed(calls: list) -> list[bytes] | None:
    """Each call pickled, as it travels to a worker process, or None when one cannot be (checked before any
    worker starts: a user's effect class made inside a function cannot)."""
    try:
        return [pickle.dumps(c, protocol=pickle.HIGHEST_PROTOCOL) for c in calls]
    except (AttributeError, TypeError, pickle.PicklingError):
        return None


def picklable(calls: list) -> bool:
    """Whether ``calls`` can travel to worker processes."""
    return packed(calls) is not None


def parallel(calls: list, workers: int, progress=None, client=None) -> list:
    """The (function, arguments) ``calls`` in worker processes, results in order (serially when one worker, or when a
    call cannot be pickled), or as tasks on a Dask cluster when ``client`` (a ``distributed.Client``) is given.

    On any exception or signal the workers are terminated (the cluster's tasks cancelled) before it
    propagates, so none outlive the caller."""
    if client is not None and len(calls) > 1:
        futures = client.map(call, calls, pure=False)
        try:
            results = []
            for f in futures:
                results.append(f.result())
                if progress is not None:
                    progress.step(1)
            return results
        except BaseException:
            client.cancel(futures)
            raise
    results = []
    blobs = packed(calls) if workers > 1 and len(calls) > 1 else None
    if blobs is not None:                     # pickled once: the check is the travel
        pool = _pool(min(workers, len(calls)))
        try:
            for r in pool.imap(_call_packed, blobs):
                results.append(r)
                if progress is not None:
                    progress.step(1)
            pool.close()
            pool.join()
            return results
        finally:
            pool.terminate()                  # an interrupt or a failure stops the workers, none left behind
    for c in calls:
        results.append(call(c))
        if progress is not None:
            progress.step(1)
    return results
