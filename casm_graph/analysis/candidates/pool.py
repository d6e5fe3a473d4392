"""Where a diagnosis's fits run: worker processes on this machine or tasks on a Dask cluster, one implementation for
every kind of action model's candidates. A task is a (function, arguments) pair of module-level names, so that it
pickles by reference."""
from __future__ import annotations

import multiprocessing
import os
import pickle
import signal


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


def picklable(calls: list) -> bool:
    """Whether ``calls`` can travel to worker processes (checked before any starts: a user's effect class made
    inside a function cannot)."""
    try:
        pickle.dumps(calls)
    except (AttributeError, TypeError, pickle.PicklingError):
        return False
    return True


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
    if workers > 1 and len(calls) > 1 and picklable(calls):
        pool = multiprocessing.Pool(min(workers, len(calls)), initializer=_worker_signals)
        try:
            for r in pool.imap(call, calls):
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
