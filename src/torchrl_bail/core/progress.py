"""The progress bars of every long loop: ``tqdm.auto``'s bar, with a thread lock in place of its multiprocessing one.

tqdm guards its bars with a ``multiprocessing.RLock`` by default; under TorchRL, which sets the ``spawn`` start method
on import, that lock is a named semaphore registered with Python's resource tracker. The library's bars never span
processes, so a thread lock does (:meth:`tqdm.set_lock`), and a job that Slurm stops (its whole step, resource tracker
included, is signalled) has no semaphore left for a fresh tracker to complain about at exit (a ``KeyError`` traceback
per name).
"""

from __future__ import annotations

import threading

from tqdm.auto import tqdm

tqdm.set_lock(threading.RLock())

__all__ = ["tqdm"]
